"""What one agent update dispatches: aten ops, host syncs, bytes copied host->device; counted on the CPU
(or on the agents' device, --device). These counts are what a GPU's update time is made of when its
kernels are small (a launch and a few us of host work per op, a stall per sync, a copy per batch), and
no machine changes them but through the optimiser's path (below).

    python benchmarks/update_counts.py                        # every method, the paper's sizes, batch 8
    python benchmarks/update_counts.py --methods drq sear --top 25
    python benchmarks/update_counts.py --check                # exit 1 when a target below is missed

What is counted, per update (`count_update`), with a TorchDispatchMode, so below autograd: the forward
ops, the backward ops autograd runs, the optimisers' ops, everything dispatched from the call's thread
or from autograd's threads while `agent.update(batch, step)` runs:

  ops        every aten op dispatched, except pure views: ops whose schema returns an alias of an input
             they do not write (`OpOverload.is_view`: view, t, expand, detach, split, unbind, as_strided,
             lift_fresh, ...), which only make new metadata. In-place ops (`add_`, `lerp_`) count.
  syncs      reads of device data by the host, each a stall of the host until the device has caught up:
             `aten._local_scalar_dense` (what .item(), float(t), int(t) and bool(t) call); the ops whose
             output size is computed on the device (tagged `torch.Tag.dynamic_output_shape`: nonzero,
             masked_select, unique, repeat_interleave by a tensor, ..., and indexing with a boolean
             mask, which calls nonzero); a copy from a device to the CPU (`_to_copy`, `copy_`). On a
             CPU run a copy to the CPU dispatches nothing, so there `Tensor.tolist`, `.numpy`,
             `.__array__`, `.cpu` and `.to(<cpu>)` are counted where they are called (a TorchFunctionMode).
             Not a sync: reading what torch keeps on the host by design, an optimiser's `step` count when
             it is neither `capturable` nor `fused` (Adam reads it with .item() for every parameter, on
             any device); on a CPU run every tensor is on the CPU, so those reads are told apart by
             the tensor (`host_reads`), on a GPU run by its device.
  h2d_bytes  bytes that enter the agent's device from host memory: a tensor made from host data
             (`aten.lift_fresh`, which torch.as_tensor, torch.tensor and torch.from_numpy dispatch)
             on the agent's device, and a copy from the CPU to a non-CPU device. On a CPU run the
             agent's device is the CPU: the count is the numpy batch that `update` turns into tensors
             (about 43 MB at batch 256), 0 once the replay hands it tensors on the device.

The counts do not depend on the batch size or the networks' widths (the same ops run on larger
tensors); they depend on the method and its flags (torch's fused Adam steps all of an optimiser's
parameters with one `_fused_adam_`; the Polyak step of the target critic is one `lerp_` per
parameter). CURL steps its key encoder every second update: the CLI counts two consecutive updates
and shows the larger. A compiled update's fused kernels are not aten ops: these counts are of the
plain update.
"""
import argparse
import contextlib
import dataclasses
import os
import sys
import types
from collections import Counter
from typing import NamedTuple

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_agent  # noqa: E402
from harness import cli  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402

# The targets: at most this many ops per update, and host syncs inside any update.
OPS_TARGET = {"drq": 250, "sear": 400}
SYNCS_TARGET = 0


class Counts(NamedTuple):
    ops: int            # aten ops dispatched, views excluded
    syncs: int          # host reads of device data
    h2d_bytes: int      # bytes from host memory onto the agent's device
    names: Counter      # op name -> times dispatched (views excluded)
    sync_names: Counter  # what each sync was: an op's name, or the Tensor method called
    host_reads: int     # .item() of a tensor the host keeps (an optimiser's step count): not a sync


def op_name(func) -> str:
    return func.overloadpacket.__name__  # lerp_ for aten.lerp_.Scalar and aten.lerp_.Tensor


# Indexing by a boolean mask finds the mask's nonzeros on the device and sizes the result on the host.
MASK_INDEXING = {torch.ops.aten.index, torch.ops.aten.index_put, torch.ops.aten.index_put_,
                 torch.ops.aten._index_put_impl_}


def is_device_read(func, args, kwargs) -> bool:
    """An op whose result the host must wait for: a data-dependent output (a scalar read), or an output
    whose size the device computes; indexing is one with a boolean mask, not with integer indices."""
    if func.overloadpacket in MASK_INDEXING:
        return any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in args[1])
    if func.overloadpacket is torch.ops.aten.one_hot:  # sized by the largest label unless num_classes is given
        return kwargs.get("num_classes", args[1] if len(args) > 1 else -1) == -1
    return bool({torch.Tag.data_dependent_output, torch.Tag.dynamic_output_shape} & set(func.tags))


def tensor_bytes(t: torch.Tensor) -> int:
    return t.numel() * t.element_size()


def on_host(device: torch.device) -> bool:
    return device.type == "cpu"


