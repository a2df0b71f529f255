"""Our DrQ beside the official DrQ-v2 (facebookresearch/drqv2), piece by piece: the checks that
EXPERIMENTS.md "Rung PC" runs when a learning curve does not match the published one.

    # 1. the env: the official dmc.make and our envs.make_env from the same state, with the same actions
    MUJOCO_GL=egl python benchmarks/official_compare.py env --official /path/to/drqv2 --episodes 2
    # 2. what was collected: per-episode return and action statistics of the official run's episode
    #    files (its buffer/, kept with save_snapshot=true) beside our runs' buffer.npz (--save-buffer)
    python benchmarks/official_compare.py replay /path/to/official-run RUN_DIR [RUN_DIR ...]
    # 3. the policy of a snapshot: the mean action on the eval and the train env, and sampled actions
    MUJOCO_GL=egl python benchmarks/official_compare.py policy RUN_DIR --episodes 10 --stds 0.82
    # 4. the simulator across MuJoCo / dm_control versions: record under each stack, then compare
    MUJOCO_GL=egl /old/venv/bin/python benchmarks/official_compare.py physics --record old.npz
    MUJOCO_GL=egl python benchmarks/official_compare.py physics --record new.npz --compare old.npz
    # 5. the replay loader: the official one's batches beside benchmarks/drqv2_loader.py's, same episodes
    python benchmarks/official_compare.py loader --official /path/to/drqv2
    # 6. the actor's saturation and spread per block of frames: our runs' train.csv beside an official
    #    run's actor.csv (a read-only probe's rows, see actor_rows)
    python benchmarks/official_compare.py saturation /path/to/official-run RUN_DIR [RUN_DIR ...]

Nothing is written; every line printed is a measurement. The official code is read from a checkout
(bring it with `git clone`; this project ships none of it); it needs hydra-free modules only (dmc.py).
"""
import argparse
import glob
import json
import os
import pathlib
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402
import plot  # noqa: E402


def fail(message):
    print(f"official_compare.py: {message}", file=sys.stderr)
    sys.exit(2)


def action_stats(episodes) -> dict:
    """Over a list of episodes' actions: |a| mean, the share of entries at the bounds (|a| > 0.99) and
    how often an action's sign flips from one step to the next within an episode (bang-bang control
    flips rarely, a uniform random policy half the time)."""
    episodes = [np.asarray(a).reshape(len(a), -1) for a in episodes]
    a = np.concatenate(episodes)
    flips = sum(int((np.sign(e[1:]) != np.sign(e[:-1])).sum()) for e in episodes)
    pairs = sum(e[1:].size for e in episodes)
    return {"|a|": float(np.abs(a).mean()), "at bound": float(np.mean(np.abs(a) > 0.99)),
            "sign flips": flips / max(pairs, 1)}


