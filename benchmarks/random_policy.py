"""The return of a uniformly random policy: the floor a learning curve must clear.

Builds the evaluation env exactly as `sear.py` does for the same flags (action repeat, render
quality, distractions, seeds) and plays N episodes with actions drawn uniformly from the action
space. Prints the mean, the standard deviation and the 95% confidence interval of the mean
(Student t), the numbers the laptop rung in EXPERIMENTS.md compares against.

    MUJOCO_GL=egl python benchmarks/random_policy.py --env cartpole-balance --action-repeat 8 --episodes 50
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from harness import experiment  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="cartpole-balance")
    parser.add_argument("--action-repeat", type=int, default=0, help="0 = the suite's default")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--render-quality", default="fast")
    args = parser.parse_args()

    cfg = train.Config(env=args.env, action_repeat=args.action_repeat, seed=args.seed, method="drq",
                      render_quality=args.render_quality)
    _, env = runenvs.make_envs(cfg, sear.METHODS[cfg.method].uses_mask)  # the eval env: the run's evaluation seeds and settings
    rng = np.random.default_rng(args.seed)
    returns = []
    for i in range(args.episodes):
        env.reset(seed=runenvs.episode_seed(cfg.seed + 100_000, i))
        done, ret = False, 0.0
        while not done:
            _, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            ret += reward
            done = terminated or truncated
        returns.append(ret)
    returns = np.array(returns)
    print(f"{args.env} (action repeat {cfg.action_repeat}), random policy: mean {experiment.mean_ci(returns)}, "
          f"std {returns.std(ddof=1):.1f}, min {returns.min():.1f}, max {returns.max():.1f}")


if __name__ == "__main__":
    main()
