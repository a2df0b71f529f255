"""The training loop of sear.py's agent, as drqv2's train.py to its drqv2.py: the experiment's
settings (Config), each method's agent and replay, evaluation, and `train`: one loop for one seed
(--seed k) or several in lockstep (--seeds 1-16), each seed the run --seed k is.
`python sear.py ...` and `python train.py ...` are the same command.

Around it: harness/ (the command line, the run directories, the seeds' envs, the speed layer) and
methods/ (the paper's baselines, Ego-Foresight, DrM).

Usage:  python sear.py --env walker-walk-distracting [--method sear] [--seed 1]
        python sear.py --resume runs/<run dir>     |     python sear.py --evaluate runs/<run dir>
"""
from __future__ import annotations

import random
import sys
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

import sear
from harness import cli, experiment, group, runenvs, speed
from methods import baselines, drm, foresight
from sear import Agent, ReplayBuffer, arg

# Every --method: SEAR's and DrQ-v2's rows, the paper's baselines' and Ego-Foresight's.
METHODS = {**sear.METHODS, **baselines.METHODS, **foresight.METHODS}


@dataclass
class Config(sear.Config, baselines.BaselineConfig, foresight.ForesightConfig, drm.DrMConfig,
             experiment.EnvConfig):
    """The experiment: the task, its budget and its evaluation, on top of the algorithm's
    hyper-parameters (sear.Config), the baselines' and DrM's settings and the envs' (masks,
    distractors, rendering). One --flag each (the doc is its help). How a process runs it
    (device, files, snapshots) is cli.RunConfig."""
    env: str = arg("walker-walk", "task name; see envs.py (e.g. walker-walk-distracting, "
                                  "metaworld-door-open)", metavar="ENV", group="what to run")
    seed: int = arg(1, "seeds python, numpy, torch and the environments", group="what to run",
                    low=0, high=cli.MAX_SEED,
                    why=f"numpy seeds below 2^32, and the eval env's is --seed + {cli.EVAL_SEED}")
    frames: int = arg(1_000_000, "environment frames to train for (frames = agent steps x action "
                                 "repeat)", above=0, group="what to run", resume_may_change=True)
    action_repeat: int = arg(0, "0 = the suite's default (2 dm_control and Meta-World, 1 Kitchen "
                                "and Adroit)", low=0)
    max_episode_steps: int = arg(0, "0 = the suite's time limit; N > 0 truncates episodes after N "
                                    "agent steps", low=0, group="budgets")
    eval_every: int = arg(10_000, "frames between evaluations (snapshots follow "
                                  "--snapshot-minutes)", above=0, group="budgets")
    eval_episodes: int = arg(10, "episodes per evaluation, mean action (task sets: at least this "
                                 "many in all)", above=0, when="episodes not per task",
                             evaluate_may_set=True)
    eval_episodes_per_task: int = arg(0, "task sets (metaworld-mt*): evaluation episodes of every "
                                         "task; 0 = ceil(--eval-episodes / number of tasks)", low=0,
                                      envs="task sets", group="the suites", evaluate_may_set=True)


def make_agent(cfg: Config, action_dim: int, device: torch.device) -> Agent:
    """The run's agent: sear.Agent, Ego-Foresight's (foresight.ForesightAgent), and with --drm
    DrM's on top (drm.DrMAgent first in the order of the methods each overrides)."""
    agent = {"ef": foresight.ForesightAgent, "rgbm": baselines.RGBMAgent}.get(cfg.method, Agent)
    if cfg.drm:
        both = (drm.DrMAgent, agent)
        agent = drm.DrMAgent if agent is Agent else type("DrM" + agent.__name__, both, {})
    return agent(cfg, action_dim, device, METHODS[cfg.method])


def make_replay(cfg: Config, *args, **kwargs) -> ReplayBuffer:
    """The run's replay buffer: sear.ReplayBuffer, or Ego-Foresight's windows."""
    if cfg.method == "ef":
        return foresight.make_replay(cfg, *args, **kwargs)
    return ReplayBuffer(*args, **kwargs)