# --- 1. the env --------------------------------------------------------------------------------------
def compare_env(args):
    """Both envs reset, then ours is put into the official's physics state; from there every step
    gets the same action. Reports the largest state, reward and pixel difference per episode (pixels
    of the whole stack once our reset frame has left it) and how each env ends the episode."""
    if not os.path.isfile(os.path.join(args.official, "dmc.py")):
        fail(f"--official: '{args.official}' is no checkout of facebookresearch/drqv2 (no dmc.py)")
    sys.path.insert(0, args.official)
    import dmc  # the official env (its dm_control wrappers)
    import envs
    domain, _, task = args.task.partition("_")
    try:
        ours = envs.make_env(f"{domain}-{task}", seed=args.seed, frame_stack=args.frame_stack,
                             action_repeat=args.action_repeat, render_quality="paper")
    except envs.EnvError as e:
        fail(f"--task {args.task}: {e}")
    official = dmc.make(args.task, args.frame_stack, args.action_repeat, args.seed)
    physics = official
    while not hasattr(physics, "physics"):
        physics = physics._env
    physics = physics.physics
    rng = np.random.default_rng(args.seed)
    print(f"{args.task}: official dmc.make against envs.make_env('{domain}-{task}'), action repeat "
          f"{args.action_repeat}, frame stack {args.frame_stack}, uniform random actions")
    for episode in range(args.episodes):
        official.reset()
        ours.reset(seed=episode)
        ours.unwrapped.backend.physics.set_state(physics.get_state())
        ours.unwrapped.backend.physics.forward()
        returns, worst = [0.0, 0.0], {"state": 0.0, "reward": 0.0, "pixels": 0}
        t = 0
        while True:
            action = rng.uniform(-1, 1, size=official.action_spec().shape).astype(np.float32)
            ts = official.step(action)
            obs, reward, terminated, truncated, _ = ours.step(action)
            t += 1
            returns[0] += ts.reward
            returns[1] += reward
            worst["reward"] = max(worst["reward"], abs(ts.reward - reward))
            worst["state"] = max(worst["state"], float(np.abs(
                physics.get_state() - ours.unwrapped.backend.physics.get_state()).max()))
            stack = slice(None) if t >= args.frame_stack else slice(-3, None)  # our reset frame is our own
            worst["pixels"] = max(worst["pixels"], int(np.abs(
                ts.observation[stack].astype(int) - obs["pixels"][stack].astype(int)).max()))
            if ts.last() or terminated or truncated:
                break
        official_end = "time limit" if ts.last() and ts.discount == 1.0 else ("termination" if ts.last() else "running")
        ours_end = "termination" if terminated else ("time limit" if truncated else "running")
        print(f"episode {episode}: {t} steps, return {returns[0]:.1f} official / {returns[1]:.1f} ours; largest "
              f"difference: state {worst['state']:.1e}, reward {worst['reward']:.1e}, pixel {worst['pixels']}; "
              f"ends by {official_end} / {ours_end}")
    ours.close()


# --- 2. what was collected -----------------------------------------------------------------------
def official_episodes(run_dir):
    """(return, actions) per episode of an official run's buffer/ (its first step is the reset's)."""
    files = glob.glob(os.path.join(run_dir, "buffer", "*.npz"))
    if not files:
        fail(f"'{run_dir}' has no buffer/*.npz (an official run keeps its episodes with save_snapshot=true)")
    files.sort(key=lambda f: int(os.path.basename(f).split("_")[1]))  # <time>_<episode>_<length>.npz
    out = []
    for f in files:
        with np.load(f) as d:
            out.append((float(d["reward"][1:].sum()), d["action"][1:]))
    return out


def our_episodes(run_dir):
    """(return, actions) per episode of our buffer.npz (an episode starts at a `first` slot; the
    buffer is saved with a snapshot, between episodes, so every episode in it is whole)."""
    path = os.path.join(run_dir, "buffer.npz")
    if not os.path.isfile(path):
        fail(f"'{run_dir}' has no buffer.npz (runs keep their replay with --save-buffer)")
    with np.load(path) as d:
        if int(d["t"]) > len(d["rewards"]):
            fail(f"'{path}' is a full ring (its oldest episodes are gone); this compares from the start")
        first = np.flatnonzero(d["first"])
        ends = [*first[1:], len(d["first"])]
        return [(float(d["rewards"][s + 1:e].sum()), d["actions"][s + 1:e]) for s, e in zip(first, ends)]


def run_label(run_dir):
    """'drq seed 1' ('drq+drm seed 1' with --drm) from a run's config.json (the folder's name if it has none)."""
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            c = json.load(f)
        return f"{cli.method_label(c)} seed {c['seed']}"
    except (OSError, ValueError, KeyError):
        return os.path.basename(os.path.normpath(run_dir))


def compare_replay(args):
    runs = [(f"official ({os.path.basename(os.path.normpath(args.official_run))})", official_episodes(args.official_run))]
    runs += [(run_label(r), our_episodes(r)) for r in args.run_dirs]
    block = args.block
    print(f"each cell, over a block of {block} episodes: mean return / mean abs action / share at the bound / "
          f"share of sign flips")
    print("| episodes | " + " | ".join(name for name, _ in runs) + " |\n|---|" + "---|" * len(runs))
    for lo in range(0, max(len(e) for _, e in runs), block):
        cells = []
        for _, episodes in runs:
            part = episodes[lo:lo + block]
            if not part:
                cells.append("")
                continue
            s = action_stats([a for _, a in part])
            cells.append(f"{np.mean([r for r, _ in part]):.0f} / {s['|a|']:.2f} / {s['at bound']:.2f} / "
                         f"{s['sign flips']:.2f}")
        print(f"| {lo}–{lo + block - 1} | " + " | ".join(cells) + " |")


