"""The speed layer (harness/speed.py) computes what the plain update computes: torch.compile's
update and the seeds' batched update (SeedBatch) within rounding, the CUDA graph's to the bit;
DRAWS_INSIDE names exactly the methods whose update draws random numbers; a compiled run resumes
exactly.

Each rounding bound is shown to separate: the same check runs on controls, the plain update with
every learning rate x 1.01 or with the sign of every step flipped (tests/reference.py's
put_wrong), and each control must fail it. Tiny networks; the compile tests are skipped where
inductor has no C++ compiler (a CPU compile takes up to a minute per method)."""
import copy

import pytest
import torch

from harness import cli, speed
import sear
import train
from tests import reference
from tests.test_baselines import numpy_batch
from tests.test_cli import only_run_dir, rows, run, tiny
from tests.test_sear import fake_batch, small_cfg

needs_compiler = pytest.mark.skipif(cli.cxx_compiler() is None,
                                    reason="inductor's CPU kernels need a C++ compiler")
CONTROLS = ("control: lr x 1.01", "control: wrong sign")
NETWORKS = ("encoder", "actor", "critic", "critic_target", "aux", "value")  # value: DrM's V
# Where torch.compile breaks the update's graph by torch's design: its optimisers (zero_grad, the
# step's no-grad region, the fused kernel) and backward()
OPTIMISER_BREAKS = ("Optimizer.zero_grad", "Tensor.backward()", "_fused_adam",
                    "torch._dynamo.graph_break()")


def agent_of(label, device, **kw):
    """An agent of a method label (METHOD or METHOD+drm), built after torch.manual_seed(0)."""
    method, drm = label.removesuffix("+drm"), label.endswith("+drm")
    torch.manual_seed(0)
    return train.make_agent(small_cfg(method=method, drm=drm, **kw), 2, device)


def control(agent, case):
    """A copy of `agent` whose every update is wrong as `case` says."""
    wrong = copy.deepcopy(agent)
    reference.put_wrong(wrong, case)
    return wrong


def parameters(agent) -> dict:
    """{network: its parameters, flattened into one tensor}."""
    nets = {n: getattr(agent, n, None) for n in NETWORKS}
    return {n: torch.cat([p.detach().flatten() for p in net.parameters()]).clone()
            for n, net in nets.items() if net is not None and any(True for _ in net.parameters())}


def drift(agent, reference_agent, start) -> float:
    """The largest, over the networks, of ||agent's move - the reference's move|| / ||the
    reference's move||: the moves from `start`, 2-norms over each network's parameters."""
    mine, theirs = parameters(agent), parameters(reference_agent)
    return max(((mine[n] - theirs[n]).norm() / (theirs[n] - start[n]).norm()).item()
               for n in start)


def metric_gap(got: list, want: list) -> float:
    """The largest relative difference of a metric over the updates' metrics (each value against
    max(|want|, 1e-3): a metric at 0, actor_saturated, compares absolutely)."""
    assert [g.keys() for g in got] == [w.keys() for w in want]
    return max(abs(float(g[k]) - float(w[k])) / max(abs(float(w[k])), 1e-3)
               for g, w in zip(got, want) for k in w)


def graph_counters():
    import torch._dynamo.utils
    return torch._dynamo.utils.counters


# ---------------------------------------------------------------- --compile
# A compiled update rounds otherwise than the plain one (inductor fuses and reorders), and Adam
# turns a rounding-sized gradient near 0 into a step of lr whatever its sign, so a few weights move
# apart by up to 2 lr. Measured on the CPU (1 and 2 threads) after 4 updates: the metrics 1.9e-4
# apart at most (sear; drq and drq+drm 1.3e-5), the networks' moves 0.0099 (sear's decoders; drq
# 9e-4, drq+drm 1.6e-3); the lr x 1.01 control 0.038 and 0.064 at least, the wrong sign 9 and 1.9.
# The bounds sit between, a factor 2.5 or more from each side.
COMPILED_METRICS, COMPILED_MOVES, UPDATES = 1e-3, 0.025, 4