def seed_everything(seed):
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def act(agents: list[Agent], obs: dict, step: int, eval_mode: bool) -> np.ndarray:
    """Every seed's action (seed first): the seeds' observations cross to the device in one copy
    (the masks only for DrQ-RGBM, whose encoder reads them), each seed's agent acts on its own,
    and the actions come back in one read."""
    device = agents[0].device
    pixels = torch.as_tensor(obs["pixels"], device=device)
    rgbm = isinstance(agents[0], baselines.RGBMAgent)
    masks = torch.as_tensor(obs["mask"], device=device) if rgbm else None
    actions = [a.act(pixels[i], None if masks is None else masks[i], step, eval_mode)
               for i, a in enumerate(agents)]
    return torch.stack(actions).cpu().numpy()


# ================================================================================================
# Evaluation
# ================================================================================================
class Episode(NamedTuple):
    """An evaluation episode: its return, its success (None where the env reports none), its task
    (a task set's; None for one task)."""
    ret: float
    success: bool | None
    task: str | None


def evaluate(agents, envs: runenvs.SeedEnvs, step: int, watches=None, on_step=None, stop=None):
    """Every seed's evaluation episodes with the mean action, side by side, each seed's episode e
    from the reset seed of a single run of that seed (the same at every evaluation, so that they
    compare); a task set runs each of its tasks (runenvs.eval_tasks). `watches` (one per seed) see
    every observation (decoder metrics, videos); on_step(episode, t) is called after every step;
    stop() before every episode: once true the evaluation ends there, with fewer episodes (a first
    SIGTERM cuts an evaluation at an episode end). Returns each seed's Episodes."""
    n, cfg = len(agents), agents[0].cfg
    stacks, episodes = runenvs.Stacks(n, cfg.frame_stack, envs.frame_shape), [[] for _ in agents]
    for e, task in enumerate(runenvs.eval_tasks(envs.tasks, cfg)):
        if stop is not None and stop():
            break
        seeds = [runenvs.episode_seed(a.cfg.seed + runenvs.EVAL_SEED, e) for a in agents]
        options = None if task is None else {"task": task}
        newest, _ = envs.reset("eval", np.ones(n, bool), seeds, options)
        stacks.reset(slice(None), newest)
        running, ret, success, last, t = np.ones(n, bool), np.zeros(n), np.zeros(n, bool), {}, 0
        for i, watch in enumerate(watches or ()):
            watch.see(stacks.seed(i), new_episode=True)
        while running.any():
            actions = act(agents, stacks.obs, step, eval_mode=True)
            newest, reward, terminated, truncated, infos = envs.step("eval", actions)
            stacks.push(running, newest)
            t += 1
            for i in np.flatnonzero(running):
                info = last[i] = runenvs.seed_info(infos, i)
                ret[i] += reward[i]
                success[i] |= bool(info.get("success", False))
                if watches:
                    watches[i].see(stacks.seed(i))
            ended = running & (terminated | truncated)
            for i in np.flatnonzero(ended):
                reported = success[i] if "success" in last[i] else None
                episodes[i].append(Episode(ret[i], reported, task))
            running &= ~ended
            if on_step:
                on_step(e, t)
    return episodes


def evaluate_and_log(agents, envs, runs: group.Runs) -> None:
    """An evaluation of every seed now: its episodes scored and filmed by each run dir, eval.csv's
    row. While a first SIGTERM waits there is none, and one it cuts short at an episode end leaves
    last_eval_frame as it was: the run stops at its stop point, and its resume evaluates again."""
    if runs.dirs[0].stop_pending():
        return
    watches = runs.each("start_eval", envs.tasks)
    lead = runs.dirs[0]
    episodes = evaluate(agents, envs, lead.counters.step, watches, on_step=runs.show_eval,
                        stop=lead.stop_pending)
    learned_iou = [None] * len(runs)
    if runenvs.measures_learned_iou(lead.cfg):
        learned_iou = envs.call("eval", "pop")
    for i, d in enumerate(runs):
        # False: cut short
        if runs.call(i, "end_eval", watches[i], episodes[i], learned_iou[i]):
            d.counters.last_eval_frame = d.counters.step * d.cfg.action_repeat
    runs.say_eval(episodes)