class OpCounter(TorchDispatchMode):
    """The dispatch-level count of `Counts` (see the module's doc); `device`: the agent's device."""

    def __init__(self, device):
        super().__init__()
        self.device = torch.device(device)
        self.names, self.sync_names, self.h2d_bytes = Counter(), Counter(), 0
        self.scalar_reads = []  # the tensor of each _local_scalar_dense: a sync or a host read, told apart after

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        packet = func.overloadpacket
        if packet in (torch.ops.aten.lift_fresh, torch.ops.aten.lift_fresh_copy):
            if out.device.type == self.device.type:
                self.h2d_bytes += tensor_bytes(out)
        if func.is_view or func.namespace != "aten":  # not aten: the optimisers' record_function markers
            return out
        self.names[op_name(func)] += 1
        if packet in (torch.ops.aten._to_copy, torch.ops.aten.copy_):
            src, dst = (args[0], out) if packet is torch.ops.aten._to_copy else (args[1], args[0])
            if isinstance(src, torch.Tensor):
                if on_host(src.device) and not on_host(dst.device):
                    self.h2d_bytes += tensor_bytes(src)
                elif not on_host(src.device) and on_host(dst.device):
                    self.sync_names[op_name(func) + " (to the host)"] += 1
        elif packet is torch.ops.aten._local_scalar_dense:
            self.scalar_reads.append(args[0])
        elif is_device_read(func, args, kwargs):
            self.sync_names[op_name(func)] += 1
        return out


# The Tensor methods that hand a tensor's values to the host; on a CPU run they dispatch no copy.
HOST_METHODS = {torch.Tensor.tolist: "tolist", torch.Tensor.numpy: "numpy", torch.Tensor.__array__: "__array__",
                torch.Tensor.cpu: "cpu"}


def to_host(args, kwargs) -> bool:
    """Whether a Tensor.to(...) call names the CPU as its device."""
    for a in (*args[1:], kwargs.get("device")):
        if isinstance(a, (str, torch.device)) and torch.device(a).type == "cpu":
            return True
    return False


class HostReads(TorchFunctionMode):
    """On a CPU run: the Tensor methods that would copy to the host on a GPU, counted where called."""

    def __init__(self, sync_names: Counter):
        super().__init__()
        self.sync_names = sync_names

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in HOST_METHODS:
            self.sync_names["Tensor." + HOST_METHODS[func]] += 1
        elif func is torch.Tensor.to and to_host(args, kwargs):
            self.sync_names["Tensor.to (the host)"] += 1
        return func(*args, **kwargs)


def optimizers(root) -> list:
    """Every optimiser reachable from `root` (an agent) through attributes, dicts, lists and tuples:
    the agent's own, an auxiliary loss's (CURL's), DrM's, wherever the agent keeps them."""
    found, seen, todo = [], set(), [root]
    while todo:
        obj = todo.pop()
        if id(obj) in seen or isinstance(obj, (torch.Tensor, type, types.ModuleType, types.FunctionType)):
            continue
        seen.add(id(obj))
        if isinstance(obj, torch.optim.Optimizer):
            found.append(obj)
        elif isinstance(obj, dict):
            todo += obj.values()
        elif isinstance(obj, (list, tuple, set)):
            todo += obj
        elif hasattr(obj, "__dict__"):
            todo += vars(obj).values()
    return found


def host_steps(agent) -> list:
    """The step counts torch's optimisers keep on the host by design (neither capturable nor fused):
    Adam reads each with .item(), on any device, and no device waits for that."""
    steps = []
    for opt in optimizers(agent):
        for group in opt.param_groups:
            if group.get("capturable") or group.get("fused"):
                continue
            for p in group["params"]:
                step = opt.state.get(p, {}).get("step")
                if isinstance(step, torch.Tensor) and on_host(step.device):
                    steps.append(step)
    return steps


def count_update(agent, batch, step, warmup: int = 1) -> Counts:
    """Counts of one `agent.update(batch, step)`, after `warmup` uncounted updates (so that lazy state,
    Adam's moments and step counts among it, exists). See the module's doc for what is counted."""
    for _ in range(warmup):
        agent.update(batch, step)
    counter = OpCounter(agent.device)
    # On a CPU run a copy to the host dispatches nothing: the Tensor methods that would make one count.
    with HostReads(counter.sync_names) if on_host(counter.device) else contextlib.nullcontext(), counter:
        agent.update(batch, step)
    # A read of the host's own memory is no sync: on a GPU run, any CPU tensor's; on a CPU run, where
    # everything is on the CPU, the optimisers' step counts (which a GPU run keeps on the host too).
    if on_host(counter.device):
        steps = {id(s) for s in host_steps(agent)}
        host_reads = sum(id(t) in steps for t in counter.scalar_reads)
    else:
        host_reads = sum(on_host(t.device) for t in counter.scalar_reads)
    if len(counter.scalar_reads) > host_reads:
        counter.sync_names["_local_scalar_dense"] += len(counter.scalar_reads) - host_reads
    return Counts(sum(counter.names.values()), sum(counter.sync_names.values()), counter.h2d_bytes, counter.names,
                  counter.sync_names, host_reads)


