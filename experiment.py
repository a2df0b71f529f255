"""What sear.py's training loop calls besides the algorithm: the envs a config describes, the run
directory (config.json, train.csv / eval.csv and TensorBoard, snapshots with the replay buffer beside
them, resume and its side files, one owner at a time, atomic writes and storage errors in one line,
what a Ctrl-C or SIGTERM leaves), the progress line, the evaluation's decoder metrics and videos,
--evaluate's scores, the background sampler, and transfer (--init-from).

Layering: imports cli.py, segment.py and (lazily) envs.py; never sear.py, whose agent, buffer and
config it receives as arguments.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import os
import queue
import random
import socket
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

import cli
from cli import storing, torch_save, write_atomically
import segment  # the learned mask source; it imports envs only when collecting frames


# ================================================================================================
# Envs: the run's train and eval env, as its config describes them
# ================================================================================================
def load_mask_model(cfg):
    """The learned mask source of --mask-source learned:PATH (None for sim); a missing or damaged
    file is a ConfigError, raised before any run directory exists."""
    if cfg.mask_source == "sim":
        return None
    try:
        model = segment.load_model(cfg.mask_source[len("learned:"):])
    except segment.SegmentError as e:
        raise cli.ConfigError(f"--mask-source: {e}") from None
    message = other_robot_warning(cfg, model.meta)
    if message:
        cli.warn(message)
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
    return (f"--mask-source: the mask model was trained on {trained_env or 'frames'} (robot: {robot}), but "
            f"{cfg.env}'s robot is {here}: its masks will miss the robot (eval.csv learned_mask_iou shows how far)")


def make_envs(cfg, uses_mask: bool, train=True):
    """The train (None with train=False) and the eval env; sets cfg.action_repeat 0 to the suite's
    default. `uses_mask`: the method trains on (or acts on) the robot mask. With a learned mask
    source, obs["mask"] is the model's prediction on each frame (envs.make_env(mask_model=)): the
    train env never renders the simulator's mask, the eval env renders it only for the
    learned_mask_iou metric (info["true_mask"], which nothing stores or trains on)."""
    import envs  # imported here so that `--help` and config errors need no MuJoCo
    mask_model = load_mask_model(cfg)
    train_env = make_run_env(cfg, "train", uses_mask and mask_model is None, mask_model) if train else None
    eval_env = make_run_env(cfg, "eval", uses_mask and (mask_model is None or cfg.learned_mask_iou), mask_model)
    cfg.action_repeat = cfg.action_repeat or envs.default_action_repeat(cfg.env)
    if mask_model is not None and cfg.learned_mask_iou:
        eval_env = segment.LearnedMaskIoU(eval_env)
    return train_env, eval_env


def make_run_env(cfg, split: str, render_mask: bool, mask_model=None, **overrides):
    """The run's train or eval env, as its config describes it; `overrides` replace make_env
    arguments (plot.py maps: clean masks)."""
    import envs
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
        raise cli.ConfigError(str(e))
    if cfg.max_episode_steps:  # a time limit of the run's own is a truncation, like the suite's
        from gymnasium.wrappers import TimeLimit
        env = TimeLimit(env, cfg.max_episode_steps)
    return env


def episode_seed(seed, episode):
    """Each episode's reset seed: backgrounds, task variation and noise are reproducible, and a
    resumed run continues with the episodes an uninterrupted run would have had."""
    return seed * 1_000_003 + episode


def eval_tasks(env, cfg) -> list:
    """The task of every evaluation episode: None (the env's own draw) --eval-episodes times, or for a
    task set k episodes of each task, task after task (k = --eval-episodes-per-task, by default
    ceil(--eval-episodes / tasks): at least --eval-episodes in all). The authors evaluate task sets
    on 10 episodes of random tasks; per-task numbers need every task."""
    tasks = getattr(env.unwrapped, "tasks", None)
    if not tasks:
        return [None] * cfg.eval_episodes
    k = cfg.eval_episodes_per_task or math.ceil(cfg.eval_episodes / len(tasks))
    return [task for task in tasks for _ in range(k)]


# ================================================================================================
# Evaluation: what the decoders make of the eval env's frames (metrics and videos)
# ================================================================================================
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
    """The eval env as sear.evaluate() sees it, plus a look at what the decoders make of it.

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

    def __init__(self, agent, env, video_path: str | None = None):
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
            with storing(self.video_path):
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
            with storing(self.video_path):
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


def eval_columns(episodes) -> dict:
    """eval.csv's success rate (where the env reports success) and, for a task set, each task's mean
    return and success rate. `episodes`: sear.evaluate()'s."""
    row = {}
    successes = [float(e.success) for e in episodes if e.success is not None]
    if successes:
        row["success"] = float(np.mean(successes))
    for task in dict.fromkeys(e.task for e in episodes if e.task is not None):
        mine = [e for e in episodes if e.task == task]
        row[f"return/{task}"] = float(np.mean([e.ret for e in mine]))
        row[f"success/{task}"] = float(np.mean([float(bool(e.success)) for e in mine]))
    return row


# ================================================================================================
# --evaluate: a snapshot scored on its eval env, nothing written but a new video
# ================================================================================================
def score_snapshot(cfg, run: cli.RunConfig, snapshot: dict, agent, env, evaluate) -> None:
    """--evaluate RUN_DIR: `agent` (the snapshot's, loaded) on the run's eval env for --eval-episodes
    episodes by sear.evaluate, with the evaluations' own reset seeds (the run's episode count gives
    eval.csv's row at the snapshot's frame again). Prints the mean return (and success) with 95% CIs
    over the episodes, and the decoder metrics. Writes nothing into the run but, with --save-video, a
    new videos/evaluate_<frame>[-k].mp4. Takes no lock: a running run can be scored."""
    for message in cli.start_warnings(cfg, run, training=False):
        cli.warn(message)
    step = snapshot["counters"]["step"]
    frame = step * cfg.action_repeat
    video = claim_video(run.evaluate, frame) if run.save_video else None
    n = len(eval_tasks(env, cfg))
    print(f"evaluating {run.evaluate} (snapshot at frame {frame}) on {cfg.env}: {n} episode{'s' * (n != 1)}, "
          f"device {agent.device}", flush=True)
    watch = EvalWatch(agent, env, video)
    try:
        episodes = evaluate(agent, watch, cfg, step)
        scores = watch.finish()
        if isinstance(env, segment.LearnedMaskIoU):
            scores["learned_mask_iou"] = env.pop()
    except BaseException as e:
        if video:  # our own new file, unfinished: never leave half a video in the run
            with contextlib.suppress(OSError):
                os.remove(video)
        if isinstance(e, KeyboardInterrupt):
            cause, code = cli.stop_cause(e)
            raise cli.Interrupted(f"{cause} during the evaluation; nothing was written", code) from None
        raise
    finally:
        env.close()
    print("return " + mean_ci([e.ret for e in episodes]))
    successes = [float(e.success) for e in episodes if e.success is not None]
    if successes:
        print("success " + rate_ci(successes))
    for name, value in {**{k: v for k, v in eval_columns(episodes).items() if "/" in k}, **scores}.items():
        print(f"  {name} {value:.3g}")  # task sets: return/<task>, success/<task>; the decoder metrics
    if video:
        print(f"video: {video}")


def claim_video(run_dir, frame) -> str:
    """A new RUN_DIR/videos/evaluate_<frame>[-k].mp4, created empty (ffmpeg then writes it): an
    existing video is never overwritten, not even by a second --evaluate started the same moment."""
    folder = os.path.join(run_dir, "videos")
    with storing(folder):
        os.makedirs(folder, exist_ok=True)
    base = os.path.join(folder, f"evaluate_{frame}")

    def create(path):  # O_EXCL: FileExistsError if the name is taken
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))

    with storing(base + ".mp4"):
        return claim_new_path(base, ".mp4", create)


