"""Agent benchmark, every number measured in one run of this script: the machine's GEMM peaks, the
replay footprint, each method's update (FLOPs, s/update, achieved GFLOP/s, share of peak) in fp32
and bf16, the split of a training step into env / act / sample / update, and optionally the official
DrQ-v2 update timed against this project's drq update in the same process.

    python benchmarks/bench_agent.py                                  # batch 256, drq and sear, fp32 and bf16
    python benchmarks/bench_agent.py --methods drq sear ae mae curl --updates 5
    python benchmarks/bench_agent.py --methods drq drq+drm sear sear+drm --split-steps 0   # what --drm costs
    python benchmarks/bench_agent.py --official /path/to/facebookresearch/drqv2 --rounds 7
    python benchmarks/bench_agent.py --compare-allocators             # glibc default vs tunables vs mallopt
    python benchmarks/bench_agent.py --breakdown --split-steps 0      # + time and GFLOP/s per op class
    python benchmarks/bench_agent.py --compare-layouts --rounds 3 --updates 2   # channels_last vs NCHW
    python benchmarks/bench_agent.py --compare-compile --official DIR --precisions fp32   # eager vs --compile (TF32 off/on on CUDA)
    python benchmarks/bench_agent.py --snapshot runs/<run dir> --profile --subnormals     # trained vs fresh
    python benchmarks/bench_agent.py --device cuda --profile --precisions fp32 --split-steps 0   # kernels, syncs, H2D
    python benchmarks/bench_agent.py --snapshot runs/<run dir> --threads 1 --flush-denormal   # + subnormals flushed

Synthetic batches (no rendering) for the update table, so those are the learner's cost alone. Times
are wall clock at the thread count shown; on a shared machine, compare ratios taken in the same run.
"""
import argparse
import copy
import functools
import os
import resource
import subprocess
import sys
import time
import types
from typing import NamedTuple

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402
from harness import experiment  # noqa: E402
from harness import runenvs  # noqa: E402
from harness import speed  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402

try:
    from methods import baselines  # noqa: E402, F401  # registers the baseline methods into sear.METHODS
except ImportError:
    pass


def gemm_size(device):
    """(n, reps) of the peak's square matmul: a GPU needs far larger products than 2048^3 to reach it."""
    return (8192, 20) if torch.device(device).type == "cuda" else (2048, 6)


def gemm_gflops(dtype, device="cpu"):
    """Square matmul throughput on `device`: the peak the convolutions are measured against."""
    n, reps = gemm_size(device)
    a, b = (torch.randn(n, n, dtype=dtype, device=device) for _ in range(2))
    a @ b
    sync(device)
    start = time.perf_counter()
    for _ in range(reps):
        a @ b
    sync(device)
    return 2 * n ** 3 * reps / (time.perf_counter() - start) / 1e9


def sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def cpu_flags() -> set:
    """The CPU's feature flags as Linux lists them (x86 "flags", Arm "Features"); empty elsewhere."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("flags", "Features"):
                    return set(value.split())
    except OSError:
        pass
    return set()


# oneDNN's ISA names (ONEDNN_MAX_CPU_ISA) from which on it has bf16 instructions.
ONEDNN_BF16_ISAS = ("AVX512_CORE_BF16", "AVX512_CORE_AMX", "AVX10", "ALL")


def native_bf16() -> tuple[bool, str]:
    """(whether this CPU computes bf16 natively, why): x86 with AVX-512's bf16 extension or AMX, Arm with
    its bf16 instructions, unless ONEDNN_MAX_CPU_ISA keeps oneDNN below them. torch's CPU capability
    ('AVX512', 'AVX2', 'DEFAULT') does not say it: an AVX-512 CPU without avx512_bf16 converts too.
    Without native bf16, oneDNN emulates it: a bf16 2048^3 matmul ran at ~1 GFLOP/s against 55-130
    fp32 on a 2-core AVX2 EPYC, and bf16 updates slow down alike. SEAR_ASSUME_NO_BF16=1 answers no, to
    try that path on a machine that has bf16."""
    capability = torch.backends.cpu.get_cpu_capability()
    if os.environ.get("SEAR_ASSUME_NO_BF16") == "1":
        return False, f"SEAR_ASSUME_NO_BF16=1 (CPU capability {capability})"
    isa = os.environ.get("ONEDNN_MAX_CPU_ISA", "").upper()
    if isa and not isa.startswith(ONEDNN_BF16_ISAS):
        return False, f"ONEDNN_MAX_CPU_ISA={isa} (CPU capability {capability})"
    native = sorted(cpu_flags() & {"avx512_bf16", "amx_bf16", "bf16"})
    if native:
        return True, f"CPU capability {capability}, {' '.join(native)}"
    return False, f"CPU capability {capability}, no avx512_bf16, amx_bf16 or Arm bf16 in /proc/cpuinfo"


def choose_precisions(args) -> None:
    """args.precisions when not given: fp32 and bf16, but fp32 alone on a CPU that emulates bf16 (one
    line says so); given, as given, with a line when bf16 is emulated."""
    native, why = native_bf16() if torch.device(args.device).type == "cpu" else (True, "")
    if args.precisions is None:
        args.precisions = ["fp32", "bf16"] if native else ["fp32"]
        if not native:
            print(f"bf16: skipped, this CPU emulates it ({why}); --precisions bf16 times it anyway\n")
    elif "bf16" in args.precisions and not native:
        print(f"bf16: emulated on this CPU ({why}): its GEMM peak and updates take many times fp32's\n")


def fake_batch(batch_size, action_dim=6, seed=0):
    rng = np.random.default_rng(seed)
    n = batch_size
    return (rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8), rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8),
            rng.uniform(-1, 1, (n, action_dim)).astype(np.float32), rng.normal(size=(n, 1)).astype(np.float32),
            np.full((n, 1), 0.99 ** 3, np.float32), rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8),
            rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8))


def device_batch(batch, device):
    """The batch as the replay on the run's device hands it to the update: tensors already there (uint8
    frames and masks), so a timed update copies nothing from the host."""
    return sear.Batch._make(torch.as_tensor(x).to(device) for x in batch)


def make_agent(method, precision, batch_size, device="cpu", action_dim=6):
    """method: a sear.py method, or METHOD+drm for it with --drm; precision bf16 set on its networks
    as a run sets it (speed.bf16)."""
    method, drm_flag = cli.split_method_label(method)
    cfg = train.Config(method=method, batch_size=batch_size, action_repeat=2, precision=precision, drm=bool(drm_flag))
    agent = train.make_agent(cfg, action_dim, torch.device(device))
    if precision == "bf16":
        speed.bf16(agent)
    return agent


def time_updates(agent, batch, updates):
    agent.update(batch, step=5_000)  # warm-up: allocator, oneDNN kernel selection
    start = time.perf_counter()
    for _ in range(updates):
        agent.update(batch, step=5_000)
    sync(agent.device)
    return (time.perf_counter() - start) / updates


def update_flops(agent, batch):
    with FlopCounterMode(display=False) as counter:
        agent.update(batch, step=5_000)
    return counter.get_total_flops()


def peak_rss_gb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # KB on Linux


def update_table(args, peaks):
    batch = device_batch(fake_batch(args.batch_size), args.device)
    print(f"## Updates at batch {args.batch_size} on {args.device} ({torch.get_num_threads()} threads), "
          f"{args.updates} timed updates each\n")
    print("| method | precision | GFLOP/update | s/update | GFLOP/s | share of GEMM peak | peak RSS so far |")
    print("|---|---|---|---|---|---|---|")
    results = {}
    for precision in args.precisions:
        for method in args.methods:
            agent = make_agent(method, precision, args.batch_size, args.device)
            flops = update_flops(agent, batch)
            seconds = time_updates(agent, batch, args.updates)
            results[method, precision] = (flops, seconds)
            rate = flops / seconds / 1e9
            print(f"| {method} | {precision} | {flops / 1e9:.1f} | {seconds:.3f} | {rate:.0f} | "
                  f"{100 * rate / peaks[precision]:.0f}% | {peak_rss_gb():.2f} GB |", flush=True)
            del agent
    if "drq" in args.methods:
        print("\n| method | precision | time ratio to drq | FLOP ratio to drq | time ratio / FLOP ratio |")
        print("|---|---|---|---|---|")
        for (method, precision), (flops, seconds) in results.items():
            if method != "drq":
                f0, s0 = results["drq", precision]
                print(f"| {method} | {precision} | {seconds / s0:.2f} | {flops / f0:.2f} | "
                      f"{(seconds / s0) / (flops / f0):.2f} |")
    print()


# The ops that carry an update's FLOPs, by the names FlopCounterMode and the profiler give them.
FLOP_OPS = {"convolution": "conv forward", "convolution_backward": "conv backward",
            "mm": "matmul", "addmm": "matmul", "bmm": "matmul"}


def op_breakdown(args, peaks):
    """Where an update's time goes: per op class, its FLOPs (FlopCounterMode) and wall time (the
    profiler's inclusive CPU time of that op on the calling thread), and the rest (memory-bound ops:
    shift, ReLU, layout copies, optimiser, losses). The last column bounds what the update can reach
    with the rest at zero: the FLOP ops' own speed."""
    batch = device_batch(fake_batch(args.batch_size), args.device)
    print(f"## Where an update's time goes (batch {args.batch_size}, {torch.get_num_threads()} threads, one profiled update)\n")
    print("| method | precision | op class | GFLOP | seconds | GFLOP/s | share of GEMM peak |")
    print("|---|---|---|---|---|---|---|")
    for precision in args.precisions:
        for method in args.methods:
            agent = make_agent(method, precision, args.batch_size, args.device)
            with FlopCounterMode(display=False) as counter:
                agent.update(batch, step=5_000)
            flops = {}
            for op, n in counter.get_flop_counts()["Global"].items():
                name = FLOP_OPS.get(str(op).split(".")[-1])
                if name:
                    flops[name] = flops.get(name, 0) + n
            time_updates(agent, batch, 1)  # warm
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
                start = time.perf_counter()
                agent.update(batch, step=5_000)
                total = time.perf_counter() - start
            seconds = {}
            for event in prof.key_averages():
                name = FLOP_OPS.get(event.key.removeprefix("aten::"))
                if name:
                    seconds[name] = seconds.get(name, 0) + event.cpu_time_total / 1e6
            peak = peaks[precision]
            for name in ("conv forward", "conv backward", "matmul"):
                f, t = flops.get(name, 0), seconds.get(name, 0)
                if t:
                    print(f"| {method} | {precision} | {name} | {f / 1e9:.1f} | {t:.3f} | {f / t / 1e9:.0f} | "
                          f"{100 * f / t / 1e9 / peak:.0f}% |")
            f_all, t_ops = sum(flops.values()), sum(seconds.values())
            print(f"| {method} | {precision} | everything else | 0 | {total - t_ops:.3f} | | |")
            print(f"| {method} | {precision} | **update (profiled)** | {f_all / 1e9:.1f} | {total:.3f} | "
                  f"{f_all / total / 1e9:.0f} | {100 * f_all / total / 1e9 / peak:.0f}% "
                  f"(FLOP ops alone: {100 * f_all / t_ops / 1e9 / peak:.0f}%) |", flush=True)
            del agent
    print()