# --- agents and batches ---------------------------------------------------------------------------
def make_agent(method_label, cfg_overrides, device):
    """An agent of a method label of train.METHODS, or METHOD+drm for it with DrM (drm.DrMAgent), as
    train.py builds it."""
    method, drm_flags = cli.split_method_label(method_label)
    cfg = train.Config(method=method, drm=bool(drm_flags), **cfg_overrides)
    return train.make_agent(cfg, 6, torch.device(device))


def default_methods() -> list:
    return [*train.METHODS, "drq" + cli.DRM_SUFFIX, "sear" + cli.DRM_SUFFIX]


def count_method(label, overrides, batch_size, device="cpu") -> Counts:
    """The heavier of two consecutive updates of a fresh agent (CURL's key EMA runs every second one), on
    a batch already on the agent's device, as the replay there hands it."""
    torch.manual_seed(0)
    agent = make_agent(label, overrides, device)
    batch = bench_agent.device_batch(bench_agent.fake_batch(batch_size), device)
    first = count_update(agent, batch, 5_000)
    second = count_update(agent, batch, 5_000, warmup=0)
    return max(first, second, key=lambda c: (c.ops, c.syncs))


def misses(label: str, c: Counts) -> list:
    """The targets `c` misses, one line each."""
    out = []
    if label in OPS_TARGET and c.ops > OPS_TARGET[label]:
        out.append(f"{label}: {c.ops} ops per update, target <= {OPS_TARGET[label]}")
    if c.syncs > SYNCS_TARGET:
        out.append(f"{label}: {c.syncs} host syncs in an update, target {SYNCS_TARGET} "
                   f"({', '.join(f'{k} x{n}' for k, n in c.sync_names.most_common())})")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", nargs="+", default=default_methods(),
                   choices=[m + d for d in ("", cli.DRM_SUFFIX) for m in train.METHODS])
    p.add_argument("--batch-size", type=int, default=8, help="the counts do not depend on it (the H2D bytes do)")
    p.add_argument("--top", type=int, default=15, help="ops listed per method, most dispatched first (0: none)")
    p.add_argument("--check", action="store_true", help="exit 1 when a method misses a target "
                   f"(ops per update: {OPS_TARGET}; host syncs: {SYNCS_TARGET})")
    p.add_argument("--device", default="cpu", help="the agents' device (cuda: the counts of a GPU run)")
    p.add_argument("--latent-dim", type=int, help="default: the paper's (counts do not depend on the widths)")
    p.add_argument("--hidden-dim", type=int)
    p.add_argument("--feature-dim", type=int)
    args = p.parse_args(argv)
    # One thread: the counts do not depend on it, and on cores that other processes share, a second
    # thread waits for the first at every op (tiny networks then took 10x as long).
    torch.set_num_threads(1)
    overrides = {"batch_size": args.batch_size, "action_repeat": 2,
                 **{k: getattr(args, k) for k in ("latent_dim", "hidden_dim", "feature_dim") if getattr(args, k)}}
    sizes = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in overrides.items() if k != "action_repeat")
    counts = {label: count_method(label, overrides, args.batch_size, args.device) for label in args.methods}
    for label, c in counts.items() if args.top else ():
        print(f"### {label}: the {args.top} most dispatched of {len(c.names)} ops\n\n| op | count |\n|---|---|")
        for name, n in c.names.most_common(args.top):
            print(f"| {name} | {n} |")
        print()
    # The table last, where a log's tail shows it.
    print(f"## One update's ops, host syncs and host->device bytes on {args.device} ({sizes}; the batch on "
          f"the device, as the replay there hands it)\n")
    print("| method | ops | host syncs | H2D bytes | H2D at batch 256 | lerp | Adam step reads (host) | the syncs |")
    print("|---|---|---|---|---|---|---|---|")
    failed = []
    for label, c in counts.items():
        syncs = ", ".join(f"{k} x{n}" for k, n in c.sync_names.most_common())
        at_256 = c.h2d_bytes * 256 / args.batch_size  # the batch's arrays: bytes in proportion to its size
        lerps = c.names["lerp_"] + c.names["_foreach_lerp_"]  # one per parameter, or one per list
        print(f"| {label} | {c.ops} | {c.syncs} | {c.h2d_bytes:,} | {at_256 / 1e6:.1f} MB | {lerps} | "
              f"{c.host_reads} | {syncs} |")
        failed += misses(label, c)
    print(f"\ntargets: ops per update {OPS_TARGET}, host syncs {SYNCS_TARGET}: "
          + ("all met" if not failed else f"{len(failed)} missed" + ("" if args.check else " (--check lists them)")))
    for line in failed if args.check else ():
        print(f"  MISSED {line}")
    return 1 if args.check and failed else 0


if __name__ == "__main__":
    sys.exit(main())
