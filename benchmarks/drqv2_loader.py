"""sear.py with its replay batches drawn the way the official DrQ-v2's replay loader draws them, worker
split included: a diagnostic for EXPERIMENTS.md "Rung PC", not a mode of sear.py.

    MUJOCO_GL=egl python benchmarks/drqv2_loader.py [--workers 4] -- --env cartpole-balance_sparse ...
    MUJOCO_GL=egl python benchmarks/drqv2_loader.py -- --resume RUN_DIR

Everything after `--` is sear.py's flags. sear.ReplayBuffer draws as the official loader's
ReplayBuffer._sample does (drqv2 replay_buffer.py; docs/replay.md): ended episodes only, an episode
uniformly, then a start from which all n steps lie inside it. What the official loader (a torch
DataLoader over an IterableDataset with replay_buffer_num_workers=4) adds, and this sampler does too:
a batch comes whole from one worker, and worker w holds only the episodes whose index is w modulo the
worker count (an episode of fewer than n steps, on which the official loader fails, keeps its index
but is never drawn); batches come from the workers in turn.
`python benchmarks/official_compare.py loader --official DRQV2` shows the official loader's batches
beside this sampler's on the same episodes.
What it leaves out: each worker re-reads the episode files every 1000 samples and runs two batches
ahead, so an ended episode reaches the batches ~20-50 agent steps later there.

The run directory gets a drqv2_loader.json; --resume through this script needs it (resume such a run
through this script only: sear.py itself would continue without the worker split).
"""
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402
from harness import experiment  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402

MARKER = "drqv2_loader.json"


class LoaderReplay(sear.ReplayBuffer):
    """sear.ReplayBuffer, sampled as the official loader samples: its workers' episodes in turn."""
    workers = 4       # the official replay_buffer_num_workers
    update_every = 2  # agent steps per update: which worker's turn it is follows from the step

    def worker_episodes(self):
        """(first slot, last possible start) of each ended episode the current batch's worker holds."""
        if self.t > self.capacity:
            raise cli.ConfigError("drqv2_loader.py: the replay ring has wrapped; give a --replay-size "
                                  "above the run's agent steps plus its episodes")
        firsts = np.flatnonzero(self.first[:self.t])  # each episode's reset slot, oldest first
        step = self.t - len(firsts)                    # agent steps so far (each episode adds a reset slot)
        ended_first, ended_last = firsts[:-1], firsts[1:] - 1  # the newest episode is still running
        last_start = ended_last - self.nstep           # all n steps inside the episode
        index = np.arange(len(ended_first))
        mine = (index % self.workers == (step // self.update_every) % self.workers) & (last_start >= ended_first)
        if not mine.any():  # fewer ended episodes than workers: the official loader would fail here
            mine = last_start >= ended_first
        return ended_first[mine], last_start[mine]

    def draw_starts(self, n, rng: np.random.Generator, lo):
        first, last_start = self.worker_episodes()
        e = rng.integers(0, len(first), size=n)  # an episode uniformly, then a start in it
        return first[e] + rng.integers(0, last_start[e] - first[e] + 1)


def install(workers):
    """sear.py trains with LoaderReplay: its buffer class, the run dir's marker (checked on --resume)
    and the resume command that an interrupted run prints."""
    LoaderReplay.workers = workers
    train.ReplayBuffer = LoaderReplay  # train.train builds its buffer from this name
    create, train_run, interrupted = experiment.RunDir.create, train.train, experiment.interrupt_message

    def create_marked(rundir):
        resumed = rundir.path is not None
        if resumed:
            marker = os.path.join(rundir.path, MARKER)
            if not os.path.isfile(marker):
                raise cli.ConfigError(f"--resume: '{rundir.path}' was not trained by drqv2_loader.py (no {MARKER})")
            with open(marker) as f:
                LoaderReplay.workers = int(json.load(f)["workers"])  # the run's own, whatever --workers says
        create(rundir)
        if not resumed:
            with open(os.path.join(rundir.path, MARKER), "w") as f:
                json.dump({"workers": workers}, f)

    def train_loader(cfg, run, snapshot=None):
        LoaderReplay.update_every = cfg.update_every
        return train_run(cfg, run, snapshot)

    def interrupt_message(*a, **k):  # resumed through sear.py, the run would go on without the workers
        return interrupted(*a, **k).replace("python sear.py --resume", "python benchmarks/drqv2_loader.py -- --resume")

    experiment.RunDir.create, train.train, experiment.interrupt_message = create_marked, train_loader, interrupt_message


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    ours, sear_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    p = cli.OneLineParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, default=4, help="the official replay_buffer_num_workers")
    try:
        args = p.parse_args(ours)
    except cli.ConfigError as e:
        print(f"drqv2_loader.py: {e}", file=sys.stderr)
        return 2
    if args.workers < 1 or not sear_args:
        print("drqv2_loader.py: give --workers 1 or more and sear.py's flags after --", file=sys.stderr)
        return 2
    install(args.workers)
    return train.main(sear_args)


if __name__ == "__main__":
    sys.exit(main())
