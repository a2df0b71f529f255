"""The run directories of the loop's seeds (train.train): one run (--seed k), or a seed group (--seeds
1-16): N ordinary run directories (config.json, train.csv, eval.csv, snapshot.pt: what plot.py, sweep.py
and --resume read of any run) inside one folder with group.json. Seed k of a group is the run --seed k
is: its own envs, replay, sampling RNG, initial weights and random draws (sear.Agent.rng).

A group's seeds print their lines to their own console.log; the terminal shows one progress line for
the group. `--resume GROUP_DIR` continues every seed; `--resume` of one seed's run directory continues
that seed alone, as a single run.

Layering: imports cli.py and experiment.py; never sear.py or train.py.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import sys
import time

import numpy as np

from harness import cli, experiment

GROUP_FILE = "group.json"
WORKERS = "SEAR_ENV_WORKERS"  # spawn (the default: worker processes) | serial (a group's envs in this process)
# A seed's peak memory beside its envs (SEAR at batch 256: docs/speed.md) and its two env workers'
PEAK_BYTES_PER_SEED = 2.7e9


def split_argv(argv: list[str]) -> tuple[list[int] | None, str | None, list[str]]:
    """(seeds, group folder to resume, argv of one seed) of a command line: --seeds SPEC (removed; each
    seed's --seed is set), or --resume GROUP_DIR (its first seed's run dir in its place)."""
    argv, seeds, group_dir = list(argv), None, None
    for flag in ("--seeds", "--resume"):
        for i, token in enumerate(argv):
            name, eq, value = token.partition("=")
            if name != flag or (not eq and i + 1 >= len(argv)):
                continue
            value = value if eq else argv[i + 1]
            if flag == "--seeds":
                seeds, argv = cli.parse_seeds(value), argv[:i] + argv[i + 1 + (not eq):]
            elif os.path.isfile(os.path.join(value, GROUP_FILE)):
                group_dir, saved = value, read_group_file(value)
                seeds = saved["seeds"]
                argv[i:i + 1 + (not eq)] = ["--resume", os.path.join(value, saved["runs"][str(seeds[0])])]
            break
    return seeds, group_dir, argv


def read_group_file(group_dir) -> dict:
    """group.json: {"seeds": [...], "runs": {seed: run dir name}}; a damaged one is one line."""
    path = os.path.join(group_dir, GROUP_FILE)
    try:
        with open(path) as f:
            saved = json.load(f)
        runs = {str(k): saved["runs"][str(k)] for k in saved["seeds"]}
        return {"seeds": [int(k) for k in saved["seeds"]], "runs": runs}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise cli.ConfigError(f"--resume: {path} is damaged ({cli.first_sentence(e) or type(e).__name__}); "
                              "each seed's run directory resumes alone: --resume <its run dir>") from None


def check_size(seeds: list[int]) -> None:
    """More seeds than this machine holds is one line, before anything starts: each seed takes a core
    for its envs and PEAK_BYTES_PER_SEED of memory."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") if hasattr(os, "sysconf") else None
    fits = min(8 * cores, int(memory // PEAK_BYTES_PER_SEED) if memory else 8 * cores)
    if len(seeds) > max(fits, 1):
        raise cli.ConfigError(f"--seeds: {len(seeds)} seeds do not fit this machine ({cores} cores, "
                              f"{(memory or 0) / 1e9:.0f} GB: about {PEAK_BYTES_PER_SEED / 1e9:.1f} GB and two "
                              f"env workers a seed hold at most {max(fits, 1)}); give fewer, or split them "
                              "across jobs (sweep.py --seeds-per-job)")


def workers(runs) -> bool:
    """Whether the seeds' envs run in worker processes: a group's do, unless $SEAR_ENV_WORKERS=serial."""
    return len(runs) > 1 and os.environ.get(WORKERS, "spawn") != "serial"


class Runs:
    """The loop's seeds' run directories (experiment.RunDir), entered and left together: a Ctrl-C, a
    SIGTERM, a storage error or a value that is not finite stops every seed as it stops one run (a
    snapshot between episodes, one line of what stands), with one line for all."""

    def __init__(self, cfg, run: cli.RunConfig, snapshot: dict | None, seeds=None, group_dir=None):
        self.group_dir, self.seeds = group_dir, seeds
        self.dirs, self.consoles, self.closables = [], [], []  # consoles: a group's console.log files (create())
        # a group's progress line (show_line): the seeds' last returns, (time, frame) of its start (create())
        self.returns, self.began, self.shown = [float("nan")] * len(seeds or ()), None, 0.0
        self.every = min(run.log_every, 1.0) if sys.stdout.isatty() else run.log_every
        if seeds is None:  # one run
            self.dirs = [experiment.RunDir(cfg, run, snapshot)]
            return
        check_size(seeds)
        for k in seeds:
            if group_dir is None:
                member_run, state = run, None
            else:
                path = os.path.join(group_dir, read_group_file(group_dir)["runs"][str(k)])
                state = snapshot if k == seeds[0] else cli.load_snapshot(path)
                if state["counters"]["step"] != snapshot["counters"]["step"]:
                    raise cli.ConfigError(f"--resume: the group's seeds stopped at different steps ({path}): "
                                          "resume each seed's run directory on its own")
                member_run = dataclasses.replace(run, resume=path)
            self.dirs.append(experiment.RunDir(dataclasses.replace(cfg, seed=k), member_run, state))

    def __len__(self):
        return len(self.dirs)

    def __iter__(self):
        return iter(self.dirs)

    def closing(self, thing):
        """`thing` (envs, a sampler thread; None: nothing) is closed when the runs end, however they end."""
        if thing is not None:
            self.closables.append(thing)
        return thing

    def quiet(self, i):
        """What seed i's run dir prints goes to its console.log in a group (the terminal shows the group's)."""
        return contextlib.redirect_stdout(self.consoles[i]) if self.consoles else contextlib.nullcontext()

    def each(self, method: str, *args):
        """RunDir.method(*args) of every seed, each printing where it prints."""
        return [self.call(i, method, *args) for i in range(len(self))]

    def call(self, i, method: str, *args):
        with self.quiet(i):
            return getattr(self.dirs[i], method)(*args)

    # --- start ---
    def __enter__(self):
        for d in self.dirs:
            d.__enter__()
        return self

    def create(self, where: str):
        """Every new seed's run directory (in a new group's folder, with group.json), once the envs are made:
        each seed's config with the suite's action repeat for 0. `where`: the envs and device, said."""
        import envs
        for d in self.dirs:
            d.cfg.action_repeat = d.cfg.action_repeat or envs.default_action_repeat(d.cfg.env)
        if self.seeds is not None and self.group_dir is None:
            cfg, run = self.dirs[0].cfg, self.dirs[0].run
            label = f"{cfg.env}__{cli.method_label(cfg)}__seeds{self.seeds[0]}-{self.seeds[-1]}"
            self.group_dir = experiment.new_run_dir(run.run_root, label)
            for d in self.dirs:
                d.run = dataclasses.replace(run, run_root=self.group_dir)
        for d in self.dirs:
            d.group = self.group_dir
            d.create()
        if self.seeds is not None:
            self.consoles = [open(os.path.join(d.path, "console.log"), "a") for d in self.dirs]
            runs = {str(d.cfg.seed): os.path.basename(d.path) for d in self.dirs}
            cli.write_atomically(os.path.join(self.group_dir, GROUP_FILE),
                                 lambda f: json.dump({"seeds": self.seeds, "runs": runs}, f, indent=2), mode="w")
            self.began, cfg = (time.monotonic(), self.dirs[0].frame), self.dirs[0].cfg
            print(f"group: {len(self)} seeds ({self.seeds[0]}..{self.seeds[-1]}) of {cli.method_label(cfg)} on "
                  f"{cfg.env} in {self.group_dir}; {where}", flush=True)

    def start(self, agents, buffers, rngs) -> list:
        """Each seed's RunDir.start (a resumed seed restored); their counters."""
        return [self.call(i, "start", a, b, r) for i, (a, b, r) in enumerate(zip(agents, buffers, rngs))]

    # --- the loop's calls ---
    def log_updates(self, metrics: list[dict]):
        for d, mine in zip(self.dirs, metrics):
            d.log_update(mine)

    def log_episode(self, i, ep_return, ep_len, ep_success, info):
        self.call(i, "log_episode", ep_return, ep_len, ep_success, info)
        if self.consoles:
            self.returns[i] = ep_return

    def show_step(self, i, ep_len):
        self.call(i, "show_step", ep_len)
        if self.consoles and i == 0:
            self.show_line()

    def show_line(self):
        """The group's one progress line: frame, frames/s of all seeds together, the seeds' last returns."""
        now, cfg, frame = time.monotonic(), self.dirs[0].cfg, self.dirs[0].frame
        if now - self.shown < self.every:
            return
        (start, start_frame), self.shown = self.began, now
        fps = len(self) * (frame - start_frame) / max(now - start, 1e-9)
        done = [r for r in self.returns if r == r]
        print(f"frame {frame}/{cfg.frames} ({100 * frame / cfg.frames:.1f}%) | {fps:.1f} frames/s, "
              f"{len(self)} seeds" + (f" | last returns {min(done):.1f} to {max(done):.1f} "
                                      f"(mean {np.mean(done):.1f})" if done else ""), flush=True)

    def show_eval(self, episode, t):
        """The evaluation's progress: seed 0's run dir's line; a group's line as each episode ends."""
        lead = self.dirs[0].console  # its eval_episode: the episode under way until this call
        if self.consoles and episode != lead.eval_episode:
            print(f"eval {episode}/{lead.eval_episodes} done", flush=True)
        self.call(0, "show_eval", episode, t)

    def say_eval(self, episodes):
        """The group's lines at an evaluation's end: each seed's mean return."""
        whole = self.dirs[0].console.eval_episodes
        if self.consoles and episodes[0]:
            print(f"eval {len(episodes[0])}/{whole} done", flush=True)
        if self.consoles and all(len(e) == whole for e in episodes):
            means = [np.mean([e.ret for e in mine]) for mine in episodes]
            print(f"eval @ frame {self.dirs[0].frame}: mean return over seeds {np.mean(means):.1f} (seeds: "
                  + ", ".join(f"{d.cfg.seed}: {r:.1f}" for d, r in zip(self.dirs, means)) + ")", flush=True)

    def finish(self) -> str:
        self.each("finish")
        if self.consoles:
            print(f"done: {len(self)} seeds in {self.group_dir}")
        return self.group_dir or self.dirs[0].path

    # --- how it stops ---
    def __exit__(self, kind, error, traceback):
        for thing in self.closables:
            with contextlib.suppress(Exception):  # a worker already gone, a thread already stopped
                thing.close()
        try:
            if len(self) == 1:
                return self.dirs[0].__exit__(kind, error, traceback)
            self.stopped(kind, error)
        finally:
            for d in self.dirs:
                d.release()
            for console in self.consoles:
                console.close()

    def stopped(self, kind, error):
        """Every seed's run dir does what it does for a single run; one line for all of them."""
        if kind is None:
            return
        lines, said = [], {}
        for i, d in enumerate(self.dirs):
            try:
                with self.quiet(i):
                    d.stopped(kind, error)
            except (cli.Interrupted, cli.StorageError, cli.NonFinite) as e:
                lines.append(str(e))
                said[d.path] = e
        if issubclass(kind, (cli.StorageError, cli.NonFinite)) and said:  # the seed it happened to says what stands
            raise next((e for p, e in said.items() if p and p in str(error)), next(iter(said.values()))) from None
        if issubclass(kind, KeyboardInterrupt) and lines:
            cause, code = cli.stop_cause(error)
            frames = sorted({d.snapshot_frame for d in self.dirs}, key=lambda f: -1 if f is None else f)
            stands = (f"every seed's snapshot holds frame {frames[0]}" if len(frames) == 1 and frames[0] is not None
                      else f"the seeds' last snapshots stand (frames {', '.join(map(str, frames))})")
            resume = f"continue with: python sear.py --resume {self.group_dir}" if self.group_dir else "nothing to resume"
            raise cli.Interrupted(f"{cause} at frame {self.dirs[0].frame}: {stands}; {resume}", code) from None


def main(argv, Config, methods, train, evaluate) -> int:
    """sear.py's command line: `--seeds SPEC` or `--resume GROUP_DIR` trains a seed group,
    train(cfg, run, snapshot, seeds, group_dir); the rest is cli.main's."""
    try:
        seeds, group_dir, argv = split_argv(argv)
    except cli.ConfigError as e:
        print(f"sear.py: error: {e}", file=sys.stderr)
        return 2
    if seeds is None:
        return cli.main(argv, Config, methods, train, evaluate)

    def train_group(cfg, run, snapshot):
        if run.evaluate:
            raise cli.ConfigError("--evaluate scores one run directory; give one seed's, not --seeds")
        done = group_dir and cli.finished(cfg, run, snapshot, group=group_dir)
        if done:
            # every seed stopped where the first did (Runs checks it when it trains on)
            return print(done)
        return train(cfg, run, snapshot, seeds, group_dir)
    return cli.main(argv, Config, methods, train_group, train_group)