def mean_ci(values) -> str:
    """'12.3 (95% CI 10.1 to 14.5, 10 episodes)': Student-t interval of the mean over episodes."""
    from scipy import stats
    n, mean = len(values), float(np.mean(values))
    if n < 2:
        return f"{mean:.1f} (1 episode: no interval; give --eval-episodes 2 or more)"
    half = float(stats.t.ppf(0.975, n - 1)) * float(np.std(values, ddof=1)) / math.sqrt(n)
    return f"{mean:.1f} (95% CI {mean - half:.1f} to {mean + half:.1f}, {n} episodes)"


def rate_ci(values) -> str:
    """'0.60 (95% CI 0.31 to 0.83, 10 episodes)': Wilson interval of a success rate (a t interval of
    0/1 values would say [1, 1] after ten successes)."""
    from scipy import stats
    n, k = len(values), int(round(sum(values)))
    ci = stats.binomtest(k, n).proportion_ci(0.95, method="wilson")
    return f"{k / n:.2f} (95% CI {ci.low:.2f} to {ci.high:.2f}, {n} episodes)"


# ================================================================================================
# --compile: the update through torch.compile
# ================================================================================================
def compile_update(agent, run) -> None:
    """--compile, in place on this agent: its two loss functions (Eq. 6's joint_loss, forward and, through
    AOTAutograd, backward; the actor's loss) and both Adam steps through torch.compile (inductor's fused
    kernels), the pattern of LeanRL (pytorch-labs/LeanRL); --cuda-graphs adds CUDA graphs (mode
    reduce-overhead). The Agent's methods stay the eager reference (tests/test_compile.py holds the two
    equal); the calls between them (zero_grad, backward, the critic's freeze, Polyak averaging, the logs'
    one sync) stay eager. Compiling happens at the first update."""
    if not run.compile:
        return
    import torch._inductor.config
    # Inductor would draw the shifts and the exploration noise from its own generator; its eager
    # fallbacks draw eager's numbers, so a compiled run samples what an eager one samples.
    torch._inductor.config.fallback_random = True
    try:  # the agent step (the noise schedule's) varies: compile for any step, not first for one
        torch.compiler.config.dynamic_sources = "L['step']"
    except AttributeError:  # an older torch: dynamo compiles once more at the second step
        pass
    mode = "reduce-overhead" if run.cuda_graphs else None
    agent.joint_loss = torch.compile(agent.joint_loss, mode=mode)
    agent.actor_loss = torch.compile(agent.actor_loss, mode=mode)
    for opt in (agent.model_opt, agent.actor_opt):
        opt.step = torch.compile(opt.step, mode=mode)
    if run.cuda_graphs:
        update = agent.update

        def update_step(batch, step):  # a new step: CUDA graph trees may reuse the last step's outputs
            torch.compiler.cudagraph_mark_step_begin()
            return update(batch, step)
        agent.update = update_step


