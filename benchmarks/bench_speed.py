"""The speed layer's table (harness/speed.py): per method, the plain update's s/update and kernels
per update, then each speed device's gain over it, all measured in this run in alternating rounds.

    python benchmarks/bench_speed.py                    # CUDA: drq and sear at batch 256, 8 seeds
    python benchmarks/bench_speed.py --methods sear --seeds-batch 4 --rounds 5 --updates 30
    python benchmarks/bench_speed.py --quick            # the CPU, tiny networks: what runs there
    python benchmarks/bench_speed.py --quick --cpu-compile   # and --compile (a minute a method)

Rows of a method, each in fp32 and with TF32 where TF32 applies (CUDA's convolutions and matmuls):

  plain                 sear.py's update as written: eager, fp32, the batch already on the device
  --cuda-graph          the update captured once (speed.GraphedUpdate) and replayed
  --compile             agent.learn through torch.compile
  --compile + graph     both, as a CUDA run takes them by default
  host ring             a batch sampled from a filled sear.ReplayBuffer on the host, copied to
                        the GPU
  --replay-device cuda  the same batch sampled from the same ring on the GPU
  in turn               a batch sampled on the host, then the plain update on it
  --prefetch            the same with speed.Prefetcher sampling the next batch beside the update
  one by one            N seeds' plain updates, one agent.update after another (per seed-update)
  --batch-seeds N       the same N seeds as one speed.SeedBatch.update (per seed-update)

A gain is the reference's time over the row's, the reference named in the row (the plain update in
fp32 for the update's devices: their TF32 column is the device and TF32 together). The first call
(compiling, capturing, cuDNN's search) is timed apart and is in no gain. Kernels: CUDA kernels per
call as torch.profiler sees them; a CUDA graph's own launches said beside them.
"""
from __future__ import annotations

import gc
import os
import statistics
import sys
import time
from typing import Callable, NamedTuple

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_agent  # noqa: E402
from harness import cli, speed  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402

STEP = 5_000  # the agent step of every timed update
EPISODE = 500  # steps per episode of the filled ring: dm_control's 1000 frames at action repeat 2
TINY = dict(latent_dim=64, hidden_dim=32, feature_dim=16)  # --quick's networks
GRAPH_LAUNCHES = ("cudaGraphLaunch", "cuGraphLaunch")
NEEDS_CUDA = "needs CUDA"
MODES = ("plain", "graph", "compile", "compile+graph")
LABELS = ("plain: eager, fp32, the batch on the device", "--cuda-graph", "--compile",
          "--compile + --cuda-graph")


class Contender(NamedTuple):
    """One call of what a row times, and whether TF32 is on while it runs."""
    call: Callable[[], object]
    tf32: bool = False


# ------------------------------------------------------------------------------------------------
# Timing and kernel counts
# ------------------------------------------------------------------------------------------------
def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def set_tf32(device: torch.device, on: bool) -> None:
    if device.type == "cuda":
        cli.set_tf32(on)


def timed(c: Contender, calls: int, warmup: int, device: torch.device) -> float:
    """Seconds per call of `calls` calls after `warmup` untimed ones; the device caught up before
    and after (the calls themselves do not wait for it, as in training)."""
    set_tf32(device, c.tf32)
    for _ in range(warmup):
        c.call()
    sync(device)
    start = time.perf_counter()
    for _ in range(calls):
        c.call()
    sync(device)
    return (time.perf_counter() - start) / calls


def alternate(contenders: dict, rounds: int, calls: int, warmup: int, device) -> tuple[dict, dict]:
    """Each contender's median seconds per call over `rounds` rounds, their order rotating every
    round; and {name: why} of those that raised (left out of the rounds after)."""
    times, failed, names = {n: [] for n in contenders}, {}, list(contenders)
    for r in range(rounds):
        for name in names[r % len(names):] + names[:r % len(names)]:
            if name in failed:
                continue
            try:
                times[name].append(timed(contenders[name], calls, warmup, device))
            except Exception as e:  # a compiler, graph or memory failure: said in its row
                failed[name] = cli.first_sentence(e)[:120]
    set_tf32(device, False)
    return {n: statistics.median(t) for n, t in times.items() if t and n not in failed}, failed


def first_call(c: Contender, device: torch.device) -> float:
    """Seconds of the first call (what compiles, captures or searches kernels), device included."""
    set_tf32(device, c.tf32)
    sync(device)
    start = time.perf_counter()
    c.call()
    sync(device)
    set_tf32(device, False)
    return time.perf_counter() - start