def step_split(args):
    """One real training step, part by part: env.step, agent.act, replay sample, agent.update
    (an update every `update_every` steps, as in training; the table gives the per-step share)."""
    cfg = train.Config(env=args.env, method=args.split_method, batch_size=args.batch_size, precision=args.precisions[0],
                      render_quality="fast", replay_size=2_000)
    train_env, eval_env = runenvs.make_envs(cfg, sear.METHODS[cfg.method].uses_mask)
    eval_env.close()
    agent = train.make_agent(cfg, train_env.action_space.shape[0], torch.device(args.device))
    if cfg.precision == "bf16":
        speed.bf16(agent)
    buffer = sear.ReplayBuffer(cfg.replay_size, (3, 84, 84), train_env.action_space.shape[0], cfg.frame_stack,
                               cfg.nstep, cfg.discount)
    rng = np.random.default_rng(0)
    obs, _ = train_env.reset(seed=0)
    buffer.add_first(obs)
    times = {"env": [], "act": [], "sample": [], "update": []}
    step, timed = 0, 0
    while timed < args.split_steps:
        t0 = time.perf_counter()
        action = agent.act(obs["pixels"], obs["mask"], step, eval_mode=False).cpu().numpy()
        t1 = time.perf_counter()
        obs, reward, terminated, truncated, _ = train_env.step(action)
        buffer.add(action, reward, terminated, obs)
        if terminated or truncated:
            obs, _ = train_env.reset(seed=step)
            buffer.add_first(obs)
        t2 = time.perf_counter()
        # The first steps only fill the buffer, until an episode has ended (replay draws ended episodes).
        if step >= args.split_warmup and buffer.can_sample():
            timed += 1
            times["act"].append(t1 - t0)
            times["env"].append(t2 - t1)
            if step % cfg.update_every == 0:
                t3 = time.perf_counter()
                batch = buffer.sample(cfg.batch_size, rng)
                t4 = time.perf_counter()
                agent.update(batch, step)
                t5 = time.perf_counter()
                times["sample"].append(t4 - t3)
                times["update"].append(t5 - t4)
        step += 1
    train_env.close()
    per_step = {k: sum(v) / args.split_steps for k, v in times.items()}
    total = sum(per_step.values())
    print(f"## One training step on {args.env} ({args.split_method}, batch {args.batch_size}, "
          f"{args.precisions[0]}, fast render, update every {cfg.update_every} steps; {args.split_steps} steps)\n")
    print("| part | ms per step | share |\n|---|---|---|")
    for k, v in per_step.items():
        print(f"| {k} | {1000 * v:.1f} | {100 * v / total:.1f}% |")
    print(f"| total | {1000 * total:.1f} | |\n")


def load_official(path):
    """The official DrQ-v2 agent from a checkout of facebookresearch/drqv2 (bring it with any git
    client; it is not part of this project). Its modules import hydra and omegaconf for config
    plumbing the agent does not use: stand-ins are registered when they are not installed."""
    for name in ("hydra", "omegaconf"):
        try:
            __import__(name)
        except ImportError:
            stub = types.ModuleType(name)
            stub.OmegaConf = None
            sys.modules[name] = stub
    sys.path.insert(0, os.path.abspath(path))
    import drqv2
    return drqv2


def official_update(args, batch):
    """update(i): one update of the official DrQ-v2 agent on `batch`, with this project's drq settings
    (batch, lr 1e-4, feature 50, hidden 1024, tau 0.01, clip 0.3)."""
    drqv2 = load_official(args.official)
    theirs = drqv2.DrQV2Agent((9, 84, 84), (6,), torch.device(args.device), lr=1e-4, feature_dim=50, hidden_dim=1024,
                              critic_target_tau=0.01, num_expl_steps=2000, update_every_steps=2,
                              stddev_schedule="linear(1.0,0.1,500000)", stddev_clip=0.3, use_tb=False)
    official_batch = (batch[0], batch[2], batch[3], batch[4], batch[5])  # obs, action, reward, discount, next_obs
    replay = iter(lambda: official_batch, None)

    def update(i):
        theirs.update(replay, 4_000)  # step % update_every == 0: every call updates
        sync(args.device)
    return update


def our_update(agent, batch, device):
    batch = device_batch(batch, device)

    def update(i):
        agent.update(batch, step=5_000)
        sync(device)
    return update


def official_comparison(args):
    """The official update and this project's drq update, alternating in one process on the same batch."""
    batch = fake_batch(args.batch_size)
    costs = alternate({"official": official_update(args, batch),
                       "ours": our_update(make_agent("drq", "fp32", args.batch_size, args.device), batch, args.device)},
                      args.rounds, args.updates)
    print(f"## Official DrQ-v2 update vs this project's drq update (batch {args.batch_size}, fp32, "
          f"{torch.get_num_threads()} threads, alternating, {args.rounds} rounds x {args.updates} updates)\n")
    print("| round | official s/update | ours s/update | official / ours (>1: ours faster) |\n|---|---|---|---|")
    ratios = []
    for i, (t, o) in enumerate(zip(costs["official"], costs["ours"])):
        ratios.append(t.wall / o.wall)
        print(f"| {i + 1} | {t.wall:.3f} | {o.wall:.3f} | {ratios[-1]:.2f} |")
    print(f"\nmedian official/ours {np.median(ratios):.2f}, range {min(ratios):.2f}-{max(ratios):.2f}; {load()}\n")