# --- 3. the policy of a snapshot ---------------------------------------------------------------------
def compare_policy(args):
    import torch

    from harness import experiment, runenvs
    import sear
    import train
    try:
        snapshot = cli.load_snapshot(args.run_dir, flag="")
    except cli.ConfigError as e:
        fail(str(e))
    cfg, _ = cli.split_config(snapshot["config"], train.Config)
    torch.set_num_threads(args.threads)
    method = sear.METHODS[cfg.method]
    train_env, eval_env = runenvs.make_envs(cfg, method.uses_mask)
    agent = train.make_agent(cfg, train_env.action_space.shape[0], torch.device("cpu"))
    agent.load_state_dict(snapshot["agent"])
    step = snapshot["counters"]["step"]
    std = sear.linear_std(cfg, step)
    print(f"{args.run_dir}: snapshot at frame {step * cfg.action_repeat} (agent step {step}, exploration std {std:.2f})")
    # (label, env, std to sample with or None for the mean action, episode_seed's seed and first episode):
    # the evaluation's own reset seeds (train.evaluate), and train-env seeds no training episode used
    fresh = (cfg.seed, 10 ** 6)
    rows = [("mean action, eval env (the evaluation's reset seeds)", eval_env, None, (cfg.seed + 100_000, 0)),
            ("mean action, train env (new reset seeds)", train_env, None, fresh)]
    rows += [(f"sampled with std {s:g}, train env (new reset seeds)", train_env, s, fresh) for s in args.stds]
    for label, env, sample_std, (seed, first) in rows:
        returns, actions = [], []
        for i in range(args.episodes):
            actions.append([])
            obs, _ = env.reset(seed=runenvs.episode_seed(seed, first + i))
            done, ret = False, 0.0
            while not done:
                if sample_std is None:
                    action = agent.act(obs["pixels"], obs["mask"], step, eval_mode=True)
                else:
                    with torch.no_grad():
                        pixels = torch.as_tensor(obs["pixels"]).float().unsqueeze(0)
                        mask = None if obs["mask"] is None else torch.as_tensor(obs["mask"]).float().unsqueeze(0)
                        dist = agent.actor(agent.encoder(pixels), sample_std)
                        action = dist.sample(clip=None).squeeze(0).numpy().astype(np.float32)
                actions[-1].append(action)
                obs, reward, terminated, truncated, _ = env.step(action)
                ret += reward
                done = terminated or truncated
            returns.append(ret)
        s = action_stats([np.array(a) for a in actions])
        print(f"{label}: return {np.mean(returns):.1f} ({' '.join(f'{r:.0f}' for r in returns)}); |a| {s['|a|']:.2f}, "
              f"at bound {s['at bound']:.2f}, sign flips {s['sign flips']:.2f}", flush=True)
    train_env.close()
    eval_env.close()