def count_kernels(events, calls: int) -> tuple[float, float]:
    """(CUDA kernels, CUDA graph launches) per call in torch.profiler's events (FunctionEvents: only
    `name`, `device_type` and `activity_type` are read). A kernel is a device event of activity
    "kernel" (where a torch gives no activity: any device event but a copy or a memset)."""
    kernels = launches = 0
    for e in events:
        on_device = getattr(e.device_type, "name", str(e.device_type)) != "CPU"
        activity = getattr(e, "activity_type", None)
        if on_device and (activity == "kernel" if activity else
                          not e.name.startswith(("Memcpy", "Memset"))):
            kernels += 1
        elif not on_device and e.name in GRAPH_LAUNCHES:
            launches += 1
    return kernels / calls, launches / calls


def profiled(c: Contender, device: torch.device, calls: int = 3) -> str:
    """The kernels column: CUDA kernels per call (and graph launches) of `calls` calls."""
    if device.type != "cuda":
        return NEEDS_CUDA
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    try:
        set_tf32(device, c.tf32)
        with torch.profiler.profile(activities=activities) as prof:
            for _ in range(calls):
                c.call()
            sync(device)
        kernels, launches = count_kernels(prof.events(), calls)
    except Exception as e:
        return f"profiler failed: {cli.first_sentence(e)[:60]}"
    finally:
        set_tf32(device, False)
    return kernels_cell(kernels, launches)


def start_profiler(device: torch.device) -> None:
    """One short CUDA profile before any graph is captured: the profiler's tracing (CUPTI) is set
    up before the captures whose replays `profiled` counts later."""
    if device.type != "cuda":
        return
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=activities):
        torch.ones(8, device=device).sum()
        sync(device)


def kernels_cell(kernels: float, launches: float) -> str:
    graphs = f"{launches:g} graph launch{'' if launches == 1 else 'es'}"
    if not launches:
        return f"{kernels:.0f}"
    return f"{kernels:.0f} in {graphs}" if kernels else f"not seen ({graphs})"


# ------------------------------------------------------------------------------------------------
# What is timed
# ------------------------------------------------------------------------------------------------
def make_agent(args, method: str, seed: int = 0):
    torch.manual_seed(seed)
    sizes = TINY if args.quick else {}
    cfg = train.Config(method=method, batch_size=args.batch_size, action_repeat=2, **sizes)
    return train.make_agent(cfg, args.action_dim, args.device)


def fake_batch(args, device, seed: int = 0) -> sear.Batch:
    """A batch of random frames and masks, on `device` as the ring there hands it."""
    batch = bench_agent.fake_batch(args.batch_size, args.action_dim, seed=seed)
    return bench_agent.device_batch(batch, device)


def update(agent, batch) -> Contender:
    return Contender(lambda: agent.update(batch, STEP))


def filled_ring(args, cfg) -> sear.ReplayBuffer:
    """A host ring of --ring-size steps, written full through add_first / add (episodes of EPISODE
    steps, frames from a few random ones): what sampling reads in a long run."""
    rng = np.random.default_rng(0)
    obs = [{"pixels": rng.integers(0, 256, (3 * cfg.frame_stack, 84, 84), dtype=np.uint8),
            "mask": rng.integers(0, 2, (cfg.frame_stack, 84, 84), dtype=np.uint8)}
           for _ in range(16)]
    actions = rng.uniform(-1, 1, (16, args.action_dim)).astype(np.float32)
    ring = sear.ReplayBuffer(args.ring_size, (3, 84, 84), args.action_dim, cfg.frame_stack,
                             cfg.nstep, cfg.discount)
    for t in range(args.ring_size):
        if t % EPISODE == 0:
            ring.add_first(obs[t % 16])
        else:
            ring.add(actions[t % 16], (t % 7) / 7, False, obs[t % 16])
    ring.add_first(obs[0])  # the last episode finished
    return ring


def device_ring(host: sear.ReplayBuffer, device: torch.device) -> sear.ReplayBuffer:
    """The host ring's copy on `device`: its arrays and episodes."""
    stack, gamma = host.stack, host.gamma
    ring = sear.ReplayBuffer(host.capacity, host.frame_shape, host.actions.shape[1], stack,
                             host.nstep, gamma, device=device)
    for name in sear.ReplayBuffer.ARRAYS:
        getattr(ring, name).copy_(getattr(host, name))
    ring.t, ring.episodes, ring.running = host.t, host.episodes.copy(), host.running
    return ring


def why_not_graphed(method: str) -> str | None:
    if method in speed.DRAWS_INSIDE:
        return f"not for {method}: it draws inside its update"
    return None


