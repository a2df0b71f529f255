"""Pixel environments with robot segmentation masks for SEAR.

SEAR (Structured Environment-Agent Representations, ICML 2023) trains DrQ-v2
with an auxiliary decoder that predicts the robot's binary segmentation mask.
This module gives every suite used in the paper one Gymnasium-style interface:

    env = make_env("walker-walk-distracting", seed=0)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(action)

* ``obs["pixels"]``: uint8 (3*frame_stack, size, size), channel-first, oldest
  frame first; ``obs["mask"]``: uint8 (frame_stack, size, size) with 0/1.
* Frame stacking and action repeat happen inside the env (rewards are summed
  over the repeats; repeating stops when the episode ends).  At reset the first
  frame fills the whole stack.
* Time-limit ends are ``truncated=True``; real terminations ``terminated=True``.
  A solved Kitchen task also ends as a truncation (the authors bootstrap there).
* ``info["success"]`` exists for the suites that define success (Meta-World,
  Kitchen, Adroit).
* ``make_env(mask_model=f)`` takes the mask from ``f`` (uint8 RGB (3, size, size)
  -> bool (size, size), e.g. segment.py's learned model) instead of the
  simulator; ``obs["mask"]`` is then ``f``'s, and the simulator's mask, if
  rendered at all (``render_mask=True``), only appears as ``info["true_mask"]``
  (newest frame, before noise / approximation), for measuring ``f``.
* Task sets (``metaworld-mt3``, ``-mt10``, ``-mt50``) draw a task uniformly and
  one of its variations at every reset, from the reset seed; the agent sees
  pixels only, ``info["task"]`` names the task (reset and every step),
  ``env.tasks`` lists them and ``reset(options={"task": name})`` picks one.
* ``make_env(seed=s)`` plus ``reset(seed=s)`` reproduces an episode, including
  random backgrounds, Meta-World task variations and mask noise.

The robot-mask rule (identical for all suites, no hard-coded geom-id ranges):
a pixel is robot iff MuJoCo's segmentation render labels it with an object of
type mjOBJ_GEOM whose body lies in the subtree (via ``model.body_parentid``) of
the suite's robot root body (walker ``torso``, ball_in_cup ``cup``, Sawyer
``base``, Franka ``panda0_link0``, Adroit ``forearm``).  See ``robot_geoms``.

Mask pipeline (paper appendix): for the manipulation suites the segmentation is
rendered at 3x the observation size, cleaned with a binary opening and
downsampled by a 3x3 majority vote (``mask_downsample="stride"`` keeps every
3rd pixel as the authors did).  dm_control masks are rendered at the
observation size directly.  ``mask_noise`` and ``mask_approx`` corrupt the mask
for the paper's robustness ablations, whichever its source (simulator or
``mask_model``): pixels dropped first, then approximated, as the authors.

Distracting Control backgrounds (``backgrounds=``): None = built-in procedural
images (no download; not the paper's), ``"davis"`` = DAVIS-2017 480p from the
cache (``python envs.py --fetch-davis`` downloads it; the paper's setting), or
a folder (DAVIS or any images).  See ``Backgrounds`` and docs/distracting.md.

All suites render through one path: a ``mujoco.Renderer`` on the suite's raw
MjModel/MjData (RGB plus segmentation), so camera, shadow and multisampling
settings are handled in one place (``render_quality="paper"`` keeps each
suite's own settings, ``"fast"`` switches off shadows and multisampling).

Run ``python envs.py --gallery runs/suites.png`` to draw RGB | mask | overlay
for one task of every suite (``--force`` to overwrite an existing picture).
``python envs.py --robot NAME`` checks an env's robot mask: its root body, the
robot's bodies, each geom's pixels in view (docs/robots.md: a robot of your own).
"""
from __future__ import annotations

import os

# Must precede any mujoco / dm_control import: headless EGL rendering.
os.environ.setdefault("MUJOCO_GL", "egl")

import argparse
import atexit
import collections
import difflib
import errno
import functools
import hashlib
import shutil
import sys
import warnings
import weakref
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from PIL import Image, UnidentifiedImageError
from scipy import ndimage

__all__ = [
    "EnvError", "env_names", "default_action_repeat", "robot_name", "is_task_set", "metaworld_set_tasks", "make_env",
    "SEAREnv", "robot_geoms", "robot_pixels", "downsample_mask", "approximate_mask", "procedural_background",
    "d4rl_reward", "exploration_std_steps", "Backgrounds", "FetchError", "davis_cache", "fetch_davis",
    "robot_report",
]


class EnvError(ValueError):
    """Bad user input (unknown env name, bad option, unusable backgrounds dir).

    The message is always a single line so that a CLI can print it as is.
    """


# ----------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------

# dm_control domain aliases used in env names (DrQ-v2 / SEAR convention).
_DMC_ALIASES = {"cup": "ball_in_cup"}

# Robot root body per dm_control domain: the robot is this body's subtree (robot_geoms).  A new
# domain's root is named here (docs/robots.md; `python envs.py --robot NAME` checks it).  Domains
# not listed fall back to the first child body of the world that has a joint in its subtree (the
# first moving body tree in the MJCF): only a heuristic, and --robot says it guessed.
_DMC_ROBOT_ROOTS = {
    "walker": "torso", "ball_in_cup": "cup", "cheetah": "torso",
    "hopper": "torso", "quadruped": "torso", "humanoid": "torso",
    "reacher": "arm", "finger": "proximal", "cartpole": "cart",
    "acrobot": "upper_arm", "pendulum": "pole", "fish": "torso",
    "swimmer": "head", "point_mass": "pointmass", "manipulator": "upper_arm",
    "stacker": "upper_arm",
}

# Kitchen env name -> FrankaKitchen sub-tasks to complete in one episode.  "multitask" is D4RL's
# kitchen-mixed-v0 (microwave, kettle, bottom burner, light switch), as in the authors' code.
_KITCHEN_TASKS = {"kettle": ("kettle",), "light": ("light switch",), "slider": ("slide cabinet",),
                  "multitask": ("microwave", "kettle", "bottom burner", "light switch")}
# The authors' kitchen camera (kitchen_dm_env.py): a free camera looking at (-0.3, 0.5, 2.0) from
# 1.86 m.  "fixed" is azimuth 90, elevation -60; "random" draws one of these six per episode.
_KITCHEN_CAMERA_LOOKAT, _KITCHEN_CAMERA_DISTANCE = (-0.3, 0.5, 2.0), 1.86
_KITCHEN_CAMERA_FIXED = (90.0, -60.0)
_KITCHEN_CAMERAS = tuple((az, el) for az in (70.0, 90.0, 110.0) for el in (-60.0, -30.0))
# Meta-World task sets (metaworld-<set>).  MT10 and MT50 are Meta-World's own benchmarks (their
# train classes, in their order); MT3 is the authors' MT3-customized set
# (sear/environments/metaworld_custom_envs.py).
_METAWORLD_SETS = ("mt3", "mt10", "mt50")
_MT3_TASKS = ("button-press-topdown-wall", "door-open", "hammer")
_ADROIT_TASKS = {"door": "AdroitHandDoor-v1", "hammer": "AdroitHandHammer-v1",
                 "pen": "AdroitHandPen-v1", "relocate": "AdroitHandRelocate-v1"}
# Episode lengths of D4RL's <task>-human-v1, the authors' Adroit tasks (d4rl/hand_manipulation_suite/
# __init__.py, MAX_STEPS); gymnasium-robotics registers 200 for all four.
_ADROIT_EPISODE_STEPS = {"door": 200, "hammer": 200, "pen": 100, "relocate": 200}
# D4RL's pen episode ends when the pen falls below this height (pen_v0.py, step).
_PEN_DROP_HEIGHT = 0.075

# DrQ-v2's exploration schedule by task difficulty: std 1.0 -> 0.1 over this many agent steps
# (facebookresearch/drqv2 cfgs/task/{easy,medium,hard}.yaml, stddev_schedule; the per-task cfgs say
# which file each task takes, and sear-rl/sear-rl's cfgs/task are the same).  Tasks not listed take
# medium, DrQ-v2's default task (quadruped_walk) being one.
_DRQV2_STD_STEPS = {"easy": 100_000, "medium": 500_000, "hard": 2_000_000}
_DRQV2_DIFFICULTY = {
    **dict.fromkeys(["cartpole-balance", "cartpole-balance_sparse", "cartpole-swingup", "cup-catch",
                     "finger-spin", "hopper-stand", "pendulum-swingup", "walker-stand", "walker-walk"],
                    "easy"),
    **dict.fromkeys(["humanoid-run", "humanoid-stand", "humanoid-walk"], "hard"),
}

# Original Distracting Control Suite difficulty settings.  Number of background
# videos (None = all videos of the split) and the scale of the optional camera
# and colour distractions.
_DIFFICULTY_NUM_VIDEOS = {"easy": 4, "medium": 8, "hard": None}
_DIFFICULTY_SCALE = {"easy": 0.1, "medium": 0.2, "hard": 0.3}
# Ground-plane alpha under distraction, as in the original suite
# (google-research/google-research distracting_control/suite_utils.py,
# get_background_kwargs): reacher 0 (the background replaces the ground),
# walker and cheetah 1 (opaque), every other domain 0.3.
_GROUND_ALPHA = {"reacher": 0.0, "walker": 1.0, "cheetah": 1.0}
_GROUND_ALPHA_DEFAULT = 0.3

# DAVIS 2017 train / val video names (the 60 / 30 videos the Distracting
# Control Suite uses for its train / validation backgrounds).
DAVIS17_TRAIN = (
    "bear bmx-bumps boat boxing-fisheye breakdance-flare bus car-turn cat-girl "
    "classic-car color-run crossing dance-jump dancing disc-jockey dog-agility "
    "dog-gooses dogs-scale drift-turn drone elephant flamingo hike hockey "
    "horsejump-low kid-football kite-walk koala lady-running lindy-hop "
    "longboard lucia mallard-fly mallard-water miami-surf motocross-bumps "
    "motorbike night-race paragliding planes-water rallye rhino rollerblade "
    "schoolgirls scooter-board scooter-gray sheep skate-park snowboard "
    "soccerball stroller stunt surf swing tennis tractor-sand train tuk-tuk "
    "upside-down varanus-cage walking").split()