# --- 4. the simulator across versions -------------------------------------------------------------
def compare_physics(args):
    """dm_control's own task (no wrapper of either project): a few episodes of fixed uniform random
    actions from fixed task seeds; states, rewards and camera-0 frames (every 50th step) to an npz, and
    the largest differences against another stack's file. Needs only numpy, mujoco and dm_control, so
    that an old stack in a venv of its own can record."""
    import mujoco
    from dm_control import suite
    domain, _, task = args.task.partition("_")
    rng = np.random.default_rng(0)
    from importlib.metadata import version
    out = {"versions": np.array(f"mujoco {mujoco.__version__}, dm-control {version('dm-control')}")}
    for episode in range(args.episodes):
        try:
            env = suite.load(domain, task, task_kwargs={"random": episode})
        except (ValueError, KeyError, AttributeError):
            fail(f"--task {args.task}: no such dm_control task")
        env.reset()
        states, rewards, frames = [env.physics.get_state().copy()], [], []
        for t, action in enumerate(rng.uniform(-1, 1, size=(args.steps, *env.action_spec().shape))):
            ts = env.step(action)
            states.append(env.physics.get_state().copy())
            rewards.append(ts.reward or 0.0)
            if t % 50 == 0:
                frames.append(env.physics.render(84, 84, camera_id=0))
        out[f"states{episode}"], out[f"rewards{episode}"] = np.array(states), np.array(rewards, float)
        out[f"frames{episode}"] = np.array(frames)
    if args.record:
        with cli.storing(args.record):
            np.savez(args.record, **out)
    print(f"{out['versions']}: returns " + " ".join(f"{out[f'rewards{e}'].sum():.0f}" for e in range(args.episodes)))
    if args.compare:
        try:
            other = dict(np.load(args.compare))
        except (OSError, ValueError) as e:
            fail(f"--compare: cannot read '{args.compare}': {cli.first_sentence(e)}")
        if any(f"states{e}" not in other or other[f"states{e}"].shape != out[f"states{e}"].shape
               for e in range(args.episodes)):
            fail(f"--compare: '{args.compare}' was recorded with other --task/--episodes/--steps")
        for e in range(args.episodes):
            pixels = np.abs(out[f"frames{e}"].astype(int) - other[f"frames{e}"].astype(int))
            print(f"episode {e} against {other['versions']}: largest state difference "
                  f"{np.abs(out[f'states{e}'] - other[f'states{e}']).max():.1e}, reward "
                  f"{np.abs(out[f'rewards{e}'] - other[f'rewards{e}']).max():.1e}; pixels: largest {pixels.max()}, "
                  f"mean {pixels.mean():.2f}, share of pixels that differ {(pixels.max(-1) > 0).mean():.2f}")


# --- 5. the replay loader ---------------------------------------------------------------------------
def compare_loader(args):
    """The official make_replay_loader over episode files whose observations name (episode, step), and
    drqv2_loader.LoaderReplay over the same episodes: for each batch in turn, which episodes it draws
    from and which start steps (the observation's index in its episode). Episode files are written to a
    temporary folder only."""
    if not os.path.isfile(os.path.join(args.official, "replay_buffer.py")):
        fail(f"--official: '{args.official}' is no checkout of facebookresearch/drqv2 (no replay_buffer.py)")
    sys.path.insert(0, args.official)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import replay_buffer  # the official loader
    import drqv2_loader
    lengths, n = args.lengths, args.nstep
    if not lengths or min(lengths) < n or args.workers < 1 or args.batch_size < 1:
        fail(f"loader: give --lengths of {n} (--nstep) steps or more each (the official loader cannot draw "
             f"from a shorter episode), --workers and --batch-size of 1 or more")
    ours = drqv2_loader.LoaderReplay(sum(lengths) + len(lengths) + 4 * args.batches + 8, (3, 1, 1), 1, 1, n, 0.99)
    ours.workers, ours.update_every = args.workers, 2
    with tempfile.TemporaryDirectory() as folder:
        for e, length in enumerate(lengths):
            obs = np.stack([np.full(length + 1, e), np.arange(length + 1)], 1).astype(np.uint8)[:, :, None, None]
            np.savez(pathlib.Path(folder) / f"20261201T000000_{e}_{length}.npz", observation=obs,
                     action=np.zeros((length + 1, 1), np.float32), reward=np.zeros((length + 1, 1), np.float32),
                     discount=np.ones((length + 1, 1), np.float32))
            ours.add_first({"pixels": np.full((3, 1, 1), e, np.uint8), "mask": np.zeros((1, 1, 1), bool)})
            for _ in range(length):
                ours.add(0.0, 0.0, False, {"pixels": np.zeros((3, 1, 1), np.uint8), "mask": np.zeros((1, 1, 1), bool)})
        running = {"pixels": np.zeros((3, 1, 1), np.uint8), "mask": np.zeros((1, 1, 1), bool)}
        ours.add_first(running)  # the running episode; the official loader sees only files
        while (ours.t - len(lengths) - 1) % (2 * args.workers):  # the first update is worker 0's, as at step 2000
            ours.add(0.0, 0.0, False, running)
        firsts = np.flatnonzero(ours.first[:ours.t])
        batches = iter(replay_buffer.make_replay_loader(pathlib.Path(folder), 10 ** 6, args.batch_size,
                                                        args.workers, True, n, 0.99))
        rng, same = np.random.default_rng(0), True
        print(f"{len(lengths)} episodes of {lengths} steps, n-step {n}, {args.workers} workers, batch {args.batch_size}")
        for i in range(args.batches):
            obs = next(batches)[0].numpy()
            official = set(zip(obs[:, 0, 0, 0].tolist(), obs[:, 1, 0, 0].tolist()))
            starts = ours.draw_starts(args.batch_size, rng, lo=0)
            e = np.searchsorted(firsts, starts, side="right") - 1
            mine = set(zip(e.tolist(), (starts - firsts[e]).tolist()))
            same &= official == mine
            print(f"batch {i}: official {describe(official)} | drqv2_loader {describe(mine)} | "
                  f"{'same' if official == mine else 'DIFFERENT'}")
            ours.add(0.0, 0.0, False, running), ours.add(0.0, 0.0, False, running)
        del batches  # the loader's worker processes end with it
    print("every batch the same episodes and starts" if same else "the two differ")