def tf32_update(update, on: bool):
    """`update` with TF32 set as asked before every call (it is process-wide: contenders alternate)."""
    def run(i):
        cli.set_tf32(on)
        update(i)
    return run


def compile_comparison(args):
    """--compare-compile: each method's update eager (the reference) and through --compile (on CUDA
    replayed as a CUDA graph), on CUDA each with TF32 off (the default) and on, and for drq with
    --official the official update, alternating rounds on the same batch in this process; the
    compiling (the first two updates, at two step numbers) timed apart. A mode that fails is reported
    and left out."""
    batch = fake_batch(args.batch_size, args.action_dim)
    cuda = torch.device(args.device).type == "cuda"
    print(f"## Eager vs --compile{' (a CUDA graph), TF32 off and on' if cuda else ''} (batch {args.batch_size}, "
          f"{torch.get_num_threads()} threads on {args.device}, {args.rounds} alternating rounds x {args.updates} "
          f"updates, median; compile time apart); {load()}\n")
    # The ratios are of CPU seconds (all threads of this process): on a shared machine wall seconds count
    # the time other processes hold the cores.
    header = head = ("| method | precision | mode | s/update (wall) | CPU s/update | eager / this (CPU) | "
                     "official / this (CPU) | compile s |\n|---|---|---|---|---|---|---|---|")
    for precision in args.precisions:
        for method in args.methods:
            eager = make_agent(method, precision, args.batch_size, args.device, args.action_dim)
            contenders, compile_s, rows, compiled = {"eager": our_update(eager, batch, args.device)}, {}, [], None
            agent = make_agent(method, precision, args.batch_size, args.device, args.action_dim)
            agent.load_state_dict(eager.state_dict())
            try:
                graph = "on" if cuda else "off"
                speed.speed_up(agent, cli.RunConfig(compile="on", cuda_graph=graph), agent.device)
                start = time.perf_counter()
                for step in (5_000, 5_002):
                    agent.update(device_batch(batch, args.device), step)
                sync(args.device)
                compile_s["compiled"] = time.perf_counter() - start
                contenders["compiled"], compiled = our_update(agent, batch, args.device), agent
            except Exception as e:  # a compiler or graph failure: say it, time the rest
                rows.append(f"| {method} | {precision} | compiled | failed: {cli.first_sentence(e)[:150]} | | | | |")
            if cuda:  # each mode with TF32 off (the default) and on
                contenders = {f"{mode}, TF32 {'on' if on else 'off'}": tf32_update(update, on)
                              for mode, update in contenders.items() for on in (False, True)}
                compile_s = {f"{mode}, TF32 off": s for mode, s in compile_s.items()}
            if args.official and method == "drq" and precision == "fp32":
                contenders["official DrQ-v2"] = official_update(args, fake_batch(args.batch_size))  # its 6 actions
            costs = {k: median(c) for k, c in alternate(contenders, args.rounds, args.updates).items()}
            cli.set_tf32(False)
            official, reference = costs.get("official DrQ-v2"), costs.get("eager", costs.get("eager, TF32 off"))
            for mode, c in costs.items():
                rows.append(f"| {method} | {precision} | {mode} | {c.wall:.3f} | {c.cpu:.3f} | "
                            f"{reference.cpu / c.cpu:.2f} | "
                            f"{f'{official.cpu / c.cpu:.2f}' if official else ''} | "
                            f"{f'{compile_s[mode]:.0f}' if mode in compile_s else ''} |")
            print("\n".join([header, *rows] if header else rows), flush=True)  # after dynamo's warnings, if any
            header = None
            if args.profile and compiled is not None:  # where the compiled update's time goes, op by op
                profile_ops({"eager": eager, "compiled": compiled}, device_batch(batch, args.device), 5_000, top=25)
                header = head
            torch._dynamo.reset()  # dynamo caches per function, over agents: the next method's agents start afresh
    print(f"\n{load('(at the end)')}\n")


# --- a trained agent against a fresh one -----------------------------------------------------------
class Cost(NamedTuple):
    """One measurement, per update: wall seconds, CPU seconds of this process (all its threads: on a
    shared machine the stable one), and minor page faults (the allocator's work; 0 once the heap is reused)."""
    wall: float
    cpu: float
    faults: float


