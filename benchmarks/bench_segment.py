"""The learned robot mask (segment.py): IoU against the number of labels, training time, and the
per-step cost of the mask (learned network vs the simulator's segmentation render).

IoU table: for each env and N, N labelled frames of random-action episodes (simulator masks as
labels) train the U-Net (segment.train_model, the CLI's defaults), which is scored on held-out
frames of the same episodes, on frames of other episodes and, for Distracting Control, on unseen
backgrounds (the eval split's images). Cost: agent steps of one env (frame stack 3, fast render)
with no mask, the simulator's mask, and the learned mask (the net on each new frame), timed
alternately after a warm-up; the difference to "no mask" is the mask's cost per agent step.

    OMP_NUM_THREADS=1 python benchmarks/bench_segment.py --labels 25 100 400
    OMP_NUM_THREADS=1 python benchmarks/bench_segment.py --cost-only
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
import torch  # noqa: E402

import envs  # noqa: E402
import segment  # noqa: E402

DEFAULT_ENVS = ["walker-walk-distracting", "metaworld-door-open", "kitchen-kettle", "adroit-door"]


def iou_row(env_name, n, steps, seed):
    began = time.time()
    images, masks, tests = segment.evaluation_sets(env_name, n, seed=seed, render_quality="fast")
    collect_s = time.time() - began
    model = segment.train_model(images, masks, steps=steps, seed=seed)
    scores = {name: segment.iou(segment.predict(model, x), y) for name, (x, y) in tests.items()}
    return model, scores, collect_s


def step_cost(env_name, model, steps, rng):
    """Seconds per agent step for each mask source, timed alternately in rounds."""
    built = {"none": envs.make_env(env_name, seed=0, render_quality="fast", render_mask=False),
             "simulator": envs.make_env(env_name, seed=0, render_quality="fast", render_mask=True),
             "learned": envs.make_env(env_name, seed=0, render_quality="fast", render_mask=False,
                                      mask_model=model)}
    spent = dict.fromkeys(built, 0.0)
    try:
        for env in built.values():
            env.reset(seed=0)
        for _ in range(3):
            for name, env in built.items():
                began = time.perf_counter()
                for _ in range(steps):
                    _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
                    if term or trunc:
                        env.reset()
                spent[name] += time.perf_counter() - began
    finally:
        for env in built.values():
            env.close()
    return {name: s / (3 * steps) for name, s in spent.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=DEFAULT_ENVS)
    parser.add_argument("--labels", nargs="+", type=int, default=[25, 100, 400])
    parser.add_argument("--steps", type=int, default=600, help="Adam steps per model")
    parser.add_argument("--cost-steps", type=int, default=30, help="agent steps per source and round")
    parser.add_argument("--cost-only", action="store_true", help="skip the IoU table (an untrained net costs the same)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"torch threads {torch.get_num_threads()}")
    if not args.cost_only:
        print("| env | N labels | IoU held-out frames | IoU other episodes | IoU unseen backgrounds | "
              "train s | collect s |\n|---|---|---|---|---|---|---|", flush=True)
        for env_name in args.envs:
            for n in args.labels:
                model, scores, collect_s = iou_row(env_name, n, args.steps, args.seed)
                cells = [f"{scores[k]:.3f}" if k in scores else "-"
                         for k in ("held-out", "other episodes", "unseen backgrounds")]
                print(f"| {env_name} | {n} | {' | '.join(cells)} | {model.meta['train_seconds']:.0f} | "
                      f"{collect_s:.0f} |", flush=True)
    print("\n| env | no mask ms/step | + simulator mask ms | + learned mask ms |\n|---|---|---|---|", flush=True)
    rng = np.random.default_rng(args.seed)
    for env_name in args.envs:
        cost = step_cost(env_name, segment.MaskModel(segment.UNet()), args.cost_steps, rng)
        base = cost["none"]
        print(f"| {env_name} | {1e3 * base:.1f} | {1e3 * (cost['simulator'] - base):.1f} | "
              f"{1e3 * (cost['learned'] - base):.1f} |", flush=True)


if __name__ == "__main__":
    main()