# ================================================================================================
# The training loop
# ================================================================================================
def eval_due(frame: int, last_eval_frame: int, every: int) -> bool:
    """drqv2's Every, in frames: a multiple of `every` lies in (last evaluation, frame]. Frame 0 is
    one (last_eval_frame starts at -1)."""
    return frame // every > last_eval_frame // every


def build(runs: group.Runs, envs: runenvs.SeedEnvs, run: cli.RunConfig, device, source=None):
    """Each seed's agent (its networks drawn after torch.manual_seed(seed), as a single run of the
    seed draws them; with --init-from, `source`'s networks copied in), replay and sampling RNG, a
    resumed seed's restored; then the speed layer's samplers, learner and the flush of the rings'
    writes (harness/speed.py)."""
    agents, buffers, rngs = [], [], []
    for d in runs:
        cfg = d.cfg
        seed_everything(cfg.seed)
        agents.append(make_agent(cfg, envs.action_dim, device))
        if source is not None:
            experiment.copy_parts(agents[-1], source, run.init_parts)
        ring = dict(frame_shape=envs.frame_shape, action_dim=envs.action_dim,
                    frame_stack=cfg.frame_stack, nstep=cfg.nstep, discount=cfg.discount)
        ring_bytes = len(runs) * cfg.replay_size * ReplayBuffer(1, **ring).bytes_per_transition
        buffers.append(make_replay(cfg, cfg.replay_size, **ring,
                                   device=speed.replay_device(run, device, ring_bytes)))
        rngs.append(np.random.default_rng(cfg.seed))
    runs.start(agents, buffers, rngs)
    samplers = [runs.closing(speed.prefetcher(b, d.cfg, run, r, device)) or b
                for b, d, r in zip(buffers, runs, rngs)]
    learner = speed.Learner(agents, run, device)
    return agents, buffers, samplers, learner, speed.stage_writes(buffers)


def start_episodes(runs: group.Runs, envs, buffers, stacks, which, ep) -> None:
    """Seeds `which` (a mask) start their next episodes, each from its reset seed."""
    seeds = [runenvs.episode_seed(d.cfg.seed, d.counters.episode) for d in runs]
    stacks.reset(which, envs.reset("train", which, seeds)[0])
    for i in np.flatnonzero(which):
        buffers[i].add_first(stacks.seed(i))
        runs.dirs[i].counters.mid_episode, ep[i] = True, 0


def end_steps(runs: group.Runs, buffers, stacks, actions, results, ep) -> None:
    """Every seed's step taken: its replay, its counters, its episode; an ended episode logged."""
    _, rewards, terminated, truncated, infos = results
    for i, d in enumerate(runs):
        buffers[i].add(actions[i], rewards[i], terminated[i], stacks.seed(i))
        d.counters.step += 1
        info = runenvs.seed_info(infos, i)
        ep[i, 0], ep[i, 1] = ep[i, 0] + rewards[i], ep[i, 1] + 1
        ep[i, 2] = ep[i, 2] or bool(info.get("success", False))
        if terminated[i] or truncated[i]:
            runs.log_episode(i, float(ep[i, 0]), int(ep[i, 1]), bool(ep[i, 2]), info)
            d.counters.episode, d.counters.mid_episode = d.counters.episode + 1, False
        else:
            runs.show_step(i, int(ep[i, 1]))


def update_due(frame, step, cfg: Config, samplers, buffers) -> bool:
    """Whether the agents update at this step: every --update-every agent steps once every replay
    holds the seed frames' steps (after the random phase, and again after a resume that could not
    bring its buffer back)."""
    return (frame >= cfg.seed_frames and step % cfg.update_every == 0
            and all(s.can_sample() and len(b) >= cfg.seed_frames // cfg.action_repeat
                    for s, b in zip(samplers, buffers)))