def why_not_batched(method: str) -> str | None:
    if method in (*speed.DRAWS_INSIDE, "ef"):
        return f"not for {method}: it updates seed by seed"
    return None


class Row(NamedTuple):
    device: str
    against: str
    cells: list  # [fp32 s, fp32 gain, TF32 s, TF32 gain]
    kernels: str = ""
    first: str = ""


def failure(failed: dict, key) -> str:
    return f"failed: {failed[key]}" if key in failed else ""


def tf32_settings(device: torch.device) -> tuple:
    """TF32 off, and on where it applies (CUDA)."""
    return (False, True) if device.type == "cuda" else (False,)


def gain(ref: float | None, s: float | None) -> str:
    return f"{ref / s:.2f}×" if ref and s else ""


def seconds(s: float | None, why: str = "") -> str:
    return f"{s:.5f}" if s is not None else why


# ------------------------------------------------------------------------------------------------
# The groups of rows
# ------------------------------------------------------------------------------------------------
def update_rows(args, method: str, batch) -> list[Row]:
    """plain, --cuda-graph, --compile, --compile + graph: fp32 and TF32, against plain fp32. Each
    mode and TF32 setting has an agent of its own (a graph keeps the kernels it was captured with),
    but plain's TF32 is the plain agent with TF32 on."""
    cuda, dev = args.device.type == "cuda", args.device
    settings = tf32_settings(dev)
    plain = make_agent(args, method)
    contenders = {("plain", tf32): update(plain, batch)._replace(tf32=tf32) for tf32 in settings}
    firsts, failed, why = {"plain": [first_call(contenders["plain", False], dev)]}, {}, {}
    for mode in MODES[1:]:
        if not cuda and "graph" in mode:
            why[mode] = NEEDS_CUDA
            continue
        if not cuda and not args.cpu_compile:
            why[mode] = "with --cpu-compile"
            continue
        if "graph" in mode and why_not_graphed(method):
            why[mode] = why_not_graphed(method)
            continue
        for tf32 in settings:
            agent = make_agent(args, method)
            on = {"compile": "on" if "compile" in mode else "off",
                  "cuda_graph": "on" if "graph" in mode else "off"}
            speed.speed_up(agent, cli.RunConfig(**on), dev)  # as a run sets them
            c = update(agent, batch)._replace(tf32=tf32)
            try:
                firsts.setdefault(mode, []).append(first_call(c, dev))
                contenders[mode, tf32] = c
            except Exception as e:  # a compiler or capture failure: said in its row
                failed[mode, tf32] = cli.first_sentence(e)[:120]
    costs, raised = alternate(contenders, args.rounds, args.updates, args.warmup, dev)
    failed.update(raised)
    ref, rows = costs.get(("plain", False)), []
    for mode, label in zip(MODES, LABELS):
        cells = []
        for tf32 in (False, True):
            key = (mode, tf32)
            reason = NEEDS_CUDA if tf32 and not cuda else why.get(mode) or failure(failed, key)
            s = costs.get(key)
            cells += [seconds(s, reason), gain(ref, s) if key != ("plain", False) else ""]
        kernels = profiled(contenders[mode, False], dev) if (mode, False) in contenders else ""
        kernels = kernels or (NEEDS_CUDA if not cuda else "")
        first = " / ".join(f"{x:.1f}" for x in firsts.get(mode, []))
        rows.append(Row(label, "" if mode == "plain" else "plain, fp32", cells, kernels, first))
    return rows


def ring_rows(args, host: sear.ReplayBuffer, full: bool) -> list[Row]:
    """A batch from the ring on the host (and its copy to the GPU) against one from the same ring
    on the device (`full`: on CUDA): sampling only, so fp32 alone (no arithmetic TF32 changes)."""
    dev, rng, na = args.device, np.random.default_rng(1), ["—", ""]
    copy = dev.type != "cpu"

    def from_host():
        batch = host.sample(args.batch_size, rng)
        return sear.Batch._make(x.to(dev) for x in batch) if copy else batch
    contenders = {"host": Contender(from_host)}
    if full:
        ring = device_ring(host, dev)
        contenders["device"] = Contender(lambda: ring.sample(args.batch_size, rng))
    costs, failed = alternate(contenders, args.rounds, args.updates, args.warmup, dev)
    label = f"host ring: sample {args.batch_size}" + (" + copy to the GPU" if copy else "")
    rows = [Row(label, "", [seconds(costs.get("host"), failure(failed, "host")), ""] + na)]
    label = "--replay-device cuda: sample on the GPU"
    if not full:
        return rows + [Row(label, "host ring", [NEEDS_CUDA, ""] + na)]
    s = costs.get("device")
    return rows + [Row(label, "host ring", [seconds(s, failure(failed, "device")),
                                            gain(costs.get("host"), s)] + na,
                       profiled(contenders["device"], dev))]


