"""The envs a run's config describes: each seed's train env and eval env, built by envs.make_env.

The loop steps them as gymnasium vector envs (SeedEnvs): one seed's in this process (SyncVectorEnv),
several seeds' in spawned worker processes, one per env (AsyncVectorEnv; a process that rendered with
EGL must not fork one that renders). An env sends only what the replay keeps, the newest frame and its
robot mask bit-packed (np.packbits), through the vector env's shared memory; the frame stacks are made
here (Stacks), as envs.make_env's own stacking makes them. A worker imports no torch unless it runs a
mask model (learned masks), ignores SIGINT and SIGTERM (the loop stops it) and dies with its parent.

Layering: imports cli.py and envs.py, and segment.py only for learned masks; no torch at import.
"""
from __future__ import annotations

import contextlib
import functools
import math
import multiprocessing
import signal
import sys
import types

import gymnasium as gym
import numpy as np

from harness import cli

# the eval env's seed and its episodes' reset seeds are the run's seed + this: apart from training's
EVAL_SEED = cli.EVAL_SEED


def episode_seed(seed, episode):
    """Each episode's reset seed: backgrounds, task variation and noise are reproducible, and a
    resumed run continues with the episodes an uninterrupted run would have had."""
    return seed * 1_000_003 + episode


def eval_tasks(tasks, cfg) -> list:
    """The task of every evaluation episode: None (the env's own draw) --eval-episodes times, or for
    a task set (`tasks`: its task names) k episodes of each task, task after task (k =
    --eval-episodes-per-task, by default ceil(--eval-episodes / tasks): at least --eval-episodes in
    all). The authors evaluate task sets on 10 episodes of random tasks; per-task numbers need every
    task."""
    if not tasks:
        return [None] * cfg.eval_episodes
    k = cfg.eval_episodes_per_task or math.ceil(cfg.eval_episodes / len(tasks))
    return [task for task in tasks for _ in range(k)]


# ================================================================================================
# One env, as the run's config describes it
# ================================================================================================
def load_mask_model(cfg, quiet=False):
    """The learned mask source of --mask-source learned:PATH (None for sim); a missing or damaged
    file, or one whose recorded held-out IoU is below segment.IOU_FLOOR, is a ConfigError, raised
    before any run directory exists. One written below the floor with segment.py's --force is the
    user's choice: a warning. The held-out IoU is printed (or that the file has none)."""
    if cfg.mask_source == "sim":
        return None
    import segment  # the learned mask source (torch, PIL): only where a run uses it
    try:
        model = segment.load_model(cfg.mask_source[len("learned:"):])
    except segment.SegmentError as e:
        raise cli.ConfigError(f"--mask-source: {e}") from None
    verdict, message = segment.recorded_iou(model.meta)
    if verdict == "refuse":
        raise cli.ConfigError(f"--mask-source: {message}")
    if quiet:
        return model
    if verdict == "warn":
        cli.warn(f"--mask-source: {message}")
    else:
        print(message)
    if other := other_robot_warning(cfg, model.meta):
        cli.warn(other)
    return model


def other_robot_warning(cfg, meta: dict) -> str | None:
    """A mask model knows the robot it was trained on: on another robot its masks are noise
    (learned_mask_iou near 0). segment.py records the robot and env; models without the record
    (older files, labels folders) are not checked."""
    import envs
    source = meta.get("source") if isinstance(meta.get("source"), dict) else {}
    trained_env, robot = source.get("env"), meta.get("robot")
    try:
        robot = robot or (envs.robot_name(trained_env) if trained_env else None)
        here = envs.robot_name(cfg.env)
    except envs.EnvError:  # an unknown --env is reported, in one line, when its env is made
        return None
    if robot is None or robot == here:
        return None
    return (f"--mask-source: the mask model was trained on {trained_env or 'frames'} (robot: "
            f"{robot}), but {cfg.env}'s robot is {here}: its masks will miss the robot (eval.csv "
            "learned_mask_iou shows how far)")


def measures_learned_iou(cfg) -> bool:
    """Whether the eval env scores learned masks against the simulator's (segment.LearnedMaskIoU)."""
    return cfg.mask_source != "sim" and cfg.learned_mask_iou


def render_mask(cfg, split: str, uses_mask: bool) -> bool:
    """Whether an env renders the simulator's mask: for a method that reads masks; with a learned
    mask source only the eval env, for learned_mask_iou (info["true_mask"], never trained on)."""
    if cfg.mask_source == "sim":
        return uses_mask
    return uses_mask and split == "eval" and cfg.learned_mask_iou


