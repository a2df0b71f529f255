"""The training loop of sear.py's agent, drqv2's train.py to its drqv2.py: the experiment's settings
(Config), evaluation, and `train` (build env, agent, buffer; reset / act / step / add / update).
`python sear.py ...` and `python train.py ...` are the same command.

Around it: experiment.py (envs, the run directory, logs, snapshots, progress, evaluation metrics) and
cli.py (flags, recipes, checks, device, threads); baselines.py and drm.py add their methods and flags.

Usage:  python sear.py --env walker-walk-distracting [--method sear] [--seed 1]
        python sear.py --resume runs/<run dir>     |     python sear.py --evaluate runs/<run dir>
"""
from __future__ import annotations

import random
import sys
import time
import types
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

import sear
from harness import cli, experiment, group
from methods import baselines, drm, foresight
from sear import Agent, ReplayBuffer, arg

METHODS = sear.METHODS  # SEAR's and DrQ-v2's rows, and (imported above) the baselines' and EF's


@dataclass
class Config(sear.Config, baselines.BaselineConfig, foresight.ForesightConfig, drm.DrMConfig, experiment.EnvConfig):
    """The experiment: the task, its budget and its evaluation, on top of the algorithm's hyper-parameters
    (sear.Config), the baselines' and DrM's settings and the envs' (masks, distractors, rendering). One
    --flag each (the doc is its help). How a process runs it (device, files, snapshots) is cli.RunConfig."""
    env: str = arg("walker-walk", "task name; see envs.py (e.g. walker-walk-distracting, metaworld-door-open)")
    seed: int = arg(1, "seeds python, numpy, torch and the environments")
    frames: int = arg(1_000_000, "environment frames to train for (frames = agent steps x action repeat)")
    action_repeat: int = arg(0, "0 = the suite's default (2 dm_control and Meta-World, 1 Kitchen and Adroit)")
    max_episode_steps: int = arg(0, "0 = the suite's time limit; N > 0 truncates episodes after N agent steps")
    eval_every: int = arg(10_000, "frames between evaluations (snapshots follow --snapshot-minutes)")
    eval_episodes: int = arg(10, "episodes per evaluation, mean action (task sets: at least this many in all)")
    eval_episodes_per_task: int = arg(0, "task sets (metaworld-mt*): evaluation episodes of every task; "
                                         "0 = ceil(--eval-episodes / number of tasks)")


def make_agent(cfg: Config, action_dim: int, device: torch.device) -> Agent:
    """The run's agent: sear.Agent, or with --drm drm.DrMAgent."""
    return (drm.DrMAgent if cfg.drm else Agent)(cfg, action_dim, device)


# ================================================================================================
# Evaluation
# ================================================================================================
class Episode(NamedTuple):
    """An evaluation episode."""
    ret: float
    success: bool | None  # None where the env reports no success
    task: str | None      # the task of a task set, else None


def evaluate(agent: Agent, env, cfg: Config, step: int, on_step=None, stop=None) -> list[Episode]:
    """Episodes with the mean action on the eval env, from the same reset seeds at every evaluation
    (so that evaluations compare); a task set runs each of its tasks (experiment.eval_tasks).
    on_step(episode, t), if given, is called after every step (the progress line); stop(), if given,
    before every episode: once it is true the evaluation ends there, with fewer episodes (a first
    SIGTERM cuts an evaluation at an episode end)."""
    episodes = []
    for i, task in enumerate(experiment.eval_tasks(env, cfg)):
        if stop is not None and stop():
            break
        obs, info = env.reset(seed=experiment.episode_seed(cfg.seed + experiment.EVAL_SEED, i),
                              options=None if task is None else {"task": task})
        done, ret, success, t = False, 0.0, False, 0
        while not done:
            action = agent.act(obs["pixels"], obs["mask"], step, eval_mode=True)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            success = success or bool(info.get("success", False))
            done = terminated or truncated
            t += 1
            if on_step:
                on_step(i, t)
        episodes.append(Episode(ret, success if "success" in info else None, task))
    return episodes

# ================================================================================================
# The training loop
# ================================================================================================
def seed_everything(seed):
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def eval_due(frame: int, last_eval_frame: int, every: int) -> bool:
    """drqv2's Every, in frames: a multiple of `every` lies in (last evaluation, frame]. Frame 0 is
    one (last_eval_frame starts at -1)."""
    return frame // every > last_eval_frame // every


def evaluate_and_log(agent: Agent, eval_env, cfg: Config, counters, rundir) -> None:
    """An evaluation now: its episodes scored and filmed by the run dir, eval.csv's row, the
    counter. While a first SIGTERM waits there is none, and one it cuts short at an episode end
    leaves the counter: the run stops at its next safe point, and the resumed run evaluates
    again."""
    if rundir.stop_pending():
        return
    # the eval env, scored by the decoders, filmed with --save-video
    env = rundir.start_eval(eval_env)
    episodes = evaluate(agent, env, cfg, counters.step, on_step=rundir.show_eval,
                        stop=rundir.stop_pending)
    if rundir.end_eval(episodes):  # False: cut short
        counters.last_eval_frame = counters.step * cfg.action_repeat