def prefetch_rows(args, method: str, host: sear.ReplayBuffer, full: bool) -> list[Row]:
    """The plain update on batches from the host ring: sampled in turn, and by speed.Prefetcher
    in its thread beside the update (`full`: on CUDA, where --prefetch is on by default)."""
    labels = ("in turn: sample on the host, then the plain update",
              "--prefetch: the next batch sampled beside the update")
    if not full:
        return [Row(labels[0], "", [NEEDS_CUDA, "", NEEDS_CUDA, ""]),
                Row(labels[1], "in turn, same column", [NEEDS_CUDA, "", NEEDS_CUDA, ""])]
    dev, agent, rng = args.device, make_agent(args, method), np.random.default_rng(2)
    cfg = agent.cfg
    pre = speed.Prefetcher(host, args.batch_size, np.random.default_rng(3), dev,
                           margin=cfg.frame_stack + 2 * cfg.update_every)
    try:
        contenders = {}
        for tf32 in tf32_settings(dev):
            contenders["turn", tf32] = Contender(
                lambda: agent.update(host.sample(args.batch_size, rng), STEP), tf32)
            contenders["prefetch", tf32] = Contender(lambda: agent.update(pre.next(), STEP), tf32)
        costs, failed = alternate(contenders, args.rounds, args.updates, args.warmup, dev)
    finally:
        pre.close()
    return pair_rows(labels, "in turn, same column", "turn", "prefetch", costs, failed)


def pair_rows(labels, against, ref_mode, mode, costs, failed, per: int = 1) -> list[Row]:
    """Two rows: the reference's times, then the device's and its gain, column by column."""
    rows = []
    for label, m in zip(labels, (ref_mode, mode)):
        cells = []
        for tf32 in (False, True):
            s = costs.get((m, tf32))
            s = None if s is None else s / per
            ref = costs.get((ref_mode, tf32))
            ref = None if ref is None else ref / per
            why = failure(failed, (m, tf32)) or NEEDS_CUDA
            cells += [seconds(s, why), gain(ref, s) if m == mode else ""]
        rows.append(Row(label, against if m == mode else "", cells))
    return rows