# ================================================================================================
# The replay buffer's sampler thread and its file
# ================================================================================================
def prefetcher(buffer, cfg, run, rng: np.random.Generator, device: torch.device):
    """The background sampler of --prefetch (on by default with CUDA), or None: the loop samples."""
    if run.prefetch == "on" or (run.prefetch == "auto" and device.type == "cuda"):
        # The loop writes up to update_every steps while the thread samples: keep clear of them.
        return Prefetcher(buffer, cfg.batch_size, rng, device, margin=cfg.frame_stack + 2 * cfg.update_every)
    return None


class Prefetcher:
    """Replay sampling and the host->device copy of the next batch, in a background thread while the
    current update runs (--prefetch; on by default with CUDA, where the update would otherwise wait
    for the host). One batch ahead: a batch cannot hold the newest `update_every` steps, and the sampling
    RNG runs one batch ahead of the loop. On CUDA the copy goes from pinned memory on its own stream."""

    def __init__(self, buffer, batch_size: int, rng: np.random.Generator, device: torch.device, margin: int):
        self.buffer, self.batch_size, self.rng, self.device, self.margin = buffer, batch_size, rng, device, margin
        self.queue: queue.Queue = queue.Queue(maxsize=1)
        self.stop = threading.Event()
        self.thread = None
        self.stream = torch.cuda.Stream(device) if device.type == "cuda" else None

    def sample(self):
        """buffer.sample(), but clear of the oldest `margin` slots of a full ring: those are the
        slots the loop overwrites while this thread reads."""
        b = self.buffer
        lo = max(0, b.t - b.capacity)
        if b.t > b.capacity:
            lo = min(lo + self.margin, b.t - 1 - b.nstep)
        return b.transitions(b.draw_starts(self.batch_size, self.rng, lo))

    def _produce(self):
        while not self.stop.is_set():
            try:
                batch = self.sample()
                batch = type(batch)._make(torch.as_tensor(x) for x in batch)
                event = None
                if self.stream is not None:
                    with torch.cuda.stream(self.stream):
                        batch = type(batch)._make(x.pin_memory().to(self.device, non_blocking=True) for x in batch)
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


BUFFER_ARRAYS = ("frames", "masks", "actions", "rewards", "terminal", "first")


def save_buffer(buffer, path):
    """buffer.npz: the filled slots of the ring in physical order, and `t`."""
    n = len(buffer)
    write_atomically(path, lambda f: np.savez(f, t=buffer.t, **{name: getattr(buffer, name)[:n]
                                                                 for name in BUFFER_ARRAYS}))


