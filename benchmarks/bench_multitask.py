"""Memory and speed of the Meta-World task sets: one env that switches between 10 or 50 tasks.

Each task's Meta-World env is built on its first episode and kept; the renderers are made again
when the task changes (SEAREnv._make_renderers), so the process holds one renderer pair, not one
per task. This prints, per task set, the resident memory (RSS) once every task has run, the agent
steps/s inside episodes, the seconds a task switch costs, and the steps/s of full 250-step
episodes with uniformly drawn tasks (a switch at (n-1)/n of the resets).
`--keep-renderers` instead keeps one renderer pair per task (the alternative, for comparison).

    MUJOCO_GL=egl python benchmarks/bench_multitask.py --envs metaworld-mt10   # one set per process:
    MUJOCO_GL=egl python benchmarks/bench_multitask.py --envs metaworld-mt50   # RSS is the process's
        [--steps 10] [--render-quality fast] [--keep-renderers]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import envs  # noqa: E402

EPISODE = 250  # agent steps of a Meta-World episode (500 env steps at action repeat 2)


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


def keep_renderers_per_task(env) -> None:
    """The alternative: one renderer pair per task model, made once and kept."""
    pairs = {}

    def make(self=env):
        if id(self.model) not in pairs:
            seg = self.size * self.mask_scale
            pairs[id(self.model)] = (mujoco.Renderer(self.model, self.size, self.size),
                                     mujoco.Renderer(self.model, seg, seg))
        self._rgb_renderer, self._seg_renderer = pairs[id(self.model)]

    env._close_renderers()
    env._make_renderers = make
    make()


def measure(name: str, steps: int, quality: str, keep: bool) -> dict:
    start = time.perf_counter()
    env = envs.make_env(name, seed=0, render_quality=quality)
    build = time.perf_counter() - start
    if keep:
        keep_renderers_per_task(env)
    rng = np.random.default_rng(0)
    reset_s, step_s = [], 0.0
    for i, task in enumerate(env.tasks):  # every task once: each reset switches task
        t = time.perf_counter()
        env.reset(seed=i, options={"task": task})
        reset_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        for _ in range(steps):
            env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        step_s += time.perf_counter() - t
    n = len(env.tasks)
    sps = n * steps / step_s
    # The first reset of a task also builds its env; later switches only make renderers.
    t = time.perf_counter()
    for i, task in enumerate(env.tasks[:5]):
        env.reset(seed=100 + i, options={"task": task})
    switch = (time.perf_counter() - t) / 5
    episode = EPISODE / (EPISODE / sps + switch * (n - 1) / n)
    result = dict(env=name, tasks=n, build=build, rss=rss_mb(), first_reset=float(np.mean(reset_s)), switch=switch, sps=sps, episode_sps=episode)
    env.close()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=["metaworld-mt10", "metaworld-mt50"])
    parser.add_argument("--steps", type=int, default=10, help="timed agent steps per task")
    parser.add_argument("--render-quality", default="fast", choices=["paper", "fast"])
    parser.add_argument("--keep-renderers", action="store_true", help="one renderer pair per task instead")
    args = parser.parse_args()
    rows = [measure(name, args.steps, args.render_quality, args.keep_renderers) for name in args.envs]
    print(f"render quality {args.render_quality}, renderers "
          f"{'kept per task' if args.keep_renderers else 'made again at each task switch'}, "
          f"{args.steps} steps per task, {os.cpu_count()} CPU cores\n")
    print("| env | tasks | build s | RSS MB (all tasks run) | first reset s | switch s | steps/s in episode "
          "| steps/s, 250-step episodes |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['env']} | {r['tasks']} | {r['build']:.1f} | {r['rss']:.0f} | {r['first_reset']:.2f} "
              f"| {r['switch']:.2f} | {r['sps']:.1f} | {r['episode_sps']:.1f} |")


if __name__ == "__main__":
    main()