def seed_rows(args, method: str) -> list[Row]:
    """N seeds' plain updates one after another against speed.SeedBatch's one batched update, each
    seed on its own batch; per seed-update."""
    n, dev = args.seeds_batch, args.device
    labels = (f"one by one: {n} seeds' plain updates, per seed-update",
              f"--batch-seeds: {n} seeds as one SeedBatch.update, per seed-update")
    why = why_not_batched(method)
    if why:
        return [Row(labels[1], "one by one, same column", [why, "", why, ""])]
    batches = [fake_batch(args, dev, seed=i) for i in range(n)]
    alone = [make_agent(args, method, seed=i) for i in range(n)]
    together = speed.SeedBatch([make_agent(args, method, seed=i) for i in range(n)])

    def one_by_one():
        for agent, batch in zip(alone, batches):
            agent.update(batch, STEP)
    contenders = {}
    for tf32 in tf32_settings(dev):
        contenders["alone", tf32] = Contender(one_by_one, tf32)
        contenders["batched", tf32] = Contender(lambda: together.update(batches, STEP), tf32)
    costs, failed = alternate(contenders, args.rounds, max(1, args.updates // n), args.warmup, dev)
    return pair_rows(labels, "one by one, same column", "alone", "batched", costs, failed, per=n)


def method_table(args, method: str, host: sear.ReplayBuffer) -> list[Row]:
    rows = update_rows(args, method, fake_batch(args, args.device))
    rows += prefetch_rows(args, method, host, full=args.device.type == "cuda")
    rows += seed_rows(args, method)
    torch._dynamo.reset()  # dynamo's caches hold over agents: the next method starts afresh
    gc.collect()
    if args.device.type == "cuda":
        torch.cuda.empty_cache()
    return rows


HEADER = ("| method | device | against | fp32 s | fp32 gain | TF32 s | TF32 gain | kernels/call "
          "| first call s |\n|---|---|---|---|---|---|---|---|---|")
LEGEND = ("Gain: the reference's time / the row's, both measured above (the update's devices: "
          "against plain fp32, so their TF32 column is the device with TF32). First call: "
          "compiling, capturing or cuDNN's search, fp32 / TF32; in no gain.")


def print_rows(method: str, rows: list[Row]) -> None:
    for r in rows:
        cells = " | ".join([method, r.device, r.against, *r.cells, r.kernels, r.first])
        print(f"| {cells} |", flush=True)


def describe(args) -> str:
    dev = args.device
    where = (f"{torch.cuda.get_device_name(dev)}" if dev.type == "cuda"
             else f"the CPU, {torch.get_num_threads()} threads")
    nets = ("tiny networks (latent 64, hidden 32, feature 16)" if args.quick
            else "the paper's networks")
    return (f"## The speed layer: batch {args.batch_size}, {nets}, {args.action_dim} actions, on "
            f"{where} (torch {torch.__version__})\n\n{args.rounds} alternating rounds x "
            f"{args.updates} calls after {args.warmup}, median; the seeds' rows "
            f"{max(1, args.updates // args.seeds_batch)} calls a round; a ring of {args.ring_size} "
            f"steps; {bench_agent.load()}\n")


# ------------------------------------------------------------------------------------------------
# The command line
# ------------------------------------------------------------------------------------------------
def build_parser() -> cli.OneLineParser:
    p = cli.OneLineParser(prog="bench_speed.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", nargs="+", default=["drq", "sear"], choices=list(train.METHODS))
    p.add_argument("--quick", action="store_true",
                   help="the CPU with tiny networks at batch 8: what runs on a CPU")
    p.add_argument("--cpu-compile", action="store_true",
                   help="with --quick: time --compile too (inductor builds C++ kernels, about a "
                        "minute a method)")
    p.add_argument("--batch-size", type=cli.whole_number, help="default 256, --quick 8")
    p.add_argument("--seeds-batch", type=cli.whole_number, metavar="N",
                   help="seeds of the batched update (default 8, --quick 4)")
    p.add_argument("--rounds", type=cli.whole_number,
                   help="alternating rounds (default 3, --quick 2)")
    p.add_argument("--updates", type=cli.whole_number,
                   help="timed calls a round (default 20, --quick 3; the seeds' rows: this / N)")
    p.add_argument("--warmup", type=cli.whole_number, default=1,
                   help="untimed calls before each round's timed ones")
    p.add_argument("--ring-size", type=cli.whole_number,
                   help=f"steps of the filled ring (default 100000, --quick 2000; at least "
                        f"{2 * EPISODE})")
    p.add_argument("--action-dim", type=cli.whole_number, default=6,
                   help="action size (walker's 6)")
    return p


def parse(argv=None):
    """The arguments, checked; a bad one raises cli.ConfigError (one line)."""
    args = build_parser().parse_args(argv)
    quick = args.quick
    for name, full, small in (("batch_size", 256, 8), ("seeds_batch", 8, 4), ("rounds", 3, 2),
                              ("updates", 20, 3), ("ring_size", 100_000, 2_000)):
        if getattr(args, name) is None:
            setattr(args, name, small if quick else full)
    for name, low in (("batch_size", 1), ("seeds_batch", 2), ("rounds", 1), ("updates", 1),
                      ("warmup", 0), ("ring_size", 2 * EPISODE), ("action_dim", 1)):
        if getattr(args, name) < low:
            raise cli.ConfigError(f"--{name.replace('_', '-')} must be at least {low}, "
                                  f"not {getattr(args, name)}")
    if args.cpu_compile and not quick:
        raise cli.ConfigError("--cpu-compile goes with --quick (on CUDA --compile is always timed)")
    if args.cpu_compile and not cli.cxx_compiler():
        raise cli.ConfigError("--cpu-compile needs a C++ compiler (inductor builds its CPU kernels "
                              "with one): no g++, c++ or clang++ found")
    if not quick and not torch.cuda.is_available():
        raise cli.ConfigError("torch sees no CUDA device; on a CPU run --quick")
    args.device = torch.device("cpu" if quick else "cuda")
    return args


def main(argv=None) -> int:
    try:
        args = parse(argv)
    except cli.ConfigError as e:
        print(f"bench_speed.py: error: {e}", file=sys.stderr)
        return 2
    cli.configure_allocator()
    torch.set_num_threads(cli.default_threads())
    cli.set_tf32(False)
    start_profiler(args.device)
    print(describe(args))
    print(HEADER, flush=True)
    host = filled_ring(args, make_agent(args, args.methods[0]).cfg)
    print_rows("(any)", ring_rows(args, host, full=args.device.type == "cuda"))
    for method in args.methods:
        print_rows(method, method_table(args, method, host))
    print(f"\n{LEGEND} {bench_agent.load(' (at the end)')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