def measure(update, updates, warmup=1) -> Cost:
    """`updates` calls of update(i) after `warmup` untimed ones."""
    for i in range(warmup):
        update(-1 - i)
    wall, cpu, faults = time.perf_counter(), time.process_time(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for i in range(updates):
        update(i)
    return Cost((time.perf_counter() - wall) / updates, (time.process_time() - cpu) / updates,
                (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / updates)


def alternate(contenders: dict, rounds, updates, warmup=1) -> dict:
    """Each contender's Costs over `rounds` rounds, the order of the contenders rotating every round."""
    costs, names = {name: [] for name in contenders}, list(contenders)
    for r in range(rounds):
        for name in names[r % len(names):] + names[:r % len(names)]:
            costs[name].append(measure(contenders[name], updates, warmup))
    return costs


def median(costs) -> Cost:
    return Cost(*np.median(np.array(costs), axis=0))


def load(note=""):
    return "load average " + ", ".join(f"{x:.2f}" for x in os.getloadavg()) + note


def run_agents(args):
    """The agents of --snapshot RUN_DIR: its trained agent (snapshot.pt: weights and both Adams' state),
    loaded as a resume loads it; the same, every tensor of its state copied into memory allocated now
    (the values without the loaded memory); a fresh agent of the same config (seed 0). And the batches
    they see (from the run's buffer.npz when it was saved, else random frames) and the run's agent step."""
    snapshot = cli.load_snapshot(args.snapshot, "--snapshot")
    cfg, _ = cli.split_config(snapshot["config"], train.Config)
    cfg.batch_size = args.batch_size
    action_dim = [v for k, v in snapshot["agent"]["actor"].items() if k.startswith("policy.")][-1].numel()
    device = torch.device(args.device)
    agents = {name: train.make_agent(cfg, action_dim, device) for name in ("trained", "trained, state copied")}
    agents["trained"].load_state_dict(snapshot["agent"])  # as a resume does (experiment.RunDir.restore)
    agents["trained, state copied"].load_state_dict(copy.deepcopy(snapshot["agent"]))
    torch.manual_seed(0)
    agents["fresh"] = train.make_agent(cfg, action_dim, device)
    if cfg.precision == "bf16":  # as the run's learner sets it (speed.Learner)
        for agent in agents.values():
            speed.bf16(agent)
    path = os.path.join(args.snapshot, "buffer.npz")
    rng = np.random.default_rng(0)
    if snapshot.get("buffer_saved") and os.path.exists(path):
        t = experiment.saved_buffer_t(path)
        with np.load(path) as data:
            n = len(data["rewards"])
        buffer = sear.ReplayBuffer(n if t == n else cfg.replay_size, (3, 84, 84), action_dim, cfg.frame_stack,
                                   cfg.nstep, cfg.discount)
        experiment.load_buffer(buffer, path)
        batches = [buffer.sample(args.batch_size, rng) for _ in range(args.batches)]
        source = f"its buffer.npz ({n} steps)"
    else:
        batches = [fake_batch(args.batch_size, action_dim, seed=i) for i in range(args.batches)]
        source = "random frames (the run saved no buffer)"
    return agents, batches, snapshot["counters"]["step"], cfg, source


def snapshot_comparison(args):
    """--snapshot RUN_DIR: the run's trained agent against a fresh one on the same batches, alternating
    rounds; with --profile the ops whose times differ most, with --subnormals where each holds
    subnormal numbers (forward outputs, gradients, weights, Adam's state)."""
    agents, batches, step, cfg, source = run_agents(args)
    print(f"## Trained agent (snapshot at agent step {step} of {args.snapshot}) vs a fresh one\n\n"
          f"{cfg.method}, batch {args.batch_size}, {cfg.precision}, {torch.get_num_threads()} threads, batches from "
          f"{source}; {args.rounds} alternating rounds x {args.updates} updates, median; "
          f"malloc: {malloc_setting(args)}; {load()}\n")
    updates = {k: (lambda i, a=a: a.update(batches[i % len(batches)], step)) for k, a in agents.items()}
    if args.flush_denormal:  # the copied trained agent again, subnormals flushed to 0 while it updates
        updates["trained, state copied, denormals flushed"] = flushed(updates.pop("trained, state copied"))
    costs = alternate(updates, args.rounds, args.updates, args.warmup)
    print("| agent | wall s/update | CPU s/update | minor faults/update |\n|---|---|---|---|")
    for name, c in costs.items():
        m = median(c)
        print(f"| {name} | {m.wall:.3f} | {m.cpu:.3f} | {m.faults:.0f} |")
    t, f = median(costs["trained"]), median(costs["fresh"])
    print(f"\ntrained/fresh: wall {t.wall / f.wall:.2f}, CPU {t.cpu / f.cpu:.2f} (per round, CPU: "
          + ", ".join(f"{a.cpu / b.cpu:.2f}" for a, b in zip(costs["trained"], costs["fresh"])) + f"); {load()}\n")
    pair = {k: agents[k] for k in ("trained", "fresh")}
    if args.profile:
        profile_ops(pair, batches[0], step)
    if args.subnormals:
        subnormal_table(pair, batches[0], step)


def malloc_setting(args) -> str:
    """How this process's glibc malloc is set: under glibc's default an update takes about 1.5x the
    CPU time (docs/speed.md, "Allocator")."""
    if args.allocator == "mallopt":
        return "mallopt (cli.configure_allocator)"
    return f"GLIBC_TUNABLES={os.environ['GLIBC_TUNABLES']}" if os.environ.get("GLIBC_TUNABLES") else "glibc's default"


def flushed(update):
    """update(i) with the x86 FTZ/DAZ flags on (torch.set_flush_denormal), off again after it. The flags
    are per thread: with more than one torch thread the pool's other threads keep subnormals."""
    def run(i):
        torch.set_flush_denormal(True)
        try:
            update(i)
        finally:
            torch.set_flush_denormal(False)
    return run


def profile_ops(agents: dict, batch, step, top=15):
    """One profiled update per agent: self CPU time per op (all threads), the ops that differ most first."""
    times = {}
    for name, agent in agents.items():
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            agent.update(batch, step)
        times[name] = {e.key: e.self_cpu_time_total / 1e3 for e in prof.key_averages()}
    a, b = list(times)
    ops = sorted(set(times[a]) | set(times[b]), key=lambda k: -abs(times[a].get(k, 0) - times[b].get(k, 0)))
    print(f"### One profiled update each: self CPU ms per op, largest differences first\n\n| op | {a} | {b} |\n"
          "|---|---|---|")
    for op in ops[:top]:
        print(f"| {op} | {times[a].get(op, 0):.1f} | {times[b].get(op, 0):.1f} |")
    print(f"| all ops | {sum(times[a].values()):.1f} | {sum(times[b].values()):.1f} |\n")


# The CUDA runtime and driver calls that block the host until the device has caught up: what .item(),
# .tolist(), bool(t) and a copy to pageable host memory end in. cudaMemcpy (not ...Async) is synchronous.
SYNC_CALLS = {"cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy",
              "cudaMemcpy2D", "cuStreamSynchronize", "cuCtxSynchronize", "cuEventSynchronize", "cuMemcpy"}


class DeviceProfile(NamedTuple):
    """Per update, from torch.profiler's events (`device_profile`)."""
    kernel_ms: float        # sum of the CUDA kernels' durations
    kernels: float          # kernels launched
    h2d_bytes: float | None  # bytes of the host->device copies; None when the events carry no byte counts
    h2d_copies: float
    syncs: float            # SYNC_CALLS made by the host
    sync_calls: dict        # name -> calls per update
    top: list               # (kernel name, ms per update, launches per update), the longest first


def device_profile(events, updates: int, top: int = 10, own_syncs: dict | None = None) -> DeviceProfile:
    """Sum torch.profiler's events (prof.events(): FunctionEvents; only `name`, `device_type`,
    `activity_type`, `time_range` and `event_metadata` are read) of `updates` updates. Device events: a
    kernel (activity "kernel"), or a copy named "Memcpy HtoD (<src> -> Device)" whose bytes are its
    `event_metadata.bytes`. Host events: the runtime and driver calls of SYNC_CALLS, less `own_syncs`
    (name -> calls: the benchmark's own, such as the synchronize that ends the profiled updates)."""
    time_us, launches, syncs = {}, {}, {k: -n for k, n in (own_syncs or {}).items()}
    h2d, copies, known = 0, 0, True
    for e in events:
        on_device = getattr(e.device_type, "name", str(e.device_type)) != "CPU"
        if on_device and e.name.startswith("Memcpy HtoD"):
            copies += 1
            nbytes = getattr(getattr(e, "event_metadata", None), "bytes", None)
            known = known and nbytes is not None
            h2d += nbytes or 0
        elif on_device and getattr(e, "activity_type", None) == "kernel":
            time_us[e.name] = time_us.get(e.name, 0.0) + e.time_range.elapsed_us()
            launches[e.name] = launches.get(e.name, 0) + 1
        elif not on_device and e.name in SYNC_CALLS:
            syncs[e.name] = syncs.get(e.name, 0) + 1
    syncs = {k: n for k, n in syncs.items() if n > 0}
    longest = sorted(time_us, key=lambda k: -time_us[k])[:top]
    return DeviceProfile(sum(time_us.values()) / 1e3 / updates, sum(launches.values()) / updates,
                         h2d / updates if known else None, copies / updates, sum(syncs.values()) / updates,
                         {k: n / updates for k, n in syncs.items()},
                         [(k, time_us[k] / 1e3 / updates, launches[k] / updates) for k in longest])


def batch_bytes(batch) -> int:
    return sum(np.asarray(x).nbytes for x in batch)


def update_profile(args, top=10):
    """--profile on CUDA: each method's update, per update: host seconds (the call's own, returning before
    the device has finished unless it syncs), wall seconds with the device's work (a sync after the
    loop), then from torch.profiler (CPU and CUDA activities) over the same number of updates: kernel
    time, kernels launched, host->device bytes (from the batch when the events carry none), host syncs,
    and the longest kernels."""
    batch = device_batch(fake_batch(args.batch_size), args.device)
    activities = [torch.profiler.ProfilerActivity.CPU]
    if torch.device(args.device).type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    print(f"## Per update on {args.device} (batch {args.batch_size}, {args.updates} updates after 2 of warm-up; "
          "kernels, copies and syncs from torch.profiler)\n")
    print("| method | precision | host s/update | wall s/update | GPU kernel ms/update | kernels/update | "
          "H2D MB/update | H2D copies/update | host syncs/update |\n|---|---|---|---|---|---|---|---|---|")
    tops = {}
    for precision in args.precisions:
        for method in args.methods:
            agent = make_agent(method, precision, args.batch_size, args.device)
            for _ in range(2):  # cuDNN's algorithm search, the caching allocator's first blocks
                agent.update(batch, step=5_000)
            sync(args.device)
            host, start = 0.0, time.perf_counter()
            for _ in range(args.updates):
                t = time.perf_counter()
                agent.update(batch, step=5_000)
                host += time.perf_counter() - t
            sync(args.device)
            wall = (time.perf_counter() - start) / args.updates
            with torch.profiler.profile(activities=activities) as prof:
                for _ in range(args.updates):
                    agent.update(batch, step=5_000)
                sync(args.device)  # the last kernels inside the profile; this sync is not the update's
            p = device_profile(prof.events(), args.updates, top, own_syncs={"cudaDeviceSynchronize": 1})
            h2d = (f"{p.h2d_bytes / 1e6:.1f}" if p.h2d_bytes is not None
                   else f"{batch_bytes(batch) / 1e6:.1f} (the batch)")
            syncs = f"{p.syncs:g}" + (f" ({', '.join(f'{k} {n:g}' for k, n in p.sync_calls.items())})" if p.syncs else "")
            print(f"| {method} | {precision} | {host / args.updates:.4f} | {wall:.4f} | {p.kernel_ms:.2f} | "
                  f"{p.kernels:g} | {h2d} | {p.h2d_copies:g} | {syncs} |", flush=True)
            tops[method, precision] = p.top
            del agent
    for (method, precision), rows in tops.items():
        if rows:
            print(f"\n### {method}, {precision}: the {len(rows)} longest kernels\n\n"
                  "| kernel | ms/update | launches/update |\n|---|---|---|")
            for name, ms, n in rows:
                print(f"| {name[:100]} | {ms:.3f} | {n:g} |")
    print()


def subnormals(t) -> int:
    t = t.detach()
    return int(((t != 0) & (t.abs() < torch.finfo(t.dtype).tiny)).sum()) if t.is_floating_point() else 0


def subnormal_table(agents: dict, batch, step):
    """Subnormal floats per network in one update: forward outputs and output gradients of every leaf
    module (hooks), then the weights and Adam's exp_avg / exp_avg_sq after it."""
    counts = {}
    for name, agent in agents.items():
        c, hooks = counts.setdefault(name, {}), []  # (module or network, what) -> subnormal floats
        nets = {k: getattr(agent, k) for k in ("encoder", "actor", "critic", "aux") if getattr(agent, k) is not None}
        def add(key, n):
            c[key] = c.get(key, 0) + n

        def seen(module, inputs, out, name):  # the output now, its gradient when backward reaches it
            add((name, "output"), subnormals(out))
            if out.requires_grad:
                out.register_hook(lambda g: add((name, "gradient"), subnormals(g)))
        for net_name, net in nets.items():
            for mod_name, mod in net.named_modules():
                if not list(mod.children()):
                    hooks.append(mod.register_forward_hook(functools.partial(seen, name=f"{net_name}.{mod_name}")))
        agent.update(batch, step)
        for h in hooks:
            h.remove()
        for net_name, net in nets.items():
            c[net_name, "weights"] = sum(subnormals(p) for p in net.parameters())
        for opt in (agent.model_opt, agent.actor_opt):
            for state in opt.state.values():
                for k in ("exp_avg", "exp_avg_sq"):
                    c["Adam", k] = c.get(("Adam", k), 0) + subnormals(state[k])
    a, b = list(counts)
    print(f"### Subnormal floats in one update (rows with any)\n\n| where | what | {a} | {b} |\n|---|---|---|---|")
    for key in sorted(set(counts[a]) | set(counts[b])):
        if counts[a].get(key, 0) or counts[b].get(key, 0):
            print(f"| {key[0]} | {key[1]} | {counts[a].get(key, 0)} | {counts[b].get(key, 0)} |")
    print()


def compare_layouts(args):
    """Each method's update with the encoder and decoders in channels_last (as sear.py) and set back
    to NCHW, alternating in this process on the same batch."""
    batch = device_batch(fake_batch(args.batch_size), args.device)
    print(f"## Layout: NCHW vs channels_last (batch {args.batch_size}, {torch.get_num_threads()} threads, "
          f"{args.rounds} alternating rounds x {args.updates} updates, median)\n")
    print("| method | precision | channels_last s/update | NCHW s/update | NCHW / channels_last |\n|---|---|---|---|---|")
    for precision in args.precisions:
        for method in args.methods:
            ours, nchw = (make_agent(method, precision, args.batch_size, args.device) for _ in range(2))
            for net in (nchw.encoder, nchw.aux):
                if net is not None:
                    net.to(memory_format=torch.contiguous_format)
            times = np.array([(time_updates(ours, batch, args.updates), time_updates(nchw, batch, args.updates))
                              for _ in range(args.rounds)])
            cl, nc = np.median(times, axis=0)
            print(f"| {method} | {precision} | {cl:.3f} | {nc:.3f} | {nc / cl:.2f} |", flush=True)
    print()


# glibc's malloc: the default; the GLIBC_TUNABLES that sear.py used to restart itself with (huge pages
# for the heap, no mmap, no trim); and what it sets now at run time (cli.configure_allocator: no mmap,
# no trim, no huge pages: mallopt has none).
ALLOCATORS = {"glibc default": ("none", ""),
              "GLIBC_TUNABLES restart (before)": ("none", "glibc.malloc.hugetlb=1:glibc.malloc.mmap_max=0:"
                                                          f"glibc.malloc.trim_threshold={64 << 30}"),
              "mallopt at run time (cli.configure_allocator)": ("mallopt", "")}


def compare_allocators(args):
    """Each method's update under each of ALLOCATORS, each measurement a fresh process (glibc reads
    GLIBC_TUNABLES only at start-up), alternating rounds."""
    print(f"## glibc's malloc (batch {args.batch_size}, {args.threads or cli.default_threads()} threads, "
          f"{args.rounds} alternating rounds of a fresh process x {args.updates} updates after {args.warmup}, "
          f"median); {load()}\n")
    print("| method | allocator | wall s/update | CPU s/update | minor faults/update | wall / mallopt's |\n"
          "|---|---|---|---|---|---|")
    for m in args.methods:
        def child(name):
            allocator, tunables = ALLOCATORS[name]
            env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--batch-size", str(args.batch_size),
                                  "--updates", str(args.updates), "--methods", m, "--device", args.device,
                                  "--threads", str(args.threads), "--allocator", allocator, "--warmup",
                                  str(args.warmup), "--updates-only"],
                                 env={**env, **({"GLIBC_TUNABLES": tunables} if tunables else {})},
                                 capture_output=True, text=True, check=True).stdout
            return Cost(*map(float, out.split()))
        costs = {name: [] for name in ALLOCATORS}
        for r in range(args.rounds):
            names = list(ALLOCATORS)
            for name in names[r % len(names):] + names[:r % len(names)]:
                costs[name].append(child(name))
        ref = median(costs[list(ALLOCATORS)[-1]])
        for name, c in costs.items():
            c = median(c)
            print(f"| {m} | {name} | {c.wall:.3f} | {c.cpu:.3f} | {c.faults:.0f} | {c.wall / ref.wall:.2f} |",
                  flush=True)
    print(f"\n{load('(at the end)')}\n")


