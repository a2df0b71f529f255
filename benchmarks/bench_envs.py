"""Environment throughput per suite: render_quality paper vs fast, RGB vs RGB+mask.

Prints a markdown table of agent steps per second (one agent step = the
suite's default action repeat of physics steps + one RGB render, plus the
segmentation render and mask pipeline for "RGB+mask").  Each env is built
once per render quality; both mask modes are timed on it after a warm-up.

    MUJOCO_GL=egl python benchmarks/bench_envs.py [--steps 24] [--envs ...] [--clock cpu]

--clock cpu counts this process's CPU seconds (every thread of it, the renderer's too) instead of
wall seconds: steps per CPU-second, what one core gives, also on a machine that others share.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import envs  # noqa: E402

DEFAULT_ENVS = ["walker-walk", "walker-walk-distracting", "cup-catch", "metaworld-door-open",
                "kitchen-kettle", "adroit-door"]


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def steps_per_second(env, steps: int, rng: np.random.Generator, clock=time.perf_counter) -> float:
    env.reset(seed=0)
    env.step(rng.uniform(-1, 1, env.action_space.shape))  # warm-up (first render)
    start = clock()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
        if terminated or truncated:
            env.reset()
    return steps / (clock() - start)


def gl_renderer(env) -> str:
    """The OpenGL renderer that draws the env's frames: with MUJOCO_GL=egl, Mesa's llvmpipe on a CPU
    machine, the GPU where its driver provides EGL (PyOpenGL comes with mujoco)."""
    from OpenGL import GL
    env._rgb_renderer._gl_context.make_current()
    return " / ".join(GL.glGetString(k).decode() for k in (GL.GL_VENDOR, GL.GL_RENDERER))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=24, help="timed agent steps per cell")
    parser.add_argument("--envs", nargs="+", default=DEFAULT_ENVS)
    parser.add_argument("--clock", choices=list(CLOCKS), default="wall",
                        help="wall: steps per wall second; cpu: per CPU-second of this process (one core's rate)")
    args = parser.parse_args()

    rows, renderer = [], None
    for name in args.envs:
        cells = {}
        for quality in ("paper", "fast"):
            env = envs.make_env(name, seed=0, render_quality=quality)
            renderer = renderer or gl_renderer(env)
            rng = np.random.default_rng(0)
            for render_mask in (False, True):
                env.render_mask = render_mask
                cells[quality, render_mask] = steps_per_second(env, args.steps, rng, CLOCKS[args.clock])
            env.close()
        rows.append((name, envs.default_action_repeat(name), cells))
        print(f"# done {name}", file=sys.stderr, flush=True)

    per = "CPU-second of this process" if args.clock == "cpu" else "wall second"
    print(f"Agent steps per {per} ({args.steps} steps per cell, 84x84, {os.cpu_count()} CPU cores, "
          f"MUJOCO_GL={os.environ['MUJOCO_GL']}, OpenGL: {renderer})\n")
    print("| env | action repeat | paper RGB | paper RGB+mask | fast RGB | fast RGB+mask |")
    print("|---|---|---|---|---|---|")
    for name, repeat, c in rows:
        print(f"| {name} | {repeat} | {c['paper', False]:.1f} | {c['paper', True]:.1f} "
              f"| {c['fast', False]:.1f} | {c['fast', True]:.1f} |")


if __name__ == "__main__":
    main()