DAVIS17_VAL = (
    "bike-packing blackswan bmx-trees breakdance camel car-roundabout "
    "car-shadow cows dance-twirl dog dogs-jump drift-chicane drift-straight "
    "goat gold-fish horsejump-high india judo kite-surf lab-coat libby loading "
    "mbike-trick motocross-jump paragliding-launch parkour pigs scooter-black "
    "shooting soapbox").split()

# The paper's backgrounds: DAVIS-2017 trainval 480p, the archive the original suite's README and the
# authors' README download.  DAVIS publishes no checksum; size and SHA-256 are those TensorFlow
# Datasets records for this URL (tensorflow/datasets tensorflow_datasets/video/davis/checksums.tsv).
DAVIS_URL = "https://data.vision.ee.ethz.ch/csergi/share/davis/DAVIS-2017-trainval-480p.zip"
DAVIS_BYTES = 832_766_765
DAVIS_SHA256 = "e3d0b5b77c3d031b000a19e0e25e3e2cac65d183755601bc2cf066df1a2aa492"
DAVIS_KEYWORD = "davis"   # --backgrounds davis: the cache below
_DAVIS_FRAMES = Path("DAVIS", "JPEGImages", "480p")
_DAVIS_SETS = Path("DAVIS", "ImageSets", "2017")   # train.txt / val.txt: the official split

_IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".gif", ".webp", ".tif", ".tiff"}


@functools.lru_cache(maxsize=None)
def _dmc_tasks() -> tuple[tuple[str, str], ...]:
    from dm_control import suite
    return tuple(suite.ALL_TASKS)


@functools.lru_cache(maxsize=None)
def _metaworld_tasks() -> tuple[str, ...]:
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS
    return tuple(name[: -len("-v3")] for name in ALL_V3_ENVIRONMENTS)


def metaworld_set_tasks(set_name: str) -> tuple[str, ...]:
    """The task names of a Meta-World task set ("mt3", "mt10", "mt50"), without "-v3"."""
    if set_name == "mt3":
        return _MT3_TASKS
    from metaworld import env_dict   # MT10(seed).train_classes is env_dict.MT10_V3, and so on
    classes = env_dict.MT10_V3 if set_name == "mt10" else env_dict.MT50_V3
    return tuple(name[: -len("-v3")] for name in classes)


def _dmc_name(domain: str, task: str) -> str:
    inverse = {v: k for k, v in _DMC_ALIASES.items()}
    return f"{inverse.get(domain, domain)}-{task}"


def env_names() -> list[str]:
    """Every registered env name: each dm_control ``<domain>-<task>``, each of them again with
    ``-distracting`` (the paper's two, walker-walk and cup-catch, first), then the other suites."""
    names = ["walker-walk", "cup-catch"]
    names += [n for n in (_dmc_name(d, t) for d, t in _dmc_tasks()) if n not in names]
    names += [f"{n}-distracting" for n in names]
    names += [f"metaworld-{t}" for t in _metaworld_tasks()]
    names += [f"metaworld-{s}" for s in _METAWORLD_SETS]
    names += [f"kitchen-{t}" for t in _KITCHEN_TASKS]
    names += [f"adroit-{t}" for t in _ADROIT_TASKS]
    return names


def _valid_names_line() -> str:
    mw = _metaworld_tasks()
    return ("walker-walk, cup-catch, any dm_control <domain>-<task> (e.g. cheetah-run), "
            "<domain>-<task>-distracting (e.g. walker-walk-distracting), "
            f"metaworld-<task> ({len(mw)} MT1 tasks, e.g. {', '.join(mw[:3])}), "
            f"metaworld-{{{','.join(_METAWORLD_SETS)}}} (task sets), "
            f"kitchen-{{{','.join(_KITCHEN_TASKS)}}}, adroit-{{{','.join(_ADROIT_TASKS)}}}")


def _parse_name(name: str) -> tuple[str, tuple]:
    """Map an env name to (suite, args); raise EnvError for unknown names."""
    if not isinstance(name, str):
        raise EnvError(f"env name must be a string, got {name!r}")
    if name.startswith("metaworld-") and name[len("metaworld-"):] in (*_metaworld_tasks(), *_METAWORLD_SETS):
        return "metaworld", (name[len("metaworld-"):],)
    if name.startswith("kitchen-") and name[len("kitchen-"):] in _KITCHEN_TASKS:
        return "kitchen", (name[len("kitchen-"):],)
    if name.startswith("adroit-") and name[len("adroit-"):] in _ADROIT_TASKS:
        return "adroit", (name[len("adroit-"):],)
    distracting = name.endswith("-distracting")
    base = name[: -len("-distracting")] if distracting else name
    for domain, task in _dmc_tasks():
        if base == _dmc_name(domain, task) or base == f"{domain}-{task}":
            return ("distracting" if distracting else "dmc"), (domain, task)
    close = difflib.get_close_matches(name, env_names(), n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    raise EnvError(f"unknown env {name!r}; {hint}valid: {_valid_names_line()}")


def is_task_set(name: str) -> bool:
    """True for the multi-task Meta-World sets (metaworld-mt3, -mt10, -mt50): every episode draws
    one of several tasks, and the env lists them in ``env.tasks``."""
    return name.startswith("metaworld-") and name[len("metaworld-"):] in _METAWORLD_SETS


def exploration_std_steps(name: str) -> int | None:
    """The agent steps over which DrQ-v2 decays the exploration std on a plain dm_control task
    (100k easy, 500k medium, 2M hard); None for other suites and unknown names.  Distracting
    Control is not in DrQ-v2's table: the authors' distracting.yaml keeps 500k for every task."""
    try:
        suite, args = _parse_name(name)
    except EnvError:
        return None
    if suite != "dmc":
        return None
    return _DRQV2_STD_STEPS[_DRQV2_DIFFICULTY.get(_dmc_name(*args), "medium")]


def default_action_repeat(name: str) -> int:
    """2 for dm_control / Distracting Control / Meta-World, 1 for Kitchen / Adroit."""
    suite, _ = _parse_name(name)
    return 1 if suite in ("kitchen", "adroit") else 2


def robot_name(name: str) -> str:
    """The robot of an env: the dm_control domain (walker, ball_in_cup, ...), sawyer (Meta-World),
    franka (Kitchen) or adroit-hand. Envs of one robot share its look, and so its masks."""
    suite, args = _parse_name(name)
    return {"metaworld": "sawyer", "kitchen": "franka", "adroit": "adroit-hand"}.get(suite) or args[0]


# ----------------------------------------------------------------------------
# The robot-mask rule
# ----------------------------------------------------------------------------

def robot_geoms(model: mujoco.MjModel, root_body: str) -> np.ndarray:
    """Boolean array (ngeom,): geom belongs to the subtree of ``root_body``.

    This is the single definition of "robot" used for every suite.
    """
    root = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root_body)
    if root < 0:
        raise RuntimeError(f"robot root body {root_body!r} not in model")
    return body_subtree(model, root)[model.geom_bodyid]


def body_subtree(model: mujoco.MjModel, root: int) -> np.ndarray:
    """Boolean array (nbody,): body lies in the subtree of body id ``root``."""
    in_subtree = np.zeros(model.nbody, dtype=bool)
    in_subtree[root] = True
    # Bodies are stored in topological order (parent id < child id), so one
    # forward pass propagates membership from the root to all descendants.
    for b in range(root + 1, model.nbody):
        in_subtree[b] = in_subtree[model.body_parentid[b]]
    return in_subtree


def robot_pixels(seg: np.ndarray, geom_is_robot: np.ndarray) -> np.ndarray:
    """Boolean (H, W) robot mask from a MuJoCo segmentation image (H, W, 2).

    Channel 0 is the object id, channel 1 the object type (-1 = background).
    Sites and other non-geom objects also show up in segmentation renders;
    only geoms count.
    """
    ids, types = seg[..., 0], seg[..., 1]
    # int(): comparing an int array with the pybind enum directly would go
    # through slow object-dtype comparisons.
    is_geom = types == int(mujoco.mjtObj.mjOBJ_GEOM)
    return is_geom & geom_is_robot[np.where(is_geom, ids, 0)]


def downsample_mask(mask: np.ndarray, factor: int, mode: str = "majority") -> np.ndarray:
    """Downsample a boolean mask by an integer factor.

    ``majority``: a pixel is robot if more than half of its factor x factor
    block is (fills the one-pixel holes that mesh seams leave).  ``stride``:
    keep every factor-th pixel, as the SEAR authors did.
    """
    if factor == 1:
        return mask
    if mode == "stride":
        return mask[::factor, ::factor]
    if mode != "majority":
        raise EnvError(f"mask_downsample must be 'majority' or 'stride', got {mode!r}")
    h, w = mask.shape
    blocks = mask.reshape(h // factor, factor, w // factor, factor)
    return blocks.sum(axis=(1, 3)) * 2 > factor * factor


def approximate_mask(mask: np.ndarray, factor: int = 3, sigma: float = 0.5,
                     threshold: float = 0.9) -> np.ndarray:
    """The paper's "approximate mask": downsample, upsample, Gaussian blur, threshold.

    The paper gives no numbers; these are the authors' (``SlimMaskWrapper`` in
    sear/environments/wrappers.py, ``slim_mask_cfg`` in cfgs/train_config.yaml): bilinear
    resampling without anti-aliasing (skimage's ``rescale``: pixel centres aligned, edges
    mirrored) down by 3 and back up, sigma 0.5, threshold 0.9.  The high threshold erodes the
    mask: edges and thin parts go.
    """
    m = mask.astype(np.float64)
    small = ndimage.zoom(m, 1 / factor, order=1, mode="mirror", grid_mode=True)
    big = ndimage.zoom(small, np.divide(m.shape, small.shape), order=1, mode="mirror", grid_mode=True)
    return ndimage.gaussian_filter(big, sigma, mode="nearest") > threshold


# ----------------------------------------------------------------------------
# Backgrounds for Distracting Control
# ----------------------------------------------------------------------------

def procedural_background(seed: int, size: int = 256) -> np.ndarray:
    """A deterministic synthetic background image, uint8 (size, size, 3).

    The default background set needs no download: smooth random colour fields,
    stripes and blobs (cycled by seed), colourful and textured enough to be a
    real distraction.
    """
    rng = np.random.default_rng(seed)
    kind = seed % 3
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    if kind == 0:  # smooth random colour field: a few octaves of blurred noise
        field = np.zeros((size, size, 3), np.float32)
        for sigma, weight in ((size / 8, 1.0), (size / 24, 0.5), (size / 64, 0.25)):
            octave = ndimage.gaussian_filter(rng.standard_normal((size, size, 3)).astype(np.float32),
                                             sigma=(sigma, sigma, 0), mode="wrap")
            field += weight * octave / max(float(octave.std()), 1e-6)
    elif kind == 1:  # stripes between two random colours, random angle/frequency
        angle = rng.uniform(0, np.pi)
        freq = rng.uniform(3, 12)
        phase = np.sin(2 * np.pi * freq * (xx * np.cos(angle) + yy * np.sin(angle)))
        t = (phase[..., None] + 1) / 2
        c1, c2 = rng.random(3), rng.random(3)
        field = t * c1 + (1 - t) * c2
    else:  # soft blobs on a random base colour
        field = np.broadcast_to(rng.random(3), (size, size, 3)).copy()
        for _ in range(rng.integers(6, 16)):
            cy, cx = rng.random(2)
            r = rng.uniform(0.04, 0.2)
            alpha = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r))[..., None]
            field = alpha * rng.random(3) + (1 - alpha) * field
    field = (field - field.min()) / max(float(np.ptp(field)), 1e-6)
    return (field * 255).astype(np.uint8)