@needs_compiler
@pytest.mark.parametrize("label", ["sear", "drq", "drq+drm"])
def test_the_compiled_update_equals_the_plain_one(label):
    """torch.compile(agent.learn) on the CPU (what --compile sets), the plain update and the
    controls from the same weights, batches and draws: the compiled metrics and moves agree with
    the plain ones within the bounds above, each control's do not. The update is compiled at its
    first call and never again, and breaks its graph only at OPTIMISER_BREAKS."""
    torch._dynamo.reset()
    graph_counters().clear()
    plain = agent_of(label, torch.device("cpu"))
    start = parameters(plain)
    compiled = copy.deepcopy(plain)
    compiled.learn = torch.compile(compiled.learn)
    agents = {"plain": plain, "compiled": compiled,
              **{case: control(plain, case) for case in CONTROLS}}
    metrics, graphs = {name: [] for name in agents}, []
    for i in range(UPDATES):
        batch = fake_batch(seed=i)
        for name, agent in agents.items():
            agent.rng.manual_seed(100 + i)
            metrics[name].append(agent.update(batch, 5_000 + 2 * i))
        graphs.append(graph_counters()["stats"]["unique_graphs"])
    gaps = {name: (metric_gap(metrics[name], metrics["plain"]), drift(agent, plain, start))
            for name, agent in agents.items() if name != "plain"}
    assert gaps["compiled"][0] <= COMPILED_METRICS, gaps
    assert gaps["compiled"][1] <= COMPILED_MOVES, gaps
    for case in CONTROLS:
        assert gaps[case][0] > COMPILED_METRICS and gaps[case][1] > COMPILED_MOVES, (case, gaps)
    # no recompilation after the first update (a guard on a new object each update would make one)
    assert graphs[0] > 0 and graphs[-1] == graphs[0], graphs
    breaks = list(graph_counters()["graph_break"])
    assert all(any(where in reason for where in OPTIMISER_BREAKS) for reason in breaks), breaks


@needs_compiler
def test_the_compiled_objective_keeps_its_gradient_where_the_method_adds_no_term():
    """CURL's auxiliary loss adds no term to Eq. 6 (its step is its own): AuxLoss.forward's 0.0.
    A zero tensor there made the compiled critic objective lose its gradient (inductor folds
    critic_loss + 0 into critic_loss, which the metrics also return detached), and the compiled
    update then failed at its first backward()."""
    torch._dynamo.reset()
    agent = agent_of("curl", torch.device("cpu"))
    batch = fake_batch()._replace(mask=None, next_mask=None)  # curl reads no mask
    step = torch.full((), 5_000.0, dtype=torch.float64)
    loss, metrics, latent = torch.compile(agent.critic_objective)(batch, step, agent.draw(4))
    assert loss.requires_grad and latent.requires_grad
    assert float(loss.detach()) == pytest.approx(float(metrics["critic_loss"]))


@needs_compiler
def test_a_compiled_run_resumes_exactly(tmp_path):
    """With --compile on, 32 frames + --resume to 48 equal 48 frames in one go, as a plain run does
    (tests/test_cli.py): the compiled update is deterministic and its draws come from the agent's
    generator, saved in the snapshot."""
    common = ["--env", "walker-walk", "--method", "drq", "--seed", "5", "--save-buffer",
              "--compile", "on", *tiny("drq")]
    straight, split = tmp_path / "straight", tmp_path / "split"
    for d in (straight, split):
        d.mkdir()
    r = run([*common, "--frames", "48"], straight)
    assert r.returncode == 0, r.stderr[-2000:]
    assert run([*common, "--frames", "32"], split).returncode == 0
    split_dir = only_run_dir(split)
    r = run(["--resume", str(split_dir), "--frames", "48"], split)
    assert r.returncode == 0, r.stderr[-2000:]
    straight_dir = only_run_dir(straight)
    losses = ["frame", "return", "critic_loss", "actor_loss", "q"]
    table = [[x[c] for c in losses] for x in rows(split_dir / "train.csv")]
    assert table == [[x[c] for c in losses] for x in rows(straight_dir / "train.csv")]
    assert table[-1][2] != "" and int(table[-1][0]) > 32  # updates happened after the resume
    a = torch.load(straight_dir / "snapshot.pt", weights_only=False)["agent"]
    b = torch.load(split_dir / "snapshot.pt", weights_only=False)["agent"]
    for net in ("encoder", "critic", "actor"):
        assert all(torch.equal(a[net][k], b[net][k]) for k in a[net]), net
    assert torch.equal(a["rng"], b["rng"])