def load_buffer(buffer, path):
    with np.load(path) as data:
        n = len(data["rewards"])
        if n > buffer.capacity:
            raise cli.ConfigError(f"saved buffer holds {n} transitions, more than --replay-size {buffer.capacity}")
        for name in BUFFER_ARRAYS:
            getattr(buffer, name)[:n] = data[name]
        buffer.t = int(data["t"])  # a wrapped ring is saved in physical order: same slots here


def saved_buffer_t(path):
    """The `t` (steps ever written) of a saved buffer, read without loading the buffer."""
    with np.load(path) as data:
        return int(data["t"])


# ================================================================================================
# Transfer (--init-from)
# ================================================================================================
def init_source(cfg, run, action_dim):
    """The agent state of the --init-from run, checked against this run (its config was checked by
    cli.parse_args; the action size is known once the env is built). Called before the run dir exists."""
    state = cli.load_snapshot(run.init_from, "--init-from", mmap=True)
    if run.init_parts == "all":
        # The actor's last layer maps to the actions: its output size is the source's action size.
        source_dim = [v for k, v in state["agent"]["actor"].items() if k.endswith(".weight")][-1].shape[0]
        if source_dim != action_dim:
            raise cli.ConfigError(f"--init-parts all: the source run's actor has {source_dim} actions, {cfg.env} "
                                  f"has {action_dim}; copy encoder or encoder+decoders instead")
    return state["agent"]


def copy_parts(agent, source: dict, parts: str) -> None:
    """Load `parts` of a saved agent state (a snapshot's "agent") into a freshly built agent; the other
    networks keep their fresh initialisation and the optimisers stay fresh (Adam's moments are
    empty; the loads write into the parameters the optimisers already hold). "aux" is the method's
    auxiliary networks: SEAR's two decoders, AE's and MAE's decoder, CURL's heads and key encoder;
    drq and rgbm have none. As in the authors' load_pretrained_weights, the target critic starts as
    a copy of the loaded critic."""
    names = cli.INIT_PARTS[parts]
    agent.encoder.load_state_dict(source["encoder"])
    if agent.aux is not None:
        if "aux" in names:
            agent.aux.load_state_dict(source["aux"])
        elif hasattr(agent.aux, "key_encoder"):  # CURL's momentum copy of the encoder starts equal to it
            agent.aux.key_encoder.load_state_dict(source["encoder"])
    if "actor" in names:
        agent.actor.load_state_dict(source["actor"])
        agent.critic.load_state_dict(source["critic"])
        agent.critic_target.load_state_dict(agent.critic.state_dict())


# ================================================================================================
# The run directory
# ================================================================================================
def claim_new_path(base, suffix, make) -> str:
    """base + suffix, or base-1 + suffix, base-2 + suffix, ...: the first that `make` creates. make
    raises FileExistsError for a taken name, so two processes never claim the same path."""
    path, k = base + suffix, 1
    while True:
        try:
            make(path)
            return path
        except FileExistsError:
            path, k = f"{base}-{k}{suffix}", k + 1


class RunLock:
    """One owner per run directory: an exclusive flock on RUN_DIR/run.lock, taken by a new run and by
    --resume before they write anything and held until the run ends. The kernel drops a flock when
    its process dies, however it dies (kill -9, OOM, a lost node), so a leftover file never blocks;
    the file holds the owner's pid and host, for the message of a process that is refused
    (cli.lock_holder; cli.lock_owner asks without taking it)."""

    def __init__(self, run_dir):
        self.run_dir, self.path, self.fd = run_dir, os.path.join(run_dir, cli.LOCK_FILE), None
        try:
            import fcntl
        except ImportError:  # not a POSIX system
            cli.warn(f"cannot lock {run_dir} on this system: nothing stops a second process using it")
            return
        with storing(self.path):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = cli.lock_holder(fd)
            os.close(fd)
            raise cli.ConfigError(f"'{run_dir}' is in use by {owner}: a run directory has one owner; wait for it "
                                  f"to end, or stop it, then resume") from None
        except OSError as e:  # a file system without flock (Lustre mounted without -o flock: ENOSYS)
            os.close(fd)
            cli.warn(f"cannot lock {self.path} ({e.strerror}): nothing stops a second process using this run")
            return
        self.fd = fd
        with storing(self.path):
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)

    def release(self):
        if self.fd is not None:
            os.close(self.fd)  # releases the lock
            self.fd = None


