"""SEAR: Structured Environment-Agent Representations for visual RL (ICML 2023).

One readable file: DrQ-v2 (DDPG from pixels: random-shift augmentation, n-step returns, clipped
double-Q, linearly decaying exploration noise) whose image encoder is also trained by two decoders.
The encoder's latent is split in two halves: one half predicts the robot's binary segmentation
mask (Eq. 4), the other reconstructs the image (Eq. 5); the total loss is Eq. 6,

    L = L_critic + c1 * L_recon + c2 * L_mask,    c1 = 0.01, c2 = 0.0025.

The baselines of the paper are the same agent with another auxiliary loss (one seam, `AuxLoss`):
drq (none), ae, mae, curl, rgbm (mask as an input channel) and sear-nosplit.

Sections, in reading order:
  1. Config            - a dataclass; the CLI flags are generated from it.
  2. Networks          - encoders, decoders, actor, critic.
  3. Augmentation      - random shift, the same shift for image and mask.
  4. Auxiliary losses  - SEAR and the baselines behind one seam; the METHODS table.
  5. Agent             - act, update_critic (Eq. 6), update_actor.
  6. Replay buffer     - frames stored once, masks bit-packed, n-step returns at sampling.
  7. Run directory     - CSV logs, progress line, atomic snapshots.
  8. Training loop
  9. CLI

Usage:  python sear.py --env walker-walk-distracting [--method sear] [--seed 1]
        python sear.py --resume runs/<run dir>
        python sear.py --env metaworld-mt10                                # multi-task, per-task evaluation
        python sear.py --env metaworld-hammer --init-from runs/<mt10 run>  # transfer
"""
from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import json
import math
import os
import queue
import random
import sys
import threading
import time
from dataclasses import dataclass, field

# Huge pages for malloc'd blocks; never mmap a block of its own (mmap_max=0) and never give freed
# heap back to the OS (trim_threshold 64 GiB): the update's large activation buffers are then
# reused from one update to the next instead of being mapped, faulted in and unmapped each time.
GLIBC_MALLOC = ("glibc.malloc.hugetlb=1", "glibc.malloc.mmap_max=0", f"glibc.malloc.trim_threshold={64 << 30}")


def reexec_with_huge_pages():
    """On Linux/glibc, restart this process once with the GLIBC_MALLOC tunables above.
    Why: on CPU the 84x84x32 decoder activations (tens of MB at batch 256) would otherwise be mapped
    and unmapped by glibc at every update: with 4 KB pages ~1.8M page faults per SEAR update, and
    still ~60k with huge pages alone (EXPERIMENTS.md, "Update speed"). glibc reads GLIBC_TUNABLES
    only at start-up, hence the re-exec. Other platforms ignore the variable."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if not sys.platform.startswith("linux") or "glibc.malloc.hugetlb" in tunables:
        return
    os.environ["GLIBC_TUNABLES"] = ":".join(filter(None, [tunables, *GLIBC_MALLOC]))
    os.execv(sys.executable, sys.orig_argv)  # orig_argv keeps interpreter flags such as -u


if __name__ == "__main__":  # before numpy and torch load: a re-exec costs a bare interpreter, not torch's import
    reexec_with_huge_pages()

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn as nn  # noqa: E402
import torch.nn.functional as F  # noqa: E402

import segment  # noqa: E402  (the learned mask source; it imports envs only when collecting frames)


# ================================================================================================
# 1. Config
# ================================================================================================
def arg(default, doc):
    """A config field with its one-line doc (shown by --help)."""
    return field(default=default, metadata={"doc": doc})


@dataclass
class Config:
    # --- run ---
    env: str = arg("walker-walk", "task name; see envs.py (e.g. walker-walk-distracting, metaworld-door-open)")
    method: str = arg("sear", "sear | drq | ae | mae | curl | rgbm | sear-nosplit")
    seed: int = arg(1, "seeds python, numpy, torch and the environments")
    frames: int = arg(1_000_000, "environment frames to train for (frames = agent steps x action repeat)")
    device: str = arg("auto", "auto (cuda when available, else cpu) | cpu | cuda | cuda:N")
    precision: str = arg("fp32", "fp32 | bf16: the convolutional encoder and decoders under bf16 autocast; "
                                 "actor, critic and losses stay fp32")
    prefetch: str = arg("auto", "auto (on with CUDA) | on | off: sample and copy the next batch in a "
                                "background thread while the current update runs")
    threads: int = arg(0, "torch CPU threads; 0 = $OMP_NUM_THREADS, else every core this process may use. "
                          "Several runs on one machine: give each cores / runs")
    run_root: str = arg("runs", "folder that holds run directories")
    resume: str = arg("", "run directory to continue from its last snapshot")
    recipe: str = arg("paper", "paper (the paper's hyper-parameter table) | authors (their released code "
                               "where the two differ: RECIPES below, README's table); explicit flags win")
    save_buffer: bool = arg(False, "also snapshot the replay buffer: --resume then continues exactly")
    save_video: bool = arg(False, "write each evaluation's first episode to videos/eval_<frame>.mp4: camera | true "
                                  "mask | predicted mask | reconstruction (the panels the method has)")
    init_from: str = arg("", "transfer: start from the snapshot.pt of this run directory (e.g. pre-trained on "
                             "metaworld-mt10); method and network sizes follow that run unless given")
    init_parts: str = arg("all", "with --init-from, what to copy: encoder | encoder+decoders (the method's "
                                 "auxiliary networks too) | all (also actor and critic: the authors' default, "
                                 "just_encoder_decoders false); the rest and the optimisers start fresh")
    # --- environment (paper hyper-parameter table) ---
    action_repeat: int = arg(0, "0 = the suite's default (2 dm_control and Meta-World, 1 Kitchen and Adroit)")
    frame_stack: int = arg(3, "frames stacked into one observation")
    max_episode_steps: int = arg(0, "0 = the suite's time limit; N > 0 truncates episodes after N agent steps")
    mask_noise: float = arg(0.0, "probability that a robot pixel of the mask is set to background")
    mask_approx: bool = arg(False, "use approximate masks: the authors' 3x down / up, Gaussian blur (sigma 0.5), "
                                   "threshold 0.9 (envs.approximate_mask)")
    mask_downsample: str = arg("majority", "manipulation suites' 252->84 mask: majority (3x3 vote) | stride (authors')")
    mask_source: str = arg("sim", "sim (the simulator's segmentation render) | learned:PATH (a segment.py model "
                                  "applied to every frame gives every mask target and RGBM's input mask; "
                                  "--mask-noise / --mask-approx then corrupt its masks)")
    learned_mask_iou: bool = arg(True, "with --mask-source learned:PATH, render the simulator's mask in evaluation "
                                       "episodes only to report the learned masks' IoU (eval.csv learned_mask_iou), "
                                       "never as a target; --no-learned-mask-iou never renders one")
    backgrounds: str = arg("", "Distracting Control: folder of images or DAVIS JPEGImages/480p ('' = built-in)")
    difficulty: str = arg("medium", "Distracting Control: easy | medium | hard = 4 | 8 | all backgrounds (authors: medium)")
    render_quality: str = arg("paper", "paper (suite's own shadows) | fast (no shadows, no multisampling)")
    camera_distraction: float = arg(0.0, "Distracting Control, beyond the paper: camera offset scale (original: 0.1-0.3)")
    color_distraction: float = arg(0.0, "Distracting Control, beyond the paper: robot colour shift (original: 0.1-0.3)")
    kitchen_camera: str = arg("fixed", "Kitchen: fixed (the authors' view) | random (one of their 6 views per episode)")
    # --- DrQ-v2 (paper hyper-parameter table) ---
    replay_size: int = arg(250_000, "replay buffer capacity in transitions")
    seed_frames: int = arg(4000, "frames collected before the first update (DrQ-v2's num_seed_frames)")
    exploration_steps: int = arg(2000, "first agent steps of uniformly random actions (DrQ-v2's num_expl_steps); "
                                       "then the actor plus noise acts, updated or not yet")
    nstep: int = arg(3, "n of the n-step return")
    batch_size: int = arg(256, "mini-batch size")
    discount: float = arg(0.99, "discount factor gamma")
    lr: float = arg(1e-4, "Adam learning rate of actor, critic, encoder and decoders")
    update_every: int = arg(2, "agent steps between updates")
    critic_tau: float = arg(0.01, "Polyak rate of the target critic")
    feature_dim: int = arg(50, "actor/critic trunk width (Linear + LayerNorm + tanh)")
    latent_dim: int = arg(4096, "encoder latent size (SEAR's pooled encoder); each half is 2048")
    hidden_dim: int = arg(1024, "actor and critic MLP width")
    std_start: float = arg(1.0, "exploration std at the start of the linear schedule")
    std_end: float = arg(0.1, "exploration std at the end of the linear schedule")
    std_steps: int = arg(500_000, "AGENT STEPS over which the std decays, as DrQ-v2 (frames = steps x action "
                                  "repeat); plain dm_control tasks: DrQ-v2's 100k / 500k / 2M by task, task sets 2M")
    std_clip: float = arg(0.3, "clip of the exploration noise in the actor update (DrQ-v2)")
    eval_every: int = arg(10_000, "frames between evaluations (and snapshots)")
    eval_episodes: int = arg(10, "episodes per evaluation, mean action (task sets: at least this many in all)")
    eval_episodes_per_task: int = arg(0, "task sets (metaworld-mt*): evaluation episodes of every task; "
                                         "0 = ceil(--eval-episodes / number of tasks)")
    # --- SEAR, Eq. 6 (paper: c1 = 0.01, c2 = 0.0025; authors' code: 1.0 and 0.25, same 4:1 ratio) ---
    recon_coef: float = arg(0.01, "c1: weight of the reconstruction loss (mae too; ae uses 2 x c1, as the authors)")
    mask_coef: float = arg(0.0025, "c2: weight of the mask loss")
    # --- baselines (each default from its source) ---
    ae_latent_lambda: float = arg(0.0, "ae: L2 penalty on the latent (authors' DrQ-AE: none; SAC-AE: 1e-6)")
    mae_ratio: float = arg(0.75, "mae: fraction of patches hidden (MAE, He et al. 2022)")
    mae_patch: int = arg(12, "mae: patch side in pixels (84 = 7 x 12)")
    curl_tau: float = arg(0.05, "curl: EMA rate of the key encoder (CURL, Laskin et al. 2020)")
    curl_dim: int = arg(128, "curl: projection size of query and key")
    curl_coef: float = arg(1.0, "curl: weight of the contrastive loss (CURL adds it with weight 1)")
    # --- logging ---
    log_every: float = arg(10.0, "seconds between progress lines")
    # --- run directory / snapshots ---
    snapshot_minutes: float = arg(10.0, "minutes of wall time between snapshots, each written at the next "
                                        "episode end (0 = after every episode)")


def _walker(cfg):
    return cfg.env.startswith("walker-")


def _humanoid(cfg):
    return cfg.env in ("humanoid-run", "humanoid-stand", "humanoid-walk")


def _manipulation(cfg):
    return cfg.env.split("-")[0] in ("metaworld", "kitchen", "adroit")


def _multitask(cfg):
    import envs  # imported late so --help needs no MuJoCo
    return envs.is_task_set(cfg.env)


def _authors_discount(cfg):
    import envs  # the suite's default action repeat; imported late so --help needs no MuJoCo
    return round(0.99 ** (1 + (cfg.action_repeat or envs.default_action_repeat(cfg.env))), 6)


# Every value where the paper's hyper-parameter table and the authors' released code
# (github.com/sear-rl/sear-rl) differ: (field, applies to, authors' value, source). The Config defaults
# are the paper's values; --recipe authors replaces these unless the flag is given explicitly.
RECIPES = {"authors": (
    ("recon_coef", lambda cfg: True, 1.0, "sear/cfgs/agent/sear.yaml: reconstruction_loss_coeff"),
    ("mask_coef", lambda cfg: True, 0.25, "sear/cfgs/agent/sear.yaml: mask_loss_coeff"),
    ("nstep", _walker, 1, "sear/cfgs/task/distracting_walker_walk.yaml: nstep (DrQ-v2's walker config)"),
    ("batch_size", _walker, 512, "sear/cfgs/task/distracting_walker_walk.yaml: batch_size"),
    ("lr", _humanoid, 8e-5, "sear/cfgs/task/humanoid_{run,stand,walk}.yaml: lr (DrQ-v2's)"),
    ("feature_dim", _humanoid, 100, "sear/cfgs/task/humanoid_{run,stand,walk}.yaml: feature_dim (DrQ-v2's)"),
    ("replay_size", lambda cfg: cfg.env == "quadruped-run", 100_000,
     "sear/cfgs/task/quadruped_run.yaml: replay_buffer_size (DrQ-v2's)"),
    # Their Meta-World / Kitchen / Adroit wrappers return discount 0.99 for every env step, and the
    # replay multiplies by 0.99 again per agent step: gamma = 0.99^(action repeat + 1) per step.
    ("discount", _manipulation, _authors_discount,
     "sear/environments/{metaworld,kitchen,adroit}_dm_env.py step(), sear/replay_buffer.py"),
    ("mask_downsample", _manipulation, "stride", "sear/environments/wrappers.py: SegmentationFilter [::3, ::3]"),
    # The paper's multi-task latent is 512 (TASK_DEFAULTS below); the authors' code keeps 4096 there too.
    ("latent_dim", _multitask, 4096, "sear/cfgs/agent/sear.yaml: latent_dim 4096 (no task cfg overrides it)"),
)}


def _drqv2_std_steps(cfg):
    import envs  # DrQ-v2's per-task table lives with the other suite facts
    return envs.exploration_std_steps(cfg.env)


# Per-task defaults, applied under both recipes before the recipe's own rows. The paper's multi-task
# settings (its hyper-parameter table): the task sets (metaworld-mt3, -mt10, -mt50) train with a smaller
# latent and a 4x longer exploration schedule; the authors' code keeps latent 4096 there (its row in
# RECIPES). Plain dm_control tasks (the paper is silent) take DrQ-v2's exploration schedule by task.
TASK_DEFAULTS = (
    ("latent_dim", _multitask, 512, "paper, hyper-parameter table, multi-task"),
    ("std_steps", _multitask, 2_000_000, "paper, hyper-parameter table, multi-task; the authors' "
                                         "multi-task task cfgs: stddev_schedule linear(1.0,0.1,2000000)"),
    ("std_steps", lambda cfg: _drqv2_std_steps(cfg) is not None, _drqv2_std_steps,
     "DrQ-v2's and the authors' cfgs/task/{easy,medium,hard}.yaml: stddev_schedule by task"),
)


def apply_recipe(cfg, explicit: set) -> list[str]:
    """Set the per-task rows (TASK_DEFAULTS), then the recipe's values on `cfg`, except fields the user
    gave explicitly. Returns what changed."""
    changed = {}  # a recipe row may override a per-task row: report the value that stands
    for name, applies, value, source in (*TASK_DEFAULTS, *RECIPES.get(cfg.recipe, ())):
        if name in explicit or not applies(cfg):
            continue
        setattr(cfg, name, value(cfg) if callable(value) else value)
        changed[name] = f"{name}={getattr(cfg, name)} ({source})"
    return list(changed.values())


class ConfigError(ValueError):
    """Bad user input: reported as one line on stderr."""


def validate(cfg: Config) -> None:
    positive = ["frames", "frame_stack", "replay_size", "nstep", "batch_size", "update_every", "eval_episodes",
                "feature_dim", "latent_dim", "hidden_dim", "std_steps", "eval_every",
                "mae_patch", "curl_dim"]
    for name in positive:
        if getattr(cfg, name) <= 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be > 0, got {getattr(cfg, name)}")
    for name in ["action_repeat", "max_episode_steps", "seed_frames", "exploration_steps", "lr",
                 "recon_coef", "mask_coef", "ae_latent_lambda", "curl_coef", "std_end", "std_clip"]:
        if getattr(cfg, name) < 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(cfg, name)}")
    for name in ["discount", "critic_tau", "curl_tau", "mask_noise", "mae_ratio", "camera_distraction",
                 "color_distraction"]:
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise ConfigError(f"--{name.replace('_', '-')} must be in [0, 1], got {getattr(cfg, name)}")
    if cfg.recipe not in ("paper", *RECIPES):
        raise ConfigError(f"--recipe must be paper or {' or '.join(RECIPES)}, got '{cfg.recipe}'")
    if cfg.method not in METHODS:
        raise ConfigError(f"unknown method '{cfg.method}'; valid: {', '.join(METHODS)}")
    if cfg.latent_dim % 2:
        raise ConfigError(f"--latent-dim must be even (it is split in two halves), got {cfg.latent_dim}")
    if 84 % cfg.mae_patch:
        raise ConfigError(f"--mae-patch must divide 84, got {cfg.mae_patch}")
    if cfg.difficulty not in ("easy", "medium", "hard"):
        raise ConfigError(f"--difficulty must be easy, medium or hard, got '{cfg.difficulty}'")
    if cfg.mask_downsample not in ("majority", "stride"):
        raise ConfigError(f"--mask-downsample must be majority or stride, got '{cfg.mask_downsample}'")
    if cfg.mask_source != "sim" and not (cfg.mask_source.startswith("learned:") and cfg.mask_source[8:]):
        raise ConfigError(f"--mask-source must be sim or learned:PATH (a segment.py model file), got "
                          f"'{cfg.mask_source}'")
    if cfg.mask_source != "sim" and not METHODS[cfg.method].uses_mask:
        raise ConfigError(f"--mask-source {cfg.mask_source} is for methods that use the robot mask "
                          f"({', '.join(m for m in METHODS if METHODS[m].uses_mask)}), not {cfg.method}")
    if cfg.precision not in ("fp32", "bf16"):
        raise ConfigError(f"--precision must be fp32 or bf16, got '{cfg.precision}'")
    if not cfg.snapshot_minutes >= 0:
        raise ConfigError(f"--snapshot-minutes must be >= 0, got {cfg.snapshot_minutes}")
    if cfg.prefetch not in ("auto", "on", "off"):
        raise ConfigError(f"--prefetch must be auto, on or off, got '{cfg.prefetch}'")
    if cfg.threads < 0:
        raise ConfigError(f"--threads must be >= 0, got {cfg.threads}")
    if cfg.render_quality not in ("paper", "fast"):
        raise ConfigError(f"--render-quality must be paper or fast, got '{cfg.render_quality}'")
    if cfg.save_video:
        try:
            import imageio_ffmpeg  # noqa: F401  (brings its own ffmpeg binary)
        except ImportError:
            raise ConfigError("--save-video needs imageio-ffmpeg: pip install -r requirements.txt") from None
    if cfg.kitchen_camera not in ("fixed", "random"):
        raise ConfigError(f"--kitchen-camera must be fixed or random, got '{cfg.kitchen_camera}'")
    if cfg.eval_episodes_per_task < 0:
        raise ConfigError(f"--eval-episodes-per-task must be >= 0, got {cfg.eval_episodes_per_task}")
    if cfg.init_parts not in INIT_PARTS:
        raise ConfigError(f"--init-parts must be {' or '.join(INIT_PARTS)}, got '{cfg.init_parts}'")


# ================================================================================================
# 2. Networks
# ================================================================================================
def weight_init(m):
    """DrQ-v2's init: orthogonal weights, zero biases (ReLU gain for convolutions)."""
    if isinstance(m, nn.Linear):
        nn.init.orthogonal_(m.weight.data)
        if m.bias is not None:
            m.bias.data.fill_(0.0)
    elif isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
        nn.init.orthogonal_(m.weight.data, nn.init.calculate_gain("relu"))
        if m.bias is not None:
            m.bias.data.fill_(0.0)


