"""What looking at the decoders costs an evaluation: the metrics (mask IoU and BCE, reconstruction
PSNR on every evaluation frame) and --save-video (episode 0 filmed), on a trained run's snapshot.

Builds the run's eval env as sear.py does and times the same evaluation three ways: the plain env,
wrapped in EvalWatch (the metrics), and EvalWatch with a video. Prints a markdown table of CPU
seconds (this process and its children: ffmpeg) next to wall seconds: on a shared machine the
wall clock measures the neighbours as much as the evaluation, CPU time much less so.

    MUJOCO_GL=egl python benchmarks/bench_inspect.py runs/<run dir> [--episodes 2] [--threads 1]
        [--max-episode-steps 0]

The snapshot's weights do not matter for the cost, only its network sizes: a run of a few frames
at the default sizes will do (its own --max-episode-steps is replaced by this one's).
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

import plot  # noqa: E402
from harness import experiment  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402


def cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the ffmpeg encoder)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir")
    parser.add_argument("--episodes", type=int, default=2, help="evaluation episodes per timing")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-episode-steps", type=int, default=0, help="0 = the suite's own episode length")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    cfg, state = plot.load_snapshot_run(args.run_dir)
    cfg.eval_episodes, cfg.max_episode_steps = args.episodes, args.max_episode_steps
    _, env = runenvs.make_envs(cfg, sear.METHODS[cfg.method].uses_mask)
    agent = plot.trained_agent(cfg, state, env.action_space.shape[0])
    step = state["counters"]["step"]
    with tempfile.TemporaryDirectory() as tmp:
        video = os.path.join(tmp, "eval.mp4")
        variants = [("plain evaluation", lambda: (env, None)),
                    ("+ metrics (EvalWatch)", lambda: (experiment.EvalWatch(agent, env), None)),
                    ("+ metrics + --save-video", lambda: (experiment.EvalWatch(agent, env, video), video))]
        warm_up = experiment.EvalWatch(agent, env)  # first render, first encoder and decoder passes
        warm_up.reset(seed=0)
        warm_up.finish()
        rows = []
        for name, make in variants:
            watched, path = make()
            steps = []
            began, cpu = time.perf_counter(), cpu_seconds()
            train.evaluate(agent, watched, cfg, step, on_step=lambda episode, t: steps.append(t))
            if watched is not env:
                watched.finish()  # waits for ffmpeg, so its CPU time is counted
            rows.append((name, cpu_seconds() - cpu, time.perf_counter() - began))
            size = f", video {os.path.getsize(path) / 1e6:.2f} MB" if path else ""
            print(f"# {name}: {rows[-1][1]:.1f} CPU s, {rows[-1][2]:.1f} s wall{size}", file=sys.stderr, flush=True)
    observations = len(steps) + args.episodes  # every step's and every reset's
    env.close()
    print(f"{cfg.env}, method {cfg.method}, render {cfg.render_quality}, {args.episodes} episodes = {observations} "
          f"observations, {args.threads} thread(s)\n")
    print("| variant | CPU s | CPU ms per observation | extra CPU over plain | wall s |\n|---|---|---|---|---|")
    for name, cpu, wall in rows:
        print(f"| {name} | {cpu:.1f} | {1000 * cpu / observations:.1f} | {cpu - rows[0][1]:+.1f} s | {wall:.1f} |")


if __name__ == "__main__":
    main()