def build_parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--updates", type=int, default=3, help="timed updates per measurement")
    p.add_argument("--warmup", type=int, default=1, help="untimed updates before each measurement of the "
                   "comparisons (--compare-allocators: the heap of a fresh process grows for the first 3)")
    p.add_argument("--methods", nargs="+", default=["drq", "sear"],
                   choices=[m + drm for drm in ("", cli.DRM_SUFFIX) for m in sear.METHODS])
    p.add_argument("--precisions", nargs="+", choices=["fp32", "bf16"],
                   help="default: fp32 and bf16; fp32 alone on a CPU without native bf16 (native_bf16)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: sear.py's default)")
    p.add_argument("--env", default="walker-walk", help="env of the training-step split")
    p.add_argument("--split-method", default="sear", choices=list(sear.METHODS))
    p.add_argument("--split-steps", type=int, default=40, help="timed training steps of the split (0: skip)")
    p.add_argument("--split-warmup", type=int, default=300,
                   help="untimed steps that fill the split's buffer first (and until an episode has ended)")
    p.add_argument("--official", metavar="DIR", help="a checkout of facebookresearch/drqv2 to time against")
    p.add_argument("--rounds", type=int, default=5, help="alternating rounds of every comparison")
    p.add_argument("--breakdown", action="store_true",
                   help="profile one update per method and precision: time and GFLOP/s per op class")
    p.add_argument("--compare-allocators", action="store_true",
                   help="time each method under glibc's default malloc, the GLIBC_TUNABLES restart sear.py used "
                        "before, and cli.configure_allocator's mallopt, each in fresh processes, alternating")
    p.add_argument("--compare-layouts", action="store_true",
                   help="time each method with the conv nets in channels_last (sear.py) and in NCHW, alternating")
    p.add_argument("--compare-compile", action="store_true",
                   help="time each method eager and with --compile (on CUDA: a CUDA graph, TF32 off and on), and the official "
                        "update with --official, alternating; compile time apart")
    p.add_argument("--action-dim", type=int, default=6, help="--compare-compile: the agents' action size (the "
                   "compiled graphs are then those of a task with as many; cartpole 1, walker 6)")
    p.add_argument("--snapshot", metavar="RUN_DIR",
                   help="time the run's trained agent against a fresh one on batches of its own buffer, alternating")
    p.add_argument("--batches", type=int, default=4, help="--snapshot: batches drawn from the run's buffer")
    p.add_argument("--profile", action="store_true",
                   help="--snapshot, --compare-compile: per-op CPU times of one update each (trained and fresh; "
                        "eager and compiled); on CUDA otherwise: per update, host and wall time, kernel time, "
                        "kernels launched, host->device bytes, host syncs, the longest kernels")
    p.add_argument("--subnormals", action="store_true",
                   help="--snapshot: subnormal floats in one update's outputs, gradients, weights and Adam state")
    p.add_argument("--flush-denormal", action="store_true",
                   help="--snapshot: time the copied trained agent with subnormals flushed to 0 "
                        "(torch.set_flush_denormal; x86; the calling thread's flags: use --threads 1)")
    p.add_argument("--allocator", choices=["mallopt", "none"], default="mallopt",
                   help="mallopt: glibc's malloc as sear.py sets it (cli.configure_allocator); none: leave it")
    p.add_argument("--updates-only", action="store_true", help=argparse.SUPPRESS)
    return p