def conv_trunk(in_channels: int) -> nn.Sequential:
    """DrQ-v2's four 3x3 convolutions, 32 channels, first with stride 2: 84x84 -> 32x35x35."""
    return nn.Sequential(
        nn.Conv2d(in_channels, 32, 3, stride=2), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU())


class DrQEncoder(nn.Module):
    """DrQ-v2 as published: the 32x35x35 feature map, flattened (39200), goes into the trunks."""

    def __init__(self, in_channels: int):
        super().__init__()
        self.convs = conv_trunk(in_channels)
        self.repr_dim = 32 * 35 * 35
        self.apply(weight_init)

    def forward(self, obs):
        return self.convs(obs / 255.0 - 0.5).flatten(1)


class PooledEncoder(nn.Module):
    """SEAR's encoder (appendix "Architecture"): the same convolutions, then AvgPool(4) to 32x8x8,
    flatten (2048) and a linear map to the latent (4096) that the decoders read."""

    def __init__(self, in_channels: int, latent_dim: int):
        super().__init__()
        self.convs = conv_trunk(in_channels)
        self.pool = nn.AvgPool2d(4, 4)
        self.fc = nn.Linear(32 * 8 * 8, latent_dim)
        self.repr_dim = latent_dim
        self.apply(weight_init)

    def forward(self, obs):
        h = self.pool(self.convs(obs / 255.0 - 0.5))
        return self.fc(h.flatten(1))