# --- 6. the actor's saturation and spread ----------------------------------------------------------
def actor_rows(run_dir, action_repeat):
    """(label, frames, saturated, spread) of a run's actor. Ours: train.csv's actor_saturated and
    action_spread, each an episode's mean over its updates, at the frame before the episode's end (so
    that the episode falls into the block it ran in). An official run: actor.csv, one row per update,
    `step,saturated,spread`, which official DrQ-v2 does not write: a read-only probe appended after
    `self.actor_opt.step()` in `DrQV2Agent.update_actor` writes `step`, `(dist.loc.abs() == 1.0).float().mean()`
    and `dist.loc.std(0, unbiased=False).mean()` (sear.actor_metrics' two quantities); where a resume
    repeated steps, the last row of each step counts; its frame is step x action repeat."""
    probe, ours = os.path.join(run_dir, "actor.csv"), os.path.join(run_dir, "train.csv")
    if os.path.isfile(probe):
        last = {}
        with open(probe) as f:
            for line in f:
                try:
                    step, sat, spread = line.split(",")
                    last[int(step)] = (float(sat), float(spread))
                except ValueError:
                    fail(f"'{probe}': a row is not step,saturated,spread: {line.strip()!r}")
        if not last:
            fail(f"'{probe}' has no rows (the official run stopped before its first update)")
        steps = sorted(last)
        values = np.array([last[s] for s in steps])
        return (f"official ({os.path.basename(os.path.normpath(run_dir))})",
                np.array(steps) * action_repeat, values[:, 0], values[:, 1])
    if not os.path.isfile(ours):
        fail(f"'{run_dir}' has neither actor.csv (an official run with the probe) nor train.csv (our run)")
    try:  # rows with a value (none before the first update); a frame repeated by a resume keeps its last row
        sat, spread = (plot.load_run(run_dir, "train", m) for m in ("actor_saturated", "action_spread"))
    except plot.PlotError as e:
        fail(f"'{run_dir}': {e}")
    return run_label(run_dir), sat["frames"] - 1, sat["values"], spread["values"]


def compare_saturation(args):
    """Per block of frames: the share of the batch's mean actions at exactly +-1, and their spread."""
    runs = [actor_rows(r, args.action_repeat) for r in args.run_dirs]
    block = args.block
    print(f"each cell, over the updates in a block of {block} frames: share of mean-action entries at exactly "
          f"+-1 / their std over the batch (ours: the mean of each episode's means)")
    print("| frames | " + " | ".join(label for label, *_ in runs) + " |\n|---|" + "---|" * len(runs))
    for lo in range(0, int(max(frames.max() for _, frames, _, _ in runs)) + 1, block):
        cells = []
        for _, frames, sat, spread in runs:
            inside = (frames >= lo) & (frames < lo + block)
            cells.append(f"{sat[inside].mean():.2f} / {spread[inside].mean():.3g}" if inside.any() else "")
        if any(cells):
            print(f"| {lo / 1000:g}k–{(lo + block) / 1000:g}k | " + " | ".join(cells) + " |")