def make_run_env(cfg, split: str, render_mask: bool, mask_model=None, **overrides):
    """The run's train or eval env, as its config describes it; `overrides` replace make_env
    arguments (plot.py maps: clean masks; the loop: one frame, not a stack)."""
    import envs
    kwargs = dict(frame_stack=cfg.frame_stack, action_repeat=cfg.action_repeat or None, mask_noise=cfg.mask_noise,
                  mask_approx=cfg.mask_approx, backgrounds=cfg.backgrounds or None,
                  difficulty=cfg.difficulty, render_quality=cfg.render_quality,
                  mask_downsample=cfg.mask_downsample, camera_distraction=cfg.camera_distraction,
                  color_distraction=cfg.color_distraction, render_mask=render_mask,
                  kitchen_camera=cfg.kitchen_camera, mask_model=mask_model, pole_inertia=cfg.pole_inertia) | overrides
    # Both envs draw Meta-World's 50 task variations from the run's seed (as the authors' MT1);
    # the eval env's own seed only fixes its reset seeds, backgrounds and noise.
    seed = cfg.seed + (EVAL_SEED if split == "eval" else 0)
    try:
        env = envs.make_env(cfg.env, seed=seed, split=split, variation_seed=cfg.seed, **kwargs)
    except envs.EnvError as e:
        raise cli.ConfigError(str(e))
    if cfg.max_episode_steps:  # a time limit of the run's own is a truncation, like the suite's
        from gymnasium.wrappers import TimeLimit
        env = TimeLimit(env, cfg.max_episode_steps)
    return env


def make_envs(cfg, uses_mask: bool, train=True):
    """One seed's train (None with train=False) and eval env, each stacking its frames, in this
    process (the tools' envs: --evaluate, plot.py maps, benchmarks); sets cfg.action_repeat 0 to the
    suite's default. Both refuse actions that are not finite numbers (FiniteActions)."""
    import envs
    mask_model = load_mask_model(cfg)
    made = [make_run_env(cfg, split, render_mask(cfg, split, uses_mask), mask_model)
            for split in (("train", "eval") if train else ("eval",))]
    cfg.action_repeat = cfg.action_repeat or envs.default_action_repeat(cfg.env)
    if measures_learned_iou(cfg):
        import segment
        made[-1] = segment.LearnedMaskIoU(made[-1])
    made = [FiniteActions(env) for env in made]
    return tuple(made) if train else (None, made[0])


class FiniteActions:
    """The last guard before the simulator: an action that is not a finite number (an actor whose
    parameters diverged) stops the run (cli.NonFinite) instead of reaching MuJoCo, where it would
    end in a PhysicsError traceback. A check of a few floats per step."""

    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, action):
        check_finite(action)
        return self.env.step(action)


def check_finite(actions) -> None:
    finite = np.isfinite(actions)
    if not finite.all():
        raise cli.NonFinite(f"{int((~finite).sum())} of the {finite.size} entries of the "
                            f"actor's action are not finite")


# ================================================================================================
# Every seed's envs, as vector envs, and their frame stacks
# ================================================================================================
def newest_frame_env(config: dict, split: str, render: bool, worker: bool):
    """One seed's env as a vector env holds it: envs.make_env's env with a stack of one, its mask
    bit-packed (NewestFrame)."""
    if worker:
        as_worker()
    cfg = types.SimpleNamespace(**config)
    mask_model = load_mask_model(cfg, quiet=True)
    env = make_run_env(cfg, split, render, mask_model, frame_stack=1)
    if split == "eval" and measures_learned_iou(cfg):
        import segment
        env = segment.LearnedMaskIoU(env)
    return NewestFrame(env)


def as_worker():
    """In a worker process (not the parent, where AsyncVectorEnv builds one env to read the spaces):
    SIGINT and SIGTERM ignored (the loop stops its workers) and, on Linux, an end with the parent
    (prctl PR_SET_PDEATHSIG), so that a killed run leaves no worker and no traceback."""
    if multiprocessing.parent_process() is None:
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        import ctypes
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):  # not Linux: the pipe's end still stops the worker
        pass


@contextlib.contextmanager
def main_not_imported():
    """While workers spawn: this process's main script hidden from multiprocessing, which would import
    it again in every child (sear.py imports torch: ~300 MB a worker); they need only this module."""
    main = sys.modules["__main__"]
    saved = {key: main.__dict__[key] for key in ("__file__", "__spec__") if key in main.__dict__}
    main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        yield
    finally:
        main.__dict__.update(saved)


class NewestFrame(gym.ObservationWrapper):
    """An env of a stack of one whose observation's mask is bit-packed: what crosses to the loop."""

    def __init__(self, env):
        super().__init__(env)
        pixels, mask = env.observation_space["pixels"], env.observation_space["mask"]
        nbytes = (mask.shape[-2] * mask.shape[-1] + 7) // 8
        self.observation_space = gym.spaces.Dict({"pixels": pixels, "mask": gym.spaces.Box(0, 255, (nbytes,), np.uint8)})

    def observation(self, obs):
        return {"pixels": obs["pixels"], "mask": np.packbits(obs["mask"][-1].astype(bool).reshape(-1))}