class Decoder(nn.Module):
    """The decoder body shared by the mask and the reconstruction heads (appendix "Architecture").
    8x8 -> 35 (k4 s4, output_padding 3) -> 37 -> 39 -> 41 (k3 s1) -> 84 (k3 s2, output_padding 1)."""

    def __init__(self, in_dim: int, out_channels: int, in_channels: int = 16):
        super().__init__()
        self.in_channels = in_channels  # 16 for SEAR's heads; DrQ-AE's decoder starts from 32 (authors' code)
        self.fc = nn.Sequential(nn.Linear(in_dim, in_channels * 8 * 8), nn.ReLU())
        self.deconvs = nn.Sequential(
            nn.ConvTranspose2d(in_channels, 16, 4, stride=4, output_padding=3), nn.ReLU(),
            nn.ConvTranspose2d(16, 32, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(32, 32, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(32, 32, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(32, out_channels, 3, stride=2, output_padding=1))
        self.apply(weight_init)

    def forward(self, z):
        return self.deconvs(self.fc(z).view(-1, self.in_channels, 8, 8))


class TruncatedNormal(torch.distributions.Normal):
    """Normal whose samples are clipped to (-1, 1) with a straight-through gradient (DrQ-v2)."""

    def __init__(self, loc, scale, eps=1e-6):
        super().__init__(loc, scale, validate_args=False)
        self.eps = eps

    def sample(self, clip=None):
        noise = torch.randn_like(self.loc) * self.scale
        if clip is not None:
            noise = noise.clamp(-clip, clip)
        x = self.loc + noise
        clamped = x.clamp(-1 + self.eps, 1 - self.eps)
        return x - x.detach() + clamped.detach()


def trunk(repr_dim, feature_dim):
    return nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())


def mlp(in_dim, hidden_dim, out_dim):
    return nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(inplace=True),
                         nn.Linear(hidden_dim, hidden_dim), nn.ReLU(inplace=True),
                         nn.Linear(hidden_dim, out_dim))


class Actor(nn.Module):
    def __init__(self, repr_dim, action_dim, feature_dim, hidden_dim):
        super().__init__()
        self.trunk = trunk(repr_dim, feature_dim)
        self.policy = mlp(feature_dim, hidden_dim, action_dim)
        self.apply(weight_init)

    def forward(self, latent, std):
        mu = torch.tanh(self.policy(self.trunk(latent)))
        return TruncatedNormal(mu, torch.full_like(mu, std))


class Critic(nn.Module):
    """Two Q heads on one trunk; the target is the minimum of the two (clipped double-Q)."""

    def __init__(self, repr_dim, action_dim, feature_dim, hidden_dim):
        super().__init__()
        self.trunk = trunk(repr_dim, feature_dim)
        self.q1 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.apply(weight_init)

    def forward(self, latent, action):
        h = torch.cat([self.trunk(latent), action], dim=-1)
        return self.q1(h), self.q2(h)


# ================================================================================================
# 3. Augmentation
# ================================================================================================
def random_shift(x: torch.Tensor, pad: int = 4, shift: torch.Tensor | None = None):
    """DrQ's random shift: replicate-pad by `pad`, then crop back with a per-sample integer shift,
    done as a bilinear grid sample. Integer shifts land on pixel centres, so a 0/1 mask stays 0/1.
    SEAR shifts the image stack and its mask stack together by concatenating them along channels:
    the same shift for both is what makes the mask a label of the image the encoder sees."""
    n, c, h, w = x.shape
    assert h == w
    padded = F.pad(x, (pad,) * 4, mode="replicate")
    eps = 1.0 / (h + 2 * pad)
    arange = torch.linspace(-1.0 + eps, 1.0 - eps, h + 2 * pad, device=x.device, dtype=x.dtype)[:h]
    arange = arange.unsqueeze(0).repeat(h, 1).unsqueeze(2)
    base_grid = torch.cat([arange, arange.transpose(1, 0)], dim=2).unsqueeze(0).repeat(n, 1, 1, 1)
    if shift is None:
        shift = torch.randint(0, 2 * pad + 1, size=(n, 1, 1, 2), device=x.device)
    grid = base_grid + shift.to(x.dtype) * 2.0 / (h + 2 * pad)
    return F.grid_sample(padded, grid, padding_mode="zeros", align_corners=False)


def shift_together(obs: torch.Tensor, mask: torch.Tensor):
    """One random shift per sample, applied identically to the image stack and the mask stack."""
    both = random_shift(torch.cat([obs, mask], dim=1))
    return both[:, :obs.shape[1]], both[:, obs.shape[1]:]


# ================================================================================================
# 4. Auxiliary losses: one seam for SEAR and every baseline
# ================================================================================================
def summed_mse(pred, target, weight=None):
    """Squared error summed over channels and pixels, averaged over the batch (Eq. 5). c1 is
    relative to this sum, not to a per-pixel mean."""
    err = (pred.float() - target) ** 2  # fp32 even when the decoder ran in bf16
    if weight is not None:
        err = err * weight
    return err.flatten(1).sum(1).mean()


def reconstruction_loss(pred, obs, weight=None):
    """Eq. 5 on the [-0.5, 0.5]-normalised image. The prediction is clamped to that range first, as
    in the authors' code (sear/agents/sear.py and drqv2AE.py): no gradient pushes a pixel that is
    already past black or white any further."""
    return summed_mse(pred.float().clamp(-0.5, 0.5), obs / 255.0 - 0.5, weight)


def summed_bce(logits, target):
    """Binary cross-entropy on mask logits, summed over pixels, averaged over the batch (Eq. 4)."""
    bce = F.binary_cross_entropy_with_logits(logits.float(), target, reduction="none")
    return bce.flatten(1).sum(1).mean()


class AuxLoss(nn.Module):
    """The seam. An auxiliary loss sees the encoder, the latent of the augmented observation (which
    also feeds the critic), the un-augmented observation, and the augmented image and mask (same
    shift). It returns its weighted contribution to Eq. 6 and its unweighted terms for the logs.
    Its parameters are optimised together with the encoder and the critic."""
    metric_names: tuple[str, ...] = ()
    decodes: tuple[str, ...] = ()  # what decode() returns: "mask" (logits), "recon" (normalised image)

    def forward(self, encoder, latent, obs, obs_aug, mask_aug):
        raise NotImplementedError

    def decode(self, latent) -> dict:
        """What the decoders make of a latent, for the evaluation's metrics and videos."""
        return {}

    def after_update(self, encoder):
        """Called after each optimiser step (CURL updates its momentum encoder here)."""


class SearAux(AuxLoss):
    """SEAR: z_R -> robot mask (Eq. 4), z -> image (Eq. 5). As in the authors' code, the FIRST half
    of the latent is z (reconstruction) and the SECOND half is z_R (mask). With split=False both
    decoders read the whole latent (appendix "Auxiliary Mask Loss Without Latent Separation")."""
    metric_names = ("recon_loss", "mask_loss")
    decodes = ("mask", "recon")

    def __init__(self, cfg: Config, latent_dim: int, split: bool = True):
        super().__init__()
        self.split, self.c1, self.c2 = split, cfg.recon_coef, cfg.mask_coef
        dec_in = latent_dim // 2 if split else latent_dim
        self.recon_decoder = Decoder(dec_in, 3 * cfg.frame_stack)
        self.mask_decoder = Decoder(dec_in, cfg.frame_stack)

    def decoder_inputs(self, latent):
        if not self.split:
            return latent, latent
        z, z_r = latent.chunk(2, dim=1)
        return z, z_r

    def forward(self, encoder, latent, obs, obs_aug, mask_aug):
        z, z_r = self.decoder_inputs(latent)
        recon_loss = reconstruction_loss(self.recon_decoder(z), obs_aug)
        mask_loss = summed_bce(self.mask_decoder(z_r), mask_aug)
        loss = self.c1 * recon_loss + self.c2 * mask_loss
        return loss, {"recon_loss": recon_loss.item(), "mask_loss": mask_loss.item()}

    def decode(self, latent):
        z, z_r = self.decoder_inputs(latent)
        return {"mask": self.mask_decoder(z_r), "recon": self.recon_decoder(z)}


class AEAux(AuxLoss):
    """DrQ-AE: one reconstruction decoder on the whole latent, no mask. As in the authors' code
    (sear/agents/drqv2AE.py, cfgs/agent/drqv2AE.yaml), the decoder starts from 32 channels, the
    loss weight is twice SEAR's c1, and there is no latent penalty (SAC-AE's is --ae-latent-lambda)."""
    metric_names = ("recon_loss",)
    decodes = ("recon",)

    def __init__(self, cfg: Config, latent_dim: int):
        super().__init__()
        self.c1, self.latent_lambda = 2 * cfg.recon_coef, cfg.ae_latent_lambda
        self.recon_decoder = Decoder(latent_dim, 3 * cfg.frame_stack, in_channels=32)

    def forward(self, encoder, latent, obs, obs_aug, mask_aug):
        recon_loss = reconstruction_loss(self.recon_decoder(latent), obs_aug)
        penalty = 0.5 * latent.pow(2).sum(1).mean()
        loss = self.c1 * recon_loss + self.latent_lambda * penalty
        return loss, {"recon_loss": recon_loss.item()}

    def decode(self, latent):
        return {"recon": self.recon_decoder(latent)}


def patch_mask(n, size, patch, ratio, device):
    """MAE's masking: per sample, hide round(ratio * patches) of the (size/patch)^2 patches, chosen
    uniformly. Returns a (n, 1, size, size) float map, 1 where hidden."""
    side = size // patch
    num, hide = side * side, int(round(ratio * side * side))
    order = torch.rand(n, num, device=device).argsort(dim=1)
    hidden = torch.zeros(n, num, device=device)
    hidden.scatter_(1, order[:, :hide], 1.0)
    hidden = hidden.view(n, 1, side, side)
    return hidden.repeat_interleave(patch, dim=2).repeat_interleave(patch, dim=3)


class MAEAux(AuxLoss):
    """DrQ-MAE: hide random patches (the same patches in every stacked frame), encode the masked
    image, reconstruct the whole stack, and score only the hidden pixels."""
    metric_names = ("recon_loss",)

    def __init__(self, cfg: Config, latent_dim: int):
        super().__init__()
        self.c1, self.ratio, self.patch = cfg.recon_coef, cfg.mae_ratio, cfg.mae_patch
        self.recon_decoder = Decoder(latent_dim, 3 * cfg.frame_stack)

    def forward(self, encoder, latent, obs, obs_aug, mask_aug):
        hidden = patch_mask(obs_aug.shape[0], obs_aug.shape[-1], self.patch, self.ratio, obs_aug.device)
        masked = obs_aug * (1 - hidden) + 127.5 * hidden  # 127.5 -> 0 after normalisation
        pred = self.recon_decoder(encoder(masked))
        recon_loss = reconstruction_loss(pred, obs_aug, weight=hidden)
        return self.c1 * recon_loss, {"recon_loss": recon_loss.item()}

    # At evaluation nothing is hidden: the decoder reconstructs from the whole image's latent.
    decodes, decode = AEAux.decodes, AEAux.decode


class CURLAux(AuxLoss):
    """CURL: query = online encoder on the augmented view, key = momentum encoder on a differently
    shifted view of the same observation; logits q W k^T (B x B), cross-entropy with the positives
    on the diagonal. A projection (Linear + LayerNorm) keeps W small for the 4096-d latent."""
    metric_names = ("curl_loss",)

    def __init__(self, cfg: Config, latent_dim: int, encoder: nn.Module):
        super().__init__()
        self.coef, self.tau = cfg.curl_coef, cfg.curl_tau
        self.query_head = nn.Sequential(nn.Linear(latent_dim, cfg.curl_dim), nn.LayerNorm(cfg.curl_dim))
        self.W = nn.Parameter(torch.rand(cfg.curl_dim, cfg.curl_dim))
        # The key side is not trained by gradients, only by EMA; keep it out of state the optimiser sees.
        self.key_encoder = copy.deepcopy(encoder).requires_grad_(False)
        self.key_head = copy.deepcopy(self.query_head).requires_grad_(False)

    def logits(self, q, k):
        logits = q.float() @ self.W @ k.float().T
        return logits - logits.max(dim=1, keepdim=True).values  # stability, as CURL

    def forward(self, encoder, latent, obs, obs_aug, mask_aug):
        q = self.query_head(latent)
        with torch.no_grad():
            k = self.key_head(self.key_encoder(random_shift(obs)))
        logits = self.logits(q, k)
        curl_loss = F.cross_entropy(logits, torch.arange(len(q), device=q.device))
        return self.coef * curl_loss, {"curl_loss": curl_loss.item()}

    @torch.no_grad()
    def after_update(self, encoder):
        for online, key in ((encoder, self.key_encoder), (self.query_head, self.key_head)):
            for p, p_key in zip(online.parameters(), key.parameters()):
                p_key.lerp_(p, self.tau)


@dataclass(frozen=True)
class Method:
    encoder: str            # "pooled" (SEAR's) or "drq" (DrQ-v2's)
    mask_input: bool        # DrQ-RGBM: the mask is a 4th channel of every stacked frame
    uses_mask: bool         # False: the env skips the segmentation render (it costs a second pass)
    make_aux: object        # (cfg, latent_dim, encoder) -> AuxLoss | None
    doc: str


METHODS = {
    "sear": Method("pooled", False, True, lambda c, d, e: SearAux(c, d, split=True),
                   "SEAR: latent split, mask + recon"),
    "drq": Method("drq", False, False, lambda c, d, e: None, "DrQ-v2 as published"),
    "ae": Method("pooled", False, False, lambda c, d, e: AEAux(c, d), "DrQ-AE: one decoder on the whole latent"),
    "mae": Method("pooled", False, False, lambda c, d, e: MAEAux(c, d), "DrQ-MAE: reconstruct hidden patches"),
    "curl": Method("pooled", False, False, lambda c, d, e: CURLAux(c, d, e), "CURL: contrastive, momentum key"),
    "rgbm": Method("drq", True, True, lambda c, d, e: None, "DrQ-RGBM: mask appended to the input"),
    "sear-nosplit": Method("pooled", False, True, lambda c, d, e: SearAux(c, d, split=False),
                           "SEAR without latent split"),
}


# ================================================================================================
# 5. Agent
# ================================================================================================
def linear_std(cfg: Config, step: int) -> float:
    """DrQ-v2's `linear(std_start, std_end, std_steps)`, evaluated at the global AGENT step (not the
    frame): at action repeat 2 the std reaches std_end after 500k steps = 1M frames."""
    mix = min(max(step / cfg.std_steps, 0.0), 1.0)
    return (1.0 - mix) * cfg.std_start + mix * cfg.std_end


class Agent:
    def __init__(self, cfg: Config, action_dim: int, device: torch.device):
        self.cfg, self.device, self.action_dim = cfg, device, action_dim
        self.method = METHODS[cfg.method]
        in_channels = (4 if self.method.mask_input else 3) * cfg.frame_stack
        if self.method.encoder == "pooled":
            self.encoder = PooledEncoder(in_channels, cfg.latent_dim).to(device)
        else:
            self.encoder = DrQEncoder(in_channels).to(device)
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(device)
        self.critic = Critic(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.aux = self.method.make_aux(cfg, repr_dim, self.encoder)
        if self.aux is not None:
            self.aux.to(device)
        # Eq. 6 is one loss over encoder, critic and decoders; Adam is per-parameter, so one
        # optimiser for all of them equals DrQ-v2's separate encoder/critic optimisers.
        model_params = [*self.encoder.parameters(), *self.critic.parameters()]
        if self.aux is not None:
            model_params += [p for p in self.aux.parameters() if p.requires_grad]
        self.model_opt = torch.optim.Adam(model_params, lr=cfg.lr)
        # The convolutions (encoder, decoders) hold >90% of an update's FLOPs. They use the NHWC
        # ("channels_last") layout, which oneDNN's and cuDNN's fastest kernels expect, and under
        # --precision bf16 only they run in bf16: a TD target rounded to bf16's 8-bit mantissa would
        # be off by up to 0.5 at Q = 100, so actor, critic and every loss stay in fp32.
        for net in (self.encoder, self.aux):
            if net is not None:
                net.to(memory_format=torch.channels_last)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr)
        self.metric_names = (("critic_loss", "actor_loss", "q", "actor_saturated", "action_spread")
                             + (self.aux.metric_names if self.aux else ()))

    def conv_precision(self):
        """bf16 autocast for the convolutional networks under --precision bf16; a no-op for fp32."""
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.cfg.precision == "bf16")

    def encode(self, obs):
        with self.conv_precision():
            return self.encoder(obs).float()

    # --- inputs ---
    def encoder_input(self, pixels: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """The encoder's input: the RGB stack, or for RGBM each frame's RGB followed by its mask."""
        if not self.method.mask_input:
            return pixels
        if mask is None:
            raise ValueError("method rgbm needs the robot mask when acting: pass mask=obs['mask']")
        n, c, h, w = pixels.shape
        rgb = pixels.view(n, c // 3, 3, h, w)
        m = (mask.to(pixels.dtype) * 255.0).view(n, c // 3, 1, h, w)
        return torch.cat([rgb, m], dim=2).view(n, -1, h, w)

    @torch.no_grad()
    def act(self, pixels: np.ndarray, mask: np.ndarray | None, step: int, eval_mode: bool):
        obs = torch.as_tensor(pixels, device=self.device).float().unsqueeze(0)
        m = None if mask is None else torch.as_tensor(mask, device=self.device).float().unsqueeze(0)
        latent = self.encode(self.encoder_input(obs, m))
        dist = self.actor(latent, linear_std(self.cfg, step))
        if eval_mode:
            action = dist.mean
        else:
            action = dist.sample(clip=None)
            if step < self.cfg.exploration_steps:
                action.uniform_(-1.0, 1.0)
        return action.squeeze(0).cpu().numpy().astype(np.float32)

    # --- updates ---
    def joint_loss(self, obs, mask, action, reward, discount, next_obs, step):
        """Eq. 6: the critic's TD loss plus the auxiliary loss (c1 * recon + c2 * mask for SEAR).
        Returns the loss, the latent of the augmented observation, and the terms for the logs."""
        obs_aug, mask_aug = shift_together(obs, mask)
        latent = self.encode(obs_aug)
        with torch.no_grad():
            next_latent = self.encode(random_shift(next_obs))
            dist = self.actor(next_latent, linear_std(self.cfg, step))
            next_action = dist.sample(clip=self.cfg.std_clip)
            target_q = torch.min(*self.critic_target(next_latent, next_action))
            target_q = reward + discount * target_q
        q1, q2 = self.critic(latent, action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        loss, metrics = critic_loss, {}
        if self.aux is not None:
            with self.conv_precision():  # decoders (and MAE's second encoder pass) in bf16; losses fp32
                aux_loss, metrics = self.aux(self.encoder, latent, obs, obs_aug, mask_aug)
            loss = loss + aux_loss
        metrics.update(critic_loss=critic_loss.item(), q=q1.mean().item())
        return loss, latent, metrics

    def update_critic(self, obs, mask, action, reward, discount, next_obs, step):
        """One joint step on encoder, critic and decoders (Alg. 1)."""
        loss, latent, metrics = self.joint_loss(obs, mask, action, reward, discount, next_obs, step)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.model_opt.step()
        if self.aux is not None:
            self.aux.after_update(self.encoder)
        return latent.detach(), metrics

    def update_actor(self, latent, step):
        """DDPG actor loss. `latent` is detached: the actor's loss never reaches the encoder."""
        dist = self.actor(latent, linear_std(self.cfg, step))
        action = dist.sample(clip=self.cfg.std_clip)
        # Nor does it reach the critic's weights: DrQ-v2 computes their gradient here and the next
        # critic step discards it; frozen, the backward pass skips those GEMMs (the actor's gradient
        # is the same).
        self.critic.requires_grad_(False)
        try:
            actor_loss = -torch.min(*self.critic(latent, action)).mean()
        finally:
            self.critic.requires_grad_(True)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        # The failure of short DDPG runs, made visible: an actor whose mean action no longer depends
        # on the state (spread 0) and sits where float32's tanh is exactly +-1, so 1 - tanh^2 = 0 and
        # no gradient can bring it back (EXPERIMENTS.md, rung 2).
        mu = dist.mean.detach()
        values = torch.stack([actor_loss.detach(), (mu.abs() == 1.0).float().mean(),
                              mu.std(0, correction=0).mean()]).tolist()  # one device sync, not three
        return dict(zip(("actor_loss", "actor_saturated", "action_spread"), values))

    def update(self, batch, step):
        obs, mask, action, reward, discount, next_obs, next_mask = (
            torch.as_tensor(x, device=self.device) for x in batch)
        obs, mask, next_mask = obs.float(), mask.float(), next_mask.float()
        obs = self.encoder_input(obs, mask)
        next_obs = self.encoder_input(next_obs.float(), next_mask)
        latent, metrics = self.update_critic(obs, mask, action, reward, discount, next_obs, step)
        metrics.update(self.update_actor(latent, step))
        with torch.no_grad():  # Polyak averaging of the target critic
            for p, p_t in zip(self.critic.parameters(), self.critic_target.parameters()):
                p_t.lerp_(p, self.cfg.critic_tau)
        return metrics

    def state_dict(self):
        return {"encoder": self.encoder.state_dict(), "actor": self.actor.state_dict(),
                "critic": self.critic.state_dict(), "critic_target": self.critic_target.state_dict(),
                "aux": self.aux.state_dict() if self.aux is not None else None,
                "model_opt": self.model_opt.state_dict(), "actor_opt": self.actor_opt.state_dict()}

    def load_state_dict(self, state):
        for name in ("encoder", "actor", "critic", "critic_target", "model_opt", "actor_opt"):
            getattr(self, name).load_state_dict(state[name])
        if self.aux is not None:
            self.aux.load_state_dict(state["aux"])


# Transfer (--init-from): which networks of another run's agent a new run starts from.
INIT_PARTS = {"encoder": ("encoder",), "encoder+decoders": ("encoder", "aux"),
              "all": ("encoder", "aux", "actor", "critic")}


def init_fields(cfg) -> tuple[str, ...]:
    """The config fields that fix the shapes of the parts --init-parts copies: they must be the
    source run's."""
    fields = ("method", "latent_dim", "frame_stack")
    if cfg.init_parts != "encoder" and cfg.method == "curl":
        fields += ("curl_dim",)  # CURL's projection heads are its auxiliary networks
    if cfg.init_parts == "all":
        fields += ("feature_dim", "hidden_dim")
    return fields


def copy_parts(agent: Agent, source: dict, parts: str) -> None:
    """Load `parts` of a saved agent state (a snapshot's "agent") into a freshly built agent; the other
    networks keep their fresh initialisation and the optimisers stay fresh (Adam's moments are
    empty; the loads write into the parameters the optimisers already hold). "aux" is the method's
    auxiliary networks: SEAR's two decoders, AE's and MAE's decoder, CURL's heads and key encoder;
    drq and rgbm have none. As in the authors' load_pretrained_weights, the target critic starts as
    a copy of the loaded critic."""
    names = INIT_PARTS[parts]
    agent.encoder.load_state_dict(source["encoder"])
    if agent.aux is not None:
        if "aux" in names:
            agent.aux.load_state_dict(source["aux"])
        elif isinstance(agent.aux, CURLAux):  # its key encoder is a momentum copy: it starts equal
            agent.aux.key_encoder.load_state_dict(source["encoder"])
    if "actor" in names:
        agent.actor.load_state_dict(source["actor"])
        agent.critic.load_state_dict(source["critic"])
        agent.critic_target.load_state_dict(agent.critic.state_dict())


# ================================================================================================
# 6. Replay buffer
# ================================================================================================
class ReplayBuffer:
    """A ring of time steps. Slot i holds the newest RGB frame of step i (uint8, stored once), its
    robot mask bit-packed (np.packbits: 882 bytes for 84x84), the action and reward that led to it,
    whether it is terminal, and whether it starts an episode. Frame stacks are rebuilt at sampling
    time, never across an episode start (the first frame repeats, as at reset), and n-step returns
    are summed at sampling. A time-limit end (truncation) bootstraps; a termination does not."""

    def __init__(self, capacity, frame_shape, action_dim, frame_stack, nstep, discount):
        self.capacity, self.stack, self.nstep, self.discount = capacity, frame_stack, nstep, discount
        self.frame_shape = tuple(frame_shape)  # (3, H, W)
        h, w = frame_shape[1:]
        self.mask_bytes = (h * w + 7) // 8
        self.frames = np.empty((capacity, *frame_shape), dtype=np.uint8)
        self.masks = np.empty((capacity, self.mask_bytes), dtype=np.uint8)
        self.actions = np.empty((capacity, action_dim), dtype=np.float32)
        self.rewards = np.empty((capacity,), dtype=np.float32)
        self.terminal = np.empty((capacity,), dtype=bool)
        self.first = np.empty((capacity,), dtype=bool)
        self.t = 0  # slots ever written; slot of time step l is l % capacity

    @property
    def bytes_per_transition(self):
        return sum(a.itemsize * int(np.prod(a.shape[1:])) for a in
                   (self.frames, self.masks, self.actions, self.rewards, self.terminal, self.first))

    def __len__(self):
        return min(self.t, self.capacity)

    def _write(self, obs, action, reward, terminal, first):
        i = self.t % self.capacity
        self.frames[i] = obs["pixels"][-3:]
        self.masks[i] = np.packbits(np.asarray(obs["mask"][-1], dtype=bool).reshape(-1))
        self.actions[i] = action
        self.rewards[i] = reward
        self.terminal[i] = terminal
        self.first[i] = first
        self.t += 1

    def add_first(self, obs):
        """The observation returned by reset()."""
        self._write(obs, 0.0, 0.0, False, True)

    def add(self, action, reward, terminated, obs):
        """One env.step(): the action taken, the reward it earned, and the observation it led to."""
        self._write(obs, action, reward, terminated, False)

    # --- sampling ---
    def _stack_indices(self, l):
        """Time indices of the frames stacked at time l: walk back, but never past an episode
        start or the oldest slot still in the ring (the frame there is repeated instead)."""
        oldest = max(0, self.t - self.capacity)
        idx = [l]
        cur = l.copy()
        for _ in range(self.stack - 1):
            stop = self.first[cur % self.capacity] | (cur <= oldest)
            cur = np.where(stop, cur, cur - 1)
            idx.append(cur.copy())
        return np.stack(idx[::-1], axis=1)  # oldest frame first

    def _obs(self, l):
        idx = self._stack_indices(l) % self.capacity  # (B, stack)
        b = len(l)
        pixels = self.frames[idx].reshape(b, -1, *self.frame_shape[1:])
        bits = np.unpackbits(self.masks[idx], axis=-1)[..., :int(np.prod(self.frame_shape[1:]))]
        masks = bits.reshape(b, self.stack, *self.frame_shape[1:])
        return pixels, masks

    def can_sample(self):
        return self.t - max(0, self.t - self.capacity) > self.nstep + 1

    def sample(self, batch_size, rng: np.random.Generator, margin: int = 0):
        """`margin` skips the oldest slots of a full ring: a background sampler must not read a slot
        that the training loop is overwriting while it samples."""
        lo, hi = max(0, self.t - self.capacity), self.t - 1 - self.nstep
        if self.t > self.capacity:
            lo = min(lo + margin, hi)
        l = rng.integers(lo, hi + 1, size=batch_size)
        bad = self.first[(l + 1) % self.capacity]
        while bad.any():  # rejection keeps sampling uniform over valid starts without listing them
            l[bad] = rng.integers(lo, hi + 1, size=int(bad.sum()))
            bad = self.first[(l + 1) % self.capacity]
        return self.transitions(l)

    def transitions(self, l):
        """n-step transitions starting at times l: (obs, mask, action, R, bootstrap discount,
        next_obs, next_mask), with R = sum_k gamma^(k-1) r_(l+k) up to n steps or the episode's end,
        and bootstrap discount gamma^m, zero if the episode terminated at step l + m."""
        l = np.asarray(l, dtype=np.int64)
        ret = np.zeros(len(l), dtype=np.float32)
        gamma_m = np.ones(len(l), dtype=np.float32)
        last = l.copy()  # time of the bootstrap observation
        alive = np.ones(len(l), dtype=bool)  # still inside the episode
        for k in range(1, self.nstep + 1):
            j = (l + k) % self.capacity
            alive &= ~self.first[j]
            ret += np.where(alive, gamma_m * self.rewards[j], 0.0).astype(np.float32)
            gamma_m = np.where(alive, gamma_m * self.discount, gamma_m).astype(np.float32)
            last = np.where(alive, l + k, last)
        # A terminal step is always followed by a reset, so the walk above stops there too; only
        # the bootstrap differs: none after a termination, gamma^m after a time-limit truncation.
        discount = np.where(self.terminal[last % self.capacity], 0.0, gamma_m).astype(np.float32)
        obs, mask = self._obs(l)
        next_obs, next_mask = self._obs(last)
        action = self.actions[(l + 1) % self.capacity]
        return obs, mask, action, ret[:, None], discount[:, None], next_obs, next_mask

    # --- persistence ---
    def save(self, path):
        n = len(self)
        tmp = path + ".tmp.npz"
        np.savez(tmp, t=self.t, frames=self.frames[:n], masks=self.masks[:n], actions=self.actions[:n],
                 rewards=self.rewards[:n], terminal=self.terminal[:n], first=self.first[:n])
        os.replace(tmp, path)

    def load(self, path):
        with np.load(path) as data:
            n = len(data["rewards"])
            if n > self.capacity:
                raise ConfigError(f"saved buffer holds {n} transitions, more than --replay-size {self.capacity}")
            for name in ("frames", "masks", "actions", "rewards", "terminal", "first"):
                getattr(self, name)[:n] = data[name]
            self.t = int(data["t"])  # a wrapped ring is saved in physical order: same slots here


class Prefetcher:
    """Replay sampling and the host->device copy of the next batch, in a background thread while the
    current update runs (--prefetch; on by default with CUDA, where the update no longer waits for
    the host). One batch ahead: a batch cannot hold the newest `update_every` steps, and the sampling
    RNG runs one batch ahead of the loop. On CUDA the copy goes from pinned memory on its own stream."""

    def __init__(self, buffer: ReplayBuffer, batch_size: int, rng: np.random.Generator, device: torch.device,
                 margin: int):
        self.buffer, self.batch_size, self.rng, self.device, self.margin = buffer, batch_size, rng, device, margin
        self.queue: queue.Queue = queue.Queue(maxsize=1)
        self.stop = threading.Event()
        self.thread = None
        self.stream = torch.cuda.Stream(device) if device.type == "cuda" else None

    def _produce(self):
        while not self.stop.is_set():
            try:
                batch = tuple(torch.as_tensor(x) for x in self.buffer.sample(self.batch_size, self.rng, self.margin))
                event = None
                if self.stream is not None:
                    with torch.cuda.stream(self.stream):
                        batch = tuple(x.pin_memory().to(self.device, non_blocking=True) for x in batch)
                        event = torch.cuda.Event()
                        event.record(self.stream)
            except Exception as e:  # hand it to the learner, which raises it: never hang
                self.queue.put((e, None))
                return
            self.queue.put((batch, event))  # waits until the learner has taken the previous batch

    def next(self):
        if self.thread is None:  # started at the first update, once the buffer can be sampled
            self.thread = threading.Thread(target=self._produce, daemon=True)
            self.thread.start()
        batch, event = self.queue.get()
        if isinstance(batch, Exception):
            raise batch
        if event is not None:  # the update's stream waits for the copy, and owns the tensors after it
            current = torch.cuda.current_stream(self.device)
            event.wait(current)
            for x in batch:
                x.record_stream(current)
        return batch

    def close(self):
        self.stop.set()
        while self.thread is not None and self.thread.is_alive():
            try:  # unblock a producer waiting on a full queue
                self.queue.get_nowait()
            except queue.Empty:
                pass
            self.thread.join(timeout=0.05)


# ================================================================================================
# 7. Run directory: logs, progress, snapshots
# ================================================================================================
class CsvLog:
    """Rows appended to a CSV whose header is fixed by the first row."""

    def __init__(self, path):
        self.path, self.fields = path, None
        if os.path.exists(path):
            with open(path, newline="") as f:
                self.fields = next(csv.reader(f), None)

    def write(self, row: dict):
        if self.fields is None:
            self.fields = list(row)
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self.fields)
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.fields, extrasaction="ignore").writerow(row)


def set_aside_rows_after(path, frame):
    """On resume, rows logged after the snapshot describe steps that will be re-run. Keep them, in
    a side file, and leave the main CSV consistent with the snapshot."""
    if not os.path.exists(path):
        return
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2:
        return
    header, body = rows[0], rows[1:]
    col = header.index("frame")
    keep = [r for r in body if int(r[col]) <= frame]
    later = [r for r in body if int(r[col]) > frame]
    if not later:
        return
    side = f"{path[:-4]}.after_snapshot_{time.strftime('%Y%m%d-%H%M%S')}.csv"
    with open(side, "w", newline="") as f:
        csv.writer(f).writerows([header, *later])
    tmp = path + ".tmp"
    with open(tmp, "w", newline="") as f:
        csv.writer(f).writerows([header, *keep])
    os.replace(tmp, path)


def new_run_dir(cfg: Config) -> str:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    base = os.path.join(cfg.run_root, f"{cfg.env}__{cfg.method}__{cfg.seed}__{stamp}")
    path, k = base, 1
    while True:  # never reuse (and so never overwrite) an existing run, even one made this second
        try:
            os.makedirs(path)
            return path
        except FileExistsError:
            path, k = f"{base}-{k}", k + 1


def rng_state():
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def set_rng_state(state):
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if state["cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_snapshot(run_dir, payload):
    """Write snapshot.pt atomically: a crash mid-write leaves the previous snapshot intact."""
    path = os.path.join(run_dir, "snapshot.pt")
    tmp = path + ".tmp"
    torch.save(payload, tmp)
    os.replace(tmp, path)


def first_sentence(text) -> str:
    """The first sentence of a message, on one line. Error lines end at a sentence boundary; a
    length cut would stop them mid-word (torch's archive errors run on for 400 characters)."""
    text = " ".join(str(text).split())
    end = text.find(". ")
    sentence = text[: end + 1] if end >= 0 else text
    return sentence if not sentence or sentence.endswith((".", "!", "?")) else sentence + "."


def load_snapshot(run_dir, flag="--resume", mmap=False):
    """A run's snapshot.pt; every problem is a ConfigError naming `flag` (if any). mmap=True maps the
    tensors instead of reading them (--init-from reads a snapshot twice: its config, then its weights)."""
    path = os.path.join(run_dir, "snapshot.pt")
    flag = f"{flag}: " if flag else ""
    if not os.path.isdir(run_dir):
        raise ConfigError(f"{flag}no such run directory '{run_dir}'")
    if not os.path.exists(path):
        raise ConfigError(f"{flag}'{run_dir}' has no snapshot.pt (the run stopped before its first "
                          f"snapshot; see --snapshot-minutes)")
    try:
        return torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as e:  # corrupt or foreign file: say so in one line
        reason = first_sentence(e)
        raise ConfigError(f"{flag}cannot read '{path}': {type(e).__name__}" + (f": {reason}" if reason else ""))


def saved_config(saved: dict, given: dict | None = None) -> Config:
    """The Config of a snapshot's saved config dict (fields since removed are dropped, renamed ones
    carried over), with the flags in `given` on top."""
    saved = dict(saved)
    if "std_frames" in saved and "std_steps" not in saved:  # snapshots from before std counted steps
        saved["std_steps"] = max(1, saved["std_frames"] // max(1, saved.get("action_repeat") or 1))
    known = {f.name for f in dataclasses.fields(Config)}
    return Config(**{**{k: v for k, v in saved.items() if k in known}, **(given or {})})


def load_init_source(cfg, action_dim):
    """The agent state of the --init-from run, checked against this run (its config was checked by
    parse_args; the action size is known once the env is built). Called before the run dir exists."""
    state = load_snapshot(cfg.init_from, "--init-from", mmap=True)
    if cfg.init_parts == "all":
        # The actor's last layer maps to the actions: its output size is the source's action size.
        source_dim = [v for k, v in state["agent"]["actor"].items() if k.endswith(".weight")][-1].shape[0]
        if source_dim != action_dim:
            raise ConfigError(f"--init-parts all: the source run's actor has {source_dim} actions, {cfg.env} "
                              f"has {action_dim}; copy encoder or encoder+decoders instead")
    return state["agent"]


def saved_buffer_t(path):
    """The `t` (steps ever written) of a saved buffer, read without loading the buffer."""
    with np.load(path) as data:
        return int(data["t"])


class Progress:
    """The live line: frame, training speed, ETA and what the loop is doing (an episode, or which
    evaluation episode). On a terminal it is rewritten in place (at least once a second); otherwise
    (CI logs, nohup) a line is printed every `every` seconds.

    The speed counts training time only: the loop excludes evaluations and snapshots from it, so a
    ten-minute evaluation does not make the run look stalled. Evaluations are timed apart, and the
    ETA is the sum of the two: frames left / training speed + evaluations left x seconds each."""

    WIDTH = 120

    def __init__(self, total, every, eval_every):
        self.total, self.eval_every = total, eval_every
        self.tty = sys.stdout.isatty()
        self.every = min(every, 1.0) if self.tty else every
        self.last = 0.0
        self.fps = 0.0  # training frames per second, set by the loop
        self.eval_seconds = []  # duration of each evaluation of this process

    def evals_left(self, next_eval):
        """Scheduled evaluations before the end of the budget (the one due now included), plus the
        final evaluation at its end."""
        scheduled = math.ceil((self.total - next_eval) / self.eval_every) if next_eval < self.total else 0
        return scheduled + 1

    def eta(self, frame, next_eval, eval_done=0.0, eval_spent=0.0):
        """Seconds to the end of the budget, inf while a speed is unknown. While an evaluation runs,
        `eval_done` is the fraction of its episodes finished and `eval_spent` its seconds so far."""
        train = (self.total - frame) / self.fps if self.fps > 0 else (0.0 if frame >= self.total else math.inf)
        per_eval = (float(np.mean(self.eval_seconds)) if self.eval_seconds
                    else eval_spent / eval_done if eval_done > 0 else None)
        evals = self.evals_left(next_eval) - eval_done
        return train + (0.0 if evals <= 0 else math.inf if per_eval is None else evals * per_eval)

    def update(self, frame, text, eta, force=False):
        now = time.time()
        if not force and now - self.last < self.every:
            return
        self.last = now
        eta_s = ("?" if not math.isfinite(eta) else f"{eta / 86400:.1f}d" if eta > 86400
                 else time.strftime("%H:%M:%S", time.gmtime(eta)))
        line = (f"frame {frame}/{self.total} ({100 * frame / self.total:.1f}%) | {self.fps:.1f} fps | "
                f"ETA {eta_s} | {text}")
        print(("\r" + line.ljust(self.WIDTH)) if self.tty else line, end="" if self.tty else "\n", flush=True)

    def say(self, message):
        """A line of its own (evaluation result, snapshot); on a terminal it replaces the live line."""
        print(("\r" + message.ljust(self.WIDTH)) if self.tty else message, flush=True)


def tensorboard_writer(run_dir):
    try:
        from torch.utils.tensorboard import SummaryWriter
        return SummaryWriter(run_dir)
    except Exception:  # tensorboard not installed: CSVs only
        return None


# ================================================================================================
# 8. Training loop
# ================================================================================================
def pick_device(name):
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"--device: unknown device '{name}'")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: CUDA is not available on this machine")
    return device


def default_threads():
    """OMP_NUM_THREADS when set (sweep.py sets it per job), else every core this process may run on
    (taskset / cgroup affinity). Several runs sharing cores should split them: with more busy
    threads than cores, torch's threads wait on each other and an update gets ~2x slower, not 1x."""
    if os.environ.get("OMP_NUM_THREADS", "").isdigit() and int(os.environ["OMP_NUM_THREADS"]) > 0:
        return int(os.environ["OMP_NUM_THREADS"])
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def episode_seed(seed, episode):
    """Each episode's reset seed: backgrounds, task variation and noise are reproducible, and a
    resumed run continues with the episodes an uninterrupted run would have had."""
    return seed * 1_000_003 + episode


def load_mask_model(cfg: Config):
    """The learned mask source of --mask-source learned:PATH (None for sim); a missing or damaged
    file is a ConfigError, raised before any run directory exists."""
    if cfg.mask_source == "sim":
        return None
    try:
        return segment.load_model(cfg.mask_source[len("learned:"):])
    except segment.SegmentError as e:
        raise ConfigError(f"--mask-source: {e}") from None


def make_envs(cfg: Config):
    """The train and the eval env. With a learned mask source, obs["mask"] is the model's prediction
    on each frame (envs.make_env(mask_model=)): the train env never renders the simulator's mask, the
    eval env renders it only for the learned_mask_iou metric (info["true_mask"], which nothing
    stores or trains on)."""
    import envs  # imported here so that `--help` and config errors need no MuJoCo
    mask_model = load_mask_model(cfg)
    train_env, eval_env = make_run_env(cfg, "train", mask_model), make_run_env(cfg, "eval", mask_model)
    cfg.action_repeat = cfg.action_repeat or envs.default_action_repeat(cfg.env)
    if mask_model is not None and cfg.learned_mask_iou:
        eval_env = segment.LearnedMaskIoU(eval_env)
    return train_env, eval_env


def make_run_env(cfg: Config, split: str, mask_model=None, **overrides):
    """The run's train or eval env, as its config describes it; `overrides` replace make_env
    arguments (plot.py maps: clean masks, rendered for every method). With a learned mask model
    the simulator's mask is rendered only in the eval env and only for --learned-mask-iou."""
    import envs
    uses_mask = METHODS[cfg.method].uses_mask
    render_mask = uses_mask and (mask_model is None or (split == "eval" and cfg.learned_mask_iou))
    kwargs = dict(frame_stack=cfg.frame_stack, action_repeat=cfg.action_repeat or None, mask_noise=cfg.mask_noise,
                  mask_approx=cfg.mask_approx, backgrounds=cfg.backgrounds or None,
                  difficulty=cfg.difficulty, render_quality=cfg.render_quality,
                  mask_downsample=cfg.mask_downsample, camera_distraction=cfg.camera_distraction,
                  color_distraction=cfg.color_distraction, render_mask=render_mask,
                  kitchen_camera=cfg.kitchen_camera, mask_model=mask_model) | overrides
    # Both envs draw Meta-World's 50 task variations from the run's seed (as the authors' MT1);
    # the eval env's own seed only fixes its reset seeds, backgrounds and noise.
    seed = cfg.seed + (100_000 if split == "eval" else 0)
    try:
        env = envs.make_env(cfg.env, seed=seed, split=split, variation_seed=cfg.seed, **kwargs)
    except envs.EnvError as e:
        raise ConfigError(str(e))
    if cfg.max_episode_steps:  # an earlier time limit is a truncation, like the suite's own
        from gymnasium.wrappers import TimeLimit
        env = TimeLimit(env, cfg.max_episode_steps)
    return env


# --- What the decoders see at evaluation: representation metrics and videos ---------------------
def mask_iou(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Per frame, the intersection over union of two binary masks (B, H, W) -> (B,). NaN where both
    are empty: with no robot in view and none predicted there is nothing to score."""
    pred, true = pred.bool().flatten(1), true.bool().flatten(1)
    return (pred & true).sum(1) / (pred | true).sum(1)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per frame, the peak signal-to-noise ratio in dB of images in [0, 1] (B, ...) -> (B,)."""
    mse = (pred.float() - target.float()).pow(2).flatten(1).mean(1)
    return -10.0 * torch.log10(mse)  # 10 log10(1 / mse): the peak is 1


class EvalWatch:
    """The eval env as evaluate() sees it, plus a look at what the decoders make of it.

    Every SCORE_EVERY-th observation the env returns (counting each reset and step of all evaluation
    episodes) is encoded as the actor sees it, unaugmented, and decoded, in batches of BATCH; its
    newest frame is scored. Mask decoder: IoU of sigmoid > 0.5 against the true mask and the BCE per pixel, where
    the env renders masks (METHODS[m].uses_mask; the mask the decoder is trained on, so with
    --mask-noise or --mask-approx the corrupted one). Reconstruction decoder: PSNR on the [0, 1] image,
    after the [-0.5, 0.5] clamp of the loss. finish() gives the means over frames. With a video
    path the first episode is also written as an MP4, the panels side by side: camera | true mask |
    predicted mask (the sigmoid, grey) | reconstruction, each only where the method has it. A method
    without decoders and without a video has its observations passed through untouched."""

    BATCH = 32
    # Encoding and decoding a frame again costs about half of a fast-render evaluation step on CPU
    # (EXPERIMENTS.md, "Inspection"); neighbouring frames differ little, so a tenth of them (~500
    # frames per default evaluation) gives the same means at a tenth of the cost.
    SCORE_EVERY = 10
    SCALE = 4  # nearest upscaling, 84 -> 336 px: visible, and a multiple of ffmpeg's 16-px macro blocks
    LABEL = 16  # height of the strip that names the panels (336 + 16 = 22 x 16 again)
    FPS = 20
    METRICS = ("mask_iou", "mask_bce", "recon_psnr")

    def __init__(self, agent: Agent, env, video_path: str | None = None):
        self.agent, self.env, self.video_path = agent, env, video_path
        self.decodes = agent.aux.decodes if agent.aux is not None else ()
        self.true_mask = agent.method.uses_mask  # mask-free methods' envs skip the segmentation render
        self.pending, self.values, self.episode, self.seen, self.video = [], {}, -1, 0, None

    def __getattr__(self, name):  # everything else (spaces, close, ...) is the env's
        return getattr(self.env, name)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.episode += 1
        self.see(obs)
        return obs, info

    def step(self, action):
        obs, *rest = self.env.step(action)
        self.see(obs)
        return (obs, *rest)

    def see(self, obs):
        filming = self.video_path is not None and self.episode == 0
        scoring = bool(self.decodes) and self.seen % self.SCORE_EVERY == 0
        self.seen += 1
        if scoring or filming:  # the env's arrays are fresh at every step: kept, not copied
            self.pending.append((filming, scoring, obs["pixels"], obs["mask"][-1]))
            if len(self.pending) == self.BATCH:
                self.flush()

    @torch.no_grad()
    def flush(self):
        if not self.pending:
            return
        filming, scoring, pixels, masks = zip(*self.pending)
        self.pending, scored = [], np.flatnonzero(scoring)
        agent = self.agent
        pixels = torch.as_tensor(np.stack(pixels), device=agent.device).float()
        true = torch.as_tensor(np.stack(masks), device=agent.device).float()
        panels = {"camera": pixels[:, -3:] / 255.0}  # the newest frame of each stack, in [0, 1]
        if self.true_mask:
            panels["true mask"] = true
        decoded = {}
        if self.decodes:
            latent = agent.encode(pixels)  # no random shift at evaluation
            with agent.conv_precision():
                decoded = agent.aux.decode(latent)
        if "mask" in decoded:
            logits = decoded["mask"][:, -1].float()
            panels["predicted mask"] = torch.sigmoid(logits)
            if self.true_mask:
                self.add("mask_iou", mask_iou(logits > 0, true)[scored])  # sigmoid > 0.5 <=> logit > 0
                bce = F.binary_cross_entropy_with_logits(logits, true, reduction="none")
                self.add("mask_bce", bce.flatten(1).mean(1)[scored])
        if "recon" in decoded:
            panels["reconstruction"] = decoded["recon"][:, -3:].float().clamp(-0.5, 0.5) + 0.5
            self.add("recon_psnr", psnr(panels["reconstruction"], panels["camera"])[scored])
        if any(filming):
            self.film(panels, np.flatnonzero(filming))

    def add(self, name, per_frame: torch.Tensor):  # only the frames to score: films are decoded whole
        self.values.setdefault(name, []).extend(per_frame.tolist())

    def film(self, panels: dict, rows):
        """Append frames `rows` of the batch to the video: panels side by side, upscaled, labelled."""
        import imageio.v2 as imageio  # imageio-ffmpeg brings the ffmpeg binary; needed only here
        width = panels["camera"].shape[-1] * self.SCALE
        if self.video is None:
            os.makedirs(os.path.dirname(self.video_path), exist_ok=True)
            # One encoder thread: the video is a side job of an evaluation on a shared machine.
            self.video = imageio.get_writer(self.video_path, fps=self.FPS, codec="libx264", macro_block_size=16,
                                            ffmpeg_params=["-threads", "1"])
            self.label_strip = label_strip(list(panels), width, self.LABEL)
        side = [p if p.dim() == 4 else p.unsqueeze(1).expand(-1, 3, -1, -1) for p in panels.values()]
        strip = (torch.cat(side, dim=3)[rows] * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        for frame in strip:
            big = frame.repeat(self.SCALE, axis=0).repeat(self.SCALE, axis=1)
            for k in range(1, len(panels)):  # a white rule between panels, drawn over their edge pixels
                big[:, k * width - 1:k * width + 1] = 255
            self.video.append_data(np.concatenate([self.label_strip, big], axis=0))

    def finish(self) -> dict:
        """Score the frames still pending and close the video. Returns the metrics' means over frames
        (for the IoU, over the frames where robot or prediction is present)."""
        self.flush()
        if self.video is not None:
            self.video.close()
            self.video = None
        scores = {}
        for name in self.METRICS:
            values = [v for v in self.values.get(name, ()) if not math.isnan(v)]
            if name in self.values:
                scores[name] = float(np.mean(values)) if values else float("nan")
        return scores


def label_strip(labels: list[str], panel_width: int, height: int) -> np.ndarray:
    """A black strip (height, panel_width * len(labels), 3) uint8 with each panel's name in white."""
    from PIL import Image, ImageDraw
    strip = Image.new("RGB", (panel_width * len(labels), height))
    draw = ImageDraw.Draw(strip)
    for i, label in enumerate(labels):
        draw.text((i * panel_width + 4, 2), label, fill=(255, 255, 255))
    return np.asarray(strip)


def eval_tasks(env, cfg: Config) -> list:
    """The task of every evaluation episode: None (the env's own draw) --eval-episodes times, or for a
    task set k episodes of each task, task after task (k = --eval-episodes-per-task, by default
    ceil(--eval-episodes / tasks): at least --eval-episodes in all). The authors evaluate task sets
    on 10 episodes of random tasks; per-task numbers need every task."""
    tasks = getattr(env.unwrapped, "tasks", None)
    if not tasks:
        return [None] * cfg.eval_episodes
    k = cfg.eval_episodes_per_task or math.ceil(cfg.eval_episodes / len(tasks))
    return [task for task in tasks for _ in range(k)]


def per_task_columns(per_task: dict) -> dict:
    """eval.csv's per-task columns: mean return and success rate of each task's episodes."""
    row = {}
    for task, episodes in per_task.items():
        row[f"return/{task}"] = float(np.mean([ret for ret, _ in episodes]))
        row[f"success/{task}"] = float(np.mean([success for _, success in episodes]))
    return row


def evaluate(agent, env, cfg: Config, frame, on_step=None, per_task=None):
    """Mean action, separately seeded env; the same reset seeds at every eval make evals comparable.
    on_step(episode, step), if given, is called after every step (the progress line). A task set
    runs every task (eval_tasks); per_task, if given, collects {task: [(return, success), ...]}."""
    returns, successes = [], []
    for i, task in enumerate(eval_tasks(env, cfg)):
        obs, info = env.reset(seed=episode_seed(cfg.seed + 100_000, i),
                              options=None if task is None else {"task": task})
        done, ret, success, t = False, 0.0, False, 0
        while not done:
            action = agent.act(obs["pixels"], obs["mask"], frame // cfg.action_repeat, eval_mode=True)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            success = success or bool(info.get("success", False))
            done = terminated or truncated
            t += 1
            if on_step:
                on_step(i, t)
        returns.append(ret)
        if "success" in info:
            successes.append(float(success))
        if per_task is not None and task is not None:
            per_task.setdefault(task, []).append((ret, float(success)))
    return float(np.mean(returns)), (float(np.mean(successes)) if successes else None)


class Interrupted(Exception):
    """Ctrl-C during training; the message says what was saved and how to continue."""


def interrupt_message(run_dir, frame, where, snapshot_frame, snapshot_minutes):
    """What is true after a Ctrl-C: whether a snapshot exists, at which frame, and the command that
    continues from it."""
    if run_dir is None:
        return "interrupted before the run directory was made; nothing was saved"
    head = f"interrupted at frame {frame} ({where})"
    resume = f"continue with: python sear.py --resume {run_dir}"
    if snapshot_frame == frame:
        return f"{head}: snapshot.pt holds this frame; {resume}"
    if snapshot_frame is not None:
        return (f"{head}: the last snapshot (frame {snapshot_frame}) stands, the {frame - snapshot_frame} "
                f"frames after it will be re-run; {resume}")
    return (f"{head}: {run_dir} has no snapshot yet (the first is written at the first episode end after "
            f"{snapshot_minutes:g} minutes), so there is nothing to resume; start a new run")


def train(cfg: Config, resume_state: dict | None = None):
    """Train from scratch, or continue from `resume_state` (the snapshot of run dir cfg.resume).

    Snapshots are taken between episodes only: the next episode's reset seed follows from its
    number, so a resumed run (with --save-buffer) replays exactly what the uninterrupted run would
    have done. They follow a wall clock (--snapshot-minutes), not the evaluation schedule, are also
    written on Ctrl-C between episodes, and after the final evaluation at the end of the budget."""
    # What a Ctrl-C message needs to know, kept up to date as the run goes.
    run_dir = cfg.resume or None
    snapshot_frame = resume_state["counters"]["step"] * cfg.action_repeat if resume_state else None
    frame = snapshot_frame or 0
    phase = "starting"  # then "mid-episode" / "between episodes", then "end of budget"
    try:
        device = pick_device(cfg.device)
        torch.set_num_threads(cfg.threads or default_threads())
        train_env, eval_env = make_envs(cfg)  # also resolves action_repeat 0 to the suite's default
        init_source = (load_init_source(cfg, train_env.action_space.shape[0])
                       if cfg.init_from and resume_state is None else None)
        if not cfg.resume:
            run_dir = new_run_dir(cfg)
            with open(os.path.join(run_dir, "config.json"), "w") as f:
                json.dump(dataclasses.asdict(cfg), f, indent=2)

        random.seed(cfg.seed)
        np.random.seed(cfg.seed)
        torch.manual_seed(cfg.seed)
        sample_rng = np.random.default_rng(cfg.seed)

        action_dim = train_env.action_space.shape[0]
        agent = Agent(cfg, action_dim, device)
        if init_source is not None:  # transfer: a new run from another run's networks
            copy_parts(agent, init_source, cfg.init_parts)
        pixel_shape = train_env.observation_space["pixels"].shape
        buffer = ReplayBuffer(cfg.replay_size, (3, *pixel_shape[1:]), action_dim, cfg.frame_stack,
                              cfg.nstep, cfg.discount)
        prefetcher = None
        if cfg.prefetch == "on" or (cfg.prefetch == "auto" and device.type == "cuda"):
            # The loop writes up to update_every steps while the thread samples: keep clear of them.
            prefetcher = Prefetcher(buffer, cfg.batch_size, sample_rng, device,
                                    margin=cfg.frame_stack + 2 * cfg.update_every)
        print(f"run dir: {run_dir}\nmethod {cfg.method} on {cfg.env} | device {device} | action repeat "
              f"{cfg.action_repeat} | replay {cfg.replay_size} x {buffer.bytes_per_transition} B = "
              f"{cfg.replay_size * buffer.bytes_per_transition / 1e9:.2f} GB at most")
        if cfg.mask_source != "sim":
            print(f"masks: {cfg.mask_source} (the model's prediction on every frame; the simulator's mask "
                  + ("is rendered in evaluation episodes only, for learned_mask_iou)" if cfg.learned_mask_iou
                     else "is never rendered)"))

        step, episode, next_eval, last_eval_frame, wall_offset = 0, 0, 0, -1, 0.0
        if resume_state is not None:
            agent.load_state_dict(resume_state["agent"])
            set_rng_state(resume_state["rng"])
            sample_rng.bit_generator.state = resume_state["sample_rng"]
            c = resume_state["counters"]
            step, episode, next_eval, wall_offset = c["step"], c["episode"], c["next_eval"], c["wall_time"]
            last_eval_frame = c.get("last_eval_frame", -1)
            if c["mid_episode"]:  # only the end-of-budget snapshot can cut an episode: drop its rest
                episode += 1
            buffer_path = os.path.join(run_dir, "buffer.npz")
            if not (os.path.exists(buffer_path) and resume_state.get("buffer_saved")):
                print("resume: no saved replay buffer (run with --save-buffer to keep it); refilling")
            elif saved_buffer_t(buffer_path) != resume_state.get("buffer_t", saved_buffer_t(buffer_path)):
                print("resume: buffer.npz is newer than snapshot.pt (killed between the two writes); refilling")
            else:
                buffer.load(buffer_path)
            set_aside_rows_after(os.path.join(run_dir, "train.csv"), step * cfg.action_repeat)
            # A snapshot taken at an episode end precedes that frame's evaluation: the resumed run
            # evaluates again from next_eval on, so rows from there go aside too.
            set_aside_rows_after(os.path.join(run_dir, "eval.csv"), min(step * cfg.action_repeat, next_eval - 1))
            print(f"resumed at frame {step * cfg.action_repeat}, episode {episode}")

        train_log = CsvLog(os.path.join(run_dir, "train.csv"))
        eval_log = CsvLog(os.path.join(run_dir, "eval.csv"))
        writer = tensorboard_writer(run_dir)
        progress = Progress(cfg.frames, cfg.log_every, cfg.eval_every)
        start = time.time() - wall_offset
        frame = step * cfg.action_repeat
        # Training speed: frames since the last episode end over the training seconds since then.
        # Evaluations and snapshots push window_start forward by their own duration.
        window_start, window_frame = time.time(), frame
        last_snapshot_time = time.time()

        def snapshot(mid_episode=False):
            nonlocal snapshot_frame, last_snapshot_time
            payload = {"config": dataclasses.asdict(cfg), "agent": agent.state_dict(), "rng": rng_state(),
                       "sample_rng": sample_rng.bit_generator.state, "buffer_saved": cfg.save_buffer,
                       "buffer_t": buffer.t,
                       "counters": {"step": step, "episode": episode, "next_eval": next_eval,
                                    "last_eval_frame": last_eval_frame, "mid_episode": mid_episode,
                                    "wall_time": time.time() - start}}
            # Buffer first, then snapshot.pt; each write is atomic, and buffer_t tells a resume
            # whether a kill between the two left a buffer newer than the snapshot.
            if cfg.save_buffer:
                buffer.save(os.path.join(run_dir, "buffer.npz"))
            save_snapshot(run_dir, payload)
            snapshot_frame, last_snapshot_time = frame, time.time()

        def run_evaluation():
            nonlocal next_eval, last_eval_frame
            episodes = len(eval_tasks(eval_env, cfg))
            progress.say(f"evaluating at frame {frame} ({episodes} episodes)")
            began = time.time()

            def show(i, t):
                done = i / episodes
                progress.update(frame, f"eval {i + 1}/{episodes} step {t}",
                                progress.eta(frame, next_eval, done, time.time() - began))

            # The watch scores what the decoders make of every evaluation frame, and films episode 0.
            watch = EvalWatch(agent, eval_env, os.path.join(run_dir, "videos", f"eval_{frame}.mp4")
                              if cfg.save_video else None)
            per_task = {}
            eval_return, eval_success = evaluate(agent, watch, cfg, frame, on_step=show, per_task=per_task)
            scores = watch.finish()
            progress.eval_seconds.append(time.time() - began)
            row = {"frame": frame, "step": step, "episode": episode, "return": eval_return,
                   "wall_time": round(time.time() - start, 2)}
            if eval_success is not None:
                row["success"] = eval_success
            row.update(per_task_columns(per_task))
            row.update(scores)
            if isinstance(eval_env, segment.LearnedMaskIoU):  # the mask model's IoU on these episodes' frames
                row["learned_mask_iou"] = scores["learned_mask_iou"] = eval_env.pop()
            eval_log.write(row)
            if writer:
                writer.add_scalar("eval/return", eval_return, frame)
                for name, value in scores.items():
                    writer.add_scalar(f"eval/{name}", value, frame)
            progress.say(f"eval @ frame {frame}: return {eval_return:.1f}"
                         + (f", success {eval_success:.2f}" if eval_success is not None else "")
                         + "".join(f", {name} {value:.3g}" for name, value in scores.items())
                         + f" ({progress.eval_seconds[-1]:.1f} s)")
            last_eval_frame = frame
            while next_eval <= frame:
                next_eval += cfg.eval_every

        def paused(fn, *args):
            """Run an evaluation or a snapshot off the training-speed clock."""
            nonlocal window_start
            began = time.time()
            fn(*args)
            window_start += time.time() - began

        need_reset = True
        while frame < cfg.frames:
            if need_reset:
                if phase == "between episodes" and time.time() - last_snapshot_time >= 60 * cfg.snapshot_minutes:
                    paused(snapshot)
                    progress.say(f"snapshot at frame {frame}")
                phase = "mid-episode"  # from here on the next episode has begun
                obs, info = train_env.reset(seed=episode_seed(cfg.seed, episode))
                buffer.add_first(obs)
                ep_return, ep_len, ep_success, ep_metrics = 0.0, 0, False, {}
                need_reset = False

            if frame >= next_eval:
                paused(run_evaluation)

            # As DrQ-v2, the agent acts from the first step: uniformly for --exploration-steps agent steps
            # (Agent.act), then the actor plus noise, not yet updated while the seed frames are collected.
            action = agent.act(obs["pixels"], obs["mask"], step, eval_mode=False)
            # Learning starts once the buffer holds the seed frames' worth of steps: after the random
            # phase of a new run, and again after a resume that could not bring its buffer back.
            if (frame >= cfg.seed_frames and step % cfg.update_every == 0 and buffer.can_sample()
                    and len(buffer) >= cfg.seed_frames // cfg.action_repeat):
                batch = prefetcher.next() if prefetcher else buffer.sample(cfg.batch_size, sample_rng)
                metrics = agent.update(batch, step)
                for k, v in metrics.items():
                    ep_metrics.setdefault(k, []).append(v)

            obs, reward, terminated, truncated, info = train_env.step(action)
            buffer.add(action, reward, terminated, obs)
            step += 1
            frame = step * cfg.action_repeat
            ep_return += reward
            ep_len += 1
            ep_success = ep_success or bool(info.get("success", False))

            progress.fps = (frame - window_frame) / max(time.time() - window_start, 1e-9)
            if terminated or truncated:
                row = {"frame": frame, "step": step, "episode": episode, "return": ep_return, "length": ep_len}
                if "success" in info:
                    row["success"] = float(ep_success)
                if "task" in info:  # task sets: which task the episode drew
                    row["task"] = info["task"]
                row.update({k: (float(np.mean(ep_metrics[k])) if k in ep_metrics else "")
                            for k in agent.metric_names})
                row.update({"fps": round(progress.fps, 2), "wall_time": round(time.time() - start, 2)})
                train_log.write(row)
                if writer:
                    writer.add_scalar("train/return", ep_return, frame)
                    for k in ep_metrics:
                        writer.add_scalar(f"train/{k}", float(np.mean(ep_metrics[k])), frame)
                progress.update(frame, f"ep {episode} return {ep_return:.1f}", progress.eta(frame, next_eval),
                                force=True)
                window_start, window_frame = time.time(), frame
                episode += 1
                need_reset = True
                phase = "between episodes"  # the only state a snapshot can capture exactly
            else:
                progress.update(frame, f"ep {episode} step {ep_len}", progress.eta(frame, next_eval))

        # The end of the budget: a last evaluation, so eval.csv ends at the last frame, then the
        # final snapshot (it may cut an episode; a resume drops that episode's rest).
        phase = "end of budget"
        if last_eval_frame != frame:
            run_evaluation()
        snapshot(mid_episode=not need_reset)
        progress.say(f"done: {frame} frames in {time.time() - start:.0f} s; outputs in {run_dir}")
        if prefetcher:
            prefetcher.close()
        train_env.close()
        eval_env.close()
        if writer:
            writer.close()
        return run_dir
    except KeyboardInterrupt:
        # Between episodes the state is exactly resumable; at the end of the budget it is what the
        # final snapshot holds anyway (a resume then runs only the final evaluation).
        if phase in ("between episodes", "end of budget") and snapshot_frame != frame:
            try:
                snapshot(mid_episode=phase == "end of budget" and not need_reset)
            except KeyboardInterrupt:  # a second Ctrl-C: the atomic writes leave the last snapshot whole
                pass
        raise Interrupted(interrupt_message(run_dir, frame, phase, snapshot_frame, cfg.snapshot_minutes)) from None


# ================================================================================================
# 9. CLI
# ================================================================================================
class OneLineParser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


RESUME_MAY_CHANGE = {"frames", "device", "threads", "save_buffer", "log_every", "resume", "snapshot_minutes",
                     "save_video"}


def inherit_from_source(cfg, explicit: set) -> set:
    """--init-from: the fields that fix the shapes of the copied networks (init_fields) come from the
    source run's config; given explicitly, they must equal it. Returns the fields taken."""
    state = load_snapshot(cfg.init_from, "--init-from", mmap=True)
    source, defaults = state["config"], Config()
    cfg.init_from = os.path.abspath(cfg.init_from)  # config.json names the source from anywhere
    taken = set()
    if "method" not in explicit:  # first: which fields matter depends on the method
        cfg.method = source["method"]
        taken.add("method")
    for name in init_fields(cfg):
        value = source.get(name, getattr(defaults, name))
        if name in explicit and getattr(cfg, name) != value:
            flag = "--" + name.replace("_", "-")
            raise ConfigError(f"--init-from: the source run has {flag} {value} but this run {getattr(cfg, name)}; "
                              f"--init-parts {cfg.init_parts} copies networks of that size (leave {flag} out "
                              f"to take the source's)")
        if name not in explicit:
            setattr(cfg, name, value)
            taken.add(name)
    frame = state["counters"]["step"] * source.get("action_repeat", 1)
    print(f"init-from {cfg.init_from} ({source['env']}, frame {frame}): copies {cfg.init_parts}; "
          + ", ".join(f"{k}={getattr(cfg, k)}" for k in init_fields(cfg)) + " as the source run")
    return taken


def parse_args(argv=None) -> tuple[Config, dict | None]:
    """The config from the flags; with --resume, the run's saved config (plus the few flags that may
    change) and its snapshot."""
    parser = OneLineParser(prog="sear.py", description=__doc__.split("\n\n")[0])
    defaults = Config()
    for f in dataclasses.fields(Config):
        flag = "--" + f.name.replace("_", "-")
        help_text = f"{f.metadata['doc']} (default: {getattr(defaults, f.name)!r})"
        if f.name == "method":  # the METHODS table documents itself
            help_text = "; ".join(f"{name}: {m.doc}" for name, m in METHODS.items()) + " (default: 'sear')"
        if f.type in ("bool", bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS,
                                help=help_text)
        else:
            typ = {"int": int, "float": float, "str": str}[f.type if isinstance(f.type, str) else f.type.__name__]
            parser.add_argument(flag, type=typ, default=argparse.SUPPRESS, help=help_text,
                                choices=list(METHODS) if f.name == "method" else None)
    given = vars(parser.parse_args(argv))
    state = None
    if given.get("resume"):
        state = load_snapshot(given["resume"])
        saved = state["config"]
        for k, v in given.items():
            if k not in RESUME_MAY_CHANGE and saved.get(k) != v:
                raise ConfigError(f"--{k.replace('_', '-')} cannot change on --resume "
                                  f"(run has {saved.get(k)!r}); only {', '.join(sorted(RESUME_MAY_CHANGE))} can")
        cfg = saved_config(saved, given)
        validate(cfg)  # a resumed config was resolved when the run started: no recipe again
    else:
        cfg = Config(**given)
        validate(cfg)
        if cfg.mask_source.startswith("learned:"):  # config.json names the model from anywhere
            cfg.mask_source = "learned:" + os.path.abspath(cfg.mask_source[len("learned:"):])
        explicit = set(given)
        if "init_parts" in given and not cfg.init_from:
            raise ConfigError("--init-parts needs --init-from (the run to copy from)")
        if cfg.init_from:  # the source run fixes the copied networks' sizes; the recipe may not change them
            explicit |= inherit_from_source(cfg, explicit)
        changed = apply_recipe(cfg, explicit)
        if changed:
            print(f"recipe {cfg.recipe}: " + "; ".join(changed))
    return cfg, state


def main(argv=None):
    try:
        cfg, resume_state = parse_args(argv)
        train(cfg, resume_state)
    except ConfigError as e:
        print(f"sear.py: error: {e}", file=sys.stderr)
        return 2
    except Interrupted as e:
        print(f"\nsear.py: {e}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:  # while reading the flags or the snapshot: nothing started
        print("\nsear.py: interrupted before training started; nothing was saved", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
