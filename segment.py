"""Robot masks without a simulator: a small segmentation network trained on a few labelled frames.

SEAR needs the robot's mask for every frame. In simulation MuJoCo renders it (envs.py); on a real
robot it does not exist. The paper's answer (appendix "Real-World Robot Segmentation Model") is a
segmentation model fine-tuned on ~100 labelled images, and its ablations show that SEAR tolerates
noisy and approximate masks. This file trains such a model from N labelled frames and saves it;
``sear.py --mask-source learned:PATH`` then takes every mask target (and RGBM's input mask) from it.

Labelled frames come from either place, and both end up as the same arrays:
  * a folder of ``<name>.png`` (RGB) + ``<name>_mask.png`` (binary: 0/255 or 0/1) pairs, e.g. a
    real-robot user's own labels;
  * a suite (``--env``): frames of random-action episodes with the simulator's masks standing in
    for hand labels. ``export`` writes them as such a folder.

The network is a 3-level U-Net (plain torch), trained with Adam on BCE + soft dice, with the random
shift augmentation of DrQ-v2 (the same shift for image and mask). IoU is reported on held-out
frames of the training episodes, on frames of other episodes and, for Distracting Control, on
frames with unseen backgrounds (the envs' "eval" split). The model file (.pt) holds the weights,
the sizes needed to rebuild the network, and how it was trained: from a suite, its env and robot
(sear.py warns when the model is used on another robot), and its IoUs. ``train`` writes no model
whose held-out IoU is below IOU_FLOOR unless --force, and sear.py refuses one (IoUWatch: the same
floor on a run's learned_mask_iou).

    python segment.py train --env walker-walk-distracting --labels 100 --out masks/walker.pt
    python segment.py train --folder my_labels/ --out my.pt
    python segment.py export --env metaworld-door-open --labels 100 --out my_labels/

Layering: this file imports envs.py (only to collect frames); experiment.py imports this file; envs.py
knows nothing of it (make_env takes any callable as ``mask_model``).
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
import warnings
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError

from harness import cli  # storage errors as one line (cli imports nothing of the project)

FORMAT = "sear-mask-model"
VERSION = 1

# The held-out IoU below which `train` writes no model (unless --force) and sear.py refuses one.
# The paper's ablations show SEAR still learning on the authors' approximate masks, whose IoU with
# the clean mask is as low as 0.53 (walker-walk, docs/masks.md); below 0.5 a mask has more pixels
# wrong (robot missed, or background called robot) than robot pixels right, where no experiment
# says SEAR still works. A working model is far above it (0.97 with 100 labels, EXPERIMENTS.md
# rung LM); a broken one (too few steps) is near 0.
IOU_FLOOR = 0.5


class SegmentError(ValueError):
    """Bad user input (unreadable folder, mismatched pair, non-binary mask, bad model file): one line."""


# ================================================================================================
# The network
# ================================================================================================
def double_conv(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """A small U-Net (Ronneberger et al. 2015): len(channels) levels, each two 3x3 convolutions,
    2x max-pool down, nearest 2x up, skip connections by concatenation, one logit per pixel.
    Fully convolutional: any frame size whose levels pool evenly (84 -> 42 -> 21 with 3 levels)."""

    def __init__(self, channels=(8, 16, 32)):
        super().__init__()
        self.channels = tuple(int(c) for c in channels)
        self.down = nn.ModuleList()
        cin = 3
        for c in self.channels:
            self.down.append(double_conv(cin, c))
            cin = c
        self.up = nn.ModuleList(double_conv(c_deep + c, c) for c_deep, c in
                                zip(self.channels[:0:-1], self.channels[-2::-1]))
        self.head = nn.Conv2d(self.channels[0], 1, 1)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        """uint8-range RGB (B, 3, H, W) -> mask logits (B, H, W)."""
        x = rgb.float() / 255.0 - 0.5
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for block, skip in zip(self.up, skips[-2::-1]):
            x = block(torch.cat([F.interpolate(x, size=skip.shape[-2:], mode="nearest"), skip], dim=1))
        return self.head(x)[:, 0]


class MaskModel:
    """A trained UNet as a mask source: ``model(rgb)`` with uint8 RGB (3, H, W) or (B, 3, H, W) gives
    the bool robot mask (H, W) or (B, H, W), the sigmoid thresholded at 0.5. This is the callable
    envs.make_env(mask_model=) takes."""

    def __init__(self, net: UNet, meta: dict | None = None):
        self.net = net.eval()
        self.meta = meta or {}

    @torch.no_grad()
    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(np.ascontiguousarray(rgb))
        single = x.dim() == 3
        logits = self.net(x[None] if single else x)
        mask = (logits > 0).numpy()   # sigmoid > 0.5 <=> logit > 0
        return mask[0] if single else mask

    def save(self, path: str) -> None:
        """Atomically; a storage error is a cli.StorageError naming the file, no .tmp left behind."""
        path = str(Path(path).expanduser())
        with cli.storing(path):
            os.makedirs(os.path.dirname(path), exist_ok=True)
        payload = {"format": FORMAT, "version": VERSION, "channels": list(self.net.channels),
                   "state_dict": self.net.state_dict(), "meta": self.meta}
        cli.write_atomically(path, lambda f: cli.torch_save(payload, f))


def load_model(path: str) -> MaskModel:
    """Read a model file written by ``MaskModel.save``; SegmentError (one line) if it is missing,
    not a torch file, or not a mask model."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise SegmentError(f"mask model {path!r} does not exist or is not a file")
    not_model = f"mask model {path!r} is not a segment.py model file"
    train = "train one with python segment.py train"
    if not zipfile.is_zipfile(p):   # torch.save writes a zip archive
        raise SegmentError(f"{not_model} (not a torch file, or one cut short); {train}")
    try:
        with warnings.catch_warnings():   # torch warns (on stderr) about the pickles it then refuses
            warnings.simplefilter("ignore")
            payload = torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:   # weights_only refuses objects: a model file holds none
        raise SegmentError(f"{not_model} (a torch file holding more than tensors and numbers, such as a "
                           f"sear.py snapshot); {train}") from None
    except Exception:   # a damaged archive, or another program's zip (torch's own words name neither)
        raise SegmentError(f"{not_model} (a zip archive torch cannot read: damaged, or not torch's); "
                           f"{train}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise SegmentError(f"{not_model}; {train}")
    try:
        net = UNet(payload["channels"])
        net.load_state_dict(payload["state_dict"])
    except Exception as e:
        reason = " ".join(str(e).split()[:12]) or type(e).__name__
        raise SegmentError(f"mask model {path!r} does not rebuild ({reason})") from None
    return MaskModel(net, payload.get("meta", {}))


# ================================================================================================
# Labelled frames: a folder of PNG pairs, or a suite with the simulator's masks as labels
# ================================================================================================
MASK_SUFFIX = "_mask"


def _open(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB") if im.mode not in ("1", "L", "P", "RGB", "RGBA", "LA")
                              else im)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        reason = " ".join(str(e).split()) or type(e).__name__
        raise SegmentError(f"{path} is not a readable image: {reason}") from None


def _binary(mask: np.ndarray, path: Path) -> np.ndarray:
    """A mask file's pixels as bool; it must be binary (0/1 or 0/255; grey or equal RGB channels)."""
    if mask.ndim == 3:
        colour = mask[..., :3]
        if not (colour == colour[..., :1]).all():
            raise SegmentError(f"mask {path} is not binary: its colour channels differ (save it as a "
                               f"black/white PNG, robot = white)")
        mask = colour[..., 0]
    if mask.dtype == bool:
        return mask
    values = np.unique(mask)
    if not (set(values.tolist()) <= {0, 1} or set(values.tolist()) <= {0, 255}):
        raise SegmentError(f"mask {path} is not binary: it has {len(values)} distinct values, not only "
                           f"0 and 255 (or 0 and 1); save it as a black/white PNG, robot = white")
    return mask > 0


def _resize(rgb: np.ndarray, mask: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Bring a pair to size x size: the image bilinearly, the mask by area with a 0.5 threshold."""
    if rgb.shape[:2] == (size, size):
        return rgb, mask
    img = np.asarray(Image.fromarray(rgb).resize((size, size), Image.BILINEAR))
    area = np.asarray(Image.fromarray(mask.astype(np.uint8) * 255).resize((size, size), Image.BOX))
    return img, area >= 128


def read_folder(folder: str, size: int = 84) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Pairs ``<name>.png`` + ``<name>_mask.png`` of a folder -> images uint8 (N, 3, size, size),
    masks bool (N, size, size), names. Each image and its mask must have the same size (any size:
    both are brought to size x size)."""
    root = Path(folder).expanduser()
    if not root.is_dir():
        raise SegmentError(f"labels folder {folder!r} does not exist or is not a directory")
    try:
        files = sorted(p for p in root.iterdir() if p.suffix.lower() == ".png")
    except OSError as e:
        raise SegmentError(f"labels folder {folder!r} is not readable: {e.strerror or e}") from None
    masks = {p.stem[: -len(MASK_SUFFIX)]: p for p in files if p.stem.endswith(MASK_SUFFIX)}
    images = {p.stem: p for p in files if not p.stem.endswith(MASK_SUFFIX)}
    names = sorted(set(images) & set(masks))
    if not names:
        raise SegmentError(f"labels folder {folder!r} holds no <name>.png + <name>{MASK_SUFFIX}.png pairs")
    unpaired = sorted(set(images) ^ set(masks))
    if unpaired:
        raise SegmentError(f"labels folder {folder!r}: {len(unpaired)} file(s) without their pair, e.g. "
                           f"{unpaired[0]!r} (each <name>.png needs <name>{MASK_SUFFIX}.png)")
    rgbs, bins = [], []
    for name in names:
        rgb, mask = _open(images[name]), _open(masks[name])
        if rgb.shape[:2] != mask.shape[:2]:
            raise SegmentError(f"{images[name].name} is {rgb.shape[1]}x{rgb.shape[0]} but its mask "
                               f"{masks[name].name} is {mask.shape[1]}x{mask.shape[0]}; they must match")
        if rgb.ndim == 2:
            rgb = np.repeat(rgb[..., None], 3, axis=-1)
        rgb, mask = _resize(rgb[..., :3], _binary(mask, masks[name]), size)
        rgbs.append(rgb.transpose(2, 0, 1))
        bins.append(mask)
    return np.stack(rgbs).astype(np.uint8), np.stack(bins), names


def write_folder(folder: str, images: np.ndarray, masks: np.ndarray, prefix: str = "frame") -> list[str]:
    """Write frames as the labels folder read_folder reads (mask: 0/255 grey PNG). Refuses a folder
    that already holds PNGs (nothing is overwritten)."""
    root = Path(folder).expanduser()
    if root.exists() and any(root.glob("*.png")):
        raise SegmentError(f"{folder} already holds PNG files; refusing to overwrite (give a new folder)")
    with cli.storing(str(root)):
        root.mkdir(parents=True, exist_ok=True)
    names = [f"{prefix}{i:05d}" for i in range(len(images))]
    for name, rgb, mask in zip(names, images, masks):
        for path, pixels in ((root / f"{name}.png", rgb.transpose(1, 2, 0)),
                             (root / f"{name}{MASK_SUFFIX}.png", mask.astype(np.uint8) * 255)):
            with cli.storing(str(path)):
                Image.fromarray(pixels).save(path)
    return names


def collect(env_name: str, n: int, *, seed: int = 0, split: str = "train", every: int = 4,
            interleave: bool = False, render_quality: str = "fast", max_steps: int = 100, **env_kwargs):
    """n frames of random-action episodes with the simulator's masks as labels: every ``every``-th
    agent step of episodes of at most ``max_steps`` steps (reset seeds seed, seed + 1, ...).
    ``interleave``: also return as many frames half-way between those (the same episodes, never the
    same frames: the "held-out frames" of the training episodes). Returns (images uint8 (n, 3, H, W),
    masks bool (n, H, W)) or, interleaved, the two pairs."""
    import envs   # here: reading a labels folder needs no MuJoCo
    env = envs.make_env(env_name, seed=seed, frame_stack=1, render_quality=render_quality, split=split,
                        **env_kwargs)
    rng = np.random.default_rng(seed)
    take, between = ([], []), ([], [])
    episode = 0
    try:
        while len(take[0]) < n:
            obs, _ = env.reset(seed=seed + episode)
            episode += 1
            for t in range(max_steps):
                if t % every == 0 and len(take[0]) < n:
                    take[0].append(obs["pixels"]), take[1].append(obs["mask"][0].astype(bool))
                elif interleave and t % every == every // 2 and len(between[0]) < len(take[0]):
                    between[0].append(obs["pixels"]), between[1].append(obs["mask"][0].astype(bool))
                obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
                if terminated or truncated:
                    break
    finally:
        env.close()
    pair = lambda lists: (np.stack(lists[0]), np.stack(lists[1]))   # noqa: E731
    return (pair(take), pair(between)) if interleave else pair(take)


# ================================================================================================
# Training and evaluation
# ================================================================================================
def iou(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean over frames of intersection / union of bool masks (N, H, W); frames where both are
    empty (nothing to find, nothing found) are left out. NaN if every frame is."""
    pred, true = pred.reshape(len(pred), -1), true.reshape(len(true), -1)
    union = (pred | true).sum(1)
    inter = (pred & true).sum(1)
    keep = union > 0
    return float(np.mean(inter[keep] / union[keep])) if keep.any() else float("nan")


def shift(x: torch.Tensor, pad: int, rng: np.random.Generator) -> torch.Tensor:
    """DrQ-v2's random shift: pad by replicating edges, crop back at a random offset per sample.
    x is the image and the mask stacked along channels, so both move together."""
    n, _, h, w = x.shape
    padded = F.pad(x, (pad,) * 4, mode="replicate")
    dy, dx = rng.integers(0, 2 * pad + 1, size=(2, n))
    return torch.stack([padded[i, :, dy[i]:dy[i] + h, dx[i]:dx[i] + w] for i in range(n)])


def dice_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1 - soft dice per frame, averaged: the overlap term IoU rewards, which BCE under-weights
    when the robot covers a few percent of the frame."""
    p = torch.sigmoid(logits).flatten(1)
    t = target.flatten(1)
    return (1 - (2 * (p * t).sum(1) + 1) / (p.sum(1) + t.sum(1) + 1)).mean()


def train_model(images: np.ndarray, masks: np.ndarray, *, steps: int = 600, batch_size: int = 16,
                lr: float = 1e-3, channels=(8, 16, 32), pad: int = 4, seed: int = 0,
                log_every: int = 0, meta: dict | None = None) -> MaskModel:
    """Adam on BCE + dice over random mini-batches of the labelled frames, randomly shifted."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = UNet(channels)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    x_all = torch.as_tensor(images).float()
    y_all = torch.as_tensor(masks).float()[:, None]
    began = time.time()
    for step in range(1, steps + 1):
        idx = rng.choice(len(images), size=min(batch_size, len(images)), replace=len(images) < batch_size)
        both = shift(torch.cat([x_all[idx], y_all[idx]], dim=1), pad, rng) if pad else \
            torch.cat([x_all[idx], y_all[idx]], dim=1)
        x, y = both[:, :3], both[:, 3]
        logits = net(x)
        loss = F.binary_cross_entropy_with_logits(logits, y) + dice_loss(logits, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if log_every and step % log_every == 0:
            print(f"step {step}/{steps}: loss {loss.item():.4f} ({time.time() - began:.0f} s)", flush=True)
    meta = {**(meta or {}), "labels": int(len(images)), "steps": steps, "batch_size": batch_size, "lr": lr,
            "train_seconds": round(time.time() - began, 1), "torch_threads": torch.get_num_threads()}
    return MaskModel(net, meta)


def predict(model: MaskModel, images: np.ndarray, batch: int = 64) -> np.ndarray:
    return np.concatenate([model(images[i:i + batch]) for i in range(0, len(images), batch)])


def evaluation_sets(env_name: str, n: int, *, seed: int, frames: int = 200, **env_kwargs):
    """The labelled frames and the test sets of a suite: (train images, masks), {name: (images, masks)}
    with "held-out" (the training episodes' other frames), "other episodes" (episodes from reset seeds
    far from the training ones) and, for Distracting Control, "unseen backgrounds" (the eval split)."""
    (images, masks), held_out = collect(env_name, n, seed=seed, interleave=True, **env_kwargs)
    tests = {"held-out": held_out,
             "other episodes": collect(env_name, frames, seed=seed + 10_000, **env_kwargs)}
    if env_name.endswith("-distracting"):
        tests["unseen backgrounds"] = collect(env_name, frames, seed=seed + 20_000, split="eval", **env_kwargs)
    return images, masks, tests


class LearnedMaskIoU(gym.Wrapper):
    """An env whose obs["mask"] comes from a mask model, with the simulator's mask in
    info["true_mask"] (envs.make_env(mask_model=, render_mask=True)): scores the newest mask of every
    observation against it. ``pop()`` gives the mean IoU over the frames seen since the last pop
    (frames where both masks are empty left out) and starts again; ``low_iou``, the run's IoUWatch on
    those means (one eval env per run). It only reads info["true_mask"]: nothing downstream (agent,
    replay) ever sees it."""

    def __init__(self, env):
        super().__init__(env)
        self.scores: list[float] = []
        self.low_iou = IoUWatch()

    def see(self, obs, info):
        self.scores.append(iou(obs["mask"][-1:].astype(bool), info["true_mask"][None]))

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.see(obs, info)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.see(obs, info)
        return obs, reward, terminated, truncated, info

    def pop(self) -> float:
        scores, self.scores = self.scores, []
        scores = [v for v in scores if not np.isnan(v)]
        return float(np.mean(scores)) if scores else float("nan")


# ================================================================================================
# CLI
# ================================================================================================
def parse_channels(text: str) -> tuple[int, ...]:
    try:
        channels = tuple(int(c) for c in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") \
            from None
    if not channels or min(channels) < 1:
        raise argparse.ArgumentTypeError(f"channels must be positive, got {text!r}")
    return channels


def build_parser() -> cli.OneLineParser:
    """segment.py's commands and flags; a bad one is a cli.ConfigError (one line)."""
    parser = cli.OneLineParser(prog="segment.py", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=cli.OneLineParser)
    train = sub.add_parser("train", help="train a mask model from labelled frames and save it")
    source = train.add_mutually_exclusive_group(required=True)
    source.add_argument("--folder", help="folder of <name>.png + <name>_mask.png pairs")
    source.add_argument("--env", help="a suite (see envs.py --list): random-action frames, simulator "
                                      "masks as labels")
    train.add_argument("--out", required=True, help="model file to write (.pt)")
    train.add_argument("--labels", type=int, default=100,
                       help="--env: number of labelled frames (default 100)")
    train.add_argument("--holdout", type=float, default=0.2,
                       help="--folder: fraction of the pairs held out to report IoU on "
                            "(default 0.2)")
    train.add_argument("--steps", type=int, default=600, help="Adam steps (default 600)")
    train.add_argument("--batch-size", type=int, default=16)
    train.add_argument("--lr", type=float, default=1e-3)
    train.add_argument("--channels", type=parse_channels, default=(8, 16, 32),
                       help="U-Net widths per level (default 8,16,32)")
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--threads", type=int, default=0,
                       help="torch threads (0 = $OMP_NUM_THREADS or all cores)")
    train.add_argument("--force", action="store_true",
                       help=f"overwrite an existing --out, and write the model even if its held-out "
                            f"IoU is below {IOU_FLOOR} (the file records it; sear.py then warns "
                            f"instead of refusing it)")
    export = sub.add_parser("export",
                            help="write a suite's frames and simulator masks as a labels folder")
    export.add_argument("--env", required=True)
    export.add_argument("--labels", type=int, default=100)
    export.add_argument("--out", required=True, help="new folder for the PNG pairs")
    export.add_argument("--seed", type=int, default=0)
    for p in (train, export):
        p.add_argument("--render-quality", default="fast", choices=["paper", "fast"],
                       help="--env: rendering (default fast)")
    return parser


def check_env_name(name: str) -> None:
    import envs
    try:
        envs._parse_name(name)
    except envs.EnvError as e:
        raise SegmentError(str(e)) from None


def robot_record(args) -> dict:
    """What the model was trained on, for sear.py's warning when it is used on another robot:
    {"robot": ...} for a suite's frames; a labels folder's robot is not known."""
    if not args.env:
        return {}
    import envs
    return {"robot": envs.robot_name(args.env)}


def run_train(args) -> None:
    if os.path.exists(args.out) and not args.force:
        raise SegmentError(f"{args.out} exists; refusing to overwrite it (use --force)")
    for name, value, low in (("--labels", args.labels, 1), ("--steps", args.steps, 1), ("--batch-size", args.batch_size, 1)):
        if value < low:
            raise SegmentError(f"{name} must be >= {low}, got {value}")
    if not 0 <= args.holdout < 1:
        raise SegmentError(f"--holdout must be in [0, 1), got {args.holdout}")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.folder:
        images, masks, names = read_folder(args.folder)
        order = np.random.default_rng(args.seed).permutation(len(images))
        k = int(round(args.holdout * len(images))) if len(images) >= 5 else 0
        tests = {"held-out": (images[order[:k]], masks[order[:k]])} if k else {}
        images, masks = images[order[k:]], masks[order[k:]]
        source = {"folder": str(Path(args.folder).resolve()), "pairs": len(names)}
    else:
        check_env_name(args.env)
        began = time.time()
        images, masks, tests = evaluation_sets(args.env, args.labels, seed=args.seed,
                                               render_quality=args.render_quality)
        print(f"collected {len(images)} labelled frames of {args.env} + "
              + ", ".join(f"{len(v[0])} {k}" for k, v in tests.items()) + f" in {time.time() - began:.0f} s")
        source = {"env": args.env, "render_quality": args.render_quality}
    print(f"training a U-Net {','.join(map(str, args.channels))} on {len(images)} frames for {args.steps} steps "
          f"({torch.get_num_threads()} threads)", flush=True)
    model = train_model(images, masks, steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                        channels=args.channels, seed=args.seed, log_every=max(1, args.steps // 5),
                        meta={"source": source, "size": int(images.shape[-1]), **robot_record(args)})
    scores = {"train": iou(predict(model, images), masks)}
    scores.update({name: iou(predict(model, x), y) for name, (x, y) in tests.items()})
    model.meta["iou"] = {k: round(v, 4) for k, v in scores.items()}
    print("IoU: " + ", ".join(f"{k} {v:.3f}" for k, v in scores.items()))
    below = below_floor(scores)
    model.meta["iou_floor"] = IOU_FLOOR
    if below and not args.force:
        raise SegmentError(f"{below}; no model written (more labels or --steps, or --force to write it anyway)")
    if below:  # the file says so, and sear.py warns at every start instead of refusing it
        model.meta["forced_below_floor"] = True
    elif "held-out" not in tests:
        print(f"held-out IoU not measured (no held-out pairs: --holdout 0, or fewer than 5 pairs); "
              f"sear.py cannot check this model against the floor {IOU_FLOOR}")
    model.save(args.out)
    if below:  # after the save: a storage error stays the one line on stderr
        print(f"segment.py: warning: {below}; written because of --force", file=sys.stderr)
    print(f"wrote {args.out} (trained in {model.meta['train_seconds']} s)")
    print(json.dumps({"labels": len(images), "train_seconds": model.meta["train_seconds"], "iou": model.meta["iou"]}))


def below_floor(scores: dict) -> str | None:
    """Why a freshly trained model fails IOU_FLOOR, or None. The held-out IoU decides; without
    held-out pairs the training frames' IoU does: a model below the floor on the very frames it
    learned from is no better on others."""
    name = "held-out" if "held-out" in scores else "train"
    value = scores[name]
    if np.isnan(value) or value >= IOU_FLOOR:   # NaN: no frame with any robot in it to score
        return None
    return f"the model's {name} IoU is {value:.3f}, below the floor {IOU_FLOOR}"


def recorded_iou(meta: dict) -> tuple[str, str]:
    """sear.py's verdict on a model file: (what, message) with what "ok" (print the message),
    "warn" (a model written below the floor with --force: the user's choice, said loudly) or
    "refuse" (below the floor without that record: only an older segment.py wrote such files).
    A file without a held-out IoU (older files, a labels folder without held-out pairs) is "ok"."""
    scores = meta.get("iou") if isinstance(meta.get("iou"), dict) else {}
    held = scores.get("held-out")
    if meta.get("forced_below_floor"):
        shown = ", ".join(f"{k} {v:.3f}" for k, v in scores.items())
        return "warn", (f"the mask model was written below the IoU floor {IOU_FLOOR} with segment.py train --force "
                        f"(IoU: {shown}): SEAR will train on masks with more pixels wrong than robot pixels "
                        f"right (eval.csv learned_mask_iou shows how far off)")
    if not isinstance(held, (int, float)) or np.isnan(held):
        return "ok", (f"mask model: held-out IoU not recorded (an older model file, or no held-out pairs); "
                      f"not checked against the floor {IOU_FLOOR}")
    if held < IOU_FLOOR:
        return "refuse", (f"the mask model's held-out IoU is {held:.3f}, below the floor {IOU_FLOOR}; train a "
                          f"better one with python segment.py train (more labels or --steps)")
    return "ok", f"mask model: held-out IoU {held:.3f} (floor {IOU_FLOOR})"


class IoUWatch:
    """A run's learned_mask_iou, evaluation after evaluation: ``see(iou, frame)`` returns a warning,
    once, when the last PATIENCE evaluations were all below IOU_FLOOR, else None. The model is fixed
    but the frames are not: a model that scored well on its labels can miss the robot in the poses a
    learning policy reaches. One evaluation can be a narrow set of frames (the untrained policy's at
    frame 0, a single episode); two in a row, at different stages of the policy, say the model misses
    the robot in this run. Evaluations without a score (NaN: the robot never in view) neither count
    nor break the run of low ones."""

    PATIENCE = 2

    def __init__(self):
        self.low: list[tuple[float, int | None]] = []
        self.warned = False

    def see(self, value: float, frame: int | None = None) -> str | None:
        if self.warned or value is None or np.isnan(value):
            return None
        self.low = self.low + [(value, frame)] if value < IOU_FLOOR else []
        if len(self.low) < self.PATIENCE:
            return None
        self.warned = True
        where = ", ".join(f"{v:.3f}" + (f" at frame {f}" if f is not None else "") for v, f in self.low)
        return (f"learned_mask_iou has stayed below {IOU_FLOOR} for {len(self.low)} evaluations ({where}): the "
                f"learned masks have more pixels wrong than robot pixels right in this run's frames, so SEAR's "
                f"mask decoder and the latent's robot half learn from wrong masks; label frames like these "
                f"and train a new model (python segment.py train)")


def run_export(args) -> None:
    check_env_name(args.env)
    if args.labels < 1:
        raise SegmentError(f"--labels must be >= 1, got {args.labels}")
    root = Path(args.out).expanduser()
    if root.exists() and (not root.is_dir() or any(root.glob("*.png"))):
        raise SegmentError(f"{args.out} exists and is not an empty folder; give a new folder")
    images, masks = collect(args.env, args.labels, seed=args.seed, render_quality=args.render_quality)
    write_folder(args.out, images, masks, prefix=args.env.replace("-", "_") + "_")
    print(f"wrote {len(images)} image + mask pairs to {args.out}")


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
        run_train(args) if args.command == "train" else run_export(args)
    except (SegmentError, cli.StorageError, cli.ConfigError) as e:
        print(f"segment.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
