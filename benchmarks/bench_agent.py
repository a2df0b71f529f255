"""Agent benchmark: replay bytes per transition and update speed of every method, in one run.

    python benchmarks/bench_agent.py                  # batch 256, every method
    python benchmarks/bench_agent.py --batch-size 64 --methods sear drq --updates 5

Synthetic batches (no rendering), so the numbers are the learner's cost alone. Prints a markdown
table; the ratio column is relative to drq measured in the same run.
"""
import argparse
import os
import subprocess
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import sear  # noqa: E402


def replay_footprint(action_dims=(6, 4, 9, 28)):
    rows = []
    for a in action_dims:
        buf = sear.ReplayBuffer(1, (3, 84, 84), a, frame_stack=3, nstep=3, discount=0.99)
        rows.append((a, buf.bytes_per_transition))
    return rows


def updates_per_second(method, batch_size, updates, action_dim=6, device="cpu"):
    cfg = sear.Config(method=method, batch_size=batch_size, action_repeat=2)
    agent = sear.Agent(cfg, action_dim, torch.device(device))
    rng = np.random.default_rng(0)
    n = batch_size
    batch = (rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8), rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8),
             rng.uniform(-1, 1, (n, action_dim)).astype(np.float32), rng.normal(size=(n, 1)).astype(np.float32),
             np.full((n, 1), 0.99 ** 3, np.float32), rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8),
             rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8))
    agent.update(batch, step=5_000)  # warm-up (allocator, kernels)
    start = time.perf_counter()
    for _ in range(updates):
        agent.update(batch, step=5_000)
    return updates / (time.perf_counter() - start)


def compare_allocators(args):
    """SEAR and DrQ update time with glibc's default pages and with sear.py's huge-page setting,
    each measured in a fresh process (glibc reads GLIBC_TUNABLES only at start-up)."""
    print(f"## glibc allocator: default vs huge pages (batch {args.batch_size})\n")
    print("| method | default s/update | hugetlb=1 s/update | speed-up |\n|---|---|---|---|")
    for m in args.methods:
        times = []
        for tunables in ("glibc.malloc.hugetlb=0", "glibc.malloc.hugetlb=1"):
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--batch-size", str(args.batch_size),
                                  "--updates", str(args.updates), "--methods", m, "--device", args.device,
                                  "--updates-only"], env={**os.environ, "GLIBC_TUNABLES": tunables},
                                 capture_output=True, text=True, check=True).stdout
            times.append(float(out))
        print(f"| {m} | {times[0]:.2f} | {times[1]:.2f} | {times[0] / times[1]:.2f}x |", flush=True)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--updates", type=int, default=3)
    p.add_argument("--methods", nargs="+", default=list(sear.METHODS))
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--compare-allocators", action="store_true",
                   help="time each method with glibc's default pages and with huge pages")
    p.add_argument("--updates-only", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.compare_allocators:
        return compare_allocators(args)
    if args.updates_only:  # one method, one number: the child process of --compare-allocators
        print(1 / updates_per_second(args.methods[0], args.batch_size, args.updates, device=args.device))
        return

    print("## Replay buffer footprint\n\n| action dim | bytes / transition | KB | 1M transitions |\n|---|---|---|---|")
    for a, b in replay_footprint():
        print(f"| {a} | {b} | {b / 1000:.2f} | {b * 1e6 / 2**30:.1f} GiB |")
    print(f"\n(official drqv2 stores 63.5 KB per step)\n\n## Updates/s at batch {args.batch_size} on "
          f"{args.device} ({torch.get_num_threads()} threads), {args.updates} timed updates each\n")
    print("| method | updates/s | s/update | relative to drq |\n|---|---|---|---|")
    results = {}
    for m in (["drq"] + [m for m in args.methods if m != "drq"]) if "drq" in args.methods else args.methods:
        results[m] = updates_per_second(m, args.batch_size, args.updates, device=args.device)
        rel = f"{results[m] / results['drq']:.2f}x" if "drq" in results else "-"
        print(f"| {m} | {results[m]:.3f} | {1 / results[m]:.2f} | {rel} |", flush=True)


if __name__ == "__main__":
    sear.reexec_with_huge_pages()  # the setting sear.py trains with (see --compare-allocators)
    main()