def train(cfg: Config, run: cli.RunConfig, snapshot: dict | None = None) -> str:
    """Train from scratch, or continue from `snapshot` (the last one of the run dir run.resume);
    returns the run directory. The loop decides when to evaluate, snapshot and stop; the
    experiment.RunDir writes config.json, the logs and the snapshots it is handed and turns a
    Ctrl-C, a SIGTERM or a storage error into one line."""
    with experiment.RunDir(cfg, run, snapshot) as rundir:
        device = cli.torch_setup(run)
        train_env, eval_env = experiment.make_envs(cfg, METHODS[cfg.method].uses_mask)
        action_dim = train_env.action_space.shape[0]
        source = experiment.init_source(cfg, run, action_dim) if run.init_from and not snapshot else None
        rundir.create()  # a new run's directory and config.json, now that every input is checked

        seed_everything(cfg.seed)
        sample_rng = np.random.default_rng(cfg.seed)
        agent = make_agent(cfg, action_dim, device)
        if source is not None:  # transfer: start from another run's networks
            experiment.copy_parts(agent, source, run.init_parts)
        if run.compile:  # the whole update as one graph (a CUDA graph on CUDA); eager otherwise
            agent.compile()
        replay = dict(frame_shape=(3, *train_env.observation_space["pixels"].shape[1:]), action_dim=action_dim,
                      frame_stack=cfg.frame_stack, nstep=cfg.nstep, discount=cfg.discount)
        ring_bytes = cfg.replay_size * ReplayBuffer(1, **replay).bytes_per_transition
        buffer = (agent.aux.replay if agent.aux is not None else ReplayBuffer)(  # a method's own (EF's windows)
            cfg.replay_size, **replay, device=experiment.replay_device(run, device, ring_bytes))
        prefetcher = experiment.prefetcher(buffer, cfg, run, sample_rng, device)  # or None
        sampler = prefetcher or buffer
        counters = rundir.start(agent, buffer, sample_rng)  # fresh, or the snapshot's
        snapshot_clock = time.monotonic()  # every --snapshot-minutes, at the next episode end

        frame = counters.step * cfg.action_repeat
        while frame < cfg.frames:  # drqv2's Until, in frames
            if not counters.mid_episode:  # between episodes: a first SIGTERM stops here
                rundir.safe_point()
                if eval_due(frame, counters.last_eval_frame, cfg.eval_every):
                    evaluate_and_log(agent, eval_env, cfg, counters, rundir)
                    rundir.safe_point()  # after an evaluation a SIGTERM cut short: redone on resume
                counters.mid_episode = True
                obs, info = train_env.reset(seed=experiment.episode_seed(cfg.seed, counters.episode))
                buffer.add_first(obs)
                ep_return, ep_len, ep_success = 0.0, 0, False
            elif eval_due(frame, counters.last_eval_frame, cfg.eval_every):  # inside an episode
                evaluate_and_log(agent, eval_env, cfg, counters, rundir)

            # As DrQ-v2, the agent acts from the first step: uniformly for --exploration-steps
            # agent steps (Agent.act), then the actor plus noise, not updated in the seed frames.
            action = agent.act(obs["pixels"], obs["mask"], counters.step, eval_mode=False)
            # Learning starts once the buffer holds the seed frames' steps: after the random
            # phase of a new run, and again after a resume that could not bring its buffer back.
            if (frame >= cfg.seed_frames and counters.step % cfg.update_every == 0 and sampler.can_sample()
                    and len(buffer) >= cfg.seed_frames // cfg.action_repeat):
                batch = prefetcher.next() if prefetcher else buffer.sample(cfg.batch_size, sample_rng)
                rundir.log_update(agent.update(batch, counters.step))

            obs, reward, terminated, truncated, info = train_env.step(action)
            buffer.add(action, reward, terminated, obs)
            counters.step += 1
            frame = counters.step * cfg.action_repeat
            ep_return += reward
            ep_len += 1
            ep_success = ep_success or bool(info.get("success", False))
            if terminated or truncated:
                rundir.log_episode(ep_return, ep_len, ep_success, info)  # train.csv, progress line
                counters.episode, counters.mid_episode = counters.episode + 1, False
                if frame < cfg.frames and time.monotonic() - snapshot_clock >= 60 * run.snapshot_minutes:
                    rundir.snapshot()  # between episodes: a resume continues exactly
                    snapshot_clock = time.monotonic()
            else:
                rundir.show_step(ep_len)

        if counters.last_eval_frame != frame:  # the budget ends with an evaluation at its end
            evaluate_and_log(agent, eval_env, cfg, counters, rundir)
            rundir.safe_point()  # cut short by a SIGTERM: the snapshot's resume evaluates again
        rundir.finish()  # the final snapshot
        for closing in (prefetcher, train_env, eval_env):
            if closing is not None:
                closing.close()
        return rundir.path


def evaluate_snapshot(cfg: Config, run: cli.RunConfig, snapshot: dict) -> None:
    """--evaluate RUN_DIR: the snapshot's agent on the run's eval env, scored and printed (no training)."""
    device = cli.torch_setup(run)
    _, eval_env = experiment.make_envs(cfg, METHODS[cfg.method].uses_mask, train=False)
    agent = make_agent(cfg, eval_env.action_space.shape[0], device)
    experiment.score_snapshot(cfg, run, snapshot, agent, eval_env, evaluate)


def main(argv=None) -> int:
    """`python sear.py --flag value ...` (or train.py): 0 when done; bad input (2), Ctrl-C (130) and SIGTERM
    (143) end in one line. `--seeds 1-16` (or --resume of a group's folder) trains several seeds at once
    (group.py)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if group.wanted(argv):
        parts = types.SimpleNamespace(make_agent=make_agent, Episode=Episode, eval_due=eval_due)
        return group.main(argv, Config, METHODS, parts)
    return cli.main(argv, Config, METHODS, train, evaluate_snapshot)


if __name__ == "__main__":
    sys.exit(main())
