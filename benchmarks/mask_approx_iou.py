"""How much --mask-approx changes the mask: IoU of the approximate mask with the clean one.

Plays random-action episodes of each env, takes the clean robot mask of every --every-th agent step
and compares it with two approximations of that same mask: `envs.approximate_mask` (the authors'
SlimMaskWrapper: 3x down / up, sigma 0.5, threshold 0.9, the default today) and this
project's earlier transform (4x area down, bilinear up, sigma 1.5, threshold 0.5). Prints, per env
and transform, the mean / min / max IoU over the frames and the share of robot pixels kept.
`--skimage` also checks `envs.approximate_mask` against scikit-image's rescale and gaussian called as
the authors call them (scikit-image must be importable; it is not a dependency of this project).

    MUJOCO_GL=egl python benchmarks/mask_approx_iou.py --frames 40
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402
from scipy import ndimage  # noqa: E402

import envs  # noqa: E402

ENVS = ("walker-walk", "cup-catch", "cheetah-run", "metaworld-door-open", "metaworld-hammer",
        "kitchen-kettle", "adroit-door", "adroit-relocate")


def earlier(mask: np.ndarray) -> np.ndarray:
    """The transform --mask-approx used before it followed the authors (kept here only to compare with)."""
    h, w = mask.shape
    small = Image.fromarray(mask.astype(np.uint8) * 255).resize((w // 4, h // 4), Image.BOX)
    big = np.asarray(small.resize((w, h), Image.BILINEAR), dtype=np.float32) / 255.0
    return ndimage.gaussian_filter(big, sigma=1.5) > 0.5


def skimage_differences(masks: list[np.ndarray]) -> int:
    """Pixels where envs.approximate_mask differs from skimage: rescale by 1/3 then 3 (bilinear, no
    anti-aliasing) on the (H, W, 1) uint8 mask, x 255, gaussian sigma 0.5, > 0.9."""
    from skimage.filters import gaussian
    from skimage.transform import rescale
    wrong = 0
    for clean in masks:
        m = clean.astype(np.uint8)[..., None]
        up = rescale(rescale(m, (1 / 3, 1 / 3, 1), anti_aliasing=False), (3, 3, 1), anti_aliasing=False)
        wrong += int((envs.approximate_mask(clean) != (gaussian(up * 255.0, sigma=0.5) > 0.9)[..., 0]).sum())
    return wrong


def clean_masks(name: str, frames: int, every: int, seed: int) -> list[np.ndarray]:
    env = envs.make_env(name, seed=seed, frame_stack=1, render_quality="fast")
    rng = np.random.default_rng(seed)
    out, episode = [], 0
    obs, _ = env.reset(seed=seed)
    while len(out) < frames:
        for _ in range(every):
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            if terminated or truncated:
                episode += 1
                obs, _ = env.reset(seed=seed + episode)
        if obs["mask"][-1].any():
            out.append(obs["mask"][-1].astype(bool))
    env.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(ENVS))
    parser.add_argument("--frames", type=int, default=40, help="masks per env (empty masks skipped)")
    parser.add_argument("--every", type=int, default=5, help="agent steps between the masks taken")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skimage", action="store_true", help="also check against scikit-image (see above)")
    args = parser.parse_args()
    print("| env | transform | IoU mean | min | max | robot pixels kept | pixels added / robot |")
    print("|---|---|---|---|---|---|---|")
    checks = []
    for name in args.envs:
        masks = clean_masks(name, args.frames, args.every, args.seed)
        for label, transform in (("authors (3x, 0.5, 0.9)", envs.approximate_mask),
                                 ("earlier (4x, 1.5, 0.5)", earlier)):
            iou, kept, added = [], [], []
            for clean in masks:
                approx = transform(clean)
                iou.append((clean & approx).sum() / (clean | approx).sum())
                kept.append((clean & approx).sum() / clean.sum())
                added.append((approx & ~clean).sum() / clean.sum())
            print(f"| {name} | {label} | {np.mean(iou):.3f} | {np.min(iou):.3f} | {np.max(iou):.3f} | "
                  f"{np.mean(kept):.3f} | {np.mean(added):.3f} |")
        if args.skimage:
            checks.append(f"{name}: {skimage_differences(masks)} pixels differ from scikit-image's "
                          f"over {len(masks)} masks")
    print("\n".join(checks))


if __name__ == "__main__":
    main()
