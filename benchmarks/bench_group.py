"""Seeds in one process (sear.py --seeds, group.py) against the same seeds as separate processes: frames/s
of all seeds together after the seed frames, for each group size, measured in one run of this script.

    python benchmarks/bench_group.py --sizes 1 4 8 16 --seconds 120     # on a GPU: the scaling table
    python benchmarks/bench_group.py --quick                            # the CPU: --seeds 2 beside 2 processes

Each measurement trains the published-curve rung's command (cartpole-balance_sparse, drq, DrQ-v2's
configuration; --quick: tiny networks) for --seconds after its seed phase and stops it with SIGINT; the
frames/s are read from each run's train.csv (frames after the seed phase over the wall time between its
first and last row after it). One size at a time: group first, then the processes, every process with
the same --threads. A run that fails stops the benchmark with its error.
"""
from __future__ import annotations

import argparse
import csv
import glob
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNG = ["--env", "cartpole-balance_sparse", "--method", "drq", "--action-repeat", "2", "--batch-size", "256",
        "--std-steps", "100000", "--eval-every", "1000000", "--eval-episodes", "1", "--replay-size", "30000"]
QUICK = ["--batch-size", "8", "--hidden-dim", "32", "--feature-dim", "16", "--max-episode-steps", "25",
         "--seed-frames", "80", "--exploration-steps", "40", "--render-quality", "fast", "--replay-size", "2000"]


class RunFailed(Exception):
    pass


def frames_per_second(run_root: str, seed_frames: int) -> float:
    """Frames/s of every run under run_root together: each run's frames after the seed phase over its
    wall time after it (train.csv's wall_time), summed."""
    total = 0.0
    for path in glob.glob(os.path.join(run_root, "**", "train.csv"), recursive=True):
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if int(r["frame"]) > seed_frames]
        if len(rows) >= 2:
            frames = int(rows[-1]["frame"]) - int(rows[0]["frame"])
            total += frames / max(float(rows[-1]["wall_time"]) - float(rows[0]["wall_time"]), 1e-9)
    return total


def measure(commands: list[list[str]], run_root: str, seconds: float, seed_frames: int, threads: int) -> float:
    """Start the commands together, stop them with SIGINT once `seconds` of training after the seed
    phase have passed (watched in train.csv), return their frames/s together."""
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": str(threads)}
    errors = [tempfile.TemporaryFile("w+") for _ in commands]
    procs = [subprocess.Popen([sys.executable, str(ROOT / "sear.py"), *c, "--run-root", f"{run_root}/{i}",
                               "--threads", str(threads)], env=env, stdout=subprocess.DEVNULL,
                              stderr=err) for i, (c, err) in enumerate(zip(commands, errors))]
    fps = 0.0
    try:
        began = None
        while all(p.poll() is None for p in procs):
            if began is None and frames_per_second(run_root, seed_frames) > 0:
                began = time.monotonic()
            if began is not None and time.monotonic() - began >= seconds:
                # read before the runs stop: a run stopped before its first snapshot leaves no directory
                fps = frames_per_second(run_root, seed_frames)
                break
            time.sleep(1)
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=120)
            except subprocess.TimeoutExpired:
                p.kill()
    for p, err in zip(procs, errors):
        if p.returncode not in (0, 130):  # 130: the SIGINT that stops it
            err.seek(0)
            raise RunFailed(f"a run failed (exit {p.returncode}): {err.read().strip().splitlines()[-1:]}")
    return fps


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 4, 8, 16])
    p.add_argument("--seconds", type=float, default=120.0, help="training after the seed phase, per measurement")
    p.add_argument("--threads", type=int, default=1, help="--threads of every run, group and processes alike")
    p.add_argument("--quick", action="store_true", help="--sizes 2, tiny networks, 15 s: the CPU's check")
    args = p.parse_args(argv)
    extra, seed_frames = [], 4000
    if args.quick:
        args.sizes, args.seconds, extra, seed_frames = [2], 15.0, QUICK, 80
    cores = len(os.sched_getaffinity(0))
    print(f"## {' / '.join(map(str, args.sizes))} seeds: one process (--seeds) against one process per seed "
          f"({cores} cores; --threads {args.threads} each; {args.seconds:g} s of training each)\n")
    print("| seeds | one process (frames/s) | processes (frames/s) | one / processes |\n|---|---|---|---|")
    for n in args.sizes:
        work = tempfile.mkdtemp(prefix="bench_group-")
        try:
            command = [*RUNG, *extra, "--frames", "100000000"]
            group = [[*command, "--seeds", f"1-{n}"]] if n > 1 else [[*command, "--seed", "1"]]
            together = measure(group, f"{work}/group", args.seconds, seed_frames, args.threads)
            apart = measure([[*command, "--seed", str(k)] for k in range(1, n + 1)], f"{work}/apart", args.seconds,
                            seed_frames, args.threads)
        except RunFailed as e:
            print(f"bench_group.py: {e}", file=sys.stderr)
            return 1
        finally:
            shutil.rmtree(work, ignore_errors=True)
        ratio = f"{together / apart:.2f}" if apart else "n/a"
        print(f"| {n} | {together:.0f} | {apart:.0f} | {ratio} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