class CsvLog:
    """Rows appended to a CSV whose header is fixed by the first row."""

    def __init__(self, path):
        self.path, self.fields = path, None
        if os.path.exists(path):
            with open(path, newline="") as f:
                self.fields = next(csv.reader(f), None)

    def write(self, row: dict):
        with storing(self.path):
            if self.fields is None:
                with open(self.path, "w", newline="") as f:
                    csv.writer(f).writerow(list(row))
                self.fields = list(row)
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
    with storing(side), open(side, "w", newline="") as f:
        csv.writer(f).writerows([header, *later])
    write_atomically(path, lambda f: csv.writer(f).writerows([header, *keep]), mode="w")


def new_run_dir(root: str, name: str) -> str:
    """root/name__<time>, made now; never an existing directory (and so never an existing run's),
    even one another process made this second."""
    base = os.path.join(root, f"{name}__{time.strftime('%Y%m%d-%H%M%S')}")
    with storing(base):
        return claim_new_path(base, "", os.makedirs)


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
    """Write snapshot.pt atomically: a crash or a full disk mid-write leaves the previous snapshot intact."""
    write_atomically(os.path.join(run_dir, "snapshot.pt"), lambda f: torch_save(payload, f))


def tensorboard_writer(run_dir):
    try:
        from torch.utils.tensorboard import SummaryWriter
        return SummaryWriter(run_dir)
    except Exception:  # tensorboard not installed: CSVs only
        return None


def interrupt_message(run_dir, frame, where, snapshot_frame, snapshot_minutes, cause="interrupted"):
    """What is true after a Ctrl-C (or SIGTERM: `cause`): whether a snapshot exists, at which frame,
    and the command that continues from it."""
    if run_dir is None:
        return f"{cause} before the run directory was made; nothing was saved"
    head = f"{cause} at frame {frame} ({where})"
    resume = f"continue with: python sear.py --resume {run_dir}"
    if snapshot_frame == frame:
        return f"{head}: snapshot.pt holds this frame; {resume}"
    if snapshot_frame is not None:
        return (f"{head}: the last snapshot (frame {snapshot_frame}) stands, the {frame - snapshot_frame} "
                f"frames after it will be re-run; {resume}")
    return (f"{head}: {run_dir} has no snapshot yet (the first is written at the first episode end after "
            f"{snapshot_minutes:g} minutes), so there is nothing to resume; start a new run")




class Progress:
    """The live line: frame, training speed, ETA and what the loop is doing (an episode, or which
    evaluation episode). On a terminal it is rewritten in place (at least once a second); otherwise
    (CI logs, nohup) a line is printed every `every` seconds.

    The speed counts training time only: frames since the last episode end over the seconds since
    then, less the evaluations and snapshots in between (pause()), so a ten-minute evaluation does
    not make the run look stalled. Evaluations are timed apart, and the ETA is the sum of the two:
    frames left / training speed + evaluations left x seconds each."""

    WIDTH = 120

    def __init__(self, total, every, eval_every):
        self.total, self.eval_every = total, eval_every
        self.tty = sys.stdout.isatty()
        self.every = min(every, 1.0) if self.tty else every
        self.last = 0.0
        self.fps = 0.0  # training frames per second
        self.eval_seconds = []  # duration of each evaluation of this process
        self.window_start, self.window_frame = time.time(), 0

    def restart_window(self, frame):
        self.window_start, self.window_frame = time.time(), frame

    def pause(self, seconds):
        """`seconds` spent off training (an evaluation, a snapshot): not counted in the speed."""
        self.window_start += seconds

    def measure(self, frame):
        self.fps = (frame - self.window_frame) / max(time.time() - self.window_start, 1e-9)

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


@dataclass
class Counters:
    """Where the training loop stands: what a snapshot records so that a resume continues from it."""
    step: int = 0               # agent steps taken (frames = steps x action repeat)
    episode: int = 0            # number of the episode under way, or of the next one
    next_eval: int = 0          # frame of the next scheduled evaluation
    last_eval_frame: int = -1   # frame of the latest evaluation
    mid_episode: bool = False   # an episode has begun and not ended