def _check_image(path: Path) -> None:
    """Raise EnvError unless ``path`` opens as an image.

    Header only: PIL's ``open`` identifies the format and reads the size
    without decoding pixels.  Catches non-images and unknown formats, not a
    file cut short after its header (``verify()`` would catch some of those
    but reads whole PNGs).  About 0.03-0.05 s per 1000 files.
    """
    try:
        Image.open(path).close()
    except UnidentifiedImageError:
        raise EnvError(f"background file {str(path)!r} is not an image (or not in a format "
                       f"PIL reads)") from None
    except Exception as e:   # PIL also raises OSError, SyntaxError, ValueError, ...
        reason = " ".join(str(e).split()) or type(e).__name__
        raise EnvError(f"background file {str(path)!r} is not a readable image: {reason}") from None


class Backgrounds:
    """Background images for one split, grouped like videos.

    ``directory=None``: procedural images (train seeds 0.., eval seeds
    100000..), one image per "video": not the paper's backgrounds.
    ``"davis"``: DAVIS-2017 480p from the cache (``davis_cache()``, filled by
    ``python envs.py --fetch-davis``); every video the split and difficulty
    name must be there.  A DAVIS-2017 ``JPEGImages/480p`` folder (or the DAVIS
    root holding it): the same lists, the videos present.  As the original
    suite (``background.py``): train videos for ``split="train"``, validation
    videos for ``"eval"``, the first 4 / 8 / all of the list for easy / medium
    / hard.  Any other folder: all images found recursively, grouped by their
    parent folder (a flat folder makes every image its own group); groups are
    sorted and every 5th group (index 4, 9, ...) is held out for
    ``split="eval"``; if that leaves either split empty, both use all groups;
    the difficulty limits the number of groups alike (procedural hard = 60
    train / 30 eval, the DAVIS counts).  Every file of the split is checked to
    be an image when the set is built.
    """

    def __init__(self, directory: str | None, split: str, difficulty: str):
        limit = _DIFFICULTY_NUM_VIDEOS[difficulty]
        if directory is None:
            count = limit or (len(DAVIS17_TRAIN) if split == "train" else len(DAVIS17_VAL))
            offset = 0 if split == "train" else 100_000
            self.groups = [[offset + i] for i in range(count)]
            self.source = f"procedural ({count} images)"
            return
        names = (DAVIS17_TRAIN if split == "train" else DAVIS17_VAL)[:limit]   # the original's num_videos
        if directory == DAVIS_KEYWORD:
            self.groups = self._cached_davis(names, split)
            self.source = f"DAVIS 2017 {split} ({len(self.groups)} videos)"
        else:
            self.groups, self.source = self._folder(directory, names, split, difficulty, limit)
        # Fail now, not hours into a run when a broken file is first sampled.
        for path in (p for g in self.groups for p in g):
            _check_image(path)

    @staticmethod
    def _cached_davis(names: list, split: str) -> list:
        """--backgrounds davis: the split's videos from the cache, every one of them there."""
        root = davis_cache() / _DAVIS_FRAMES
        if not root.is_dir():
            raise EnvError(f"--backgrounds davis: no DAVIS-2017 in {davis_cache()}; get it "
                           f"({DAVIS_BYTES / 1e6:.0f} MB) with: python envs.py --fetch-davis")
        if missing := davis_missing(root, names):
            raise EnvError(f"--backgrounds davis: {root} lacks {len(missing)} of the {split} videos "
                           f"({', '.join(missing[:3])}); fetch it again: python envs.py --fetch-davis")
        return [_images(root / n) for n in names]

    @classmethod
    def _folder(cls, directory: str, names: list, split: str, difficulty: str, limit) -> tuple[list, str]:
        """A folder: the DAVIS videos present (a DAVIS root, or its JPEGImages/480p), else every image
        grouped by parent folder. Returns (groups, source)."""
        root = Path(directory).expanduser()
        if not root.is_dir():
            raise EnvError(f"backgrounds dir {directory!r} does not exist or is not a directory")
        for davis in (root / _DAVIS_FRAMES, root / _DAVIS_FRAMES.relative_to("DAVIS")):
            if davis.is_dir():   # a --fetch-davis --cache folder, or the DAVIS root
                root = davis
                break
        subdirs = {p.name for p in root.iterdir() if p.is_dir()}
        if not subdirs & set(DAVIS17_TRAIN + DAVIS17_VAL):
            groups = cls._folder_groups(root, directory, split)[:limit]
            return groups, f"{directory} ({len(groups)} groups)"
        groups = [g for g in (_images(root / n) for n in names if n in subdirs) if g]
        if not groups:
            raise EnvError(f"backgrounds dir {directory!r} looks like DAVIS but holds none of the "
                           f"{'train' if split == 'train' else 'val'} videos {difficulty} uses")
        return groups, f"DAVIS 2017 {split} ({len(groups)} videos)"

    @staticmethod
    def _folder_groups(root: Path, directory: str, split: str) -> list:
        images = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)
        if not images:
            raise EnvError(f"backgrounds dir {directory!r} holds no images ({', '.join(sorted(_IMAGE_SUFFIXES))})")
        by_parent = collections.defaultdict(list)
        for p in images:
            by_parent[p.parent].append(p)
        groups = [by_parent[k] for k in sorted(by_parent)] if len(by_parent) > 1 else [[p] for p in images]
        train = [g for i, g in enumerate(groups) if i % 5 != 4]
        held_out = [g for i, g in enumerate(groups) if i % 5 == 4]
        if train and held_out:
            groups = train if split == "train" else held_out
        return groups

    def sample(self, rng: np.random.Generator, side: int) -> np.ndarray:
        """One episode's background, uint8 (side, side, 3): a random video (group), then a random
        frame of it, held for the whole episode: the original suite's default ``dynamic=False``,
        which the authors keep.  The whole frame is resized (bilinear) to the square sky face, as
        the original suite does (854x480 DAVIS frames are stretched, not cropped)."""
        group = self.groups[rng.integers(len(self.groups))]
        item = group[rng.integers(len(group))]
        if isinstance(item, int):
            return _procedural_frame(item, side)
        with Image.open(item) as f:
            return _resize(f.convert("RGB"), side)