# ---------------------------------------------------------------- the seeds batched (SeedBatch)
# vmap batches each seed's arithmetic into other kernels, which round otherwise. Measured on the
# CPU (1 and 2 threads): the first update's metrics 2e-5 apart at most (rgbm; the others 1e-5),
# their controls' 2e-3 at least; over 3 updates Adam's amplification of near-zero gradients (above)
# takes ae's seed 1 to 4e-3 apart in its metrics and 4.3e-3 in its moves (the others 7e-4 or
# less), the lr x 1.01 control to 0.11 and 0.098 at least, the wrong sign to 2.9 and 2.
FIRST_METRICS, BATCHED_METRICS, BATCHED_MOVES, SEEDS = 2e-4, 2e-2, 2e-2, 3


@pytest.mark.parametrize("method", ["drq", "sear", "ae", "rgbm", "sear-nosplit", "dear"])
def test_the_batched_seeds_equal_the_seeds_updated_one_after_another(method, device, monkeypatch):
    """Three seeds, each its own networks, generator and batches, updated as one (SeedBatch) and
    one after another (copies of the same agents): the first update's metrics, every update's
    metrics and every network's move agree within the bounds above, the controls' do not. The
    agents' own parameters and Adam states are views of the stacks: what a seed's snapshot, resume
    and actions read."""
    # float32 convolutions on CUDA too, as measured (cuDNN's TF32 rounds to 1e-3)
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    cfg = small_cfg(method=method)
    agents = []
    for seed in range(SEEDS):
        torch.manual_seed(seed)
        agents.append(train.make_agent(cfg, 2, device))
    starts = [parameters(a) for a in agents]
    runs = {"one after another": [copy.deepcopy(a) for a in agents],
            **{case: [control(a, case) for a in agents] for case in CONTROLS}}
    batched = speed.SeedBatch(agents)
    got, want = [[] for _ in agents], {name: [[] for _ in agents] for name in runs}
    for u in range(3):
        # Batches as the replay samples them
        batches = [sear.Batch(*numpy_batch(n=4, seed=10 * u + i)) for i in range(SEEDS)]
        for i, metrics in enumerate(batched.update(batches, 5_000 + 2 * u)):
            got[i].append(metrics)
        for name, singles in runs.items():
            for i, single in enumerate(singles):
                want[name][i].append(single.update(batches[i], 5_000 + 2 * u))
    gaps = {name: (max(metric_gap(got[i][:1], want[name][i][:1]) for i in range(SEEDS)),
                   max(metric_gap(got[i], want[name][i]) for i in range(SEEDS)),
                   max(drift(a, one, start) for a, one, start in zip(agents, singles, starts)))
            for name, singles in runs.items()}
    bounds = (FIRST_METRICS, BATCHED_METRICS, BATCHED_MOVES)
    assert all(gap <= bound for gap, bound in zip(gaps["one after another"], bounds)), gaps
    for case in CONTROLS:
        assert all(gap > bound for gap, bound in zip(gaps[case], bounds)), (case, gaps)
    for a, single in zip(agents, runs["one after another"]):  # the agents' Adam: the stacks' views
        for opt in ("model_opt", "actor_opt"):
            ours, theirs = getattr(a, opt), getattr(single, opt)
            params = zip((p for g in ours.param_groups for p in g["params"]),
                         (p for g in theirs.param_groups for p in g["params"]), strict=True)
            for p, q in params:
                mine, its = ours.state[p], theirs.state[q]
                assert float(mine["step"]) == float(its["step"]) == 3
                scale = its["exp_avg"].norm()
                gap = (mine["exp_avg"] - its["exp_avg"]).norm() / scale.clamp(min=1e-12)
                assert gap <= BATCHED_MOVES or scale < 1e-12, (opt, float(gap))
        # a seed's snapshot: its own networks, shaped as a single run's
        encoder = single.state_dict()["encoder"]
        assert all(v.shape == encoder[k].shape for k, v in a.state_dict()["encoder"].items())