class RunDir:
    """A run directory and everything written into it: config.json, train.csv, eval.csv (and
    TensorBoard events), snapshot.pt with buffer.npz beside it (--save-buffer), videos/; and what
    goes to the screen: the progress line, and on Ctrl-C or SIGTERM or a storage error (as a `with`
    block) one line that says what was saved. Nothing is created before create(). It owns the
    directory (RunLock) from before its first write to the end of the `with` block; a first SIGTERM
    in the block waits for a safe point: create(), or safe_point() at an episode end.

    Snapshots are taken between episodes (when --snapshot-minutes have passed since the last), on a
    Ctrl-C there, and after the final evaluation. A snapshot holds the agent, the RNG states, the
    counters and, beside it, the replay buffer; the next episode's reset seed follows from its number,
    so a resume (with --save-buffer) does exactly what the uninterrupted run would have done."""

    def __init__(self, cfg, run: cli.RunConfig, snapshot: dict | None = None):
        self.cfg, self.run, self.resumed = cfg, run, snapshot
        self.path = run.resume or None
        self.snapshot_frame = snapshot["counters"]["step"] * cfg.action_repeat if snapshot else None
        self.counters = None  # the loop's, from start()
        self.metrics = {}  # the updates' metrics of the episode under way
        self.lock = None

    @property
    def frame(self):
        return self.counters.step * self.cfg.action_repeat if self.counters else self.snapshot_frame or 0

    # --- the directory ---
    def create(self):
        """Once the envs are made (every input checked): the start-up warnings, then a new run's
        directory (env__method__seed__time under --run-root), owned, and its config.json; a resumed
        run has both."""
        for message in cli.start_warnings(self.cfg, self.run):
            cli.warn(message)
        if self.path is None:
            self.safe_point()  # stopped while the envs were made: nothing to keep
            self.path = new_run_dir(self.run.run_root, f"{self.cfg.env}__{self.cfg.method}__{self.cfg.seed}")
            self.lock = RunLock(self.path)
            self.write_config(cli.config_dict(self.cfg, self.run))

    def own(self):
        """--resume, before anything is written: a second process on this run stops here. A config.json
        the user moved aside (cli.check_run_config) is written again from the snapshot's copy."""
        self.lock = RunLock(self.path)
        if not os.path.lexists(os.path.join(self.path, "config.json")):
            self.write_config(self.resumed["config"])
            print(f"resume: {os.path.join(self.path, 'config.json')} was missing; written again from snapshot.pt")

    def write_config(self, config: dict):
        write_atomically(os.path.join(self.path, "config.json"), lambda f: json.dump(config, f, indent=2), mode="w")

    @staticmethod
    def safe_point():
        """Between episodes, where a snapshot holds the exact state: a SIGTERM that waited stops here."""
        if cli.TERM.pending:
            raise cli.Terminated

    def start(self, agent, buffer, sample_rng: np.random.Generator) -> Counters:
        """Say what runs, restore a resumed run (weights, RNGs, buffer, counters) and open the logs.
        Returns the counters the loop advances; the snapshots save them with agent, buffer and
        sample_rng."""
        cfg = self.cfg
        self.agent, self.buffer, self.sample_rng = agent, buffer, sample_rng
        print(f"run dir: {self.path}\nmethod {cfg.method} on {cfg.env} | device {agent.device} | action repeat "
              f"{cfg.action_repeat} | replay {cfg.replay_size} x {buffer.bytes_per_transition} B = "
              f"{cfg.replay_size * buffer.bytes_per_transition / 1e9:.2f} GB at most")
        if cfg.mask_source != "sim":
            print(f"masks: {cfg.mask_source} (the model's prediction on every frame; the simulator's mask "
                  + ("is rendered in evaluation episodes only, for learned_mask_iou)" if cfg.learned_mask_iou
                     else "is never rendered)"))
        counters, wall_time = self.restore() if self.resumed else (Counters(), 0.0)
        self.train_log = CsvLog(os.path.join(self.path, "train.csv"))
        self.eval_log = CsvLog(os.path.join(self.path, "eval.csv"))
        self.writer = tensorboard_writer(self.path)
        self.progress = Progress(cfg.frames, self.run.log_every, cfg.eval_every)
        self.start_time = time.time() - wall_time
        self.counters = counters
        self.progress.restart_window(self.frame)
        self.last_snapshot_time = time.time()
        return counters

    def restore(self) -> tuple[Counters, float]:
        """The resumed snapshot's weights, RNG states and buffer; rows logged after it go to side
        files. Returns its counters and wall time."""
        state, cfg = self.resumed, self.cfg
        self.agent.load_state_dict(state["agent"])
        set_rng_state(state["rng"])
        self.sample_rng.bit_generator.state = state["sample_rng"]
        c = state["counters"]
        # Only the end-of-budget snapshot can cut an episode: drop its rest.
        counters = Counters(c["step"], c["episode"] + (1 if c["mid_episode"] else 0), c["next_eval"],
                            c.get("last_eval_frame", -1))
        buffer_path = os.path.join(self.path, "buffer.npz")
        if not (os.path.exists(buffer_path) and state.get("buffer_saved")):
            print("resume: no saved replay buffer (run with --save-buffer to keep it); refilling")
        elif saved_buffer_t(buffer_path) != state.get("buffer_t", saved_buffer_t(buffer_path)):
            print("resume: buffer.npz is newer than snapshot.pt (killed between the two writes); refilling")
        else:
            load_buffer(self.buffer, buffer_path)
        frame = counters.step * cfg.action_repeat
        set_aside_rows_after(os.path.join(self.path, "train.csv"), frame)
        # A snapshot taken at an episode end precedes that frame's evaluation: the resumed run
        # evaluates again from next_eval on, so rows from there go aside too.
        set_aside_rows_after(os.path.join(self.path, "eval.csv"), min(frame, counters.next_eval - 1))
        print(f"resumed at frame {frame}, episode {counters.episode}")
        return counters, c["wall_time"]

    # --- snapshots ---
    def snapshot_due(self) -> bool:
        return time.time() - self.last_snapshot_time >= 60 * self.run.snapshot_minutes

    def snapshot(self):
        """A snapshot between episodes, off the training-speed clock."""
        began = time.time()
        self.save()
        self.progress.pause(time.time() - began)
        self.progress.say(f"snapshot at frame {self.frame}")

    def save(self):
        counters = {**dataclasses.asdict(self.counters), "wall_time": time.time() - self.start_time}
        payload = {"config": cli.config_dict(self.cfg, self.run), "agent": self.agent.state_dict(),
                   "rng": rng_state(), "sample_rng": self.sample_rng.bit_generator.state,
                   "buffer_saved": self.run.save_buffer, "buffer_t": self.buffer.t, "counters": counters}
        # Buffer first, then snapshot.pt; each write is atomic, and buffer_t tells a resume
        # whether a kill between the two left a buffer newer than the snapshot.
        if self.run.save_buffer:
            save_buffer(self.buffer, os.path.join(self.path, "buffer.npz"))
        save_snapshot(self.path, payload)
        self.snapshot_frame, self.last_snapshot_time = self.frame, time.time()

    def finish(self) -> str:
        """The final snapshot (it may cut an episode: a resume drops the rest of it); returns the path."""
        self.save()
        self.progress.say(f"done: {self.frame} frames in {time.time() - self.start_time:.0f} s; outputs in {self.path}")
        if self.writer:
            self.writer.close()
        return self.path

    def __enter__(self):
        if self.path is not None:
            try:
                self.own()
            except cli.StorageError as e:
                self.release()
                raise self.what_stands(e) from None
        cli.TERM.defer = True
        return self

    def what_stands(self, error: cli.StorageError) -> cli.StorageError:
        """A storage error's line, ended with what the run dir holds now and how to go on."""
        if self.path is None:
            return cli.StorageError(f"{error}; no run directory was made")
        if self.snapshot_frame is None:
            return cli.StorageError(f"{error}; {self.path} has no snapshot yet, so there is nothing to resume")
        return cli.StorageError(f"{error}; the last snapshot (frame {self.snapshot_frame}) stands: fix that, then "
                                f"python sear.py --resume {self.path}")

    def release(self):
        cli.TERM.defer = cli.TERM.pending = False
        if self.lock is not None:
            self.lock.release()

    def __exit__(self, kind, error, traceback):
        try:
            self.stopped(kind, error)
        finally:
            self.release()

    def stopped(self, kind, error):
        """Ctrl-C or SIGTERM: a snapshot where the state is exactly resumable (between episodes; at the
        end of the budget it is what the final snapshot holds anyway), then one line saying what is
        saved. A storage error: its line says what stands."""
        if kind is not None and issubclass(kind, cli.StorageError):
            raise self.what_stands(error) from None
        if kind is None or not issubclass(kind, KeyboardInterrupt):
            return
        c, frame, failed = self.counters, self.frame, ""
        where = ("starting" if c is None else "end of budget" if frame >= self.cfg.frames
                 else "mid-episode" if c.mid_episode else "between episodes")
        if where in ("between episodes", "end of budget") and self.snapshot_frame != frame:
            try:
                self.save()
            except KeyboardInterrupt:  # a second Ctrl-C: the atomic writes leave the last snapshot whole
                pass
            except cli.StorageError as e:
                failed = f" (the snapshot of frame {frame} failed: {e})"
        cause, code = cli.stop_cause(error)
        raise cli.Interrupted(interrupt_message(self.path, frame, where, self.snapshot_frame,
                                                self.run.snapshot_minutes, cause) + failed, code) from None

    # --- logs ---
    def log_update(self, metrics: dict):
        for k, v in metrics.items():
            self.metrics.setdefault(k, []).append(v)

    def show_step(self, ep_len):
        self.progress.measure(self.frame)
        self.progress.update(self.frame, f"ep {self.counters.episode} step {ep_len}",
                             self.progress.eta(self.frame, self.counters.next_eval))

    def log_episode(self, ep_return, ep_len, ep_success, info):
        """A train.csv row (and TensorBoard scalars) for the episode that just ended."""
        frame, episode, progress = self.frame, self.counters.episode, self.progress
        progress.measure(frame)
        row = {"frame": frame, "step": self.counters.step, "episode": episode, "return": ep_return, "length": ep_len}
        if "success" in info:
            row["success"] = float(ep_success)
        if "task" in info:  # task sets: which task the episode drew
            row["task"] = info["task"]
        means = {k: float(np.mean(v)) for k, v in self.metrics.items()}
        row.update({k: means.get(k, "") for k in self.agent.metric_names})
        row.update({"fps": round(progress.fps, 2), "wall_time": round(time.time() - self.start_time, 2)})
        self.train_log.write(row)
        if self.writer:
            self.writer.add_scalar("train/return", ep_return, frame)
            for k, v in means.items():
                self.writer.add_scalar(f"train/{k}", v, frame)
        progress.update(frame, f"ep {episode} return {ep_return:.1f}", progress.eta(frame, self.counters.next_eval),
                        force=True)
        progress.restart_window(frame)
        self.metrics = {}

    # --- evaluations ---
    def start_eval(self, eval_env) -> EvalWatch:
        """The eval env for sear.evaluate(), watched: the decoders' metrics, and the first episode
        filmed with --save-video. Off the training-speed clock until log_eval()."""
        self.eval_began, self.eval_episodes = time.time(), len(eval_tasks(eval_env, self.cfg))
        self.progress.say(f"evaluating at frame {self.frame} ({self.eval_episodes} episodes)")
        video = os.path.join(self.path, "videos", f"eval_{self.frame}.mp4") if self.run.save_video else None
        self.watch = EvalWatch(self.agent, eval_env, video)
        return self.watch

    def show_eval(self, episode, t):
        """The progress line during an evaluation (sear.evaluate's on_step)."""
        self.progress.update(self.frame, f"eval {episode + 1}/{self.eval_episodes} step {t}",
                             self.progress.eta(self.frame, self.counters.next_eval, episode / self.eval_episodes,
                                               time.time() - self.eval_began))

    def log_eval(self, episodes):
        """An eval.csv row (and TensorBoard scalars) for sear.evaluate()'s episodes; moves the
        counters' evaluation schedule on."""
        c, frame, progress = self.counters, self.frame, self.progress
        scores = self.watch.finish()
        progress.eval_seconds.append(time.time() - self.eval_began)
        row = {"frame": frame, "step": c.step, "episode": c.episode, "return": float(np.mean([e.ret for e in episodes])),
               "wall_time": round(time.time() - self.start_time, 2), **eval_columns(episodes), **scores}
        if isinstance(self.watch.env, segment.LearnedMaskIoU):  # the mask model's IoU on these episodes' frames
            row["learned_mask_iou"] = scores["learned_mask_iou"] = self.watch.env.pop()
        self.eval_log.write(row)
        if self.writer:
            self.writer.add_scalar("eval/return", row["return"], frame)
            for name, value in scores.items():
                self.writer.add_scalar(f"eval/{name}", value, frame)
        progress.say(f"eval @ frame {frame}: return {row['return']:.1f}"
                     + (f", success {row['success']:.2f}" if "success" in row else "")
                     + "".join(f", {name} {value:.3g}" for name, value in scores.items())
                     + f" ({progress.eval_seconds[-1]:.1f} s)")
        c.last_eval_frame = frame
        while c.next_eval <= frame:
            c.next_eval += self.cfg.eval_every
        progress.pause(time.time() - self.eval_began)