def _images(folder: Path) -> list[Path]:
    """A video's frames in order (the fork of the suite the authors installed sorts them too)."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def _resize(img: Image.Image, side: int) -> np.ndarray:
    """The whole image to (side, side, 3), bilinear: the original suite's tf.image.resize (the
    authors' packaged fork: cv2.resize INTER_LINEAR) up to PIL's wider kernel when it shrinks
    (854 -> 800: 0.3 grey levels apart on average on a smooth frame)."""
    return np.asarray(img.resize((side, side), Image.BILINEAR), dtype=np.uint8)


@functools.lru_cache(maxsize=32)
def _procedural_frame(seed: int, side: int) -> np.ndarray:
    """Procedural images are slow to draw and resize (~0.08 s): keep the last few (1.9 MB each at
    the sky's 800 x 800), shared by a run's train and eval env."""
    frame = _resize(Image.fromarray(procedural_background(seed)), side)
    frame.setflags(write=False)
    return frame


# ----------------------------------------------------------------------------
# DAVIS-2017: the cache and its download
# ----------------------------------------------------------------------------

class FetchError(EnvError):
    """A download or unpacking failure, in one line."""


def davis_cache() -> Path:
    """Where ``--backgrounds davis`` looks and ``--fetch-davis`` writes by default:
    ``$SEAR_DATA/davis``, without SEAR_DATA ``~/.cache/sear/davis``."""
    return Path(os.environ.get("SEAR_DATA") or Path.home() / ".cache" / "sear").expanduser() / "davis"


def davis_missing(frames: Path, names) -> list[str]:
    """The videos among ``names`` without a JPEG frame under ``frames``."""
    return [n for n in names if not any((frames / n).glob("*.jpg"))]


def fetch_davis(cache: str | None = None, *, url: str = DAVIS_URL, size: int = DAVIS_BYTES,
                sha256: str = DAVIS_SHA256, progress: bool = True) -> Path:
    """Download DAVIS-2017 trainval 480p into ``cache`` (default ``davis_cache()``) and return its
    frames folder (``<cache>/DAVIS/JPEGImages/480p``).  The archive goes to a ``.part`` file that a
    later call resumes (HTTP Range); then its size and SHA-256 are checked (a mismatch deletes it),
    its frames and split lists are unpacked, every train and validation video is checked to have
    frames, and the archive is deleted.  A complete cache is left as it is.  Every failure is a
    one-line FetchError, and leaves no half-unpacked folder."""
    cache = Path(cache).expanduser() if cache else davis_cache()
    frames = cache / _DAVIS_FRAMES
    if (cache / "DAVIS").exists():
        if missing := davis_missing(frames, DAVIS17_TRAIN + DAVIS17_VAL):
            raise FetchError(f"{cache / 'DAVIS'} exists but lacks {len(missing)} of the 90 videos "
                             f"({', '.join(missing[:3])}); move it away and run again")
        return frames
    part = cache / "DAVIS-2017-trainval-480p.zip.part"
    try:
        cache.mkdir(parents=True, exist_ok=True)
        _download(url, part, size, progress)
        with open(part, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
        if digest != sha256:
            part.unlink()
            raise FetchError(f"{url}: SHA-256 {digest[:16]}... is not the official archive's {sha256[:16]}...; "
                             "the download was deleted, run again")
        _unpack_davis(part, cache)
        part.unlink()
    except OSError as e:   # disk full, no permission, ...
        raise FetchError(f"cannot write {e.filename or cache}: {e.strerror or e}"
                         + (" (disk full)" if e.errno == errno.ENOSPC else "")) from None
    return frames


def _need_space(folder: Path, nbytes: int) -> None:
    free = shutil.disk_usage(folder).free
    if free < nbytes:
        raise FetchError(f"{folder} has {free / 1e6:.0f} MB free, {nbytes / 1e6:.0f} MB needed")


def _download(url: str, part: Path, size: int, progress: bool) -> None:
    """``url`` into ``part``, appending to what an earlier call left there (HTTP Range)."""
    import http.client
    import urllib.error
    import urllib.request
    from tqdm import tqdm
    have = part.stat().st_size if part.exists() else 0
    if have > size:   # not a piece of this archive
        part.unlink()
        have = 0
    if have == size:
        return
    _need_space(part.parent, size - have)
    request = urllib.request.Request(url, headers={"Range": f"bytes={have}-"} if have else {})
    try:
        response = urllib.request.urlopen(request, timeout=60)
    except urllib.error.HTTPError as e:
        raise FetchError(f"cannot download {url}: HTTP {e.code} {e.reason}") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
        raise FetchError(f"cannot reach {url}: {getattr(e, 'reason', None) or e} (no network?)") from None
    with response:
        if response.status != 206:   # the whole file: start again from its first byte
            have = 0
        length = response.headers.get("Content-Length")
        if length is not None and have + int(length) != size:
            raise FetchError(f"{url} is {have + int(length)} bytes, the DAVIS-2017 trainval 480p archive is "
                             f"{size}: not that archive")
        with open(part, "ab" if have else "wb") as f, \
                tqdm(total=size, initial=have, unit="B", unit_scale=True, unit_divisor=1024,
                     desc="DAVIS-2017-trainval-480p.zip", disable=not progress) as bar:
            while True:
                try:
                    chunk = response.read(1 << 20)
                except (OSError, http.client.HTTPException):   # reset, timed out, cut short
                    break
                if not chunk:
                    break
                f.write(chunk)
                bar.update(len(chunk))
    if (got := part.stat().st_size) != size:
        raise FetchError(f"the download of {url} broke off at {got} of {size} bytes; run again to resume")


def _unpack_davis(archive: Path, cache: Path) -> None:
    """The archive's frames (``DAVIS/JPEGImages/480p``) and split lists (``DAVIS/ImageSets/2017``)
    into ``cache/DAVIS``, through a scratch folder renamed once everything is there and checked."""
    import zipfile
    import zlib
    scratch = cache / ".DAVIS.unpacking"
    shutil.rmtree(scratch, ignore_errors=True)   # an earlier, interrupted unpack
    try:
        try:
            with zipfile.ZipFile(archive) as z:
                members = [m for m in z.infolist()
                           if m.filename.startswith((f"{_DAVIS_FRAMES.as_posix()}/", f"{_DAVIS_SETS.as_posix()}/"))]
                _need_space(cache, sum(m.file_size for m in members))
                for m in members:
                    z.extract(m, scratch)   # CRC-checked; zipfile keeps names inside scratch
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            archive.unlink()
            raise FetchError(f"{archive.name} is not a readable zip archive ({e}); deleted, run again") from None
        try:
            splits = {s: set((scratch / _DAVIS_SETS / f"{s}.txt").read_text().split()) for s in ("train", "val")}
        except FileNotFoundError:
            splits = {}
        missing = davis_missing(scratch / _DAVIS_FRAMES, DAVIS17_TRAIN + DAVIS17_VAL)
        if splits != {"train": set(DAVIS17_TRAIN), "val": set(DAVIS17_VAL)} or missing:
            archive.unlink()
            raise FetchError(f"{archive.name} is not DAVIS-2017 trainval: "
                             + (f"no frames for {len(missing)} videos ({', '.join(missing[:3])})" if missing
                                else "its ImageSets/2017 train / val lists are not the suite's")
                             + "; deleted")
        (scratch / "DAVIS").rename(cache / "DAVIS")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


class _Distractions:
    """Distracting Control Suite perturbations applied to a dm_control model.

    * background: the skybox texture is turned into a single square face
      (``tex_height = tex_width``: MuJoCo then repeats that face on all six
      cube sides, as the original's ``tex_height = 800``) and every episode
      one frame of the backgrounds (``Backgrounds.sample``) is written into it; the
      ground plane gets the original suite's alpha (``_GROUND_ALPHA``), so
      the background shows through it except for walker and cheetah.
    * camera (optional, ``camera_distraction=s``): static per-episode random
      offset of the camera position (up to s x its distance) and rotation
      (up to s x 30 degrees) -- a simplified, non-drifting version of the
      original suite's camera distraction.
    * colour (optional, ``color_distraction=s``): per-episode random shift in
      [-s, s] of the RGB of the robot's materials / geoms.
    """

    def __init__(self, model, domain, geom_is_robot, camera_id, backgrounds,
                 camera_scale=0.0, color_scale=0.0):
        self.model = model
        self.backgrounds = backgrounds
        self.camera_id = camera_id
        self.camera_scale = camera_scale
        self.color_scale = color_scale
        self.sky = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, "skybox")
        if self.sky < 0:
            skies = np.flatnonzero(model.tex_type == int(mujoco.mjtTexture.mjTEXTURE_SKYBOX))
            if not len(skies):
                raise EnvError(f"dm_control domain {domain!r} has no skybox; cannot add backgrounds")
            self.sky = int(skies[0])
        self.side = int(model.tex_width[self.sky])
        # One square face; the texture buffer (6 faces) is larger than needed,
        # so the first side*side*nchannel bytes hold the image.
        model.tex_height[self.sky] = self.side
        self.nchannel = int(model.tex_nchannel[self.sky])
        grid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, "grid")
        if grid >= 0:
            model.mat_rgba[grid, 3] = _GROUND_ALPHA.get(domain, _GROUND_ALPHA_DEFAULT)
        # Originals, restored before each episode's perturbation.
        # Tracking cameras (walker's trackcom) are placed from cam_pos0 /
        # cam_mat0, fixed ones from cam_pos / cam_quat: perturb both.
        self.cam_pos_orig = model.cam_pos[camera_id].copy()
        self.cam_quat_orig = model.cam_quat[camera_id].copy()
        self.cam_pos0_orig = model.cam_pos0[camera_id].copy()
        self.cam_mat0_orig = model.cam_mat0[camera_id].copy()
        self.robot_mats = np.unique(model.geom_matid[geom_is_robot & (model.geom_matid >= 0)])
        self.robot_plain_geoms = np.flatnonzero(geom_is_robot & (model.geom_matid < 0))
        self.mat_rgba0 = model.mat_rgba.copy()
        self.geom_rgba0 = model.geom_rgba.copy()

    def apply(self, rng: np.random.Generator) -> list[int]:
        """Perturb the model for a new episode; returns textures to re-upload."""
        m = self.model
        img = self.backgrounds.sample(rng, self.side)
        if self.nchannel == 4:
            img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], axis=-1)
        adr = int(m.tex_adr[self.sky])
        m.tex_data[adr: adr + img.size] = img.reshape(-1)
        if self.camera_scale > 0:
            s, c = self.camera_scale, self.camera_id
            offset = rng.uniform(-s, s, 3)
            m.cam_pos[c] = self.cam_pos_orig + offset * np.linalg.norm(self.cam_pos_orig)
            m.cam_pos0[c] = self.cam_pos0_orig + offset * np.linalg.norm(self.cam_pos0_orig)
            axis = rng.normal(size=3)
            dq = np.zeros(4)
            mujoco.mju_axisAngle2Quat(dq, axis / np.linalg.norm(axis), rng.uniform(-s, s) * np.pi / 6)
            q = np.zeros(4)
            mujoco.mju_mulQuat(q, self.cam_quat_orig, dq)
            m.cam_quat[c] = q
            q0, mat = np.zeros(4), np.zeros(9)
            mujoco.mju_mat2Quat(q0, self.cam_mat0_orig)
            mujoco.mju_mulQuat(q, q0, dq)
            mujoco.mju_quat2Mat(mat, q)
            m.cam_mat0[c] = mat.reshape(m.cam_mat0[c].shape)
        if self.color_scale > 0:
            s = self.color_scale
            m.mat_rgba[:] = self.mat_rgba0
            m.geom_rgba[:] = self.geom_rgba0
            for mat in self.robot_mats:
                m.mat_rgba[mat, :3] = np.clip(self.mat_rgba0[mat, :3] + rng.uniform(-s, s, 3), 0, 1)
            for g in self.robot_plain_geoms:
                m.geom_rgba[g, :3] = np.clip(self.geom_rgba0[g, :3] + rng.uniform(-s, s, 3), 0, 1)
        return [self.sky]


# ----------------------------------------------------------------------------
# Suite backends: physics, reward, episode bookkeeping (no rendering)
# ----------------------------------------------------------------------------

class _DMCBackend:
    """dm_control suite task; episodes of 1000 physics-control steps."""

    has_success = False
    flip = False
    mask_scale = 1       # masks rendered at the observation size
    opening = False

    def __init__(self, domain: str, task: str, seed: int, pole_inertia: str = "exact"):
        from dm_control import suite
        self.env = suite.load(domain, task, task_kwargs={"random": seed})
        self.physics = self.env.physics
        if pole_inertia == "2021":
            mujoco2_pole_inertia(self.physics)
        self.model = self.physics.model.ptr
        self.data = self.physics.data.ptr
        self.domain = domain
        self.camera = 2 if domain == "quadruped" else 0   # DrQ-v2 convention
        self.robot_root = _DMC_ROBOT_ROOTS.get(domain) or self._default_root()
        self.robot_root_named = domain in _DMC_ROBOT_ROOTS   # False: _default_root's guess
        spec = self.env.action_spec()
        # DrQ-v2's action path (its dmc.py, and the authors'): dm_control's action_scale.Wrapper maps
        # [-1, 1] onto the bounds of an ActionDTypeWrapper(float32) spec, which holds them in float32,
        # computes in float64 and casts the result to float32; the ActionDTypeWrapper hands that on
        # as float64.  So the bounds are float32 here, and dm_control receives a float32 value, bit for
        # bit the one DrQ-v2's code gives on this project's NumPy (run_official.py's runs; under its
        # NumPy 1.19, value-based casting also rounded action + 1 to float32 before the scaling).
        low, high = spec.minimum.astype(np.float32), spec.maximum.astype(np.float32)
        self._low, self._scale = low.astype(np.float64), (high - low) / np.float64(2.0)
        self.action_dim = int(spec.shape[0])

    def _default_root(self) -> str:
        m = self.model
        for b in range(1, m.nbody):
            if m.body_parentid[b] != 0:
                continue
            if np.any(body_subtree(m, b)[m.jnt_bodyid]):
                return m.body(b).name
        return m.body(1).name

    def reset(self, seed: int) -> None:
        # dm_control tasks draw initial states from task.random.
        self.env.task._random = np.random.RandomState(seed)
        self.env.reset()

    def step(self, action: np.ndarray):
        # Agent actions live in [-1, 1]; map to the actuator spec as DrQ-v2 does (__init__).
        a = self._low + self._scale * (np.asarray(action, np.float64) + 1.0)
        a = a.astype(np.float32).astype(np.float64)
        ts = self.env.step(a)
        reward = float(ts.reward or 0.0)
        if ts.last():
            # discount 0 = true termination, 1 = time limit.
            terminated = ts.discount == 0.0
            return reward, terminated, not terminated, {}
        return reward, False, False, {}

    def close(self):
        self.env.close()
        # dm_control makes GL contexts of its own when a task touches
        # physics.contexts (quadruped-escape uploads its terrain at every reset).
        # Free them now: freed later by the garbage collector, while another
        # env's renderer is current, they broke that env's segmentation render
        # (quadruped-fetch after quadruped-escape: colours instead of ids).
        self.physics.free()


def mujoco2_pole_inertia(physics) -> None:
    """Cartpole's poles with the inertia MuJoCo 2.0 gave them, under DrQ-v2's 2021 curves. MuJoCo 2.1.1
    made capsule inertias exact; before, a capsule of radius r and half-length h weighed as a cylinder of
    length 2h + r: m (3r^2 + (2h + r)^2) / 12 across, m r^2 / 2 along (pole_1: 0.00915083 and 0.00010125,
    against 0.00942459 and 0.00010010 now: 0.8% more about the hinge). Each pole body is one capsule."""
    m = physics.model.ptr
    for b in range(m.nbody):
        if m.body(b).name.startswith("pole_"):
            g = m.body_geomadr[b]
            r, h, mass = m.geom_size[g][0], m.geom_size[g][1], m.body_mass[b]
            m.body_inertia[b] = [mass * (3 * r * r + (2 * h + r) ** 2) / 12] * 2 + [mass * r * r / 2]
    mujoco.mj_setConst(m, physics.data.ptr)  # what compiling derives from inertias (solver weights)


def _dist(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)))


def d4rl_reward(task: str, data: mujoco.MjData) -> float:
    """D4RL's dense reward of an Adroit task, from the simulator state after a step
    (d4rl/hand_manipulation_suite/<task>_v0.py, ``step``; bonuses on, as in D4RL).

    Computed here rather than taken from gymnasium-robotics: its AdroitHand{Door,Hammer,Relocate}-v1
    (1.4.2) flip the sign of the hand-to-object term and so pay the hand for moving away from the
    handle, hammer or ball (Gymnasium-Robotics PR #220). The authors trained on D4RL's envs.
    """
    palm = data.site("S_grasp").xpos
    if task == "door":
        door = float(data.joint("door_hinge").qpos[0])
        reward = -0.1 * _dist(palm, data.site("S_handle").xpos)     # get to the handle
        reward -= 0.1 * (door - 1.57) ** 2                            # open the door
        reward -= 1e-5 * float(np.sum(data.qvel ** 2))                # velocity cost
        return reward + 2 * (door > 0.2) + 8 * (door > 1.0) + 10 * (door > 1.35)
    if task == "hammer":
        hammer, tool = data.body("Object").xpos, data.site("tool").xpos
        nail, goal = data.site("S_target").xpos, data.site("nail_goal").xpos
        reward = -0.1 * _dist(palm, hammer)                           # get to the hammer
        reward -= _dist(tool, nail)                                   # hammer head to the nail
        reward -= 10 * _dist(nail, goal)                              # nail into the board
        reward -= 1e-2 * float(np.linalg.norm(data.qvel))             # velocity cost
        reward += 2 * (hammer[2] > 0.04 and tool[2] > 0.04)           # hammer lifted
        return reward + 25 * (_dist(nail, goal) < 0.02) + 75 * (_dist(nail, goal) < 0.01)
    if task == "relocate":
        ball, target = data.body("Object").xpos, data.site("target").xpos
        reward = -0.1 * _dist(palm, ball)                             # hand to the ball
        if ball[2] > 0.04:                                            # lifted: carry it to the target
            reward += 1.0 - 0.5 * _dist(palm, target) - 0.5 * _dist(ball, target)
        return reward + 10 * (_dist(ball, target) < 0.1) + 20 * (_dist(ball, target) < 0.05)
    if task == "pen":
        # Orientations are the unit vectors bottom -> top of the pen and of the target pen.
        pen = data.site("object_top").xpos - data.site("object_bottom").xpos
        want = data.site("target_top").xpos - data.site("target_bottom").xpos
        similarity = float(np.dot(pen, want) / (np.linalg.norm(pen) * np.linalg.norm(want)))
        dist = _dist(data.body("Object").xpos, data.site("eps_ball").xpos)
        reward = -dist + similarity
        reward += 10 * (dist < 0.075 and similarity > 0.9) + 50 * (dist < 0.075 and similarity > 0.95)
        return reward - 5 * (data.body("Object").xpos[2] < _PEN_DROP_HEIGHT)   # dropped
    raise ValueError(f"no Adroit task {task!r}")


class _GymBackend:
    """Gymnasium-Robotics Kitchen / Adroit via gym.make (TimeLimit included).

    Adroit follows D4RL's <task>-human-v1 (the authors' envs): D4RL's reward (``d4rl_reward``),
    its episode lengths, and the pen episode ends when the pen drops, as a truncation: the
    authors' wrapper (adroit_dm_env.py) ends every D4RL ``done`` with dm_env.truncation."""

    flip = False
    mask_scale = 3
    opening = True
    has_success = True

    def __init__(self, suite: str, task: str, seed: int, kitchen_camera: str = "fixed"):
        # ``seed`` is unused here: these envs draw everything random at reset,
        # which SEAREnv seeds from its own generator.
        import gymnasium_robotics
        gym.register_envs(gymnasium_robotics)
        self.kitchen_camera = kitchen_camera
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if suite == "kitchen":
                # FrankaKitchen's reward is the number of sub-tasks completed at this step (each
                # counts once: a completed one leaves tasks_to_complete), so an episode's return
                # is the number of sub-tasks solved, as D4RL's kitchen-mixed.
                self.env = gym.make("FrankaKitchen-v1", tasks_to_complete=list(_KITCHEN_TASKS[task]),
                                    max_episode_steps=280, disable_env_checker=True)
                self.robot_root = "panda0_link0"
                # A free camera: RGB and segmentation both render through this one object, so
                # the mask follows it when reset() moves it.
                cam = mujoco.MjvCamera()
                cam.type = mujoco.mjtCamera.mjCAMERA_FREE
                cam.lookat[:] = _KITCHEN_CAMERA_LOOKAT
                cam.distance = _KITCHEN_CAMERA_DISTANCE
                cam.azimuth, cam.elevation = _KITCHEN_CAMERA_FIXED
                self.camera = cam
            else:
                self.env = gym.make(_ADROIT_TASKS[task], max_episode_steps=_ADROIT_EPISODE_STEPS[task],
                                    disable_env_checker=True)
                self.robot_root = "forearm"
                self.camera = "fixed"
        self.suite, self.task = suite, task
        u = self.env.unwrapped
        self.model, self.data = u.model, u.data
        self.action_dim = int(self.env.action_space.shape[0])

    def reset(self, seed: int) -> None:
        if self.kitchen_camera == "random":   # one of the authors' six views per episode
            view = np.random.default_rng(seed).integers(len(_KITCHEN_CAMERAS))
            self.camera.azimuth, self.camera.elevation = _KITCHEN_CAMERAS[view]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.env.reset(seed=seed)

    def step(self, action):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, reward, terminated, truncated, info = self.env.step(
                np.asarray(action, dtype=self.env.action_space.dtype))
        if self.suite == "kitchen":
            # Sparse: 1 per completed task; success = every task completed.
            success = len(info["episode_task_completions"]) == len(self.env.unwrapped.goal)
            # FrankaKitchen terminates exactly when every task is completed
            # (its robot never terminates).  The authors' kitchen wrapper ends
            # that episode as dm_env.truncation (discount 1): the solved state
            # is not absorbing, the agent bootstraps from it.  So do we.
            truncated, terminated = truncated or terminated, False
        else:
            success = bool(info["success"])   # Adroit's goal_achieved (D4RL's)
            reward = d4rl_reward(self.task, self.data)
            # D4RL's pen ends when the pen drops; the authors' wrapper makes that a truncation.
            dropped = self.task == "pen" and self.data.body("Object").xpos[2] < _PEN_DROP_HEIGHT
            truncated = truncated or bool(dropped)
        return float(reward), bool(terminated), bool(truncated), {"success": success}

    def close(self):
        self.env.close()


@functools.lru_cache(maxsize=8)
def _metaworld_variations(name: str, variation_seed: int) -> dict:
    """{task: its 50 variations (metaworld.Task: object and goal placements)} of a Meta-World task
    or task set, drawn from the variation seed as the authors' code does: MT10 and MT50 are
    Meta-World's benchmarks; one task and MT3 use one MT1 benchmark per task (so metaworld-mt3
    sees exactly the placements of metaworld-door-open with the same seed).  Cached: the train
    and the eval env of a run share one draw (building MT50 takes about 25 s)."""
    import metaworld
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # Every benchmark draws from np.random seeded with the variation seed and restores the
        # global state afterwards.
        if name in ("mt10", "mt50"):
            benchmark = (metaworld.MT10 if name == "mt10" else metaworld.MT50)(seed=variation_seed)
            by_task = collections.defaultdict(list)
            for t in benchmark.train_tasks:
                by_task[t.env_name[: -len("-v3")]].append(t)
            return dict(by_task)
        tasks = metaworld_set_tasks(name) if name in _METAWORLD_SETS else (name,)
        return {t: metaworld.MT1(f"{t}-v3", seed=variation_seed).train_tasks for t in tasks}


class _MetaWorldBackend:
    """Meta-World v3: one task (MT1) or a task set (MT3, MT10, MT50); a new variation every reset.

    As in the authors' code, the variations are drawn once from a *variation seed* (50 per task,
    ``_metaworld_variations``) and every reset samples a task uniformly (task sets only), then
    one of its 50 variations, and ``set_task``s it; both draws follow from the reset seed.
    ``reset(seed, task=name)`` picks the task instead (per-task evaluation).  Giving the train
    and the eval env the same variation seed (``make_env(variation_seed=)``) makes evaluation
    draw from the same placements as training.  Episodes: 500 env steps.

    Each task's env is built on its first episode and kept (about 20 MB each, 1 GB for MT50);
    ``model`` / ``data`` are the current task's, and SEAREnv re-binds its renderers when they
    change (one renderer pair per SEAREnv, not one per task: a pair holds 0.1-0.3 GB).
    """

    flip = True        # v3's 'corner' camera renders upside down
    mask_scale = 3
    opening = True
    has_success = True

    def __init__(self, name: str, variation_seed: int):
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS
        self._classes = ALL_V3_ENVIRONMENTS
        self._variations = _metaworld_variations(name, variation_seed)
        self.task_names = tuple(self._variations)
        # Task sets list their tasks (SEAREnv.tasks, info["task"]); a single task does not.
        self.tasks = self.task_names if name in _METAWORLD_SETS else None
        self._envs: dict = {}
        self._activate(self.task_names[0], 0)   # the env refuses to reset before a set_task
        self.camera = "corner"
        self.robot_root = "base"
        self.action_dim = int(self.env.action_space.shape[0])   # 4 for every Sawyer task

    def _activate(self, task: str, variation: int) -> None:
        if task not in self._envs:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self._envs[task] = self._classes[f"{task}-v3"]()
        self.task, self.env = task, self._envs[task]
        self.variations = self._variations[task]   # this task's 50 metaworld.Task
        self.variation = variation
        self.env.set_task(self.variations[variation])

    @property
    def model(self):
        return self.env.model

    @property
    def data(self):
        return self.env.data

    def draw(self, seed: int, task: str | None = None) -> tuple[str, int]:
        """The (task, variation) a reset with this seed plays: a uniform task (task sets, unless
        given), then a uniform variation of it.  A single task draws only the variation, so its
        episodes are those of the MT1-only version of this class."""
        rng = np.random.default_rng(seed)
        if task is None:
            task = (self.task_names[int(rng.integers(len(self.task_names)))] if self.tasks
                    else self.task_names[0])
        return task, int(rng.integers(len(self._variations[task])))

    def reset(self, seed: int, task: str | None = None) -> None:
        # A frozen task leaves nothing else random in a Meta-World reset.
        self._activate(*self.draw(seed, task))
        self.env.reset()

    def step(self, action):
        _, reward, terminated, truncated, info = self.env.step(np.asarray(action, np.float32))
        return float(reward), bool(terminated), bool(truncated), {"success": bool(info["success"])}

    def close(self):
        for env in self._envs.values():
            env.close()


# ----------------------------------------------------------------------------
# The SEAR env: rendering, mask pipeline, action repeat, frame stack
# ----------------------------------------------------------------------------

# Envs not yet closed.  Closed at interpreter exit while EGL still works;
# otherwise the renderers' __del__ runs after EGL teardown and prints errors.
# dm_control registers an atexit eglTerminate when it is first imported, so
# the hook is re-registered at every env construction to run before it (LIFO).
_LIVE_ENVS: "weakref.WeakSet[SEAREnv]" = weakref.WeakSet()


def _close_live_envs():
    for env in list(_LIVE_ENVS):
        env.close()


class SEAREnv(gym.Env):
    """Pixel + robot-mask env with action repeat and frame stacking.

    Attributes useful beyond the contract: ``robot_root`` (root body name),
    ``geom_is_robot`` (bool per geom), ``model`` / ``data`` (raw MuJoCo),
    ``segmentation()`` (raw segmentation at mask resolution, before flipping
    and downsampling), ``mask_scale`` (segmentation / observation size).
    """

    metadata = {"render_modes": []}

    def __init__(self, backend, *, name: str, seed: int, frame_stack: int, action_repeat: int,
                 size: int, mask_noise: float, mask_approx: bool, mask_downsample: str,
                 render_quality: str, render_mask: bool = True, mask_model=None,
                 distractions_kwargs: dict | None = None):
        self.name = name
        self.backend = backend
        # Task sets: the task names, for reset(options={"task": name}); None for one task.
        self.tasks = getattr(backend, "tasks", None)
        self.robot_root = backend.robot_root
        self.frame_stack, self.action_repeat, self.size = frame_stack, action_repeat, size
        self.mask_noise, self.mask_approx, self.mask_downsample = mask_noise, mask_approx, mask_downsample
        self.mask_scale = backend.mask_scale
        self.render_quality = render_quality
        # False: skip segmentation, obs["mask"] is all zeros (mask-free baselines) or mask_model's.
        self.render_mask = render_mask
        # A callable RGB (3, H, W) -> bool (H, W) mask that replaces the simulator's in obs["mask"].
        self.mask_model = mask_model
        self.segmentation_renders = 0   # counted: a learned-mask run proves it never renders one
        self._rgb_renderer = self._seg_renderer = None
        self._bind_model()

        self._distractions = None
        if distractions_kwargs is not None:
            cam_id = backend.camera
            self._distractions = _Distractions(self.model, backend.domain, self.geom_is_robot, cam_id,
                                               **distractions_kwargs)
        self._make_renderers()

        self.action_space = spaces.Box(-1.0, 1.0, (backend.action_dim,), np.float32)
        self.observation_space = spaces.Dict({
            "pixels": spaces.Box(0, 255, (3 * frame_stack, size, size), np.uint8),
            "mask": spaces.Box(0, 1, (frame_stack, size, size), np.uint8),
        })
        self._rng = np.random.default_rng(seed)
        self._frames: collections.deque = collections.deque(maxlen=frame_stack)
        self._masks: collections.deque = collections.deque(maxlen=frame_stack)
        self._needs_reset = True
        self._closed = False
        _LIVE_ENVS.add(self)
        atexit.unregister(_close_live_envs)
        atexit.register(_close_live_envs)

    # -- rendering ------------------------------------------------------------
    def _bind_model(self):
        """Take the backend's current MuJoCo model: its robot geoms and render settings."""
        self.model, self.data = m, _ = self.backend.model, self.backend.data
        self.geom_is_robot = robot_geoms(m, self.robot_root)
        if self.render_quality == "fast":
            # No shadows, no multisampling (must be set before the GL context
            # is created).  Everything else (lights, reflections) unchanged.
            # Without shadows the shadow map is never drawn: shadowsize 0 saves
            # its 4096^2 depth buffer (64 MB per renderer; same pixels).
            m.light_castshadow[:] = 0
            m.vis.quality.offsamples = 0
            m.vis.quality.shadowsize = 0
        seg_size = self.size * self.mask_scale
        m.vis.global_.offwidth = max(m.vis.global_.offwidth, seg_size)
        m.vis.global_.offheight = max(m.vis.global_.offheight, seg_size)

    def _make_renderers(self):
        """One renderer for RGB; a second one for segmentation when masks are rendered at a
        higher resolution.  A task set's models differ per task (other objects, meshes and
        textures): the renderers are made again when the task changes, which costs ~0.5 s per
        switch but holds one pair at a time (a pair holds 0.1-0.3 GB of textures and buffers;
        one per MT50 task would take many GB; EXPERIMENTS.md, "Task sets: memory and task switches")."""
        self._close_renderers()
        self._rgb_renderer = mujoco.Renderer(self.model, self.size, self.size)
        seg_size = self.size * self.mask_scale
        self._seg_renderer = (self._rgb_renderer if seg_size == self.size
                              else mujoco.Renderer(self.model, seg_size, seg_size))

    def _close_renderers(self):
        for r in {id(r): r for r in (self._rgb_renderer, self._seg_renderer) if r is not None}.values():
            r.close()
        self._rgb_renderer = self._seg_renderer = None

    def _upload(self, textures=(), hfields=()):
        """Send changed textures / height fields to the GPU copies our renderers hold."""
        renderers = {id(r): r for r in (self._rgb_renderer, self._seg_renderer)}.values()
        for r in renderers:
            # mujoco.Renderer keeps its GL / MjrContext private; re-uploading
            # a texture needs both (MuJoCo has no other way to refresh one).
            r._gl_context.make_current()
            for t in textures:
                mujoco.mjr_uploadTexture(self.model, r._mjr_context, t)
            for h in hfields:
                mujoco.mjr_uploadHField(self.model, r._mjr_context, h)

    def segmentation(self) -> np.ndarray:
        """Raw segmentation (H, W, 2) int32 at mask resolution, camera orientation."""
        self.segmentation_renders += 1
        r = self._seg_renderer
        r.enable_segmentation_rendering()
        try:
            r.update_scene(self.data, camera=self.backend.camera)
            return r.render().copy()
        finally:
            r.disable_segmentation_rendering()

    def _render(self):
        """(RGB (3, size, size), mask (size, size), simulator's clean mask or None). The mask is the
        simulator's, or mask_model's prediction on this RGB frame; either way corrupted afterwards
        by --mask-approx / --mask-noise. With a mask_model the simulator's mask is rendered only if
        render_mask, and only returned third (for info["true_mask"]), never as the mask."""
        r = self._rgb_renderer
        r.update_scene(self.data, camera=self.backend.camera)
        rgb = r.render()
        if self.backend.flip:
            rgb = rgb[::-1, ::-1]
        rgb = np.ascontiguousarray(rgb.transpose(2, 0, 1))
        true = self.clean_mask() if self.render_mask else None
        if self.mask_model is not None:
            mask = self._corrupt(np.asarray(self.mask_model(rgb), dtype=bool))
        elif true is not None:
            mask, true = self._corrupt(true), None
        else:
            mask = np.zeros((self.size, self.size), bool)
        return rgb, mask, true

    def clean_mask(self) -> np.ndarray:
        """Current robot mask (size, size) bool before noise / approximation."""
        full = robot_pixels(self.segmentation(), self.geom_is_robot)
        if self.backend.opening:
            # Remove one-pixel artifacts (thin slivers at mesh seams/edges).
            full = ndimage.binary_opening(full)
        mask = downsample_mask(full, self.mask_scale, self.mask_downsample)
        if self.backend.flip:
            mask = mask[::-1, ::-1]
        return mask

    def _corrupt(self, mask: np.ndarray) -> np.ndarray:
        """The paper's robustness ablations, applied to the mask whatever its source: pixels dropped
        first, then the approximation, in the authors' order (NoisyMaskWrapper inside
        SlimMaskWrapper in every sear/environments/*_dm_env.py and distracting_dmc.py)."""
        if self.mask_noise > 0:
            mask = mask & (self._rng.random(mask.shape) >= self.mask_noise)
        if self.mask_approx:
            mask = approximate_mask(mask)
        return mask

    def _obs(self):
        return {"pixels": np.concatenate(list(self._frames), axis=0),
                "mask": np.stack(list(self._masks)).astype(np.uint8)}

    # -- gymnasium API ------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """``options={"task": name}`` (task sets only) starts an episode of that task; without it a
        task set draws the task from the seed.  Task sets name the task in ``info["task"]``."""
        task = (options or {}).get("task")
        if task is not None and task not in (self.tasks or ()):
            raise EnvError(f"reset: {self.name} has no task {task!r}"
                           + (f"; tasks: {', '.join(self.tasks)}" if self.tasks else " (not a task set)"))
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        episode_seed = int(self._rng.integers(2**31 - 1))
        if self._distractions is not None:
            # Before the physics reset: its mj_forward places the (perturbed) camera.
            self._upload(textures=self._distractions.apply(self._rng))
        if task is None:
            self.backend.reset(episode_seed)
        else:
            self.backend.reset(episode_seed, task=task)
        if self.backend.model is not self.model:   # a task set switched tasks
            self._bind_model()
            self._make_renderers()
        if self.model.nhfield:
            # Tasks that draw a new terrain per episode (quadruped-escape) write
            # it into the model; our renderers hold their own GPU copy (without
            # this upload the first episode showed the XML's flat floor).
            self._upload(hfields=range(self.model.nhfield))
        rgb, mask, true = self._render()
        for _ in range(self.frame_stack):
            self._frames.append(rgb)
            self._masks.append(mask)
        self._needs_reset = False
        return self._obs(), {**self._task_info(), **self._true_mask_info(true)}

    def _task_info(self) -> dict:
        return {"task": self.backend.task} if self.tasks else {}

    @staticmethod
    def _true_mask_info(true) -> dict:
        return {} if true is None else {"true_mask": true}

    def step(self, action):
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (episode over or never started)")
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        total, terminated, truncated, info = 0.0, False, False, {}
        success = False
        for _ in range(self.action_repeat):
            reward, terminated, truncated, info = self.backend.step(action)
            total += reward
            success = success or bool(info.get("success", False))
            if terminated or truncated:
                break
        if self.backend.has_success:
            info = {**info, "success": success}
        rgb, mask, true = self._render()
        info = {**info, **self._task_info(), **self._true_mask_info(true)}
        self._frames.append(rgb)
        self._masks.append(mask)
        self._needs_reset = terminated or truncated
        return self._obs(), total, bool(terminated), bool(truncated), info

    def close(self):
        if self._closed:
            return
        self._closed = True
        _LIVE_ENVS.discard(self)
        self._close_renderers()
        self.backend.close()


def _check_arguments(name, suite, args, *, difficulty, render_quality, split, mask_downsample, mask_noise,
                     frame_stack, size, action_repeat, backgrounds, kitchen_camera, pole_inertia) -> None:
    """make_env's arguments: an EnvError (one line) for the first that is wrong for this env."""
    if difficulty not in _DIFFICULTY_NUM_VIDEOS:
        raise EnvError(f"difficulty must be one of easy, medium, hard; got {difficulty!r}")
    if render_quality not in ("paper", "fast"):
        raise EnvError(f"render_quality must be 'paper' or 'fast'; got {render_quality!r}")
    if split not in ("train", "eval"):
        raise EnvError(f"split must be 'train' or 'eval'; got {split!r}")
    if mask_downsample not in ("majority", "stride"):
        raise EnvError(f"mask_downsample must be 'majority' or 'stride'; got {mask_downsample!r}")
    if not 0.0 <= mask_noise <= 1.0:
        raise EnvError(f"mask_noise must be in [0, 1]; got {mask_noise}")
    if frame_stack < 1 or size < 1:
        raise EnvError(f"frame_stack and size must be positive; got {frame_stack}, {size}")
    if action_repeat < 1:
        raise EnvError(f"action_repeat must be >= 1; got {action_repeat}")
    if backgrounds is not None and suite != "distracting":
        raise EnvError(f"backgrounds only apply to *-distracting envs, not {name!r}")
    if kitchen_camera not in ("fixed", "random"):
        raise EnvError(f"kitchen_camera must be 'fixed' or 'random'; got {kitchen_camera!r}")
    if kitchen_camera == "random" and suite != "kitchen":
        raise EnvError(f"a random kitchen camera only applies to kitchen-* envs, not {name!r}")
    if pole_inertia not in ("exact", "2021"):
        raise EnvError(f"pole_inertia must be 'exact' or '2021'; got {pole_inertia!r}")
    if pole_inertia == "2021" and not (suite in ("dmc", "distracting") and args[0] == "cartpole"):
        raise EnvError(f"the 2021 pole inertia only applies to cartpole-* envs, not {name!r}")


def make_env(name: str, *, seed: int = 0, frame_stack: int = 3, action_repeat: int | None = None,
             size: int = 84, mask_noise: float = 0.0, mask_approx: bool = False,
             backgrounds: str | None = None, difficulty: str = "medium",
             render_quality: str = "paper", split: str = "train",
             mask_downsample: str = "majority", camera_distraction: float = 0.0,
             color_distraction: float = 0.0, render_mask: bool = True,
             variation_seed: int | None = None, kitchen_camera: str = "fixed",
             mask_model=None, pole_inertia: str = "exact") -> SEAREnv:
    """Build a SEAR pixel env.  See the module docstring for the contract.

    ``backgrounds``/``difficulty``/``split``/``camera_distraction``/
    ``color_distraction`` only matter for ``*-distracting`` envs.
    ``backgrounds``: None (built-in procedural images, not the paper's),
    "davis" (DAVIS-2017 from ``davis_cache()``: the paper's) or a folder; see
    ``Backgrounds``.  ``split``: "train" (DAVIS train videos) or "eval" (DAVIS
    validation videos).
    ``difficulty`` picks the number of background videos: easy / medium / hard =
    4 / 8 / all of the split; the default, medium, is the run's (sear.py
    --difficulty, the authors' distracting.yaml); the camera/colour
    distraction scales are given explicitly (the original suite's values per
    difficulty are 0.1 / 0.2 / 0.3) and default to off, as in the paper.
    ``mask_downsample``: "majority" (default) or "stride" (the authors').
    ``render_mask=False`` skips the segmentation render (obs["mask"] is then
    all zeros), for mask-free baselines.
    ``mask_model``: a callable uint8 RGB (3, size, size) -> bool (size, size)
    that gives obs["mask"] instead of the simulator (a learned segmentation
    model, segment.py); the simulator's mask is then rendered only with
    ``render_mask=True`` and only reported as ``info["true_mask"]``.
    ``variation_seed`` (Meta-World only; defaults to ``seed``) seeds the MT1
    benchmark (MT10, MT50 for those sets) whose 50 variations per task the
    resets sample from: give the train and the eval env the same value so both
    see the same placements.
    ``kitchen_camera`` (Kitchen only): "fixed" (the authors' view) or "random" (one of their six per episode).
    ``pole_inertia`` (cartpole only): "exact" (MuJoCo 3's) or "2021" (MuJoCo 2.0's: mujoco2_pole_inertia).
    """
    suite, args = _parse_name(name)
    action_repeat = default_action_repeat(name) if action_repeat is None else action_repeat
    _check_arguments(name, suite, args, difficulty=difficulty, render_quality=render_quality, split=split,
                     mask_downsample=mask_downsample, mask_noise=mask_noise, frame_stack=frame_stack, size=size,
                     action_repeat=action_repeat, backgrounds=backgrounds, kitchen_camera=kitchen_camera,
                     pole_inertia=pole_inertia)

    distractions_kwargs = None
    if suite == "distracting":
        # Validate the backgrounds before paying for physics construction.
        bgs = Backgrounds(backgrounds, split, difficulty)
        distractions_kwargs = dict(backgrounds=bgs, camera_scale=float(camera_distraction),
                                   color_scale=float(color_distraction))
    if suite in ("dmc", "distracting"):
        backend = _DMCBackend(*args, seed=seed, pole_inertia=pole_inertia)
    elif suite == "metaworld":
        backend = _MetaWorldBackend(*args, variation_seed=seed if variation_seed is None else variation_seed)
    else:
        backend = _GymBackend(suite, *args, seed=seed, kitchen_camera=kitchen_camera)
    return SEAREnv(backend, name=name, seed=seed, frame_stack=frame_stack,
                   action_repeat=action_repeat, size=size, mask_noise=mask_noise,
                   mask_approx=mask_approx, mask_downsample=mask_downsample,
                   render_quality=render_quality, render_mask=render_mask, mask_model=mask_model,
                   distractions_kwargs=distractions_kwargs)


# ----------------------------------------------------------------------------
# Pictures
# ----------------------------------------------------------------------------

GALLERY_ENVS = ("walker-walk-distracting", "cup-catch-distracting", "metaworld-door-open",
                "kitchen-kettle", "adroit-door")


def _overlay(rgb_hwc: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = rgb_hwc.astype(np.float32)
    out[mask] = 0.45 * out[mask] + 0.55 * np.array([255, 40, 200])
    return out.astype(np.uint8)


def gallery(path: str, names=GALLERY_ENVS, *, backgrounds=None, render_quality="paper",
            steps: int = 10, seed: int = 0) -> None:
    """Save RGB | mask | overlay for each env (after a few random steps)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    for i, name in enumerate(names):
        # A different seed per row so that distracting envs show different backgrounds.
        env = make_env(name, seed=seed + i, frame_stack=1, render_quality=render_quality,
                       backgrounds=backgrounds if name.endswith("-distracting") else None)
        obs, _ = env.reset(seed=seed + i)
        rng = np.random.default_rng(seed + i)
        for _ in range(steps):
            obs, _, term, trunc, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            if term or trunc:
                obs, _ = env.reset()
        rgb = obs["pixels"][-3:].transpose(1, 2, 0)
        mask = obs["mask"][-1].astype(bool)
        rows.append((name, rgb, mask))
        env.close()
    fig, axes = plt.subplots(len(rows), 3, figsize=(7.5, 2.5 * len(rows)))
    axes = np.atleast_2d(axes)
    for i, (name, rgb, mask) in enumerate(rows):
        for j, (img, title) in enumerate([(rgb, "RGB"), (mask, "robot mask"),
                                          (_overlay(rgb, mask), "overlay")]):
            ax = axes[i, j]
            ax.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest",
                      vmin=0, vmax=1 if img.ndim == 2 else None)
            ax.set_xticks([]), ax.set_yticks([])
            if j == 0:
                ax.set_ylabel(name, fontsize=8)
            if i == 0:
                ax.set_title(title, fontsize=10)
        axes[i, 1].set_xlabel(f"mask fraction {mask.mean():.3f}", fontsize=8)
    fig.suptitle(f"SEAR observations ({rows[0][1].shape[0]}x{rows[0][1].shape[1]}, "
                 f"render_quality={render_quality})", fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def mask_downsample_figure(path: str, name: str = "metaworld-door-open", seed: int = 0) -> None:
    """Authors' stride-3 downsampling vs 3x3 majority on one Sawyer frame."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = make_env(name, seed=seed, frame_stack=1, render_quality="fast")
    obs, _ = env.reset(seed=seed)
    full = robot_pixels(env.segmentation(), env.geom_is_robot)
    opened = ndimage.binary_opening(full)
    flip = (lambda a: a[::-1, ::-1]) if env.backend.flip else (lambda a: a)
    stride = flip(downsample_mask(opened, env.mask_scale, "stride"))
    majority = flip(downsample_mask(opened, env.mask_scale, "majority"))
    env.close()
    fig, axes = plt.subplots(1, 4, figsize=(12, 3.4))
    panels = [(obs["pixels"][-3:].transpose(1, 2, 0), "RGB 84x84"),
              (flip(opened), f"segmentation {opened.shape[0]}px + opening"),
              (stride, f"authors: every 3rd pixel ({stride.mean():.3f})"),
              (majority, f"3x3 majority ({majority.mean():.3f})")]
    for ax, (img, title) in zip(axes, panels):
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------
# Checking a robot root (docs/robots.md)
# ----------------------------------------------------------------------------

def robot_report(env: SEAREnv, frames: int = 5, seed: int = 0) -> dict:
    """What the robot-mask rule makes of an env, to check its robot root (``--robot``).

    Over ``frames`` frames (the reset's, then random actions) it counts the segmentation's pixels
    of each geom in view, robot or not, and compares ``obs["mask"]`` with the robot geoms' pixels
    of the same render, brought to the observation size by majority (IoU 1.0: the mask is the
    segmentation's robot; an opening, mask noise or a mask model lower it).  Returns ``root``,
    ``named`` (False: guessed by ``_DMCBackend._default_root``), ``bodies`` (the robot's),
    ``robot_px`` and ``other_px`` ({geom label: pixels}), ``mask_fraction`` and ``iou``.
    """
    m, rng = env.model, np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    counts = np.zeros(m.ngeom, np.int64)
    inter = union = 0
    fraction = 0.0
    for i in range(frames):
        if i:
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            if terminated or truncated:
                obs, _ = env.reset()
        seg = env.segmentation()
        is_geom = seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
        counts += np.bincount(seg[..., 0][is_geom], minlength=m.ngeom)
        robot = downsample_mask(robot_pixels(seg, env.geom_is_robot), env.mask_scale, "majority")
        robot = robot[::-1, ::-1] if env.backend.flip else robot
        mask = obs["mask"][-1].astype(bool)
        inter, union = inter + int((mask & robot).sum()), union + int((mask | robot).sum())
        fraction += float(mask.mean()) / frames

    def label(g):
        return f"{m.geom(g).name or f'geom {g}'} ({m.body(m.geom_bodyid[g]).name or 'world'})"

    root, others = m.body(env.robot_root).id, np.flatnonzero(~env.geom_is_robot & (counts > 0))
    return {"root": env.robot_root, "named": getattr(env.backend, "robot_root_named", True),
            "bodies": [m.body(b).name for b in np.flatnonzero(body_subtree(m, root))],
            "robot_px": {label(g): int(counts[g]) for g in np.flatnonzero(env.geom_is_robot)},
            "other_px": {label(g): int(counts[g]) for g in others},
            "mask_fraction": fraction, "iou": inter / union if union else float("nan")}


def _print_robot_report(name: str, frames: int) -> None:
    env = make_env(name, seed=0, frame_stack=1, render_quality="fast")
    try:
        r = robot_report(env, frames=frames)
    finally:
        env.close()
    where = ("named in envs._DMC_ROBOT_ROOTS" if r["named"] and env.backend.__class__ is _DMCBackend
             else "named by its backend" if r["named"]
             else "GUESSED (the first moving body tree): name it in envs._DMC_ROBOT_ROOTS")

    def px(counts: dict) -> str:
        ranked = sorted(counts.items(), key=lambda kv: -kv[1])
        return ", ".join(f"{k} {v}" for k, v in ranked) or "none"

    print(f"{name}: robot root body {r['root']!r}, {where}")
    print(f"robot bodies ({len(r['bodies'])}): {', '.join(r['bodies'])}")
    print(f"mask: {100 * r['mask_fraction']:.1f}% of the frame over {frames} frames; IoU with the "
          f"segmentation's robot geoms {r['iou']:.3f}")
    print(f"robot geoms, px in view: {px({k: v for k, v in r['robot_px'].items() if v})}")
    unseen = [k for k, v in r["robot_px"].items() if not v]
    print(f"robot geoms never in view: {', '.join(unseen) or 'none'}")
    print(f"other geoms in view (not robot), px: {px(r['other_px'])}")


class _OneLineParser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def main(argv=None) -> int:
    parser = _OneLineParser(prog="envs.py", description=__doc__.splitlines()[0])
    parser.add_argument("--gallery", metavar="PNG", help="draw RGB | mask | overlay per suite")
    parser.add_argument("--mask-figure", metavar="PNG",
                        help="draw the stride vs majority mask downsampling comparison")
    parser.add_argument("--envs", nargs="+", default=list(GALLERY_ENVS), help="envs for --gallery")
    parser.add_argument("--backgrounds", metavar="DIR",
                        help="backgrounds for *-distracting: davis (the cache, see --fetch-davis) or a folder")
    parser.add_argument("--render-quality", default="paper", choices=["paper", "fast"])
    parser.add_argument("--list", action="store_true", help="print the registered env names")
    parser.add_argument("--robot", metavar="NAME",
                        help="check an env's robot mask: its root body, the robot's bodies, the "
                             "pixels of each geom in view, robot or not (docs/robots.md)")
    parser.add_argument("--frames", type=int, default=5,
                        help="frames of random actions for --robot")
    parser.add_argument("--force", action="store_true", help="overwrite an existing --gallery / --mask-figure PNG")
    parser.add_argument("--fetch-davis", action="store_true",
                        help=f"download DAVIS-2017 trainval 480p ({DAVIS_BYTES / 1e6:.0f} MB, the paper's Distracting "
                             "Control backgrounds) into the cache, for --backgrounds davis; run again to resume")
    parser.add_argument("--cache", metavar="DIR",
                        help="--fetch-davis into DIR (then --backgrounds DIR) instead of $SEAR_DATA/davis "
                             "(default ~/.cache/sear/davis)")
    parser.add_argument("--davis-url", metavar="URL", default=DAVIS_URL,
                        help="--fetch-davis from a mirror (its size and SHA-256 are still the official archive's)")
    args = parser.parse_args(argv)
    if not (args.gallery or args.mask_figure or args.list or args.fetch_davis or args.robot):
        parser.error("nothing to do: give --gallery PNG, --mask-figure PNG, --robot NAME, --list "
                     "or --fetch-davis")
    if args.frames < 1:
        parser.error(f"--frames must be at least 1, got {args.frames}")
    if args.fetch_davis:
        return _fetch_main(args.cache, args.davis_url)
    try:
        for out in filter(None, (args.gallery, args.mask_figure)):
            if os.path.exists(out) and not args.force:  # e.g. a tracked picture in docs/
                raise EnvError(f"{out} exists; refusing to overwrite it (use --force)")
        for name in args.envs:   # fail fast, before any slow construction
            _parse_name(name)
        if args.backgrounds is not None:
            Backgrounds(args.backgrounds, "train", "hard")
        if args.robot:
            _parse_name(args.robot)
        if args.list:
            print("\n".join(env_names()))
        if args.robot:
            _print_robot_report(args.robot, args.frames)
        if args.gallery:
            gallery(args.gallery, args.envs, backgrounds=args.backgrounds,
                    render_quality=args.render_quality)
            print(f"wrote {args.gallery}")
        if args.mask_figure:
            mask_downsample_figure(args.mask_figure)
            print(f"wrote {args.mask_figure}")
    except EnvError as e:
        print(f"envs.py: error: {e}", file=sys.stderr)
        return 2
    return 0


def _fetch_main(cache: str | None, url: str) -> int:
    """--fetch-davis: 0 once the cache holds DAVIS-2017, 1 (one line) when it could not."""
    try:
        frames = fetch_davis(cache, url=url)
    except FetchError as e:
        print(f"envs.py: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("envs.py: interrupted; run the same command again to resume the download", file=sys.stderr)
        return 130
    use = "--backgrounds davis" if cache is None else f"--backgrounds {cache}"
    print(f"DAVIS-2017 480p ({len(DAVIS17_TRAIN)} train, {len(DAVIS17_VAL)} validation videos) in {frames}; "
          f"use it with {use}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
