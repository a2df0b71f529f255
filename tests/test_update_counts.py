"""benchmarks/update_counts.py: the counter on functions whose ops, syncs and host->device bytes
are known, then the budgets on the real agent's plain update (every method of train.METHODS, and
DrM on drq and sear: no host sync inside an update; drq and sear: at most update_counts.OPS_TARGET
ops). The agents are small (the counts do not depend on the widths or the batch, which
test_counts_do_not_depend_on_sizes checks against the paper's widths)."""
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import train  # noqa: E402
import update_counts  # noqa: E402

SMALL = {"latent_dim": 64, "hidden_dim": 32, "feature_dim": 16, "batch_size": 4, "action_repeat": 2}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """As update_counts.py runs: on shared cores a second torch thread waits for the first at every op."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


class Calls:
    """What count_update needs of an agent: `device`, and `update(batch, step)`, here fn(batch)."""

    def __init__(self, fn, device="cpu"):
        self.fn, self.device = fn, torch.device(device)

    def update(self, batch, step):
        return self.fn(batch)


def count(fn, batch=None):
    return update_counts.count_update(Calls(fn), batch, step=0, warmup=0)


def test_ops_are_counted_and_views_are_not():
    x = torch.ones(4, 4)

    def fn(_):
        y = x + 1
        y.view(16)[:4].unsqueeze(0).expand(2, 4).t().detach()  # views: metadata only
        y.add_(1)
        return (y * 2).sum()
    c = count(fn)
    assert dict(c.names) == {"add": 1, "add_": 1, "mul": 1, "sum": 1}
    assert (c.ops, c.syncs, c.h2d_bytes) == (4, 0, 0)


@pytest.mark.parametrize("fn, syncs", [
    (lambda x: x.sum().item(), 1),
    (lambda x: float(x.mean()), 1),
    (lambda x: bool((x > 0).all()), 1),
    (lambda x: x.tolist(), 1),
    (lambda x: torch.stack([x.sum(), x.mean()]).tolist(), 1),  # the update's metrics today
    (lambda x: x.numpy(), 1),
    (lambda x: x.cpu(), 1),
    (lambda x: x.to("cpu"), 1),
    (lambda x: x[x > 0], 1),        # a boolean mask: the output's size is computed on the device
    (lambda x: x.clone().index_put_((x > 0,), torch.tensor(0.0)), 1),
    (lambda x: x.nonzero(), 1),
    (lambda x: x[torch.arange(2)], 0),  # integer indices: the size is known
    (lambda x: x.to(torch.float64), 0),
    (lambda x: (x * 2).exp_(), 0),
], ids=["item", "float", "bool", "tolist", "stack-tolist", "numpy", "cpu", "to-cpu", "bool-mask", "bool-mask-put", "nonzero",
        "int-index", "to-dtype", "arithmetic"])
def test_host_syncs(fn, syncs):
    c = count(lambda _: fn(torch.linspace(-1, 1, 6)))
    assert c.syncs == syncs, c.sync_names


def test_a_scalar_read_is_one_op_and_one_sync():
    c = count(lambda _: torch.ones(3).sum().item())
    assert dict(c.names) == {"ones": 1, "sum": 1, "_local_scalar_dense": 1}
    assert dict(c.sync_names) == {"_local_scalar_dense": 1}


def test_adam_step_counts_are_host_reads_not_syncs():
    """Adam reads each parameter's step count with .item(): torch keeps it on the host when Adam is
    neither capturable nor fused, so no device waits for it; any other .item() is a sync."""
    net = torch.nn.Linear(3, 2)
    agent = Calls(lambda _: (net(torch.ones(5, 3)).square().mean().backward(), agent.opt.step(),
                             net.weight.sum().item()))
    agent.opt = torch.optim.Adam(net.parameters(), foreach=False)
    c = update_counts.count_update(agent, None, step=0)  # the warm-up makes the step counts
    assert c.host_reads == 2  # weight and bias
    assert c.syncs == 1 and dict(c.sync_names) == {"_local_scalar_dense": 1}
    assert c.names["_local_scalar_dense"] == 3
    agent.opt = torch.optim.Adam(net.parameters(), fused=True)  # the step count on the device, read by the kernel
    c = update_counts.count_update(agent, None, step=0)
    assert (c.host_reads, c.syncs) == (0, 1)


def test_host_to_device_bytes_on_the_cpu():
    """On a CPU run: the bytes of tensors made from host data (numpy arrays, Python lists); none for a
    tensor that exists already."""
    t = torch.ones(10)
    c = count(lambda _: (torch.as_tensor(np.zeros((4, 5), np.uint8)).float(), torch.tensor([1.0, 2.0]),
                         torch.from_numpy(np.zeros(3, np.float32)), torch.as_tensor(t).float(), t.to("cpu")))
    assert c.h2d_bytes == 20 + 8 + 12
    assert c.syncs == 1  # t.to("cpu"): on a GPU run, a copy to the host


def test_copies_between_devices():
    """Where the agent is not on the CPU (a 'meta' device, and a fake CUDA one, which this machine can
    count without a GPU): a copy from the CPU is host->device bytes, a copy to the CPU a sync."""
    counter = update_counts.OpCounter("meta")
    with counter:
        torch.ones(8, dtype=torch.uint8).to("meta")
        torch.empty(4, device="meta").copy_(torch.ones(4))
    assert counter.h2d_bytes == 8 + 16 and not counter.sync_names
    from torch._subclasses.fake_tensor import FakeTensorMode
    with FakeTensorMode():
        x = torch.empty(4, 4, device="cuda")
        counter = update_counts.OpCounter("cuda")
        with counter:
            x.sum()
            x.cpu()
            torch.empty(4, 4).copy_(x)
    assert dict(counter.sync_names) == {"_to_copy (to the host)": 1, "copy_ (to the host)": 1}
    assert counter.h2d_bytes == 0


def test_h2d_bytes_are_the_numpy_batch_and_none_for_tensors():
    """The update's host->device bytes: the numpy batch, all of it; none when it arrives as tensors."""
    agent = update_counts.make_agent("drq", SMALL, "cpu")
    batch = update_counts.sear.Batch(*update_counts.bench_agent.fake_batch(4))
    assert update_counts.count_update(agent, batch, 5_000).h2d_bytes == sum(x.nbytes for x in batch)
    on_device = update_counts.sear.Batch(*(torch.as_tensor(x) for x in batch))
    assert update_counts.count_update(agent, on_device, 5_000).h2d_bytes == 0