class Stacks:
    """Every seed's frame stack and mask stack, made from the newest frames as envs.make_env stacks
    them: at a reset the first frame repeated, then the newest appended. `obs` holds them, seed first:
    {"pixels": (N, 3 x stack, H, W), "mask": (N, stack, H, W)}."""

    def __init__(self, n, stack, frame_shape):
        c, h, w = frame_shape
        self.stack, self.c, self.hw = stack, c, (h, w)
        self.obs = {"pixels": np.zeros((n, c * stack, h, w), np.uint8), "mask": np.zeros((n, stack, h, w), np.uint8)}

    def masks(self, bits):
        h, w = self.hw
        return np.unpackbits(bits, axis=-1, count=h * w).reshape(len(bits), h, w)

    def reset(self, which, newest):
        """Seeds `which` (indices) start episodes at `newest` (their first frames, seed first)."""
        pixels, masks = newest["pixels"][which], self.masks(newest["mask"][which])
        self.obs["pixels"][which] = np.tile(pixels, (1, self.stack, 1, 1))
        self.obs["mask"][which] = masks[:, None]

    def push(self, which, newest):
        """Seeds `which` stepped to `newest`: their stacks drop the oldest frame."""
        c, p, m = self.c, self.obs["pixels"], self.obs["mask"]
        p[which] = np.concatenate([p[which][:, c:], newest["pixels"][which]], axis=1)
        m[which] = np.concatenate([m[which][:, 1:], self.masks(newest["mask"][which])[:, None]], axis=1)

    def seed(self, i) -> dict:
        return {"pixels": self.obs["pixels"][i], "mask": self.obs["mask"][i]}


def seed_info(infos: dict, i: int) -> dict:
    """Env i's info out of a vector env's merged infos."""
    return {k: v[i] for k, v in infos.items() if not k.startswith("_") and infos.get("_" + k, np.ones(i + 1))[i]}


class SeedEnvs:
    """Every seed's train and eval env, as two gymnasium vector envs without autoreset: the loop
    resets each seed's env with its own reset seed (reset_mask). A vector env steps all its envs at
    once: an eval env whose episode ended before the others' is reset and stepped along, unread,
    until every seed's episode has ended (each evaluation episode starts with a seeded reset).
    `kind` says where they run."""

    def __init__(self, configs: list[dict], uses_mask: bool, workers: bool, make=None):
        """Each config's train and eval env; `make(config, split, render, worker)` builds one env of
        a stack of one (newest_frame_env: envs.make_env's; a benchmark's stand-in)."""
        self.n, self.vectors, make = len(configs), {}, make or newest_frame_env
        self.kind = f"{2 * self.n} worker processes, each seed's train and eval env" if workers else "this process"
        for split in ("train", "eval"):
            render = render_mask(types.SimpleNamespace(**configs[0]), split, uses_mask)
            fns = [functools.partial(make, c, split, render, workers) for c in configs]
            self.vectors[split] = self.vector(fns, workers)
            workers = workers and isinstance(self.vectors[split], gym.vector.AsyncVectorEnv)
        self.ended = {"train": np.ones(self.n, bool), "eval": np.ones(self.n, bool)}
        self.pending = {}  # the actions of a step sent to envs in this process
        space = self.vectors["train"].single_observation_space
        self.action_dim = self.vectors["train"].single_action_space.shape[0]
        self.frame_shape = space["pixels"].shape
        self.tasks = self.vectors["eval"].get_attr("tasks")[0] if self.n else None

    def vector(self, fns, workers: bool):
        """A vector env of `fns`: in spawned workers, or (asked, or when they do not start) here."""
        autoreset = gym.vector.AutoresetMode.DISABLED
        if workers:
            try:
                with main_not_imported():
                    return gym.vector.AsyncVectorEnv(fns, context="spawn", autoreset_mode=autoreset)
            except Exception as e:  # noqa: BLE001 (any failure to start: the fallback runs, and says why)
                print(f"envs: the worker processes did not start ({cli.first_sentence(e)}); stepping them here")
                self.kind = "this process, one seed after another"
        return gym.vector.SyncVectorEnv(fns, autoreset_mode=autoreset)

    def reset(self, split: str, which, seeds, options=None):
        """Envs `which` (a bool mask) reset with their reset seeds (seed first); returns the newest
        observations of all (the others' unchanged) and the infos."""
        which = np.asarray(which, bool)
        obs, infos = self.vectors[split].reset(seed=[None if s is None else int(s) for s in seeds],
                                                options={**(options or {}), "reset_mask": which})
        self.ended[split] &= ~which
        return obs, infos

    def send(self, split: str, actions):
        """Every env starts its step (workers step while this process goes on; an ended eval env is
        reset first, unseeded, and its results are not meant to be read)."""
        check_finite(actions)
        if self.ended[split].any():
            self.reset(split, self.ended[split], [None] * self.n)
        actions, vector = np.asarray(actions, np.float32), self.vectors[split]
        if isinstance(vector, gym.vector.AsyncVectorEnv):
            vector.step_async(actions)
        else:
            self.pending[split] = actions

    def receive(self, split: str):
        """The step send() started: the vector env's (obs, rewards, terminated, truncated, infos)."""
        vector = self.vectors[split]
        if isinstance(vector, gym.vector.AsyncVectorEnv):
            out = vector.step_wait()
        else:
            out = vector.step(self.pending.pop(split))
        self.ended[split] |= out[2] | out[3]
        return out

    def step(self, split: str, actions):
        self.send(split, actions)
        return self.receive(split)

    def call(self, split: str, name: str):
        return self.vectors[split].call(name)

    def close(self):
        for vector in self.vectors.values():
            vector.close()