def describe(pairs):
    """'episodes 0,4, starts 0-7': a batch's (episode, start) pairs, in short."""
    eps = sorted({e for e, _ in pairs})
    return "episodes " + ",".join(map(str, eps)) + ", starts " + "; ".join(
        f"{min(s for x, s in pairs if x == e)}-{max(s for x, s in pairs if x == e)}" for e in eps)


def main(argv=None):
    p = cli.OneLineParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="check", required=True)
    e = sub.add_parser("env", help="the official env and ours in lockstep")
    e.add_argument("--official", required=True, help="a checkout of facebookresearch/drqv2")
    e.add_argument("--task", default="cartpole_balance_sparse", help="DrQ-v2's task name")
    e.add_argument("--frame-stack", type=int, default=3)
    e.add_argument("--action-repeat", type=int, default=2)
    e.add_argument("--episodes", type=int, default=2)
    e.add_argument("--seed", type=int, default=1)
    r = sub.add_parser("replay", help="what the official run and ours collected, per block of episodes")
    r.add_argument("official_run", help="an official run directory (with buffer/)")
    r.add_argument("run_dirs", nargs="+", help="our run directories (with buffer.npz)")
    r.add_argument("--block", type=int, default=5, help="episodes per table row")
    q = sub.add_parser("policy", help="a snapshot's policy: mean action and sampled actions")
    q.add_argument("run_dir")
    q.add_argument("--episodes", type=int, default=10)
    q.add_argument("--stds", type=lambda s: [float(x) for x in s.split(",") if x], default=[],
                   help="comma-separated exploration stds to sample with")
    q.add_argument("--threads", type=int, default=1)
    m = sub.add_parser("physics", help="dm_control's task under this interpreter's MuJoCo, against another's")
    m.add_argument("--task", default="cartpole_balance_sparse")
    m.add_argument("--episodes", type=int, default=3)
    m.add_argument("--steps", type=int, default=1000, help="physics steps per episode (no action repeat)")
    m.add_argument("--record", help="write states, rewards and frames to this .npz")
    m.add_argument("--compare", help="an .npz recorded under another stack")
    w = sub.add_parser("loader", help="the official replay loader's batches beside drqv2_loader.py's")
    w.add_argument("--official", required=True, help="a checkout of facebookresearch/drqv2")
    w.add_argument("--lengths", type=lambda s: [int(x) for x in s.split(",") if x], default=[10, 8, 12, 10, 6, 10, 9, 3],
                   help="comma-separated steps of each ended episode")
    w.add_argument("--workers", type=int, default=4)
    w.add_argument("--nstep", type=int, default=3)
    w.add_argument("--batch-size", type=int, default=1024, help="large enough that a batch shows every start")
    w.add_argument("--batches", type=int, default=8)
    a = sub.add_parser("saturation", help="the actor's saturation and spread per block of frames, runs side by side")
    a.add_argument("run_dirs", nargs="+", help="official run dirs (with the probe's actor.csv) and ours (train.csv)")
    a.add_argument("--block", type=int, default=2000, help="frames per table row")
    a.add_argument("--action-repeat", type=int, default=2, help="the official run's (its probe logs agent steps)")
    try:
        args = p.parse_args(argv)
    except cli.ConfigError as e:
        fail(str(e))
    if min(getattr(args, "block", 1), getattr(args, "action_repeat", 1)) < 1:
        fail(f"{args.check}: --block and --action-repeat must be 1 or more")
    {"env": compare_env, "replay": compare_replay, "policy": compare_policy,
     "physics": compare_physics, "loader": compare_loader,
     "saturation": compare_saturation}[args.check](args)


if __name__ == "__main__":
    main()
