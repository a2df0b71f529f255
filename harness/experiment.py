"""What train.py's loop calls besides the algorithm: the envs' settings, the evaluation's decoder metrics and videos,
--evaluate, the replay buffer's file, --init-from, and the run directory (config.json, the CSVs and TensorBoard,
snapshots, resume, one owner, what a stop leaves) with its progress line and the health checks of every update.

Imports cli.py, and lazily envs.py and segment.py (`import sear` needs only torch, numpy and the standard library);
never sear.py, whose agent, buffer and config it receives as arguments."""
from __future__ import annotations

import collections
import contextlib
import csv
import dataclasses
import json
import math
import os
import random
import shutil
import socket
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
import tqdm

from harness import cli
from harness.cli import arg, storing, torch_save, write_atomically


@dataclass
class EnvConfig:
    """The envs' settings of sear.Config (which inherits them): masks, Distracting Control, rendering."""
    mask_noise: float = arg(0.0, "probability that a robot pixel of the mask is set to background", low=0, high=1,
                            acts="mask", group="robot masks")
    mask_approx: bool = arg(False, "use approximate masks: the authors' 3x down / up, Gaussian blur (sigma 0.5), "
                                   "threshold 0.9 (envs.approximate_mask)", acts="mask", group="robot masks")
    mask_downsample: str = arg("majority", "manipulation suites' 252->84 mask: majority (3x3 vote) | stride "
                                           "(authors')", ("majority", "stride"), envs="manipulation", acts="mask",
                               group="robot masks")
    mask_source: str = arg("sim", "sim (the simulator's segmentation render) | learned:PATH (a segment.py model "
                                  "applied to every frame gives every mask target and RGBM's input mask; --mask-noise "
                                  "/ --mask-approx then corrupt its masks)", metavar="sim|learned:PATH", acts="mask",
                           group="robot masks")
    learned_mask_iou: bool = arg(True, "with --mask-source learned:PATH, render the simulator's mask in evaluation "
                                       "episodes only to report the learned masks' IoU (eval.csv learned_mask_iou), "
                                       "never as a target; --no-learned-mask-iou never renders one",
                                 when="learned masks", acts="mask")
    backgrounds: str = arg("", "Distracting Control: davis (the paper's DAVIS-2017: python envs.py --fetch-davis), a "
                               "DAVIS or image folder, or '' = built-in procedural images (not the paper's)",
                           metavar="davis|DIR", envs="distracting", group="the suites")
    difficulty: str = arg("medium", "Distracting Control: easy | medium | hard = 4 | 8 | all backgrounds (authors: "
                                    "medium)", ("easy", "medium", "hard"), envs="distracting", group="the suites")
    render_quality: str = arg("paper", "paper (suite's own shadows) | fast (no shadows, no multisampling)",
                              ("paper", "fast"), group="the suites")
    pole_inertia: str = arg("exact", "cartpole: exact (MuJoCo 3's capsule) | 2021 (MuJoCo 2.0's, under DrQ-v2's "
                                     "curves: 0.8% less about the hinge)", ("exact", "2021"), envs="cartpole",
                            group="the suites")
    camera_distraction: float = arg(0.0, "Distracting Control, beyond the paper: camera offset scale (original: "
                                         "0.1-0.3)", low=0, high=1, envs="distracting", group="the suites")
    color_distraction: float = arg(0.0, "Distracting Control, beyond the paper: robot colour shift (original: "
                                        "0.1-0.3)", low=0, high=1, envs="distracting", group="the suites")
    kitchen_camera: str = arg("fixed", "Kitchen: fixed (the authors' view) | random (one of their 6 views per "
                                       "episode)", ("fixed", "random"), envs="kitchen", group="the suites")