def test_the_batched_seeds_draw_from_each_seeds_generator():
    """SeedBatch draws each seed's shifts and noise from that seed's generator (Agent.draw): two
    seeds with the same weights and batch but other generators update differently, and each
    generator moves on as a single update of its seed moves it."""
    agent = agent_of("drq", torch.device("cpu"))
    twin = copy.deepcopy(agent)
    twin.rng.manual_seed(1)
    single = copy.deepcopy(twin)
    metrics = speed.SeedBatch([agent, twin]).update([fake_batch(seed=1)] * 2, 5_000)
    assert float(metrics[0]["critic_loss"]) != float(metrics[1]["critic_loss"])
    single.update(fake_batch(seed=1), 5_000)
    assert torch.equal(single.rng.get_state(), twin.rng.get_state())


# ---------------------------------------------------------------- DRAWS_INSIDE
@pytest.mark.parametrize("method", list(train.METHODS))
def test_draws_inside_names_exactly_the_methods_whose_update_draws(method, device):
    """The generator's state after the update's draws (Agent.draw) and after its learn(): it moves
    on inside learn() exactly for the methods of DRAWS_INSIDE (MAE's patches, CURL's shifts), which
    a CUDA graph would replay unchanged and vmap cannot draw."""
    agent = train.make_agent(small_cfg(method=method), 2, device)
    drawn, draw = {}, agent.draw

    def recorded(n):
        noise = draw(n)
        drawn["state"] = agent.rng.get_state()
        return noise
    agent.draw = recorded
    agent.update(numpy_batch(n=4), 5_000)
    assert "state" in drawn
    draws_inside = not torch.equal(agent.rng.get_state(), drawn["state"])
    assert draws_inside == (method in speed.DRAWS_INSIDE)


def test_draws_inside_names_only_methods():
    assert set(speed.DRAWS_INSIDE) <= set(train.METHODS)


# ---------------------------------------------------------------- --cuda-graph
@pytest.mark.parametrize("label", ["drq", "sear", "drq+drm"])
def test_the_cuda_graph_replays_the_plain_update_to_the_bit(label, device, monkeypatch):
    """GraphedUpdate (--cuda-graph) against the plain update on the same weights, batches and
    draws: the same kernels (cuDNN's deterministic ones for both), so every metric and every weight
    after 3 updates is equal, bit for bit. Needs SEAR_TEST_DEVICE=cuda (DEVELOPERS.md)."""
    if device.type != "cuda":
        pytest.skip("a CUDA graph needs a GPU: SEAR_TEST_DEVICE=cuda")
    monkeypatch.setattr(torch.backends.cudnn, "deterministic", True)
    monkeypatch.setattr(torch.backends.cudnn, "benchmark", False)
    # the same weights and generator, each built after torch.manual_seed(0)
    plain, graphed = agent_of(label, device), agent_of(label, device)
    graphed.learn = speed.GraphedUpdate(graphed)
    for i in range(3):
        batch = fake_batch(seed=i, device=device)
        metrics = []
        for agent in (plain, graphed):
            agent.rng.manual_seed(100 + i)
            metrics.append(agent.update(batch, 5_000 + 2 * i))
        assert metrics[0].keys() == metrics[1].keys()
        assert all(torch.equal(metrics[0][k], metrics[1][k]) for k in metrics[0]), (i, metrics)
    ours, theirs = parameters(graphed), parameters(plain)
    assert all(torch.equal(ours[n], theirs[n]) for n in theirs)


@pytest.mark.parametrize("tf32", [False, True])
def test_the_batched_seeds_run_whatever_tf32_is_set_to(tf32):
    """sear.py sets TF32 at start (off by default): the seeds' vmapped convolutions run after either."""
    from harness import process
    process.set_tf32(tf32)
    try:
        agents = []
        for seed in range(2):
            torch.manual_seed(seed)
            agents.append(train.make_agent(small_cfg(method="drq"), 2, torch.device("cpu")))
        metrics = speed.SeedBatch(agents).update([fake_batch(seed=1), fake_batch(seed=2)], 5000)
        assert all(torch.isfinite(m["critic_loss"]) for m in metrics)
    finally:
        process.set_tf32(False)