def main():
    args = build_parser().parse_args()
    if args.allocator == "mallopt":
        cli.configure_allocator()
    torch.set_num_threads(args.threads or cli.default_threads())
    if args.snapshot:
        return snapshot_comparison(args)
    if args.compare_allocators:
        return compare_allocators(args)
    if args.updates_only:  # one method: the child process of --compare-allocators prints its Cost
        agent = make_agent(args.methods[0], "fp32", args.batch_size, args.device)
        batch = device_batch(fake_batch(args.batch_size), args.device)
        print(*measure(lambda i: agent.update(batch, step=5_000), args.updates, args.warmup))
        return
    choose_precisions(args)
    if args.compare_layouts:
        return compare_layouts(args)
    if args.compare_compile:
        return compile_comparison(args)
    peaks = machine(args)
    update_table(args, peaks)
    if args.profile and torch.device(args.device).type == "cuda":
        update_profile(args)
    if args.breakdown:
        op_breakdown(args, peaks)
    if args.split_steps:
        step_split(args)
    if args.official:
        official_comparison(args)


def machine(args) -> dict:
    """The machine's and the replay buffer's tables; returns the GEMM peak of each precision."""
    peaks = {p: gemm_gflops({"fp32": torch.float32, "bf16": torch.bfloat16}[p], args.device) for p in args.precisions}
    n = gemm_size(args.device)[0]
    on = (f"{torch.cuda.get_device_name(args.device)} (fp32 matmul TF32: {torch.backends.cuda.matmul.allow_tf32}, "
          f"cuDNN conv TF32: {torch.backends.cudnn.allow_tf32})" if torch.device(args.device).type == "cuda"
          else f"{os.cpu_count()} cores, {torch.get_num_threads()} torch threads")
    print(f"## Machine\n\n{on}; GEMM {n}^3 on {args.device}: "
          + ", ".join(f"{p} {g:.0f} GFLOP/s" for p, g in peaks.items()) + "\n")
    print("## Replay buffer footprint\n\n| action dim | bytes / transition | 1M transitions |\n|---|---|---|")
    for a in (6, 4, 9, 28):
        b = sear.ReplayBuffer(1, (3, 84, 84), a, frame_stack=3, nstep=3, discount=0.99).bytes_per_transition
        print(f"| {a} | {b} | {b * 1e6 / 2**30:.1f} GiB |")
    print("\n(official drqv2 stores 63.5 KB per step)\n")
    return peaks


if __name__ == "__main__":
    main()