# --- Evaluation: what the decoders make of the eval env's frames (metrics and videos) ------------------------------
def mask_iou(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Per frame, the IoU of two binary masks (B, H, W) -> (B,); NaN where both are empty (nothing to score)."""
    pred, true = pred.bool().flatten(1), true.bool().flatten(1)
    return (pred & true).sum(1) / (pred | true).sum(1)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per frame, the peak signal-to-noise ratio in dB of images in [0, 1] (B, ...) -> (B,)."""
    mse = (pred.float() - target.float()).pow(2).flatten(1).mean(1)
    return -10.0 * torch.log10(mse)  # 10 log10(1 / mse): the peak is 1


class EvalWatch:
    """What the decoders make of an evaluation's observations (train.evaluate shows it each of its seed's). Every
    SCORE_EVERY-th observation is encoded as the actor sees it, unaugmented, and decoded, in batches of BATCH; its
    newest frame is scored: the mask decoder's IoU of sigmoid > 0.5 and BCE per pixel against the mask it is trained
    on (where the env renders one), the reconstruction's PSNR after the loss's [-0.5, 0.5] clamp. With a video path
    the first episode is also an MP4: camera | true mask | predicted mask | reconstruction, where the method has it."""

    BATCH = 32
    # Encoding and decoding a frame again costs about half of a fast-render evaluation step on CPU (EXPERIMENTS.md,
    # "Inspection"); neighbouring frames differ little, so a tenth of them gives the same means at a tenth of the cost.
    SCORE_EVERY = 10
    SCALE = 4  # nearest upscaling, 84 -> 336 px: visible, and a multiple of ffmpeg's 16-px macro blocks
    LABEL = 16  # height of the strip that names the panels (336 + 16 = 22 x 16 again)
    FPS = 20
    METRICS = ("mask_iou", "mask_bce", "recon_psnr")

    def __init__(self, agent, video_path: str | None = None):
        self.agent, self.video_path = agent, video_path
        self.decodes = agent.aux.decodes if agent.aux is not None else ()
        self.true_mask = agent.method.uses_mask  # mask-free methods' envs skip the segmentation render
        self.pending, self.values, self.episode, self.seen, self.video, self.label_strip = [], {}, -1, 0, None, None

    def see(self, obs, new_episode=False):
        """An observation of the eval env (a stack: pixels and masks); new_episode at a reset."""
        self.episode += new_episode
        filming = self.video_path is not None and self.episode == 0
        scoring = bool(self.decodes) and self.seen % self.SCORE_EVERY == 0
        self.seen += 1
        if scoring or filming:
            self.pending.append((filming, scoring, obs["pixels"].copy(), obs["mask"][-1].copy()))
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
        decoded = agent.aux.decode(agent.encoder(pixels)) if self.decodes else {}  # no random shift at evaluation
        if "mask" in decoded:
            logits = decoded["mask"][:, -1].float()
            panels["predicted mask"] = torch.sigmoid(logits)
            if self.true_mask:  # sigmoid > 0.5 <=> logit > 0
                self.add("mask_iou", mask_iou(logits > 0, true)[scored])
                bce = F.binary_cross_entropy_with_logits(logits, true, reduction="none")
                self.add("mask_bce", bce.flatten(1).mean(1)[scored])
        if "recon" in decoded:
            panels["reconstruction"] = decoded["recon"][:, -3:].float().clamp(-0.5, 0.5) + 0.5
            self.add("recon_psnr", psnr(panels["reconstruction"], panels["camera"])[scored])
        if any(filming):
            with storing(self.video_path):
                self.film(panels, np.flatnonzero(filming))

    def add(self, name, per_frame: torch.Tensor):
        self.values.setdefault(name, []).extend(per_frame.tolist())

    def film(self, panels: dict, rows):
        """Frames `rows` of the batch onto the video: the panels side by side, upscaled, under their names."""
        import imageio.v2 as imageio  # imageio-ffmpeg brings the ffmpeg binary; needed only here
        from PIL import Image, ImageDraw
        width = panels["camera"].shape[-1] * self.SCALE
        if self.video is None:
            os.makedirs(os.path.dirname(self.video_path), exist_ok=True)
            # One encoder thread: the video is a side job of an evaluation on a shared machine.
            self.video = imageio.get_writer(self.video_path, fps=self.FPS, codec="libx264", macro_block_size=16,
                                            ffmpeg_params=["-threads", "1"])
            names = Image.new("RGB", (width * len(panels), self.LABEL))
            for i, label in enumerate(panels):
                ImageDraw.Draw(names).text((i * width + 4, 2), label, fill=(255, 255, 255))
            self.label_strip = np.asarray(names)
        side = [p if p.dim() == 4 else p.unsqueeze(1).expand(-1, 3, -1, -1) for p in panels.values()]
        strip = (torch.cat(side, dim=3)[rows] * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        for frame in strip:
            big = frame.repeat(self.SCALE, axis=0).repeat(self.SCALE, axis=1)
            for k in range(1, len(panels)):  # a white rule between panels, over their edge pixels
                big[:, k * width - 1:k * width + 1] = 255
            self.video.append_data(np.concatenate([self.label_strip, big], axis=0))

    def finish(self) -> dict:
        """The metrics' means over frames (the IoU's where robot or prediction is present); closes the video."""
        self.flush()
        if self.video is not None:
            with storing(self.video_path):
                self.video.close()
            self.video = None
        kept = {name: [v for v in self.values[name] if not math.isnan(v)] for name in self.METRICS
                if name in self.values}
        return {name: float(np.mean(values)) if values else float("nan") for name, values in kept.items()}


def eval_columns(episodes) -> dict:
    """eval.csv's success rate (where the env reports success) and, for a task set, each task's mean return and
    success rate. `episodes`: sear.evaluate()'s."""
    row = {}
    successes = [float(e.success) for e in episodes if e.success is not None]
    if successes:
        row["success"] = float(np.mean(successes))
    for task in dict.fromkeys(e.task for e in episodes if e.task is not None):
        mine = [e for e in episodes if e.task == task]
        row[f"return/{task}"] = float(np.mean([e.ret for e in mine]))
        row[f"success/{task}"] = float(np.mean([float(bool(e.success)) for e in mine]))
    return row


# --- --evaluate: a snapshot scored on its eval env, nothing written but a new video --------------------------------
def load_agent(agent, state: dict, cfg, flag: str) -> None:
    """A snapshot's agent state into `agent`; one this sear.py cannot take (a curl run from before CURL followed
    curl_sac.py: its networks differ) is one line."""
    try:
        agent.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError) as e:  # names, shapes or optimiser groups that differ
        first = str(e).strip().splitlines()[0][:120] if str(e).strip() else type(e).__name__
        raise cli.ConfigError(f"{flag}: the snapshot's {cfg.method} networks do not fit this "
                              f"sear.py's (saved by an older version?): {first}") from None


def score_snapshot(cfg, run: cli.RunConfig, snapshot: dict, agent, envs, evaluate) -> None:
    """--evaluate RUN_DIR: the snapshot's agent on the run's eval env (one seed's runenvs.SeedEnvs) for --eval-episodes
    episodes, with the evaluations' own reset seeds. Prints the mean return (and success) with 95% CIs and the decoder
    metrics; writes nothing into the run but, with --save-video, a new video. Takes no lock: a running run can be
    scored."""
    from harness import runenvs
    load_agent(agent, snapshot["agent"], cfg, "--evaluate")
    for message in cli.start_warnings(cfg, run, training=False):
        cli.warn(message)
    step = snapshot["counters"]["step"]
    frame = step * cfg.action_repeat
    video = claim_video(run.evaluate, frame) if run.save_video else None
    n = len(runenvs.eval_tasks(envs.tasks, cfg))
    print(f"evaluating {run.evaluate} (snapshot at frame {frame}) on {cfg.env}: {n} "
          f"episode{'s' * (n != 1)}, device {agent.device}", flush=True)
    watch = EvalWatch(agent, video)
    try:
        episodes = evaluate([agent], envs, step, [watch])[0]
        scores = watch.finish()
        if runenvs.measures_learned_iou(cfg):
            scores["learned_mask_iou"] = envs.call("eval", "pop")[0]
    except BaseException as e:
        if video:  # our own new file, unfinished: never leave half a video in the run
            with contextlib.suppress(OSError):
                os.remove(video)
        if isinstance(e, KeyboardInterrupt):
            cause, code = cli.stop_cause(e)
            raise cli.Interrupted(f"{cause} during the evaluation; nothing was written", code) from None
        raise
    print("return " + mean_ci([e.ret for e in episodes]))
    successes = [float(e.success) for e in episodes if e.success is not None]
    if successes:
        print("success " + rate_ci(successes))
    for name, value in {**{k: v for k, v in eval_columns(episodes).items() if "/" in k}, **scores}.items():
        print(f"  {name} {value:.3g}")  # task sets' return/<task>, success/<task>; the decoder metrics
    if video:
        print(f"video: {video}")


def claim_video(run_dir, frame) -> str:
    """A new RUN_DIR/videos/evaluate_<frame>[-k].mp4, created empty (ffmpeg then writes it): an existing video is
    never overwritten, not even by a second --evaluate started the same moment."""
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
    """'0.60 (95% CI 0.31 to 0.83, 10 episodes)': Wilson interval of a success rate (a t interval of 0/1 values
    would say [1, 1] after ten successes)."""
    from scipy import stats
    n, k = len(values), int(round(sum(values)))
    ci = stats.binomtest(k, n).proportion_ci(0.95, method="wilson")
    return f"{k / n:.2f} (95% CI {ci.low:.2f} to {ci.high:.2f}, {cli.plural(n, 'episode')})"


# --- The replay buffer's file --------------------------------------------------------------------------------------
def save_buffer(buffer, path):
    """buffer.npz: the filled slots of the ring in physical order, and `t` (episodes follow from the `first` flags)."""
    arrays = {name: getattr(buffer, name)[:len(buffer)].cpu().numpy() for name in buffer.ARRAYS}
    write_atomically(path, lambda f: np.savez(f, t=buffer.t, **arrays))


def load_buffer(buffer, path):
    """buffer.npz back into `buffer` (sear.ReplayBuffer), its episode index rebuilt."""
    with np.load(path) as data:
        n = len(data["rewards"])
        if n > buffer.capacity:
            raise cli.ConfigError(f"saved buffer holds {n} transitions, more than --replay-size "
                                  f"{buffer.capacity}")
        for a in buffer.ARRAYS:
            getattr(buffer, a)[:n] = torch.from_numpy(np.asarray(data[a]))
        buffer.t = int(data["t"])
    # the episode index, from the `first` flags of the slots held (a wrapped ring in the same slots)
    lo = max(0, buffer.t - buffer.capacity)
    firsts = lo + np.flatnonzero(buffer.first[:n].cpu().numpy()[np.arange(lo, buffer.t) % buffer.capacity])
    steps = np.diff(firsts) - 1
    buffer.episodes = np.stack([firsts[:-1], steps], axis=1)[steps >= buffer.nstep]
    buffer.running = firsts[-1] if len(firsts) else -1


def saved_buffer_t(path):
    """The `t` (steps ever written) of a saved buffer, read without loading the buffer."""
    with np.load(path) as data:
        return int(data["t"])


# --- Transfer (--init-from) ----------------------------------------------------------------------------------------
def init_source(cfg, run, action_dim):
    """The agent state of the --init-from run, its actor checked against this env's action size (the config was
    checked by cli.parse_args). Called before the run dir exists."""
    state = cli.load_snapshot(run.init_from, "--init-from", mmap=True)
    if run.init_parts == "all":
        # The actor's last layer maps to the actions: its output size is the source's action size.
        source_dim = [v for k, v in state["agent"]["actor"].items() if k.endswith(".weight")][-1].shape[0]
        if source_dim != action_dim:
            raise cli.ConfigError(f"--init-parts all: the source run's actor has {source_dim} actions, {cfg.env} has "
                                  f"{action_dim}; copy encoder or encoder+decoders instead")
    return state["agent"]


def copy_parts(agent, source: dict, parts: str) -> None:
    """`parts` of a saved agent state (a snapshot's "agent") into a fresh agent; the rest and the optimisers stay
    fresh. "aux": SEAR's two decoders, AE's and MAE's decoder, CURL's W and key encoder. As in the authors'
    load_pretrained_weights, the target critic starts as a copy of the loaded critic."""
    names = cli.INIT_PARTS[parts]
    agent.encoder.load_state_dict(source["encoder"])
    if agent.aux is not None and "aux" in names:  # an aux's own optimiser and counter (CURL's) stay fresh
        fresh = {k: v for k, v in agent.aux.state_dict().items() if k.endswith("_extra_state")}
        agent.aux.load_state_dict({**source["aux"], **fresh})
    if "actor" in names:
        agent.actor.load_state_dict(source["actor"])
        agent.critic.load_state_dict(source["critic"])
        agent.critic_target.load_state_dict(agent.critic.state_dict())
    if hasattr(agent.aux, "key"):  # CURL's momentum key starts as a copy of what was loaded, as the target critic
        agent.aux.key.load_state_dict(agent.aux.query[0].state_dict())


# --- The run directory ---------------------------------------------------------------------------------------------
def claim_new_path(base, suffix, make) -> str:
    """base + suffix, or base-1 + suffix, base-2 + suffix, ...: the first that `make` creates (it raises
    FileExistsError for a taken name, so two processes never claim the same path)."""
    path, k = base + suffix, 1
    while True:
        try:
            make(path)
            return path
        except FileExistsError:
            path, k = f"{base}-{k}{suffix}", k + 1


def take_lock(run_dir) -> int | None:
    """One owner per run directory: an exclusive flock on RUN_DIR/run.lock, held by the fd returned until the run
    ends. The kernel drops a flock when its process dies, however it dies, so a leftover file never blocks; the file
    holds the owner's pid and host for the message of a process refused (cli.lock_holder)."""
    path = os.path.join(run_dir, cli.LOCK_FILE)
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        cli.warn(f"cannot lock {run_dir} on this system: nothing stops a second process using it")
        return None
    with storing(path):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        owner = cli.lock_holder(fd)
        os.close(fd)
        raise cli.ConfigError(f"'{run_dir}' is in use by {owner}: a run directory has one "
                              f"owner; wait for it to end, or stop it, then resume") from None
    except OSError as e:  # a file system without flock (Lustre mounted without -o flock: ENOSYS)
        os.close(fd)
        cli.warn(f"cannot lock {path} ({e.strerror}): nothing stops a second process using this run")
        return None
    with storing(path):
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
    return fd


def set_aside_rows_after(path, frame):
    """On resume, rows logged after the snapshot describe steps that will be re-run: they go to a side file, and the
    main CSV stays consistent with the snapshot."""
    if not os.path.exists(path):
        return
    with open(path, newline="") as f:
        header, *body = [*csv.reader(f)] or [[]]
    later = [r for r in body if int(r[header.index("frame")]) > frame]
    if not later:
        return
    side = f"{path[:-4]}.after_snapshot_{time.strftime('%Y%m%d-%H%M%S')}.csv"
    with storing(side), open(side, "w", newline="") as f:
        csv.writer(f).writerows([header, *later])
    keep = [r for r in body if int(r[header.index("frame")]) <= frame]
    write_atomically(path, lambda f: csv.writer(f).writerows([header, *keep]), mode="w")


def new_run_dir(root: str, name: str) -> str:
    """root/name__<time>, made now; never an existing directory, even one another process made this second."""
    base = os.path.join(root, f"{name}__{time.strftime('%Y%m%d-%H%M%S')}")
    with storing(base):
        return claim_new_path(base, "", os.makedirs)


def size(n: float) -> str:
    """'3.8 MB', '207 MB', '5.52 GB'."""
    return f"{n / 1e9:.2f} GB" if n >= 1e9 else f"{n / 1e6:.0f} MB" if n >= 1e7 else f"{n / 1e6:.1f} MB"


def snapshot_bytes(agent) -> int:
    """snapshot.pt's size at its largest: every network's state and Adam's two moments of each parameter an optimiser
    trains (RNG states, counters and config add kilobytes)."""
    networks = sum(t.numel() * t.element_size() for part in agent.state_dict().values()
                   if isinstance(part, dict) for t in part.values() if torch.is_tensor(t))
    moments = sum(2 * p.numel() * p.element_size() for opt in vars(agent).values()
                  if isinstance(opt, torch.optim.Optimizer) for group in opt.param_groups for p in group["params"])
    return networks + moments


def compact(state):
    """A state dict whose tensors own their memory: a view of a larger tensor (a seed's part of a batched group's
    weights, harness/speed.py) is copied, so a snapshot holds this agent alone."""
    if isinstance(state, dict):
        return {k: compact(v) for k, v in state.items()}
    if torch.is_tensor(state) and state.untyped_storage().nbytes() > state.nbytes:
        return state.clone()
    return state


def save_snapshot(run_dir, payload):
    """snapshot.pt, written atomically: a crash or a full disk mid-write leaves the previous one intact."""
    write_atomically(os.path.join(run_dir, "snapshot.pt"), lambda f: torch_save(payload, f))


def interrupt_message(run_dir, frame, where, snapshot_frame, snapshot_minutes, cause="interrupted", removed=False):
    """What is true after a Ctrl-C (or SIGTERM: `cause`): whether a snapshot exists, at which frame, and the command
    that continues from it; with none, whether the run directory was `removed`."""
    if run_dir is None:
        return f"{cause} before the run directory was made; nothing was saved"
    head = f"{cause} at frame {frame} ({where})"
    resume = f"continue with: python sear.py --resume {run_dir}"
    if snapshot_frame == frame:
        return f"{head}: snapshot.pt holds this frame; {resume}"
    if snapshot_frame is not None:
        return (f"{head}: the last snapshot (frame {snapshot_frame}) stands, the "
                f"{frame - snapshot_frame} frames after it will be re-run; {resume}")
    first = f"the first is written at the first episode end after {snapshot_minutes:g} minutes"
    if removed:
        return f"{head}, before its first snapshot ({first}): nothing to resume, so {run_dir} was removed"
    return f"{head}: {run_dir} has no snapshot yet ({first}), so there is nothing to resume; start a new run"


def duration(seconds: float) -> str:
    """'6d 19h', '21h 33m', '12m 05s', '7s'; 'measuring' while unknown (inf)."""
    if not math.isfinite(seconds):
        return "measuring"
    d, s = divmod(max(0, round(seconds)), 86400)
    h, s = divmod(s, 3600)
    m, s = divmod(s, 60)
    return f"{d}d {h}h" if d else f"{h}h {m:02d}m" if h else f"{m}m {s:02d}s" if m else f"{s}s"


class Lines:
    """tqdm's file off a terminal (a log, SLURM, a pipe): each redraw a line of its own, a clearing nothing; on the
    stdout of the moment (a seed group redirects it)."""

    def write(self, text):
        if text := text.replace("\r", "").rstrip():
            print(text, flush=True)


class Progress:
    """The progress line (docs/health.md): a tqdm bar over the frames, in place on a terminal, else a line every
    `every` seconds. `fps`: the speed since the last episode end, time off training left out (pause()). The ETA: the
    frames left at the speed of training with updates, timed after WARMUP updates and standing once MEASURE_UPDATES
    over MEASURE_SECONDS are, plus the evaluations left, the final one included; "measuring" until both are timed. The
    longest episodes bound what a first SIGTERM waits for. state() keeps speeds and lengths for a resumed run."""

    LINE = "frame {n}/{total} ({percentage:.1f}%) {bar}| {desc}"  # tqdm's; {bar} on a terminal
    WARMUP = 2  # the first updates also build the kernels (oneDNN, cuDNN): not timed
    MEASURE_UPDATES = 10  # the learning speed stands once this many updates after the warm-up ...
    MEASURE_SECONDS = 5.0  # ... and this many seconds of them are timed

    def __init__(self, total, every, eval_every, saved: dict | None = None, clock=None):
        self.total, self.every, self.eval_every = total, every, eval_every
        self.clock, self.saved = clock or time.time, saved or {}  # saved: the snapshot's state()
        self.bar, self.fps, self.eval_seconds, self.cost_said = None, 0.0, [], False
        self.updates = 0  # of this process (RunDir.log_update)
        self.learn_frames, self.learn_seconds = 0, 0.0  # timed training with updates
        self.tick_time, self.tick_frame, self.tick_updates = None, 0, 0
        self.window_start, self.window_frame = self.clock(), 0
        self.flags: list[str] = []  # health warnings, at the end of every line
        self.longest = {name: self.saved.get(name) or 0 for name in (  # this process's or saved
            "episode_frames", "episode_seconds", "eval_episode_seconds", "eval_episode_steps")}

    def restart_window(self, frame):
        self.window_start, self.window_frame = self.clock(), frame

    def see(self, **lengths):
        """An episode's lengths (episode_frames=, eval_episode_steps=, ...): the longest kept."""
        self.longest.update({k: max(v, self.longest[k]) for k, v in lengths.items()})

    def episode_bound(self) -> float | None:
        """Seconds a training episode takes at most, as measured: the longest one, or the most frames one had at the
        slowest speed measured (learning, or the episode under way)."""
        now = self.fps if self.tick_frame > self.window_frame else math.inf
        slowest = min(self.learning_fps() or math.inf, now)
        frames = self.longest["episode_frames"] / slowest if 0 < slowest < math.inf else 0.0
        return max(self.longest["episode_seconds"], frames) or None

    def pause(self, seconds):
        """`seconds` spent off training (an evaluation, a snapshot): not counted in any speed."""
        self.window_start += seconds
        if self.tick_time is not None:
            self.tick_time += seconds

    def measure(self, frame):
        """After every env step: a step counts towards the learning speed when the warm-up was done before it."""
        now = self.clock()
        if self.tick_time is not None and self.tick_updates >= self.WARMUP:
            self.learn_frames += frame - self.tick_frame
            self.learn_seconds += now - self.tick_time
        self.tick_time, self.tick_frame, self.tick_updates = now, frame, self.updates
        self.fps = (frame - self.window_frame) / max(now - self.window_start, 1e-9)

    def measured(self) -> bool:
        return self.updates >= self.WARMUP + self.MEASURE_UPDATES and self.learn_seconds >= self.MEASURE_SECONDS

    def learning_fps(self) -> float | None:
        """Frames per second of training with updates: this process's once measured, else saved."""
        return self.learn_frames / self.learn_seconds if self.measured() else self.saved.get("learning_fps")

    def eval_length(self, done=0.0, spent=0.0) -> float | None:
        """Seconds per evaluation: this process's, else the one under way's pace, else saved."""
        if self.eval_seconds:
            return float(np.mean(self.eval_seconds))
        return spent / done if done > 0 else self.saved.get("eval_seconds")

    def state(self) -> dict:
        return {"learning_fps": self.learning_fps(), "eval_seconds": self.eval_length(), **self.longest}

    def evals_left(self, next_eval):
        """The scheduled ones (that due now included) and the final one at the budget's end."""
        return max(0, math.ceil((self.total - next_eval) / self.eval_every)) + 1

    def eta(self, frame, next_eval, under_way=None):
        """Seconds to the end of the budget, inf while a speed it needs is unknown. During an evaluation `under_way`
        is (the fraction of it done, its seconds so far): its rest at its own pace, those after it at their length."""
        fps, per_eval = self.learning_fps(), self.eval_length(*(under_way or ()))
        per_eval = math.inf if per_eval is None else per_eval
        train = 0.0 if frame >= self.total else (self.total - frame) / fps if fps else math.inf
        evals, rest = self.evals_left(next_eval), 0.0
        if under_way:
            (done, spent), evals = under_way, evals - 1
            rest = spent / done - spent if done else max(per_eval - spent, 0.0)
        return train + rest + (evals * per_eval if evals else 0.0)

    def cost(self, frame, next_eval) -> str | None:
        """Once, when this process has first measured its learning speed: what the rest costs."""
        if self.cost_said or not self.measured():
            return None
        self.cost_said, fps, left = True, self.learning_fps(), max(0, self.total - frame)
        evals, per_eval = self.evals_left(next_eval), self.eval_length()
        line = (f"cost on this device: {fps:.3g} frames/s with updates (timed over {self.updates - self.WARMUP} "
                f"updates), so the {left:,} frames left take {duration(left / fps)}")
        evaluations = cli.plural(evals, "evaluation")
        if per_eval is None:
            return line + f", plus {evaluations} not timed yet"
        return (line + f", and the {evaluations} left {duration(evals * per_eval)} ({duration(per_eval)} each): "
                f"about {duration(left / fps + evals * per_eval)} in all")

    def show(self, frame, text, eta, force=False):
        """The line, at most every `every` seconds (on a terminal at least every second), or now (force)."""
        line = " | ".join([f"{self.fps:.1f} fps", f"ETA {duration(eta)}", text, *self.flags])
        if self.bar is None:  # made where stdout is now (a seed group redirects it)
            # a terminal with a size (tqdm hides its bar on one without, a pty of `script`)
            tty = sys.stdout.isatty() and shutil.get_terminal_size((0, 0)).lines > 0
            self.bar = tqdm.tqdm(  # shows its first line
                total=max(self.total, frame), initial=frame, desc=line, position=0, leave=tty, miniters=0,
                bar_format=self.LINE.replace("{bar}", "{bar:12} " if tty else ""), dynamic_ncols=tty,
                file=sys.stdout if tty else Lines(), mininterval=min(self.every, 1.0) if tty else self.every)
            return
        self.bar.total = max(self.bar.total, frame)  # a budget no multiple of the action repeat
        self.bar.set_description_str(line, refresh=False)
        if not self.bar.update(frame - self.bar.n) and force:
            self.bar.refresh()
            self.bar.unpause()  # tqdm's interval restarts from this line

    @staticmethod
    def say(message):
        """A line of its own: on a terminal above the bar, which is redrawn below it."""
        with tqdm.tqdm.external_write_mode():
            print(message, flush=True)

    def close(self):
        """The line's end (RunDir.release): on a terminal it stays, and what follows goes below."""
        if self.bar is not None:
            self.bar.close()


class Health:
    """What every update's metrics say (RunDir.read_updates), beyond the numbers in train.csv: a loss or Q that is not
    finite stops the run (cli.NonFinite) before the next action reaches the simulator; two warnings, each given once
    on the progress line and stderr, say that the actor has collapsed and that the critic diverges (the largest return
    any policy can have assumes rewards of at least 1 per step until larger ones are seen). docs/health.md says how
    the thresholds were chosen from the runs of EXPERIMENTS.md."""

    COLLAPSE_WINDOW, SATURATED, SPREAD = 500, 0.99, 1e-3
    DIVERGE_WINDOW, DIVERGE_FACTOR = 100, 2.0
    EVERY = 10  # the windows are looked at every 10th update: ~10 us an update, not ~100

    def __init__(self, discount: float):
        self.discount, self.updates, self.reward_scale = discount, 0, 1.0
        self.saturated = collections.deque(maxlen=self.COLLAPSE_WINDOW)
        self.spread = collections.deque(maxlen=self.COLLAPSE_WINDOW)
        self.q = collections.deque(maxlen=self.DIVERGE_WINDOW)
        self.warned: set[str] = set()

    def see_rewards(self, rewards: np.ndarray):
        if len(rewards):
            self.reward_scale = max(self.reward_scale, float(np.abs(rewards).max()))

    def check(self, metrics: dict) -> list[tuple[str, str]]:
        """One update's metrics: cli.NonFinite on a value not finite, else the warnings (flag, line) firing first."""
        self.updates += 1
        for name, value in metrics.items():
            if not math.isfinite(value):
                raise cli.NonFinite(f"{name} is {value} at update {self.updates} of this process")
        if "actor_saturated" in metrics:
            self.saturated.append(metrics["actor_saturated"])
            self.spread.append(metrics["action_spread"])
        if "q" in metrics:
            self.q.append(abs(metrics["q"]))
        if self.updates % self.EVERY:
            return []
        checks = (("actor collapsed", self.collapsed), ("critic diverging", self.diverging))
        fired = [(kind, message) for kind, check in checks if kind not in self.warned and (message := check())]
        self.warned.update(kind for kind, _ in fired)
        return fired

    def q_bound(self) -> float:
        return self.reward_scale / (1.0 - self.discount) if self.discount < 1 else math.inf

    def collapsed(self) -> str | None:
        if len(self.saturated) < self.COLLAPSE_WINDOW:
            return None
        saturated, spread = np.mean(self.saturated), np.mean(self.spread)
        if saturated < self.SATURATED or spread > self.SPREAD:
            return None
        return (f"the actor has collapsed: over the last {self.COLLAPSE_WINDOW} updates {saturated:.1%} of its mean "
                f"actions sat at exactly +-1 (actor_saturated) and they spread {spread:.2g} over the batch "
                "(action_spread): one action in every state, where tanh passes no gradient back. Such runs rarely "
                "recover: docs/health.md")

    def diverging(self) -> str | None:
        median = float(np.median(self.q)) if len(self.q) == self.DIVERGE_WINDOW else 0.0
        if median <= self.DIVERGE_FACTOR * self.q_bound():
            return None
        return (f"the critic diverges: the median |Q| of the last {self.DIVERGE_WINDOW} updates is {median:.3g}, "
                f"more than {self.DIVERGE_FACTOR:g} x the largest return any policy can have here "
                f"({self.reward_scale:.3g} per step / (1 - {self.discount:g}) = {self.q_bound():.3g}); the run will "
                "not learn (too high a --lr?): docs/health.md")


@dataclass
class Counters:
    """Where the training loop stands: what a snapshot records so that a resume continues from it."""
    step: int = 0  # agent steps taken (frames = steps x action repeat)
    episode: int = 0  # number of the episode under way, or of the next one
    last_eval_frame: int = -1  # frame of the latest evaluation (the loop's schedule follows from it)
    mid_episode: bool = False  # an episode has begun and not ended


class Console:
    """What a run shows: what runs where and how long it should take, at its start; the progress line during episodes
    and evaluations; each evaluation's result and each snapshot; and what a first SIGTERM waits for."""

    def __init__(self, cfg, run: cli.RunConfig, saved: dict | None):
        self.cfg = cfg
        self.progress = Progress(cfg.frames, run.log_every, cfg.eval_every, saved)
        self.evaluating = False  # between start_eval() and end_eval()
        self.eval_began = self.episode_began = 0.0  # the evaluation's start, its episode's
        self.eval_episodes = self.eval_episode = self.eval_step = 0  # its length, where it is

    def say_run(self, path, agent, buffer):
        cfg, replay = self.cfg, buffer.bytes_per_transition
        print(f"run dir: {path}\nmethod {cli.method_label(cfg)} on {cfg.env} | device {agent.device} | action repeat "
              f"{cfg.action_repeat} | replay {cfg.replay_size} x {replay} B = {cfg.replay_size * replay / 1e9:.2f} GB "
              "at most")
        if cfg.mask_source != "sim":
            print(f"masks: {cfg.mask_source} (the model's prediction on every frame; the simulator's mask "
                  + ("is rendered in evaluation episodes only, for learned_mask_iou)" if cfg.learned_mask_iou
                     else "is never rendered)"))

    def say_expected_time(self, frame, next_eval):
        p = self.progress
        if p.learning_fps():  # a resumed run: the speeds its snapshot kept
            print(f"speed when last run: {p.learning_fps():.3g} frames/s with updates"
                  + (f", {duration(p.eval_length())} per evaluation" if p.eval_length() else "")
                  + f"; ETA {duration(p.eta(frame, next_eval))} until measured again here")
        else:
            print("ETA: measuring; the cost of this run is said once its first updates are timed "
                  f"(they start at frame {max(frame, self.cfg.seed_frames)}"
                  + (", after the frame-0 evaluation of the untrained policy)" if frame == 0 else ")"))

    def tick(self, frame, next_eval):
        """After every env step: the speeds, and once they are measured what the run costs here."""
        self.progress.measure(frame)
        if cost := self.progress.cost(frame, next_eval):
            self.progress.say(cost)

    def show_step(self, frame, episode, ep_len, next_eval):
        self.tick(frame, next_eval)
        self.progress.show(frame, f"ep {episode} step {ep_len}", self.progress.eta(frame, next_eval))

    def show_episode(self, frame, episode, ep_return, next_eval):
        """The line of an episode that just ended (after tick()); its length is measured."""
        p = self.progress
        p.show(frame, f"ep {episode} return {ep_return:.1f}", p.eta(frame, next_eval), force=True)
        p.see(episode_frames=frame - p.window_frame, episode_seconds=p.clock() - p.window_start)
        p.restart_window(frame)

    def warn(self, kind, message):
        """A health warning: on stderr (above the bar on a terminal), and on the line from now on."""
        self.progress.flags.append(f"warning: {kind}")
        with tqdm.tqdm.external_write_mode(file=sys.stderr):
            cli.warn(message)

    def start_eval(self, frame, episodes: int, untrained: str):
        self.evaluating, self.eval_episodes, self.eval_episode, self.eval_step = True, episodes, 0, 0
        self.eval_began = self.episode_began = self.progress.clock()
        self.progress.say(f"evaluating at frame {frame} ({cli.plural(episodes, 'episode')})"
                          + (f": {untrained}, before any update" if untrained else ""))

    def show_eval(self, frame, episode, t, untrained: str, next_eval):
        """The line during an evaluation: which episode (of which policy at frame 0) and, once an evaluation episode's
        steps are known, how long it has left at its pace in episodes and steps."""
        p, now = self.progress, self.progress.clock()
        if episode != self.eval_episode:  # the one before has ended
            p.see(eval_episode_seconds=now - self.episode_began, eval_episode_steps=self.eval_step)
            self.eval_episode, self.episode_began = episode, now
        self.eval_step, steps = t, p.longest["eval_episode_steps"]
        done = (episode + (min(t / steps, 1.0) if steps else 0.0)) / self.eval_episodes
        spent = now - self.eval_began
        text = (f"eval {episode + 1}/{self.eval_episodes} step {t}" + (f" ({untrained})" if untrained else "")
                + (f", ends in ~{duration(spent / done - spent)}" if done else ""))
        p.show(frame, text, p.eta(frame, next_eval, (done, spent)))

    def end_eval(self, frame, episodes: int) -> float:
        """The evaluation ended after `episodes`, whole or cut short: its seconds, off the training-speed clock."""
        p, now = self.progress, self.progress.clock()
        if episodes > self.eval_episode:  # its last episode ran to its end
            p.see(eval_episode_seconds=now - self.episode_began, eval_episode_steps=self.eval_step)
        seconds, self.evaluating = now - self.eval_began, False
        if episodes == self.eval_episodes:
            p.eval_seconds.append(seconds)
        else:
            p.say(f"evaluation at frame {frame} stopped by SIGTERM after {episodes} of "
                  f"{self.eval_episodes} episodes: no eval.csv row; a resume evaluates again")
        p.pause(seconds)
        return seconds

    def say_eval(self, frame, row: dict, scores: dict, seconds: float):
        self.progress.say(f"eval @ frame {frame}: return {row['return']:.1f}"
                          + (f", success {row['success']:.2f}" if "success" in row else "")
                          + "".join(f", {name} {value:.3g}" for name, value in scores.items())
                          + f" ({seconds:.1f} s)")

    def waits_for(self, frame, mid_episode: bool) -> str:
        """What a first SIGTERM waits for, and how long at most as measured (cli.TermSignal's line)."""
        p, longest = self.progress, self.progress.longest["eval_episode_seconds"]
        episode = (f"at most one episode: ~{duration(math.ceil(p.episode_bound()))}, measured"
                   if p.episode_bound() else "at most one episode, not timed yet in this process")
        if not self.evaluating:
            return f"the next episode end ({episode}), with a snapshot"
        bound = (f"at most ~{duration(math.ceil(longest))}, measured" if longest else f"not timed yet: the first of "
                 f"this process, at step {self.eval_step} after {duration(p.clock() - self.episode_began)}")
        then = (f", then the end of the training episode under way ({episode})"
                if mid_episode and frame < self.cfg.frames else "")
        return (f"the end of this evaluation episode ({bound}){then}, with a snapshot; the "
                f"evaluation is redone on resume")


class RunDir:
    """The `with` block a run trains in: its directory (config.json, train.csv / eval.csv and TensorBoard, snapshot.pt
    with buffer.npz, videos/, a resume's side files, run.lock), made by create() and owned until release(), and its
    Console. A Ctrl-C, SIGTERM, storage error or value that is not finite ends in one line of what stands; a first
    SIGTERM waits for a safe point (create(), safe_point() between episodes; an evaluation ends at its episode end).
    The loop (train.train) decides when to evaluate and snapshot and moves the Counters; RunDir writes what it is
    handed, and snapshots on its own only on a stop between episodes and at the end. A snapshot holds agent, RNG
    states and counters, buffer.npz the replay: with it a resume does exactly what the uninterrupted run would have."""

    def __init__(self, cfg, run: cli.RunConfig, snapshot: dict | None = None):
        self.cfg, self.run, self.resumed = cfg, run, snapshot
        self.path = run.resume or None  # a new run's is made by create(): removed if it ends before a snapshot
        self.group = None  # the seed group's folder (group.py): what --resume takes then, else self.path
        self.snapshot_frame = snapshot["counters"]["step"] * cfg.action_repeat if snapshot else None
        self.lock = self.writer = None
        self.fields = {}  # each CSV's header, as its first row fixed it
        self.console = Console(cfg, run, (snapshot or {}).get("progress"))
        self.health = Health(cfg.discount)
        self.counters = self.agent = self.buffer = self.sample_rng = None  # the loop's, from start()
        self.low_iou = None  # the learned masks' IoU over evaluations (segment.IoUWatch), if measured
        if getattr(cfg, "mask_source", "sim") != "sim" and cfg.learned_mask_iou:
            import segment
            self.low_iou = segment.IoUWatch()
        self.cut = ""  # what a SIGTERM cut short: said when the run stops
        self.pending, self.metrics = [], {}  # the updates' metrics not read from the device yet; the episode's
        self.start_time = time.time()  # less the wall time of the runs a resume continues (start())

    @property
    def frame(self):
        return self.counters.step * self.cfg.action_repeat if self.counters else self.snapshot_frame or 0

    # --- start ---
    def create(self):
        """Once the envs are made (every input checked): the start-up warnings, then a new run's directory
        (env__method__seed__time under --run-root), owned, and its config.json; a resumed run has both."""
        for message in cli.start_warnings(self.cfg, self.run):
            cli.warn(message)
        if self.path is None:
            self.safe_point()  # stopped while the envs were made: nothing to keep
            cfg = self.cfg
            self.path = new_run_dir(self.run.run_root, f"{cfg.env}__{cli.method_label(cfg)}__{cfg.seed}")
            self.lock = take_lock(self.path)
            self.write_config(cli.config_dict(cfg, self.run))

    def write_config(self, config: dict):
        write_atomically(os.path.join(self.path, "config.json"), lambda f: json.dump(config, f, indent=2), mode="w")

    @staticmethod
    def safe_point():
        """Between episodes, where a snapshot holds the exact state: a SIGTERM that waited stops here."""
        if cli.TERM.pending:
            raise cli.Terminated

    @staticmethod
    def stop_pending() -> bool:
        """A first SIGTERM waits for the next safe point: an evaluation ends at its episode end."""
        return cli.TERM.pending

    def start(self, agent, buffer, sample_rng: np.random.Generator) -> Counters:
        """Says what runs, restores a resumed run (weights, RNGs, buffer, counters) and opens the logs. Returns the
        counters the loop advances; the snapshots save them with agent, buffer and sample_rng."""
        self.agent, self.buffer, self.sample_rng = agent, buffer, sample_rng
        self.console.say_run(self.path, agent, buffer)
        counters, wall_time = self.restore() if self.resumed else (Counters(), 0.0)
        try:
            from torch.utils.tensorboard import SummaryWriter
            self.writer = SummaryWriter(self.path)
        except Exception:  # tensorboard not installed: CSVs only
            self.writer = None
        self.health.see_rewards(buffer.rewards[:len(buffer)].cpu().numpy())
        self.start_time, self.counters = time.time() - wall_time, counters
        self.check_free_space(snapshot_bytes(agent), self.cfg.replay_size * buffer.bytes_per_transition)
        self.console.say_expected_time(self.frame, self.next_eval())
        self.console.progress.restart_window(self.frame)
        return counters

    def check_free_space(self, snapshot: int, buffer: int):
        """Before any compute is spent: a disk that cannot hold the next snapshot.pt (`snapshot` bytes) is refused;
        one that cannot hold what the run writes at its largest (two snapshot.pt while one replaces the other, and
        with --save-buffer two buffer.npz of the full replay, `buffer` bytes) is warned of."""
        on_disk = sum(os.path.getsize(p) for p in (os.path.join(self.path, n) for n in ("snapshot.pt", "buffer.npz"))
                      if os.path.exists(p))
        free, with_buffer = shutil.disk_usage(self.path).free, self.run.save_buffer
        more = 2 * snapshot + (2 * buffer if with_buffer else 0) - on_disk
        print(f"disk: snapshot.pt {size(snapshot)}" + (f", buffer.npz up to {size(buffer)}" if with_buffer else "")
              + f"; {size(free)} free in {self.path}")
        if free < snapshot:
            raise cli.ConfigError(f"{self.path}: {size(free)} free, but a snapshot.pt of this run takes "
                                  f"{size(snapshot)}: free some space, or give --run-root on a larger disk")
        if free < more:
            cli.warn(f"{self.path}: {size(free)} free, but this run's files need up to {size(more)} more (two "
                     f"snapshot.pt of {size(snapshot)} while one replaces the other"
                     + (f", two buffer.npz of up to {size(buffer)}" if with_buffer else "")
                     + "): it will stop on a full disk before its end, its last snapshot standing")

    def restore(self) -> tuple[Counters, float]:
        """The resumed snapshot's weights, RNG states and buffer.npz (else the buffer refills), rows logged after it
        set aside; returns its counters and wall time."""
        state, rng, buffer = self.resumed, self.resumed["rng"], os.path.join(self.path, "buffer.npz")
        load_agent(self.agent, state["agent"], self.cfg, "--resume")
        random.setstate(rng["python"])
        np.random.set_state(rng["numpy"])
        torch.set_rng_state(rng["torch"])
        if rng["cuda"] is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(rng["cuda"])
        if "rng" not in state["agent"]:  # before the agent had its own generator: torch's stream was it
            self.agent.rng.set_state(rng["torch"] if self.agent.device.type == "cpu" else
                                     rng["cuda"][self.agent.device.index or 0])
        self.sample_rng.bit_generator.state = state["sample_rng"]
        c = state["counters"]
        # Only the end-of-budget snapshot can cut an episode: drop its rest. Snapshots before the loop owned its
        # schedule saved the next evaluation's frame instead of the last one's.
        counters = Counters(c["step"], c["episode"] + (1 if c["mid_episode"] else 0),
                            c.get("last_eval_frame", c.get("next_eval", 0) - 1))
        if not (os.path.exists(buffer) and state.get("buffer_saved")):
            print("resume: no saved replay buffer (run with --save-buffer to keep it); refilling")
        elif saved_buffer_t(buffer) != state.get("buffer_t", saved_buffer_t(buffer)):
            print("resume: buffer.npz is not snapshot.pt's (killed between the two writes); refilling")
        else:
            load_buffer(self.buffer, buffer)
        frame = counters.step * self.cfg.action_repeat
        # A snapshot taken at an episode end precedes that frame's evaluation (and one a SIGTERM cut short wrote no
        # row): the resumed run evaluates again from its next evaluation on, so rows from there go aside too.
        set_aside_rows_after(os.path.join(self.path, "train.csv"), frame)
        set_aside_rows_after(os.path.join(self.path, "eval.csv"), min(frame, self.next_eval(counters) - 1))
        print(f"resumed at frame {frame}, episode {counters.episode}")
        return counters, c["wall_time"]

    def next_eval(self, counters=None) -> int:
        """The frame of the next scheduled evaluation: the first multiple of --eval-every after the last."""
        last = (counters or self.counters).last_eval_frame
        return (last // self.cfg.eval_every + 1) * self.cfg.eval_every

    # --- snapshots ---
    def snapshot(self):
        """A snapshot between episodes, off the training-speed clock."""
        began = time.time()
        self.save()
        self.console.progress.pause(time.time() - began)
        self.console.progress.say(f"snapshot at frame {self.frame}")

    def save(self):
        """snapshot.pt, and with --save-buffer buffer.npz beside it: each write atomic, the buffer's written aside and
        in place only after the snapshot, so a storage error in either leaves both of the last snapshot (buffer_t
        tells a resume whether a kill between the renames left them apart). Never of an agent whose parameters are
        no longer finite: the last snapshot then stands (a scan, ~0.2 s for SEAR's 16M on one CPU thread)."""
        if self.non_finite_networks():
            raise cli.NonFinite("the snapshot due now was not written")
        counters = {**dataclasses.asdict(self.counters), "wall_time": time.time() - self.start_time}
        payload = {"config": cli.config_dict(self.cfg, self.run), "agent": compact(self.agent.state_dict()),
                   "rng": {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
                           "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None},
                   "sample_rng": self.sample_rng.bit_generator.state,
                   "buffer_saved": self.run.save_buffer, "buffer_t": self.buffer.t, "counters": counters,
                   "progress": self.console.progress.state()}  # the ETA of the next start
        if not self.run.save_buffer:
            save_snapshot(self.path, payload)
        else:
            path = os.path.join(self.path, "buffer.npz")
            try:
                save_buffer(self.buffer, path + ".next")
                save_snapshot(self.path, payload)
                with storing(path):
                    os.replace(path + ".next", path)
            finally:
                with contextlib.suppress(OSError):  # after the rename there is nothing left to remove
                    os.remove(path + ".next")
        self.snapshot_frame = self.frame

    def finish(self) -> str:
        """The final snapshot (it may cut an episode: a resume drops the rest of it); returns the path."""
        self.read_updates()  # the cut episode's updates get no row, but their health checks
        self.save()
        self.console.progress.say(f"done: {self.frame} frames in {time.time() - self.start_time:.0f} s; outputs in "
                                  f"{self.path}")
        if self.writer:
            self.writer.close()
        return self.path

    # --- the with block: how a run stops ---
    def __enter__(self):
        if self.path is not None:  # --resume, before anything is written: a second process on this run stops here
            try:
                self.lock = take_lock(self.path)
                config = os.path.join(self.path, "config.json")
                if not os.path.lexists(config):  # moved aside by the user (cli.check_run_config)
                    self.write_config(self.resumed["config"])
                    print(f"resume: {config} was missing; written again from snapshot.pt")
            except cli.StorageError as e:
                self.release()
                raise self.what_stands(e) from None
        cli.TERM.defer, cli.TERM.stands, cli.TERM.waits_for = True, self.what_a_kill_leaves, self.waits_for
        return self

    def waits_for(self) -> str:
        """What a first SIGTERM waits for (cli.TermSignal prints it): before the run's first episode, the next safe
        point; then the next episode end, or the end of the evaluation episode under way."""
        if self.counters is None:
            return ("the end of the start-up (before the run directory is made, or at the first "
                    "episode), with a snapshot once there is a run directory")
        return self.console.waits_for(self.frame, self.counters.mid_episode)

    def release(self):
        self.console.progress.close()
        cli.TERM.defer = cli.TERM.pending = False
        cli.TERM.stands = cli.TERM.waits_for = None
        if self.lock is not None:
            os.close(self.lock)  # releases the lock
            self.lock = None

    def __exit__(self, kind, error, traceback):
        try:
            self.stopped(kind, error)
        finally:
            self.release()

    def stopped(self, kind, error):
        """Ctrl-C or SIGTERM: a snapshot where the state is exactly resumable (between episodes, or at the end of the
        budget), then one line saying what is saved. A storage error or a value that is not finite (cli.NonFinite):
        one line with what stands. A new run that ends before its first snapshot, however it ends (but for a kill),
        leaves no run directory: nothing in it resumes."""
        if kind is None:
            return
        c, frame, failed = self.counters, self.frame, ""
        where = ("starting" if c is None else "end of budget" if frame >= self.cfg.frames
                 else "mid-episode" if c.mid_episode else "between episodes")
        if (issubclass(kind, KeyboardInterrupt) and where in ("between episodes", "end of budget")
                and self.snapshot_frame != frame):
            failed = self.save_on_stop()
        removed = self.remove_if_unsaved()
        if issubclass(kind, cli.StorageError):
            raise self.what_stands(error, removed) from None
        if issubclass(kind, cli.NonFinite):
            raise cli.NonFinite(self.diverged(error, removed)) from None
        if issubclass(kind, KeyboardInterrupt):
            cause, code = cli.stop_cause(error)
            line = interrupt_message(self.path, frame, where + self.cut, self.snapshot_frame,
                                     self.run.snapshot_minutes, cause, removed)
            raise cli.Interrupted(line + failed, code) from None

    def save_on_stop(self) -> str:
        """The snapshot of a Ctrl-C or SIGTERM between episodes; '' or why there is none."""
        frame = self.frame
        try:
            self.save()
        except KeyboardInterrupt:  # a second Ctrl-C: the atomic writes leave the last snapshot whole
            pass
        except cli.StorageError as e:
            return f" (the snapshot of frame {frame} failed: {e})"
        except cli.NonFinite:
            return (f" (no snapshot of frame {frame}: parameters no longer finite in "
                    f"{self.non_finite_networks()})")
        return ""

    def remove_if_unsaved(self) -> bool:
        """A new run's directory without a snapshot: removed (True if it is gone), its lock file too."""
        if self.run.resume or self.path is None or self.snapshot_frame is not None:
            return False
        shutil.rmtree(self.path, ignore_errors=True)
        return not os.path.exists(self.path)

    def no_snapshot(self, removed: bool) -> str:
        return f"{self.path} " + ("had no snapshot yet and was removed" if removed
                                  else "has no snapshot yet, so there is nothing to resume")

    def what_stands(self, error: cli.StorageError, removed=False) -> cli.StorageError:
        """A storage error's line, ended with what the run dir holds now and how to go on."""
        if self.path is None:
            return cli.StorageError(f"{error}; no run directory was made")
        if self.snapshot_frame is None:
            return cli.StorageError(f"{error}; {self.no_snapshot(removed)}" + " (nothing to resume)" * removed)
        return cli.StorageError(f"{error}; the last snapshot (frame {self.snapshot_frame}) stands: "
                                f"fix that, then python sear.py --resume {self.group or self.path}")

    def what_a_kill_leaves(self) -> str:
        """What stands when the process is ended at once (cli.TermSignal's forced stop, from its watcher thread while
        the main thread is stuck in a native call): no other cleanup runs."""
        if self.path is None:
            return "nothing was saved"
        if self.snapshot_frame is None:
            removed = self.remove_if_unsaved()
            return self.no_snapshot(removed) + ("" if removed else ": delete it")
        return (f"the last snapshot (frame {self.snapshot_frame}) stands; continue with: python "
                f"sear.py --resume {self.group or self.path}")

    def non_finite_networks(self) -> list[str]:
        """The agent's networks with a parameter that is not a finite number."""
        nets = {name: getattr(self.agent, name, None) for name in ("encoder", "actor", "critic", "aux")}
        return [name for name, net in nets.items()
                if net is not None and not all(torch.isfinite(p).all() for p in net.parameters())]

    def diverged(self, error: cli.NonFinite, removed: bool) -> str:
        """The line of a run stopped by a value that is not finite: the first update metric that was not, if one was
        (the cause), else what stopped it (an action)."""
        try:
            self.read_updates()
        except cli.NonFinite as first:
            error = first
        nets = self.non_finite_networks()
        line = (f"the run diverged at frame {self.frame}: {error}"
                + (f" (parameters no longer finite: {', '.join(nets)})" if nets else "")
                + "; it stopped before that reached the simulator")
        if self.snapshot_frame is not None:
            return (line + f"; the last snapshot (frame {self.snapshot_frame}) stands: python sear.py --resume "
                    f"{self.group or self.path} continues from it (with --save-buffer it replays the same updates): "
                    "docs/health.md")
        return (line + f"; {self.no_snapshot(removed)}; start again with other settings (a lower --lr, smaller "
                "loss weights): docs/health.md")

    # --- logs ---
    def log_update(self, metrics: dict):
        """An update's metrics (0-d tensors on the device): kept there until the next log line reads them all at once
        (read_updates), so that updates never wait for the host."""
        self.console.progress.updates += 1
        self.pending.append(metrics)

    def read_updates(self):
        """The pending updates' metrics, read in one device sync: into the episode's means, and through the health
        checks, update by update (a value that is not finite stops the run)."""
        values = [v for metrics in self.pending for v in metrics.values()]
        tensors = [v for v in values if torch.is_tensor(v)]
        read = iter(torch.stack([v.detach().double() for v in tensors]).tolist() if tensors else [])
        values = iter([next(read) if torch.is_tensor(v) else float(v) for v in values])
        pending, self.pending = self.pending, []
        for metrics in pending:
            metrics = {k: next(values) for k in metrics}
            for kind, message in self.health.check(metrics):
                self.console.warn(kind, message)
                if self.writer:
                    self.writer.add_text("health", message, self.frame)
            for k, v in metrics.items():
                self.metrics.setdefault(k, []).append(v)

    def write_row(self, name: str, row: dict, scalars: dict, frame: int):
        """A row of train.csv or eval.csv (the columns of its first row), and its scalars as TensorBoard events."""
        path = os.path.join(self.path, name)
        if name not in self.fields and os.path.exists(path):
            with open(path, newline="") as f:
                self.fields[name] = next(csv.reader(f), None)
        with storing(path), open(path, "a", newline="") as f:
            if self.fields.get(name) is None:
                self.fields[name] = list(row)
                csv.writer(f).writerow(row)
            csv.DictWriter(f, self.fields[name], extrasaction="ignore").writerow(row)
        for tag, value in scalars.items() if self.writer else ():
            self.writer.add_scalar(tag, value, frame)

    def show_step(self, ep_len):
        self.console.show_step(self.frame, self.counters.episode, ep_len, self.next_eval())

    def log_episode(self, ep_return, ep_len, ep_success, info):
        """A train.csv row (and TensorBoard scalars) for the episode that just ended."""
        frame, episode, b = self.frame, self.counters.episode, self.buffer
        self.read_updates()
        self.console.tick(frame, self.next_eval())
        self.health.see_rewards(b.rewards[torch.arange(b.t - ep_len, b.t) % b.capacity].cpu().numpy())
        row = {"frame": frame, "step": self.counters.step, "episode": episode, "return": ep_return, "length": ep_len}
        if "success" in info:
            row["success"] = float(ep_success)
        if "task" in info:  # task sets: which task the episode drew
            row["task"] = info["task"]
        means = {k: float(np.mean(v)) for k, v in self.metrics.items()}
        row.update({k: means.get(k, "") for k in self.agent.metric_names})
        row.update({"fps": round(self.console.progress.fps, 2), "wall_time": round(time.time() - self.start_time, 2)})
        scalars = {"train/return": ep_return, **{f"train/{k}": v for k, v in means.items()}}
        self.write_row("train.csv", row, scalars, frame)
        self.console.show_episode(frame, episode, ep_return, self.next_eval())
        self.metrics = {}

    # --- evaluations ---
    def untrained(self) -> str:
        """What an evaluation before any update scores ('' once the agent has been updated)."""
        if self.frame or self.console.progress.updates:
            return ""
        return "the policy copied by --init-from" if self.run.init_from else "the untrained policy"

    def start_eval(self, tasks) -> EvalWatch:
        """An evaluation starts (of the eval env's `tasks`, None for one task), off the training-speed clock until
        end_eval(): what watches its observations (decoder metrics; with --save-video the first episode filmed)."""
        from harness import runenvs
        self.console.start_eval(self.frame, len(runenvs.eval_tasks(tasks, self.cfg)), self.untrained())
        video = os.path.join(self.path, "videos", f"eval_{self.frame}.mp4") if self.run.save_video else None
        return EvalWatch(self.agent, video)

    def show_eval(self, episode, t):
        """The progress line during an evaluation (train.evaluate's on_step)."""
        self.console.show_eval(self.frame, episode, t, self.untrained(), self.next_eval())

    def end_eval(self, watch: EvalWatch, episodes, learned_iou=None) -> bool:
        """An eval.csv row (and TensorBoard scalars) for train.evaluate()'s episodes (True), with what start_eval's
        `watch` saw; none for an evaluation that a SIGTERM cut short (False): the resumed run evaluates again.
        learned_iou: the learned masks' IoU over its frames (--mask-source learned:)."""
        c, frame = self.counters, self.frame
        scores = watch.finish()
        seconds = self.console.end_eval(frame, len(episodes))
        if len(episodes) < self.console.eval_episodes:
            self.cut = (f"; its evaluation stopped after {len(episodes)} of "
                        f"{self.console.eval_episodes} episodes, redone on resume")
            return False
        row = {"frame": frame, "step": c.step, "episode": c.episode,
               "return": float(np.mean([e.ret for e in episodes])),
               "wall_time": round(time.time() - self.start_time, 2), **eval_columns(episodes), **scores}
        if learned_iou is not None:  # the mask model's IoU on these episodes' frames
            row["learned_mask_iou"] = scores["learned_mask_iou"] = learned_iou
            if warning := self.low_iou.see(learned_iou, frame):
                cli.warn(warning)
        scalars = {"eval/return": row["return"], **{f"eval/{name}": v for name, v in scores.items()}}
        self.write_row("eval.csv", row, scalars, frame)
        self.console.say_eval(frame, row, scores, seconds)
        return True