@pytest.mark.parametrize("method", ["sear", "ef"])
def test_staged_ring_writes_equal_the_plain_ones(method, device):
    """StagedWrites (rings on a GPU: every seed's writes of a step in one copy) leaves the rings as
    ReplayBuffer.put leaves them: episodes starting, terminating and the ring wrapping; several
    flushes pending at once (an episode's first step and a step)."""
    import numpy as np
    rng = np.random.default_rng(0)
    cfg = train.Config(method=method, frame_stack=3, nstep=2)

    def rings():
        return [train.make_replay(cfg, 7, (3, 8, 8), 2, 3, 2, 0.99, device=device) for _ in range(3)]
    plain, staged = rings(), rings()
    flush = speed.stage_writes(staged) if staged[0].device.type != "cpu" else speed.StagedWrites(staged).flush
    for t in range(40):
        obs = [{"pixels": rng.integers(0, 256, (9, 8, 8), dtype=np.uint8),
                "mask": rng.integers(0, 2, (3, 8, 8))} for _ in range(3)]
        action, reward, end = rng.uniform(-1, 1, (3, 2)).astype(np.float32), rng.random(3), rng.random(3) < 0.1
        for buffers in (plain, staged):
            for i, b in enumerate(buffers):
                if t % 9 == 0:
                    b.add_first(obs[i])
                b.add(action[i], reward[i], end[i], obs[i])
        if t % 5:
            flush()
    flush()
    for p, s in zip(plain, staged):
        assert p.t == s.t and (p.episodes == s.episodes).all()
        for name in sear.ReplayBuffer.ARRAYS:
            assert torch.equal(getattr(p, name), getattr(s, name)), name
        times = rng.integers(0, 5, 4)
        for a, b in zip(p.batch(times, np.random.default_rng(1)), s.batch(times, np.random.default_rng(1))):
            assert torch.equal(a, b)


def test_a_run_with_staged_ring_writes_writes_the_plain_runs_rows(tmp_path):
    """The loop with StagedWrites (what rings on a GPU take; here on the host) trains, logs and
    snapshots what the plain writes do: the same train.csv and the same saved rings."""
    import os
    import subprocess
    import sys
    from tests.test_cli import ROOT
    driver = ("import sys, train\nfrom harness import speed\n"
              "if sys.argv.pop(1) == 'staged':\n"
              "    speed.stage_writes = lambda buffers: speed.StagedWrites(buffers).flush\n"
              "sys.exit(train.main(sys.argv[1:]))\n")
    dirs = {}
    for how in ("plain", "staged"):
        (tmp_path / how).mkdir()
        r = subprocess.run([sys.executable, "-c", driver, how, "--run-root", str(tmp_path / how / "runs"),
                            "--env", "walker-walk", "--method", "sear", "--seed", "3", "--frames", "48",
                            "--save-buffer", *tiny("sear")], capture_output=True, text=True, timeout=600,
                           cwd=ROOT, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
        assert r.returncode == 0, r.stderr[-2000:]
        dirs[how] = only_run_dir(tmp_path / how)
    ignore = {"wall_time", "fps"}
    table = [{k: v for k, v in x.items() if k not in ignore} for x in rows(dirs["plain"] / "train.csv")]
    assert table[-1]["critic_loss"] != ""
    assert table == [{k: v for k, v in x.items() if k not in ignore} for x in rows(dirs["staged"] / "train.csv")]
    import numpy as np
    nets = [torch.load(dirs[how] / "snapshot.pt", weights_only=False)["agent"]["critic"] for how in dirs]
    assert all(torch.equal(nets[0][k], nets[1][k]) for k in nets[0])
    with np.load(dirs["plain"] / "buffer.npz") as a, np.load(dirs["staged"] / "buffer.npz") as b:
        assert sorted(a.files) == sorted(b.files) and int(a["t"]) > 20
        assert all(np.array_equal(a[k], b[k]) for k in a.files)