def test_make_agent_builds_drm():
    assert type(update_counts.make_agent("drq+drm", SMALL, "cpu")).__name__ == "DrMAgent"
    assert type(update_counts.make_agent("drq", SMALL, "cpu")).__name__ == "Agent"


@pytest.mark.parametrize("method", ["drq", "sear"])
def test_counts_do_not_depend_on_sizes(method):
    """The paper's widths at batch 2 dispatch the ops the small agents of these tests do."""
    paper = {"batch_size": 2, "action_repeat": 2}
    big = update_counts.count_method(method, paper, 2)
    small = update_counts.count_method(method, SMALL, 4)
    assert (big.names, big.sync_names, big.host_reads) == (small.names, small.sync_names, small.host_reads)


# --- the budgets ----------------------------------------------------------------------------------
def test_every_method_is_counted():
    """Every --method of the run's table (not sear.py's own two alone), and DrM on drq and sear."""
    assert set(update_counts.default_methods()) == {*train.METHODS, "drq+drm", "sear+drm"}


@pytest.mark.parametrize("method", update_counts.default_methods())
def test_update_has_no_host_sync(method):
    c = update_counts.count_method(method, SMALL, SMALL["batch_size"])
    assert c.syncs <= update_counts.SYNCS_TARGET, update_counts.misses(method, c)


@pytest.mark.parametrize("method", sorted(update_counts.OPS_TARGET))
def test_update_op_budget(method):
    c = update_counts.count_method(method, SMALL, SMALL["batch_size"])
    assert c.ops <= update_counts.OPS_TARGET[method], (update_counts.misses(method, c), c.names.most_common(10))