def train(cfg: Config, run: cli.RunConfig, snapshot=None, seeds=None, group_dir=None) -> str:
    """Train the run's seeds from scratch, or on from their snapshots (one seed, or --seeds in
    lockstep); returns the run directory (a group's folder). The loop decides when to evaluate,
    snapshot and stop; the run directories write what they are handed, and turn a Ctrl-C, a
    SIGTERM or a storage error into one line."""
    with group.Runs(cfg, run, snapshot, seeds, group_dir) as runs:
        device = cli.torch_setup(run)
        # a learned mask source checked (and its held-out IoU said) once, here, before its workers
        runenvs.load_mask_model(cfg)
        configs = [cli.config_dict(d.cfg, d.run) for d in runs]
        uses_mask = METHODS[cfg.method].uses_mask
        envs = runs.closing(runenvs.SeedEnvs(configs, uses_mask, workers=group.workers(runs)))
        source = None
        if run.init_from and not snapshot:
            source = experiment.init_source(cfg, run, envs.action_dim)
        runs.create(f"envs in {envs.kind}; device {device}")
        agents, buffers, samplers, learner, flush_writes = build(runs, envs, run, device, source)
        lead, cfg, n = runs.dirs[0], runs.dirs[0].cfg, len(runs)
        stacks, ep = runenvs.Stacks(n, cfg.frame_stack, envs.frame_shape), np.zeros((n, 3))
        clock = time.monotonic()
        while True:
            c = lead.counters
            frame = c.step * cfg.action_repeat
            final = frame >= cfg.frames
            # The one evaluation site: every --eval-every frames, and at the budget's end.
            due = eval_due(frame, c.last_eval_frame, cfg.eval_every)
            if due or final and c.last_eval_frame < frame:
                evaluate_and_log(agents, envs, runs)
            between = np.array([not d.counters.mid_episode for d in runs])
            if between.all() or final:
                # The one stop point: a first SIGTERM stops every seed here (with its snapshot).
                lead.safe_point()
                if final:
                    break
                # every --snapshot-minutes, at an episode's end (not where the run starts)
                fresh = frame in (0, lead.snapshot_frame)
                if not fresh and time.monotonic() - clock >= 60 * run.snapshot_minutes:
                    runs.each("snapshot")
                    clock = time.monotonic()
            if between.any():
                start_episodes(runs, envs, buffers, stacks, between, ep)
            # As DrQ-v2, the agent acts from the first step: uniformly for --exploration-steps
            # agent steps (Agent.act), then the actor plus noise, not updated in the seed frames.
            actions = act(agents, stacks.obs, c.step, eval_mode=False)
            # The envs step (in their workers) while the agents update.
            envs.send("train", actions)
            if update_due(frame, c.step, cfg, samplers, buffers):
                batches = [s.sample(cfg.batch_size, d.sample_rng) if s is b else s.next()
                           for s, b, d in zip(samplers, buffers, runs)]
                runs.log_updates(learner.update(batches, c.step))
            results = envs.receive("train")
            stacks.push(slice(None), results[0])
            end_steps(runs, buffers, stacks, actions, results, ep)
            # every seed's writes of the step to rings on a GPU in one copy (speed.StagedWrites)
            flush_writes()
        return runs.finish()


def evaluate_snapshot(cfg: Config, run: cli.RunConfig, snapshot: dict) -> None:
    """--evaluate RUN_DIR: the snapshot's agent on the run's eval env, scored and printed."""
    device = cli.torch_setup(run)
    uses_mask = METHODS[cfg.method].uses_mask
    envs = runenvs.SeedEnvs([cli.config_dict(cfg, run)], uses_mask, workers=False)
    try:
        agent = make_agent(cfg, envs.action_dim, device)
        experiment.score_snapshot(cfg, run, snapshot, agent, envs, evaluate)
    finally:
        envs.close()


def main(argv=None) -> int:
    """`python sear.py --flag value ...` (or train.py): 0 when done; bad input (2), Ctrl-C (130) and
    SIGTERM (143) end in one line. `--seeds 1-16` (or --resume of a group's folder) trains several
    seeds in one loop (harness/group.py)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    return group.main(argv, Config, METHODS, train, evaluate_snapshot)


if __name__ == "__main__":
    sys.exit(main())
