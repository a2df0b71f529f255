"""Run the paper's grids (seeds x tasks x methods) with sear.py, on one machine or a SLURM cluster.

  python sweep.py --grid kitchen                        # a named grid of the paper (see --help)
  python sweep.py --envs walker-walk cup-catch --methods sear drq --seeds 1-5 -- --frames 100000
  python sweep.py --envs cartpole-balance_sparse --methods drq drq+drm   # METHOD+drm: with --drm
  python sweep.py --grid kitchen --status               # queued / running / done / failed
  python sweep.py --grid kitchen --report               # per task and over the tasks (rliable)
  python sweep.py --grid kitchen --engine slurm --partition gpu   # a SLURM array

Every (env, method, seed, sear.py flags) is a job with a folder of its own: a sweep run again skips
finished jobs, resumes interrupted ones and never runs a job twice at once. submitit starts them
here or as a SLURM array; seeds of a task and method may share a `sear.py --seeds` process. Flags
sweep.py does not know go to sear.py, whose parser checks them before anything is created.
docs/sweeps.md describes the folders, the memory per job and the report.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import csv
import dataclasses
import fcntl
import hashlib
import io
import itertools
import json
import math
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import types
from dataclasses import dataclass
from functools import reduce

import numpy as np
import submitit

import plot
from harness import cli
from harness.process import usable_cores

SEAR_PY = os.path.join(os.path.dirname(os.path.abspath(__file__)), "sear.py")


# ------------------------------------------------------------------------ 1. the paper's grids
@dataclass(frozen=True)
class Variant:
    """One line in a grid's plots: a sear.py --method plus the flags that make the variant."""
    label: str
    method: str
    flags: tuple[str, ...] = ()


@dataclass(frozen=True)
class Grid:
    envs: tuple[str, ...]
    variants: tuple[Variant, ...]
    metric: str                # what the report plots: success (manipulation suites) or return
    doc: str
    # The authors' task cfgs (sear/cfgs/task/{metaworld,kitchen,adroit,distracting}.yaml) all train for
    # num_train_frames 2.5M, the std decaying over 500k agent steps (sear.py's default). Every grid runs the
    # paper's recipe; add `--recipe authors` for the authors' released values.
    flags: tuple[str, ...] = ("--frames", "2500000")   # budgets shared by every run of the grid
    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)


BASELINES = tuple(Variant(m, m) for m in ("sear", "drq", "ae", "mae", "curl"))
DEAR = (Variant("dear", "dear"), Variant("dear-push", "dear", ("--dear-feature", "push")),
        Variant("sear", "sear"), Variant("drq", "drq"))
# The authors' MT10_CUSTOMIZED (sear/environments/metaworld_custom_envs.py), in their order; the ablations run
# on their 3-task subset (MT3_CUSTOMIZED).
METAWORLD10 = ("button-press-topdown-wall", "door-open", "door-unlock", "door-lock", "button-press-wall",
               "assembly", "hammer", "handle-pull", "door-close", "coffee-button")
ABLATION_TASKS = ("button-press-topdown-wall", "door-open", "hammer")
KITCHEN = ("kitchen-kettle", "kitchen-light", "kitchen-slider")
DISTRACTING = ("walker-walk-distracting", "cup-catch-distracting")
GRIDS = {
    "metaworld10": Grid(tuple(f"metaworld-{t}" for t in METAWORLD10), BASELINES, "success",
                        "10 Meta-World tasks (the authors' MT10-customized set)"),
    "kitchen": Grid(KITCHEN, BASELINES, "success", "Franka Kitchen kettle, light, slider"),
    "adroit": Grid(("adroit-door", "adroit-hammer", "adroit-pen", "adroit-relocate"), BASELINES, "success",
                   "the 4 Adroit hand tasks"),
    # distracting.yaml: difficulty medium, background distraction only (sear.py's defaults); walker's 1-step
    # returns and batch 512 are the authors' recipe (--recipe authors).
    "distracting": Grid(DISTRACTING, BASELINES, "return", "Distracting Control walker-walk and cup-catch (add "
                        "--backgrounds davis for the paper's DAVIS videos)"),
    "ablations": Grid(
        tuple(f"metaworld-{t}" for t in ABLATION_TASKS), (
            Variant("sear", "sear"), Variant("drq", "drq"),
            Variant("sear-mask-noise", "sear", ("--mask-noise", "0.25")),
            Variant("sear-mask-approx", "sear", ("--mask-approx",)),
            Variant("rgbm", "rgbm"), Variant("sear-nosplit", "sear-nosplit"),
            # c1/c2 of Eq. 6: the authors' code's values, and each decoder switched off
            Variant("sear-c-authors", "sear", ("--recon-coef", "1.0", "--mask-coef", "0.25")),
            Variant("sear-no-recon", "sear", ("--recon-coef", "0")),
            Variant("sear-no-mask", "sear", ("--mask-coef", "0"))),
        "success", "noisy / approximate masks, rgbm, no split, c1/c2 on 3 Meta-World tasks"),
    # Beyond the paper: DEAR (Pore et al. 2024) on its two benchmarks, with both signs of its cosine term (the
    # released code pulls the halves together, its paper separates them: docs/dear.md).
    "dear": Grid(DISTRACTING, DEAR, "return", "DEAR (both signs) beside SEAR and DrQ-v2 on Distracting Control "
                 "walker-walk, cup-catch"),
    "dear-kitchen": Grid(KITCHEN, DEAR, "success", "DEAR (both signs) beside SEAR and DrQ-v2 on Franka Kitchen "
                         "kettle, light, slider"),
    # What do the masks buy? SEAR learns the robot from simulator masks, Ego-Foresight (foresight.py) from its
    # own motion, DrQ-v2 not at all; EF at its release's latent (hs_dim 2048). One metric for both suites.
    "masks": Grid(("walker-walk-distracting", "metaworld-door-open"), (
        Variant("sear", "sear"), Variant("ef", "ef", ("--latent-dim", "2048")), Variant("drq", "drq")),
        "return", "SEAR (masks) beside Ego-Foresight (no masks) and DrQ-v2 on walker-walk-distracting, "
        "metaworld-door-open"),
}
# Named so that asking for them gives a clear answer instead of "unknown grid".
NOT_YET = {"transfer": "pre-training on metaworld-mt10 and then fine-tuning from it (--init-from) are two "
                       "dependent stages; run them with sear.py as EXPERIMENTS.md, 'Multi-task and transfer', shows"}


# ------------------------------------------------------------------------ 2. from flags to jobs
class SweepError(ValueError):
    """Bad user input: reported as one line on stderr, exit code 2, nothing created."""


@dataclass(frozen=True)
class JobSpec:
    sweep: str                      # folder under --out
    env: str
    variant: str                    # the method, or a grid's variant label
    seed: int
    key: str                        # short hash of the sear.py config's non-default values
    frames: int
    args: tuple[str, ...]           # sear.py arguments of a fresh run (sweep.py adds --run-root)
    resume_args: tuple[str, ...]    # what may change on --resume (device, budget, logging)

    @property
    def name(self) -> str:
        return f"{self.env}__{self.variant}__{self.seed}__{self.key}"


SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")
# sear.py flags that sweep.py sets itself, and what to use instead.
RESERVED = {"--env": "--envs", "--method": "--methods", "--seed": "--seeds", "--run-root": "--out",
            "--resume": "re-running the sweep, which resumes interrupted runs",
            "--evaluate": "python sear.py --evaluate on a run directory of the sweep"}
# Config fields that do not change the experiment, so they do not change the job's key.
UNKEYED = {"env", "method", "seed", "run_root", "resume", "device", "threads", "log_every", "save_buffer",
           "compile", "cuda_graph", "cuda_graphs", "batch_seeds"}


def parse_seeds(tokens: list[str]) -> tuple[int, ...]:
    """'1-5', '1,3,7', '1-3 9' -> seeds in the order given, without repeats."""
    seeds = []
    for tok in re.split(r"[,\s]+", " ".join(tokens).strip()):
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", tok)
        if not m:
            raise SweepError(f"--seeds: '{tok}' is neither a seed nor a range like 1-5")
        if int(m[2] or m[1]) < int(m[1]):
            raise SweepError(f"--seeds: the range '{tok}' is empty")
        seeds += [s for s in range(int(m[1]), int(m[2] or m[1]) + 1) if s not in seeds]
    return tuple(seeds)


def parse_names(tokens: list[str] | None) -> tuple[str, ...] | None:
    return tuple(dict.fromkeys(t for t in re.split(r"[,\s]+", " ".join(tokens)) if t)) if tokens else None


def sear_classes():
    """(Config, METHODS) of the run sear.py starts (train.py's): the one place that names them."""
    import train
    return train.Config, train.METHODS


def check_passthrough(tokens: list[str]) -> None:
    """Exact sear.py flag names only (argparse would take --see for --seed); a typo gets the closest flag."""
    names = [tok.split("=", 1)[0] for tok in tokens if tok.startswith("--")]
    if not names:
        return  # no sear.py import (torch) for --status / --report without flags
    known = cli.flag_names(sear_classes()[0])
    ours = {s for a in build_parser()._actions for s in a.option_strings}
    for name in names:
        if name in RESERVED:
            raise SweepError(f"{name} is set by sweep.py; use {RESERVED[name]}")
        if name in ours:  # only after --: before it, sweep.py's parser takes its own flags
            raise SweepError(f"{name} is sweep.py's, not sear.py's: put it before --")
        if name not in known:
            raise SweepError(cli.no_such_flag(name, known | ours))


def sear_config(argv: list[str], what: str, quiet: bool = False):
    """A run's settings as config.json has them, by sear.py's parser and checks; quiet: no recipe notes."""
    import envs
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(
                io.StringIO() if quiet else sys.stdout):  # argparse prints its error, then exits
            cfg, run, _ = cli.parse_args(argv, *sear_classes())
        envs.default_action_repeat(cfg.env)    # unknown env names fail here, not hours later
    except SystemExit:
        raise SweepError(f"sear.py rejects {what}: {err.getvalue().strip().removeprefix('sear.py: error: ')}")
    except (cli.ConfigError, envs.EnvError) as e:
        raise SweepError(f"sear.py rejects {what}: {e}")
    return types.SimpleNamespace(**cli.config_dict(cfg, run))


def config_key(cfg) -> str:
    """8 hex digits naming what differs from sear.py's defaults: new flags leave old keys alone."""
    defaults = cli.config_dict(sear_classes()[0](), cli.RunConfig())
    diff = {k: v for k, v in vars(cfg).items() if k not in UNKEYED and v != defaults[k]}
    return hashlib.sha1(json.dumps(diff, sort_keys=True).encode()).hexdigest()[:8]


def resume_flags(cfg) -> tuple[str, ...]:
    """The config values a resume may change (cli.RESUME_MAY_CHANGE), as flags."""
    flags = []
    for name in sorted(cli.RESUME_MAY_CHANGE - {"resume"}):
        flag, value = cli.flag(name), getattr(cfg, name)
        flags += ([flag if value else f"--no-{flag[2:]}"] if isinstance(value, bool) else [flag, str(value)])
    return tuple(flags)


def sweep_name(args) -> str:
    """The sweep's folder under --out: --name, else the grid's name, else custom."""
    sweep = args.name or args.grid or "custom"
    if not SAFE_NAME.fullmatch(sweep) or sweep.endswith(".aside"):
        raise SweepError(f"--name '{sweep}' must be letters, digits, '.', '_', '+' or '-' (and not end in .aside)")
    return sweep


def chosen_grid(args) -> Grid | None:
    """The grid --grid names, its --envs and --methods checked against it; None without one."""
    if args.grid in NOT_YET:
        raise SweepError(f"grid '{args.grid}' is not available yet: {NOT_YET[args.grid]}")
    if args.grid and args.grid not in GRIDS:
        raise SweepError(f"unknown grid '{args.grid}'; choose from {', '.join(GRIDS)}")
    if not (args.grid or (args.envs and args.methods)):
        raise SweepError("give --grid NAME, or --envs and --methods")
    grid = GRIDS.get(args.grid)
    if grid:
        check_names(args.grid, "env", args.envs, grid.envs)
        check_names(args.grid, "method", args.methods, [v.label for v in grid.variants])
    return grid


def check_names(grid: str, what: str, given: list[str] | None, have) -> None:
    """--envs / --methods pick from a grid's: one it lacks is an error (NAME+drm is NAME's)."""
    extra = [x for x in parse_names(given) or () if x not in have and cli.split_method_label(x)[0] not in have]
    if extra:
        raise SweepError(f"grid '{grid}' has no {what} {extra[0]}; it has {', '.join(have)}"
                         + (" (each also as NAME+drm)" if what == "method" else ""))


def chosen_variants(args, grid: Grid | None) -> list[Variant]:
    """The variants --methods names (default: the grid's), in the grid's order; NAME+drm adds --drm."""
    wanted = parse_names(args.methods)
    if grid is None:
        variants = [Variant(m, *cli.split_method_label(m)) for m in wanted]
    else:
        with_drm = [(v, Variant(v.label + cli.DRM_SUFFIX, v.method, (*v.flags, "--drm"))) for v in grid.variants]
        variants = [x for pair in with_drm for x in pair if x.label in (wanted or [pair[0].label])]
    for v in variants:
        if not SAFE_NAME.fullmatch(v.label):
            raise SweepError(f"method '{v.label}' cannot name a directory")
    return variants


def plan(args, passthrough: list[str]) -> tuple[str, list[JobSpec], Grid | None]:
    """(sweep name, jobs, grid) from the command line. Checks everything; creates nothing."""
    grid = chosen_grid(args)
    variants, sweep = chosen_variants(args, grid), sweep_name(args)
    seeds = parse_seeds(args.seeds) if args.seeds else (grid.seeds if grid else (1,))
    check_passthrough(passthrough)
    specs = []
    for env in parse_names(args.envs) or grid.envs:
        for v in variants:
            # Grid budgets first, then the variant's settings; the user's flags win. A grid's flag that does
            # nothing for this method is dropped (one line in its log).
            flags = [*(grid.flags if grid else ()), *v.flags, *passthrough]
            base = ["--env", env, "--method", v.method, "--drop-inapplicable"]
            cfg = sear_config([*base, "--seed", str(seeds[0]), *flags], f"{env} {v.label}")
            key, resume = config_key(cfg), resume_flags(cfg)
            specs += [JobSpec(sweep, env, v.label, seed, key, cfg.frames, (*base, "--seed", str(seed), *flags),
                              resume) for seed in seeds]
    return sweep, specs, grid


# ------------------------------------------------------------------------ 3. packs and memory
def seed_spec(seeds) -> str:
    """[1, 2, 3, 5] -> '1-3,5': sear.py's --seeds."""
    runs = [[s for _, s in g] for _, g in itertools.groupby(enumerate(seeds), lambda p: p[1] - p[0])]
    return ",".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs)


@dataclass(frozen=True)
class Pack:
    """What one process runs: a job, or seeds of one (env, variant, key), each seed keeping its job folder."""
    specs: tuple[JobSpec, ...]

    @property
    def seeds(self) -> list[int]:
        return [s.seed for s in self.specs]

    @property
    def name(self) -> str:
        s = self.specs[0]
        return s.name if len(self.specs) == 1 else f"{s.env}__{s.variant}__seeds{seed_spec(self.seeds)}__{s.key}"

    @property
    def args(self) -> tuple[str, ...]:
        args = list(self.specs[0].args)
        if len(self.specs) > 1:
            i = args.index("--seed")
            args[i:i + 2] = ["--seeds", seed_spec(self.seeds)]
        return tuple(args)


def packs(todo: list[JobSpec], k: int, sweep_dir: str) -> list[Pack]:
    """The packs seeds keep (kept_pack); the other seeds of each (env, variant, key) in packs of at most k."""
    units, fresh = {}, {}
    for spec in todo:
        unit = kept_pack(spec, k, sweep_dir)
        if unit is None:
            fresh.setdefault((spec.env, spec.variant, spec.key), []).append(spec)
        units.setdefault(unit.name if unit else spec.name, unit)  # None: its place in the order
    for chunk in (specs[i:i + k] for specs in fresh.values() for i in range(0, len(specs), k)):
        units.update((s.name, Pack(tuple(chunk))) for s in chunk)
    return list({u.name: u for u in units.values()}.values())


def kept_pack(spec: JobSpec, k: int, sweep_dir: str) -> Pack | None:
    """A seed's recorded pack (pack.json), or itself where it ran alone or k is 1; None: pack it anew."""
    recorded = read_json(os.path.join(sweep_dir, spec.name, PACK_FILE))
    if recorded:
        def with_seed(s):
            args = list(spec.args)
            args[args.index("--seed") + 1] = str(s)
            return dataclasses.replace(spec, seed=s, args=tuple(args))
        return Pack(tuple(map(with_seed, recorded["seeds"])))
    return Pack((spec,)) if run_dirs(os.path.join(sweep_dir, spec.name)) or k == 1 else None


def packing_line(units: list[Pack], k: int, why: str) -> str:
    """What the header says of seeds per job: the largest pack that runs, and why it is not k."""
    most = max(len(u.specs) for u in units)
    if most > k:
        why += "; earlier packs keep their seeds"
    if most < k:
        why += f"; at most {cli.plural(most, 'seed')} of a task and method to run"
    return f"{cli.plural(most, 'seed')} per job ({why})"


# What one sear.py run holds, measured (EXPERIMENTS.md, "Memory": VmRSS of a default run on the CPU): 0.89 GB
# until the first update, 2.66 GB at the peak of SEAR's batch-256 updates, the replay still nearly empty; then
# the replay, ReplayBuffer.bytes_per_transition for each transition it holds. The DrQ encoder's methods (drq,
# rgbm) peak 0.65 GB lower (bench_agent.py's peak RSS at batch 256: drq 1.52, sear 2.17 GB); the other
# methods, unmeasured, count as SEAR. What the updates add scales with the batch.
START_GB = 0.89
PEAK_GB = {"pooled": 2.66, "drq": 2.66 - 0.65}  # by sear.METHODS' encoder, at batch 256
# per transition at 84x84 with Adroit's 28 actions, the most of any task (walker: 22,080)
REPLAY_BYTES = 22_168
# one run's peak; another task, renderer or allocator's slack moves it: a quarter more
HEADROOM = 1.25
# Seeds per job on SLURM with GPUs, where the GPU's memory cannot be seen at submission: few enough for any
# GPU a partition of the paper's runs has (4 default runs: about 33 GB by run_memory).
SLURM_SEEDS_PER_JOB, MOST_SEEDS_PER_JOB = 4, 16


def run_memory(cfg) -> tuple[float, float, int, str]:
    """(peak GB, of it the agent's, transitions the replay holds at most, how) of a sear.py run."""
    import envs
    encoder = sear_classes()[1][cfg.method].encoder
    agent = START_GB + (PEAK_GB[encoder] - START_GB) * cfg.batch_size / 256
    held = min(cfg.replay_size, cfg.frames // (cfg.action_repeat or envs.default_action_repeat(cfg.env)))
    scaled = "" if cfg.batch_size == 256 else f" scaled to batch {cfg.batch_size}"
    how = (f"{cfg.method}: {'drq' if encoder == 'drq' else 'sear'}'s measured peak at batch 256{scaled}, "
           f"{agent:.2f} GB, + a replay of {held:,} transitions x {REPLAY_BYTES / 1e3:.0f} kB, "
           f"{held * REPLAY_BYTES / 1e9:.2f} GB, + {HEADROOM - 1:.0%}")
    return agent + held * REPLAY_BYTES / 1e9, agent, held, how


def seeds_per_job(args, engine: str, gpus: int, part: Partition | None, need: float):
    """(seeds per job, why, jobs at a time the GPUs hold or None), by the device and its memory."""
    if args.seeds_per_job:
        return args.seeds_per_job, f"--seeds-per-job {args.seeds_per_job}", None
    if not gpus:
        return 1, "no GPU: one process per seed uses the cores as well; --seeds-per-job packs them", None
    if engine != "local":
        fit = int(part.mem_mb / 1024 // need) if part and part.mem_mb else SLURM_SEEDS_PER_JOB
        k = max(1, min(SLURM_SEEDS_PER_JOB, fit))
        held = f"; a node of {part.name} holds {k} at {need:.1f} GB a seed" if k < SLURM_SEEDS_PER_JOB else ""
        return k, (f"the GPUs' memory is not visible at submission, so a conservative default{held}; "
                   "--seeds-per-job sets it"), None
    import torch
    gpu_gb = min(torch.cuda.get_device_properties(i).total_memory for i in range(len(local_gpus()))) / 2**30
    k = max(1, min(MOST_SEEDS_PER_JOB, int(min(gpu_gb, local_memory_gb()) // need)))
    return k, (f"as many as a GPU's {gpu_gb:.0f} GB and this machine's {local_memory_gb():.0f} GB hold at "
               f"{need:.1f} GB a seed, at most {MOST_SEEDS_PER_JOB}; --seeds-per-job sets it"), (
        max(1, len(local_gpus()) // gpus) if k > 1 else None)


def largest_node(engine: str, part: Partition | None) -> tuple[float | None, str]:
    """(GB, 'where has GB') of the largest node a job may run on; (None, '') when unknown."""
    if engine == "local":
        return local_memory_gb(), f"this machine has {local_memory_gb():.1f} GB"
    if part is None or not part.mem_mb:
        return None, ""
    return part.mem_mb / 1024, f"a node of {part.name} has at most {part.mem_mb / 1024:.1f} GB (sinfo)"


def job_memory(args, node: float | None, have: str, peak: tuple, seeds: int) -> tuple[int, str]:
    """(GB per job, the line that says why): --mem-gb, else the measured peak; too big for a node fails."""
    need = max(1, math.ceil(peak[0] * HEADROOM * seeds))
    how = peak[3] + (f", x {seeds} seeds a job" if seeds > 1 else "")
    if node is not None and (args.mem_gb or need) > node:
        if args.mem_gb:
            raise SweepError(f"--mem-gb {args.mem_gb}: {have}")
        raise SweepError(f"a job needs {need} GB ({how}), but {have}{memory_hint(node, peak, seeds)}")
    why = f"--mem-gb; the estimate is {need} GB" if args.mem_gb else f"{how}; --mem-gb sets it"
    return args.mem_gb or need, f"memory: {args.mem_gb or need} GB per job ({why})" + (f"; {have}" if have else "")


def memory_hint(node: float, peak: tuple, seeds: int) -> str:
    """The --seeds-per-job, else the --replay-size, that fits a node, if one does."""
    peak_gb, agent, held, _ = peak
    fits = int((math.floor(node) / HEADROOM / seeds - agent) * 1e9 / REPLAY_BYTES) // 1000 * 1000
    fewer = int(math.floor(node) // (peak_gb * HEADROOM))
    if 1 <= fewer < seeds:
        return f"; --seeds-per-job {fewer} fits"
    return f"; --replay-size {fits} fits" if 0 < fits < held else ""


def resources(args, engine: str, part: Partition | None, gpus: int, todo: list[JobSpec],
              sweep_dir: str) -> tuple[list[Pack], str, int, int]:
    """(packs, seeds-per-job line, GB per job, jobs at a time here); prints the memory line."""
    distinct = {(s.env, s.variant, s.key): s for s in todo}.values()  # the seed changes nothing
    peak = max(run_memory(sear_config(list(s.args), s.name, quiet=True)) for s in distinct)
    if gpus and not args.seeds_per_job and len(distinct) == len(todo):
        k, k_why, slots = 1, "one seed of each task and method to run", None
    else:
        k, k_why, slots = seeds_per_job(args, engine, gpus, part, peak[0] * HEADROOM)
    units = packs(todo, k, sweep_dir)
    check_pack_size(units, engine)
    node, have = largest_node(engine, part)
    mem_gb, line = job_memory(args, node, have, peak, max(len(u.specs) for u in units))
    parallel = args.jobs or min(max(1, usable_cores() // args.threads), slots or math.inf)
    if engine == "local":
        parallel, line = local_parallel(args, parallel, mem_gb, node, line)
    print(line)
    return units, packing_line(units, k, k_why), mem_gb, parallel


def check_pack_size(units: list[Pack], engine: str) -> None:
    """Here, a pack of more seeds than this machine holds (group.check_size) fails once, up front."""
    from harness import group
    if engine != "local":
        return
    pack = max(units, key=lambda u: len(u.specs))
    try:
        group.check_size(pack.seeds)
    except cli.ConfigError as e:
        raise SweepError(f"{pack.name}: {e}") from None


def local_parallel(args, parallel: int, mem_gb: int, node: float, line: str) -> tuple[int, str]:
    """Jobs at a time here, fewer where memory holds fewer (a --jobs is kept, with a note)."""
    if parallel * mem_gb <= node:
        return parallel, line
    if args.jobs:
        return parallel, f"{line}; --jobs {args.jobs} x {mem_gb} GB is more than that"
    fit = max(1, int(node // mem_gb))  # job_memory refused a job that fits nowhere
    return fit, f"{line}, room for {fit} at a time"


# ------------------------------------------------------------------------ 4. job folders
# A job's folder: job.json (its JobSpec), run/ (sear.py's --run-root), stdout.log and stderr.log, status.json,
# lock, DONE; a seed run in a pack also holds pack.json, {"pack": the pack's folder, "seeds", "seed"}: its run
# is its member of the group folder in the pack's run/.
PACK_FILE = "pack.json"
GROUP_FILE = "group.json"  # group.GROUP_FILE, read here without group.py's torch


def read_json(path: str) -> dict | None:
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):  # absent, or cut short by a crash: as if absent
        return None


def write_json(path: str, data: dict) -> None:
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)  # readers see the old or the new file, never half of one


def proc_start(pid: int) -> int | None:
    """A process's start in clock ticks (tells a reused pid apart); -1 a zombie; None: unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return -1 if fields[0] == "Z" else int(fields[19])


def whoami() -> dict:
    """This process as a lock holder: pid and host, plus the submitit job id inside a job."""
    me = {"pid": os.getpid(), "host": socket.gethostname(), "start": proc_start(os.getpid()), "time": time.time()}
    with contextlib.suppress(RuntimeError):  # not inside a submitit job (the sweep driver itself)
        env = submitit.JobEnvironment()
        me.update(job=env.job_id, cluster=env.cluster)
    return me


def alive(owner: dict | None) -> bool | None:
    """True / False, or None when this machine cannot tell (another host, no squeue)."""
    if not owner:
        return False
    if owner.get("host") == socket.gethostname() and owner.get("pid"):
        return pid_alive(owner["pid"], owner.get("start"))
    if owner.get("cluster") != "slurm" or not owner.get("job") or not shutil.which("squeue"):
        return None
    r = subprocess.run(["squeue", "-h", "-j", owner["job"], "-o", "%T"], capture_output=True, text=True)
    return bool(r.stdout.strip()) if r.returncode == 0 or "Invalid job id" in r.stderr else None


def pid_alive(pid: int, start: int | None) -> bool:
    """Whether `pid` of this host lives and is the process that started at `start`, not a zombie. (Jobs run this
    module's code by value, with no project on their path: the lock's helpers import nothing of harness.)"""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        pass
    now = proc_start(pid)
    return now is None or (now != -1 and start in (None, now))


def describe(owner: dict) -> str:
    where = f"pid {owner['pid']} on {owner['host']}" if owner.get("pid") else ""
    job = f"{owner.get('cluster', '')} job {owner['job']}".strip() if owner.get("job") else ""
    return ", ".join(x for x in (where, job) if x) or "unknown"


@contextlib.contextmanager
def guard(folder: str):
    """Serialises lock take-overs: two processes that both see a stale lock cannot both win."""
    with open(os.path.join(folder, ".guard"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)  # closing the file lets go
        yield


def take_lock(job_dir: str, me: dict) -> dict | None:
    """None if `me` now holds the lock, else the live holder; a dead holder or this requeued job is taken over."""
    with guard(job_dir):
        holder = read_json(os.path.join(job_dir, "lock"))
        requeued = holder and me.get("job") and holder.get("job") == me["job"]
        if holder and not requeued and alive(holder) is not False:
            return holder
        write_json(os.path.join(job_dir, "lock"), me)
    return None


def drop_lock(job_dir: str, me: dict) -> None:
    with guard(job_dir):
        holder = read_json(os.path.join(job_dir, "lock")) or {}
        if (holder.get("pid"), holder.get("host")) == (me["pid"], me["host"]):
            os.remove(os.path.join(job_dir, "lock"))


def run_dirs(job_dir: str) -> list[str]:
    """The job's run directories: its run/'s, or for a packed seed its member of the pack's group folders."""
    pack = read_json(os.path.join(job_dir, PACK_FILE))
    if pack:
        pack_dir = os.path.join(os.path.dirname(os.path.normpath(job_dir)), pack["pack"])
        groups = [(f, (read_json(os.path.join(f, GROUP_FILE)) or {}).get("runs", {}).get(str(pack["seed"])))
                  for f in run_dirs(pack_dir)]
        return [os.path.join(f, m) for f, m in groups if m and os.path.isdir(os.path.join(f, m))]
    root = os.path.join(job_dir, "run")
    return sorted(os.path.join(root, d) for d in os.listdir(root)
                  if os.path.isdir(os.path.join(root, d))) if os.path.isdir(root) else []


def set_status(job_dir: str, state: str, **info) -> None:
    old = read_json(os.path.join(job_dir, "status.json")) or {}
    write_json(os.path.join(job_dir, "status.json"), {
        "state": state, "time": time.strftime("%Y-%m-%d %H:%M:%S"), "attempts": old.get("attempts", 0), **info})


def mark_queued(job_dir: str, by: dict) -> None:
    """Only while no live process holds the job: one that has started (under the same guard) keeps its status."""
    with guard(job_dir):
        if alive(read_json(os.path.join(job_dir, "lock"))) is False:
            set_status(job_dir, "queued", by=by)


def is_done(job_dir: str) -> bool:
    return os.path.exists(os.path.join(job_dir, "DONE"))


def job_state(job_dir: str) -> tuple[str, str]:
    """(state, note): done / running / queued / failed / interrupted / not started."""
    holder = read_json(os.path.join(job_dir, "lock"))
    status = read_json(os.path.join(job_dir, "status.json")) or {}
    state, by = status.get("state"), status.get("by")
    if is_done(job_dir):
        return "done", ""
    if holder and alive(holder) is not False:
        return "running", describe(holder)
    if state == "queued":
        return ("not started", f"its sweep ({describe(by)}) stopped first") if alive(by) is False \
            else ("queued", describe(by))
    if state == "running":  # status says running, but the lock holder is gone
        return "interrupted", "its process is gone; re-run the sweep to resume"
    return (state, status.get("error", "")) if state in ("failed", "interrupted") else ("not started", "")


def status_table(out: str, specs: list[JobSpec]) -> str:
    """A row per job: its state, the last frame its run logged of its budget and a note; then the counts."""
    rows, counts = [("job", "state", "frames", "note")], collections.Counter()
    for spec in specs:
        d = os.path.join(out, spec.sweep, spec.name)
        (state, note), runs = job_state(d), run_dirs(d)
        frame = "0" if runs else "-"
        with contextlib.suppress(OSError, KeyError, IndexError, plot.PlotError):
            frame = plot.read_csv(os.path.join(runs[-1], "train.csv"), "train")[1][-1]["frame"]
        counts[state] += 1
        rows.append((spec.name, state, f"{frame}/{spec.frames}", note))
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    lines = [("  ".join(r[i].ljust(widths[i]) for i in range(3)) + "  " + r[3]).rstrip() for r in rows]
    return "\n".join([*lines, f"{len(specs)} jobs: {', '.join(f'{n} {s}' for s, n in sorted(counts.items()))}"])


# ------------------------------------------------------------------------ 5. the job
class SearJob(submitit.helpers.Checkpointable):
    """A job, or given seed_dirs a pack, as a fresh sear.py process (one that rendered with EGL must not fork a
    renderer) holding every seed's lock. Checkpointable: requeued at the time limit, the same call resumes."""

    def __init__(self, job_dir: str, args: list[str], resume_args: list[str], threads: int, script: str,
                 seed_dirs: list[str] | None = None, devices: str | None = None):
        self.job_dir, self.args, self.resume_args = job_dir, list(args), list(resume_args)
        self.threads, self.script, self.python = threads, script, sys.executable
        self.seed_dirs = list(seed_dirs or [job_dir])  # whose locks and DONE the job takes
        self.devices = devices  # CUDA_VISIBLE_DEVICES for sear.py; None: as given (SLURM sets it)

    def state_dirs(self) -> list[str]:
        """The folders whose status.json says what the job's process did."""
        return list(dict.fromkeys([self.job_dir, *self.seed_dirs]))

    def __call__(self) -> str:
        me, taken = whoami(), []
        try:
            for job_dir in self.seed_dirs:
                holder = take_lock(job_dir, me)
                if holder is not None:
                    return f"skipped: already running ({describe(holder)})"
                taken.append(job_dir)
            return "done" if all(map(is_done, self.seed_dirs)) else self.run(me)
        except KeyboardInterrupt:
            self.set_status("interrupted", error="interrupted; re-run the sweep to resume")
            raise
        finally:
            for held in taken:
                drop_lock(held, me)

    def set_status(self, state: str, **info) -> None:
        for job_dir in self.state_dirs():
            set_status(job_dir, state, **info)

    def run(self, me: dict) -> str:
        """sear.py on the job's run, its output appended to stdout.log and stderr.log."""
        runs = run_dirs(self.job_dir)
        if len(runs) > 1:
            error = f"{self.job_dir}/run holds {len(runs)} runs; move all but one out"
            self.set_status("failed", error=error)
            return f"failed: {error}"
        cmd, moved = self.command(runs[0] if runs else None)
        attempt = (read_json(os.path.join(self.job_dir, "status.json")) or {}).get("attempts", 0) + 1
        self.set_status("running", attempts=attempt, owner=me)
        env = {**os.environ, "OMP_NUM_THREADS": str(self.threads), "MKL_NUM_THREADS": str(self.threads),
               "PYTHONUNBUFFERED": "1", **({} if self.devices is None else {"CUDA_VISIBLE_DEVICES": self.devices})}
        with open(os.path.join(self.job_dir, "stdout.log"), "a") as out, \
                open(os.path.join(self.job_dir, "stderr.log"), "a") as err:
            for f in (out, err):
                f.write(f"=== attempt {attempt} at {time.strftime('%Y-%m-%d %H:%M:%S')}, {describe(me)}: "
                        f"{shlex.join(cmd)}\n")
            out.write(moved)
            out.flush(), err.flush()
            offset = err.tell()
            code = subprocess.run(cmd, stdout=out, stderr=err, env=env, cwd=self.job_dir).returncode
        return self.settle(code, attempt, offset)

    def command(self, run: str | None) -> tuple[list[str], str]:
        """(sear.py's command, a note or ''): resume from the snapshot(s), else start fresh, the run moved aside."""
        members = (read_json(os.path.join(run, GROUP_FILE)) or {}).get("runs", {"": ""}) if run else {}
        if run and all(os.path.exists(os.path.join(run, m, "snapshot.pt")) for m in members.values()):
            return [self.python, self.script, "--resume", run, *self.resume_args], ""
        moved = f"moved the snapshot-less run {run} to {self.move_aside(run)}\n" if run else ""
        return [self.python, self.script, *self.args, "--run-root", os.path.join(self.job_dir, "run")], moved

    def settle(self, code: int, attempt: int, offset: int) -> str:
        """DONE and status done after exit 0; interrupted after SIGTERM; else failed with the last stderr line."""
        if code == 0:
            for job_dir in self.seed_dirs:
                with open(os.path.join(job_dir, "DONE"), "w") as f:
                    f.write(time.strftime("%Y-%m-%d %H:%M:%S\n"))
            self.set_status("done", attempts=attempt, exit_code=0)
            return "done"
        how = f"exit code {code}" if code > 0 else f"killed by signal {-code}"
        if code in (-signal.SIGTERM, 128 + signal.SIGTERM):  # scancel, a time limit, a shutdown
            state, error = "interrupted", f"stopped by SIGTERM ({how}); re-run the sweep to resume"
        else:
            with open(os.path.join(self.job_dir, "stderr.log"), errors="replace") as f:
                f.seek(offset)  # its last line is the error's message
                lines = [ln.strip() for ln in f.read().replace("\r", "\n").splitlines() if ln.strip()]
            state, error = "failed", f"{how}: {lines[-1][:300] if lines else how}"
        self.set_status(state, attempts=attempt, exit_code=code, error=error)
        return f"{state}: {error}"

    def move_aside(self, run: str) -> str:
        """<out>/<sweep>/<job>/run/<run> -> <out>/<sweep>.aside/<job>/<run>, never over an earlier one."""
        sweep_dir, job = os.path.split(os.path.normpath(self.job_dir))
        base = os.path.join(f"{sweep_dir}.aside", job, os.path.basename(run))
        dest = next(d for d in itertools.chain([base], (f"{base}~{k}" for k in itertools.count(1)))
                    if not os.path.exists(d))
        os.makedirs(os.path.dirname(dest), exist_ok=True)
        shutil.move(run, dest)
        return dest


def new_job(sweep_dir: str, unit: Pack, threads: int) -> SearJob:
    """The job of a unit and its folders: each seed's with its job.json (and pack.json), and the pack's."""
    seed_dirs = [os.path.abspath(os.path.join(sweep_dir, spec.name)) for spec in unit.specs]
    for spec, job_dir in zip(unit.specs, seed_dirs):
        os.makedirs(job_dir, exist_ok=True)
        write_json(os.path.join(job_dir, "job.json"), dataclasses.asdict(spec))
        if len(unit.specs) > 1:
            write_json(os.path.join(job_dir, PACK_FILE), {"pack": unit.name, "seeds": unit.seeds, "seed": spec.seed})
    job_dir = os.path.abspath(os.path.join(sweep_dir, unit.name))
    os.makedirs(job_dir, exist_ok=True)
    return SearJob(job_dir, unit.args, unit.specs[0].resume_args, threads, script=SEAR_PY, seed_dirs=seed_dirs)


# ------------------------------------------------------------------------ 6. where the jobs run
def local_memory_gb() -> float:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30


def local_gpus() -> list[str]:
    """The GPUs this machine lets us use, as CUDA_VISIBLE_DEVICES names them."""
    import torch
    n, visible = torch.cuda.device_count(), os.environ.get("CUDA_VISIBLE_DEVICES")
    return [str(i) for i in range(n)] if visible is None else [d.strip() for d in visible.split(",") if d.strip()][:n]


def pick_engine(args) -> tuple[str, str]:
    """(engine, why): --engine, else the folder's record, else local; never SLURM for srun on the PATH."""
    srun = shutil.which("srun") is not None
    recorded, where = recorded_engine(os.path.join(args.out, args.sweep))
    if args.engine:
        engine, why = args.engine, f"--engine {args.engine}"
    elif recorded:
        engine = recorded
        why = f"{where}; --engine {'local runs it here' if recorded == 'slurm' else 'slurm submits it to SLURM'}"
    else:
        engine, why = "local", "default; --engine slurm to submit to SLURM, whose srun is on the PATH" if srun \
            else "default"
    if engine == "slurm" and not srun:
        raise SweepError(f"engine slurm ({why}), but srun is not on this machine's PATH")
    check_flags(args, engine, why)
    return engine, why


def check_flags(args, engine: str, why: str) -> None:
    """Counts below their least, and SLURM's flags on the local engine, fail in one line."""
    for name in ("jobs", "threads", "time_limit", "gpus_per_job", "mem_gb", "seeds_per_job",
                 "slurm_array_parallelism"):
        value, least = getattr(args, name), 0 if name == "gpus_per_job" else 1
        if value is not None and value < least:
            raise SweepError(f"--{name.replace('_', '-')} must be >= {least}, got {value}")
    slurm_only = [f for f in ("partition", "account", "slurm_array_parallelism") if getattr(args, f) is not None]
    if engine != "slurm" and slurm_only:
        raise SweepError(f"--{slurm_only[0].replace('_', '-')} needs SLURM, but the engine is {engine} ({why})")


# What a node of a SLURM partition can give, as sinfo reports it: name for messages ("partition gpu" or "the
# default partition"), the most GPUs, CPUs and memory (MB as SLURM counts them: 1024 a GB) of one node.
Partition = collections.namedtuple("Partition", "name gpus cpus mem_mb")


def sinfo_rows() -> list[list[str]]:
    """sinfo's rows, [partition (the default one ends in *), GPUs, CPUs, memory MB]; none without sinfo."""
    try:
        r = subprocess.run(["sinfo", "-h", "--all", "-o", "%P|%G|%c|%m"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [ln.split("|") for ln in r.stdout.splitlines() if ln.count("|") == 3] if r.returncode == 0 else []


def slurm_partition(partition: str | None) -> Partition | None:
    """`partition` (None: the cluster's default one) from sinfo; None when sinfo cannot tell."""
    rows = sinfo_rows()
    names = list(dict.fromkeys(row[0].rstrip("*") for row in rows))
    if rows and partition is not None and partition not in names:
        raise SweepError(f"SLURM has no partition '{partition}' (sinfo lists {', '.join(names)})")
    mine = [row[1:] for row in rows if (row[0].rstrip("*") == partition if partition else row[0].endswith("*"))]
    return Partition(f"partition {partition}" if partition else "the default partition",
                     *most_of_a_node(mine)) if mine else None


def most_of_a_node(rows: list[list[str]]) -> tuple[int, int, int]:
    """(GPUs, CPUs, MB) of the largest node in sinfo's rows (%G 'gpu:a100:8(S:0-1)', %c '64+', 'n/a')."""
    gpus = [sum(map(int, re.findall(r"(?:^|,)gpu(?::[^:,(]+)?:(\d+)", row[0]))) for row in rows]
    cpus, mem = ([int(re.match(r"\d*", row[i])[0] or 0) for row in rows] for i in (1, 2))
    return max(gpus), max(cpus), max(mem)


def job_gpus(args, engine: str, part: Partition | None) -> tuple[int, str]:
    """(GPUs per job, what the header says): default 1 where there are GPUs; more than a node has fails."""
    asked = args.gpus_per_job
    if engine == "local":
        have = len(local_gpus())
        if asked is not None and asked > have:
            raise SweepError(f"--gpus-per-job {asked}: this machine has {have} GPU(s)"
                             + ("; --gpus-per-job 0 runs on the CPU" if have == 0 else ""))
        gpus = min(1, have) if asked is None else asked
        return gpus, f"{gpus} of {have} GPU(s) per job" if have else "no GPU"
    if part is None:  # sinfo cannot tell: the paper's runs need a GPU; sbatch has the last word
        gpus = 1 if asked is None else asked
        return gpus, f"{gpus} GPU(s) per job"
    return partition_gpus(args, part)


def partition_gpus(args, part: Partition) -> tuple[int, str]:
    """job_gpus on SLURM where sinfo describes the partition's nodes."""
    asked = args.gpus_per_job
    if part.cpus and args.threads > part.cpus:  # pending for ever
        raise SweepError(f"--threads {args.threads}: the nodes of {part.name} have at most {part.cpus} CPUs "
                         "(sinfo), so the jobs would never start")
    if asked is not None and asked > part.gpus:
        have = f"at most {part.gpus} GPU(s)" if part.gpus else "no GPUs; --gpus-per-job 0 runs on their CPUs"
        raise SweepError(f"--gpus-per-job {asked}: the nodes of {part.name} have {have} (sinfo)")
    gpus = min(1, part.gpus) if asked is None else asked
    return gpus, f"{gpus} GPU(s) per job" if part.gpus else f"no GPU, as {part.name} has none"


# ------------------------------------------------------------------------ 7. submitit
def refusal(error: Exception, stderr: str, jobs: int, mem_gb: int) -> SweepError:
    """sbatch's reason for refusing the array, in one line, with a hint where one helps."""
    lines = [ln.strip() for ln in (str(error) or stderr).splitlines() if ln.strip()]
    reason = "; ".join(ln.removeprefix("sbatch: error: ") for ln in lines) or type(error).__name__
    hint = ""
    if re.search(r"gres|gpu", reason, re.I):
        hint = " (--gpus-per-job 0 submits without a GPU request)"
    elif re.search(r"memory|node configuration", reason, re.I):
        hint = f" (each job asks {mem_gb} GB: does a node have it? --mem-gb sets it)"
    return SweepError(f"sbatch refused the {jobs} job(s): {reason[:300]}{hint}")


def submit(executor, jobs: list[SearJob], mem_gb: int, engine: str, sweep_dir: str) -> int:
    """The jobs as one SLURM array, each job folder recording its array task."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), executor.batch():  # submitit prints sbatch's stderr
            submitted = [executor.submit(job) for job in jobs]
    except (submitit.core.utils.FailedJobError, submitit.core.utils.FailedSubmissionError, OSError) as e:
        raise refusal(e, err.getvalue(), len(jobs), mem_gb) from None
    for job, task in zip(jobs, submitted):
        for job_dir in job.state_dirs():
            mark_queued(job_dir, {"cluster": engine, "job": task.job_id})
    print(f"submitted {len(submitted)} jobs ({submitted[0].job_id.split('_')[0]}); follow them with --status, "
          f"draw the curves with --report; logs in {sweep_dir}/<job>/")
    return 0


def job_devices(gpus: int, have: list[str], slots: int) -> list[str]:
    """CUDA_VISIBLE_DEVICES of each local job slot: `gpus` per job, round robin over `have`."""
    return [",".join(have[(s * gpus + i) % len(have)] for i in range(gpus)) for s in range(slots)]


def outcome(job) -> str:
    try:
        return job.result()
    except Exception as e:  # the job process itself failed (e.g. killed): its last line says why
        return "failed: " + (str(e).strip().splitlines() or [type(e).__name__])[-1][:300]


def run_local(executor, jobs: dict, devices: list[str]) -> dict:
    """Start the jobs one per slot at a time, the one in slot k on devices[k]; {unit: outcome}."""
    pending, running, results, free = list(jobs), {}, {}, list(range(len(devices)))
    try:
        while pending or running:
            while pending and free:
                unit, slot = pending.pop(0), free.pop(0)
                jobs[unit].devices = devices[slot]
                running[unit] = executor.submit(jobs[unit]), slot, time.time()
            time.sleep(0.2)
            for unit, (job, slot, started) in [(u, r) for u, r in running.items() if r[0].done()]:
                del running[unit]
                free = sorted([*free, slot])
                results[unit] = outcome(job)
                print(f"[{len(results)}/{len(jobs)}] {unit.name}: {results[unit]} ({time.time() - started:.0f} s)",
                      flush=True)
    except KeyboardInterrupt:
        for job, _, _ in running.values():
            job.cancel(check=False)
        raise
    return results


# ------------------------------------------------------------------------ 8. a sweep's record
# <out>/<sweep>/sweep.json: {"engine", "sweeps": [{"grid", "flags", "command", "jobs"}]}, an entry per grid and
# sear.py flags submitted to the folder, its jobs those of every submission with them; "engine" the one the
# folder's sweeps last ran on, and run on again unless --engine.
RECORD = "sweep.json"


def read_record(sweep_dir: str) -> list[dict]:
    return (read_json(os.path.join(sweep_dir, RECORD)) or {}).get("sweeps", [])


def recorded_engine(sweep_dir: str) -> tuple[str | None, str]:
    """(engine, where it is written) of a sweep folder: its record, else jobs that went to SLURM."""
    engine = (read_json(os.path.join(sweep_dir, RECORD)) or {}).get("engine")
    if engine in ("local", "slurm"):
        return engine, f"{os.path.join(sweep_dir, RECORD)} records it"
    for spec in folder_specs(sweep_dir):
        status = read_json(os.path.join(sweep_dir, spec.name, "status.json")) or {}
        if any((status.get(k) or {}).get("cluster") == "slurm" for k in ("by", "owner")):
            return "slurm", f"the jobs in {sweep_dir} went to SLURM"
    return None, ""


def record_sweep(sweep_dir: str, args, specs: list[JobSpec], engine: str) -> None:
    """Add `specs` to the folder's record, in the entry of their grid and sear.py flags."""
    os.makedirs(sweep_dir, exist_ok=True)
    with guard(sweep_dir):  # two drivers submitting to one folder at once both end up in the record
        sweeps = read_record(sweep_dir)
        entry = next((e for e in sweeps if (e["grid"], e["flags"]) == (args.grid, args.flags)), None) or {
            "grid": args.grid, "flags": list(args.flags), "jobs": []}
        sweeps += [] if entry in sweeps else [entry]
        entry["command"] = list(args.argv)
        jobs = {j["name"]: j for j in entry["jobs"]}
        jobs.update({s.name: {"name": s.name, **dataclasses.asdict(s)} for s in specs})
        entry["jobs"] = list(jobs.values())
        write_json(os.path.join(sweep_dir, RECORD), {"engine": engine, "sweeps": sweeps})
    if len(sweeps) > 1:
        print(f"note: {sweep_dir} now holds {len(sweeps)} sweeps (other grids or sear.py flags); --status and "
              "--report then need the sweep's flags after -- to pick one")


def as_specs(jobs: list[dict]) -> list[JobSpec]:
    fields = [f.name for f in dataclasses.fields(JobSpec)]
    return [JobSpec(**{k: tuple(j[k]) if isinstance(j[k], list) else j[k] for k in fields}) for j in jobs]


def folder_specs(sweep_dir: str) -> list[JobSpec]:
    """The jobs a sweep folder holds, from their job.json (folders from before sweep.json)."""
    names = sorted(os.listdir(sweep_dir)) if os.path.isdir(sweep_dir) else []
    return as_specs([j for j in (read_json(os.path.join(sweep_dir, n, "job.json")) for n in names) if j])


def listed(args, verb: str, sweep: str, entries: list[dict]) -> str:
    """The sweep.py commands that show each sweep of a folder, with how many jobs each has."""
    def command(entry):
        grid, flags = entry.get("grid"), entry.get("flags")
        line = ["python", "sweep.py", *(["--out", args.out] if args.out != "sweeps" else []),
                *(["--grid", grid] if grid else []), *(["--name", sweep] if sweep != (grid or "custom") else []),
                f"--{verb}", *(["--", *flags] if flags else [])]
        return shlex.join(line) + (f" ({cli.plural(len(entry['jobs']), 'job')})" if "jobs" in entry else "")
    return "; ".join(map(command, entries))


def flag_set(flags: list[str]) -> list[tuple[str, ...]]:
    """Flags as a sorted list of (--name, values...): --frames=40 is --frames 40, in any order."""
    pairs = []
    for tok in (p for flag in flags for p in (flag.split("=", 1) if flag.startswith("--") else [flag])):
        pairs += [(tok,)] if tok.startswith("--") or not pairs else [(*pairs.pop(), tok)]
    return sorted(pairs)


def find_sweep(args, verb: str) -> tuple[list[JobSpec], Grid | None]:
    """--status / --report: the recorded jobs of the sweep in --out/--name (or --grid), or its job.json's."""
    sweep = sweep_name(args)
    folder = os.path.join(args.out, sweep)
    entries = read_record(folder)
    if entries:
        entry = pick_entry(args, verb, sweep, folder, entries)
        return select(args, as_specs(entry["jobs"]), folder), GRIDS.get(entry["grid"])
    if folder_specs(folder):
        return select(args, folder_specs(folder), folder), None
    names = [n for n in sorted(os.listdir(args.out)) if read_record(os.path.join(args.out, n))
             or folder_specs(os.path.join(args.out, n))] if os.path.isdir(args.out) else []
    holds = "; ".join(listed(args, verb, n, [{}]) for n in names)
    raise SweepError(f"no sweep in {folder}; {args.out} holds " + (
        f"{', '.join(names)}: {holds}" if names else "no sweep yet"))


def pick_entry(args, verb: str, sweep: str, folder: str, entries: list[dict]) -> dict:
    """The recorded sweep --grid and the flags after -- name (none: the one without flags, or the only one)."""
    chosen, same = matching(args, entries)
    if not chosen:
        raise SweepError(f"{folder} holds no sweep of grid {args.grid}; it holds: "
                         f"{listed(args, verb, sweep, entries)}")
    if args.flags and not same:
        raise SweepError(f"{folder} holds no sweep run with `-- {shlex.join(args.flags)}`; it holds: "
                         f"{listed(args, verb, sweep, chosen)}")
    if len(chosen) > 1 and len(same) != 1:
        raise SweepError(f"{folder} holds {len(chosen)} sweeps, show one: {listed(args, verb, sweep, chosen)}")
    if len(chosen) > 1:
        print(f"note: {folder} also holds: {listed(args, verb, sweep, [e for e in chosen if e is not same[0]])}")
    return (same or chosen)[0]


def matching(args, entries: list[dict]) -> tuple[list[dict], list[dict]]:
    """The recorded sweeps of --grid (all without it), and of those the ones run with the flags after --."""
    chosen = [e for e in entries if e["grid"] == args.grid] if args.grid else entries
    return chosen, [e for e in chosen if flag_set(e["flags"]) == flag_set(args.flags)]


def select(args, specs: list[JobSpec], folder: str) -> list[JobSpec]:
    """The jobs --envs / --methods / --seeds pick from a sweep."""
    wanted = (parse_names(args.envs), parse_names(args.methods), parse_seeds(args.seeds) if args.seeds else None)
    picked = [s for s in specs if all(w is None or x in w for w, x in zip(wanted, (s.env, s.variant, s.seed)))]
    if not picked:
        have = [", ".join(map(str, dict.fromkeys(getattr(s, f) for s in specs))) for f in ("env", "variant", "seed")]
        raise SweepError(f"the sweep in {folder} has none of these jobs: it has envs {have[0]}; methods {have[1]}; "
                         f"seeds {have[2]}")
    return picked


# ------------------------------------------------------------------------ 9. report
DM_CONTROL_STEPS = 1000  # control steps of a dm_control episode, each rewarded in [0, 1]


def dm_control_max(config: dict) -> float:
    """The highest return of a dm_control episode: 1 per control step (--max-episode-steps cuts them)."""
    steps = config.get("max_episode_steps") or 0
    return float(min(DM_CONTROL_STEPS, steps * config.get("action_repeat", 1)) if steps else DM_CONTROL_STEPS)


def normalisation(env: str, runs: list[dict], metric: str) -> tuple[list[tuple[float, float]], str]:
    """(low, high) of each run's scores, to compare across tasks, and what the report says of it."""
    import envs
    if metric == "success":
        return [(0.0, 1.0)] * len(runs), "success rate, as it is"
    if envs._parse_name(env)[0] in ("dmc", "distracting"):
        highs = [dm_control_max(r["config"]) for r in runs]
        most = " or ".join(f"{h:g}" for h in sorted(set(highs)))
        return [(0.0, h) for h in highs], f"return / {most} (dm_control's maximum: 1 per control step)"
    values = np.concatenate([r["values"] for r in runs])
    lo, hi = float(values.min()), float(values.max())
    if hi == lo:
        return [(lo, lo + 1.0)] * len(runs), f"min-max over this sweep, but every return is {lo:.4g}: all 0"
    return [(lo, hi)] * len(runs), f"min-max over this sweep: (return - {lo:.4g}) / ({hi:.4g} - {lo:.4g})"


def finished_runs(out: str, specs: list[JobSpec], metric: str | None) -> tuple[str, dict, int]:
    """(metric, {(env, variant): {seed: plot.load_run()}} of the finished runs, how many finished)."""
    finished = [(s, run_dirs(os.path.join(out, s.sweep, s.name))) for s in specs
                if is_done(os.path.join(out, s.sweep, s.name))]
    finished = [(s, runs[0]) for s, runs in finished if len(runs) == 1]
    metric = metric or report_metric([r for _, r in finished])
    runs = {}
    for spec, run in finished:
        try:
            runs.setdefault((spec.env, spec.variant), {})[spec.seed] = plot.load_run(run, "eval", metric)
        except plot.PlotError as e:
            print(f"report: skipping {spec.name}: {e}")
    return metric, runs, len(finished)


def report_metric(runs: list[str]) -> str:
    """A success rate where every run has one, else the return."""
    def has_success(run):
        with contextlib.suppress(OSError), open(os.path.join(run, "eval.csv"), newline="") as f:
            return "success" in (next(csv.reader(f), None) or [])
    return "success" if runs and all(map(has_success, runs)) else "return"


def normalised(runs: dict, envs: list[str], metric: str) -> tuple[dict, dict]:
    """Per task how its scores are normalised, and {(env, variant): {seed: (frames, scores)}}."""
    how, norm = {}, {}
    for env in envs:
        members = [(k, seed, r) for k, by_seed in runs.items() if k[0] == env for seed, r in by_seed.items()]
        bounds, how[env] = normalisation(env, [r for _, _, r in members], metric)
        for (k, seed, r), (lo, hi) in zip(members, bounds):
            norm.setdefault(k, {})[seed] = (r["frames"], (r["values"] - lo) / (hi - lo))
    return how, norm


def across_tasks(norm: dict, envs: list[str], variants: list[str]) -> tuple[dict, list[str]]:
    """rliable's IQM and mean over the tasks, stratified-bootstrap 95% CIs: the panel's lines, table rows."""
    from scipy import stats

    def iqm_and_mean(x):  # rliable's aggregate_iqm (scipy's trim_mean, 25% off each end) and mean, per frame
        flat = x.reshape(-1, x.shape[-1])
        return np.concatenate([stats.trim_mean(flat, 0.25, axis=0), flat.mean(axis=0)])
    shared = {v: shared_scores(norm, envs, v) for v in variants}
    shared = {v: s for v, s in shared.items() if s[2] is not None}
    point, ci = plot.bootstrap({v: s[2] for v, s in shared.items()}, iqm_and_mean) if shared else ({}, {})
    lines, rows = {}, []
    for v, (seeds, frames, _) in shared.items():
        f, runs = len(frames), f"{cli.plural(len(seeds), 'seed')} x {cli.plural(len(envs), 'task')}"
        lines[v] = (frames, point[v][:f], ci[v][:, :f], np.full(f, len(seeds)), f"over {cli.plural(len(envs), 'task')}")
        iqm, mean = (f"{point[v][i]:.3f} [{ci[v][0, i]:.3f}, {ci[v][1, i]:.3f}]" for i in (f - 1, 2 * f - 1))
        rows.append(f"| {v} | {runs} | {frames[-1]:.0f} | {iqm} | {mean} |")
    return lines, rows


def shared_scores(norm: dict, envs: list[str], v: str):
    """(seeds, frames, scores) of a method's seeds finished on every task at their shared evaluations."""
    seeds = sorted(set.intersection(*(set(norm.get((e, v), {})) for e in envs)))
    curves = [norm[(e, v)][s] for s in seeds for e in envs]
    frames = reduce(np.intersect1d, [f for f, _ in curves]) if seeds else np.array([])
    if seeds and not len(frames):
        print(f"report: {v}: its runs share no evaluation frame; left out of the aggregate")
    if not len(frames):
        return seeds, frames, None
    values = [y[np.isin(f, frames)] for f, y in curves]
    return seeds, frames, np.array(values).reshape(len(seeds), len(envs), len(frames))


def report(out: str, sweep: str, specs: list[JobSpec], metric: str | None) -> str | None:
    """Writes <out>/<sweep>/report.png and report.md of the finished runs; returns the tables."""
    metric, runs, finished = finished_runs(out, specs, metric)
    envs = [e for e in dict.fromkeys(s.env for s in specs) if any(k[0] == e for k in runs)]
    if not envs:
        print("report: no finished runs yet")
        return None
    variants = list(dict.fromkeys(s.variant for s in specs))
    panels = {env: task_lines(runs, env, variants) for env in envs}
    how, norm = normalised(runs, envs, metric)
    lines, rows = across_tasks(norm, envs, variants)
    draw_report(os.path.join(out, sweep, "report.png"), sweep, metric, panels, lines)
    tables = "\n\n".join([plot.summary_table(panels, metric), "\n".join([
        "| method | runs | last frame | IQM [95% CI] | mean [95% CI] |", "|---|---|---|---|---|", *rows]),
        "\n".join(["| task | normalised score |", "|---|---|", *(f"| {e} | {how[e]} |" for e in envs)])])
    note = (f"{finished} of {len(specs)} jobs finished; only finished runs count. Per task: the mean over seeds "
            "of the raw scores with its 95% percentile-bootstrap CI. Over the tasks: IQM and mean of the scores "
            "normalised per task (last table), with 95% stratified-bootstrap CIs over the seeds finished on "
            f"every task (rliable, {plot.BOOTSTRAP_REPS} resamples).")
    with open(os.path.join(out, sweep, "report.md"), "w") as f:
        f.write(f"# {sweep}\n\n{note}\n\n![curves](report.png)\n\n{tables}\n")
    print(f"{tables}\n\n{note}\nwrote {os.path.join(out, sweep, 'report.png')} and report.md")
    return tables


def draw_report(png: str, sweep: str, metric: str, panels: dict, lines: dict) -> None:
    """report.png: a panel per task (raw scores), and one of the IQM over the tasks."""
    overall = f"over {cli.plural(len(panels), 'task')}"
    ylabel = f"eval {'success rate' if metric == 'success' else 'return'}"
    plot.plot({**panels, overall: lines} if lines else panels, png, ylabel,
              f"{sweep}: {ylabel} per task; over the tasks, the IQM of scores normalised per task to 0-1 "
              "(report.md says how)", ylabels={overall: "IQM of normalised score"},
              estimates={**{e: "mean ± 95% CI over seeds" for e in panels},
                         overall: "IQM, stratified-bootstrap 95% CI"})


def task_lines(runs: dict, env: str, variants: list[str]) -> dict:
    """A task's panel: each method's mean over its finished seeds and its CI (plot.aggregate)."""
    lines = {}
    for v in (v for v in variants if runs.get((env, v))):
        curves = [(r["frames"], r["values"]) for r in runs[(env, v)].values()]
        lines[v] = (*plot.aggregate(curves), plot.coverage(curves), env)
    return lines


# ------------------------------------------------------------------------ 10. command line
def build_parser() -> argparse.ArgumentParser:
    """sweep.py's flags; a bad one is a cli.ConfigError (one line). No abbreviations: --seed is sear.py's."""
    p = cli.OneLineParser(prog="sweep.py", allow_abbrev=False, description=__doc__,
                          formatter_class=argparse.RawDescriptionHelpFormatter,
                          epilog="Unknown flags, and everything after --, go to sear.py.")
    what = p.add_argument_group("what to run")
    what.add_argument("--grid", help="a named grid of the paper: " + "; ".join(
        f"{name}: {g.doc}" for name, g in GRIDS.items()) + "; transfer: not available yet")
    what.add_argument("--envs", nargs="+", help="tasks (with --grid: a subset of the grid's)")
    what.add_argument("--methods", nargs="+", help="sear.py methods (with --grid: a subset of its variants); "
                      "METHOD+drm runs METHOD with --drm (drq+drm is DrM)")
    what.add_argument("--seeds", nargs="+", help="1-5, 1,3,7 or 1-3 9 (default: the grid's, or 1)")
    what.add_argument("--name", help="sweep folder under --out (default: the grid's name, custom)")
    what.add_argument("--out", help="folder of sweeps (default: sweeps; --status and --report in a sweep's "
                      "folder: that folder)")
    do = p.add_argument_group("what to do (default: run what is not finished)")
    do.add_argument("--status", action="store_true", help="print the jobs' states and exit")
    do.add_argument("--report", action="store_true", help="draw report.png / report.md and exit")
    do.add_argument("--dry-run", action="store_true", help="print the jobs' sear.py commands only")
    eng = p.add_argument_group("engine (submitit: this machine, or a SLURM array)")
    eng.add_argument("--engine", choices=("local", "slurm"),
                     help="default: the one the sweep's folder records (sweep.json), else local")
    eng.add_argument("--jobs", type=int, help="local: jobs at a time (default: cores // --threads)")
    eng.add_argument("--threads", type=int, default=1, help="torch threads per job (default 1)")
    eng.add_argument("--time-limit", type=int, default=4300, help="minutes per job (default 4300, the authors')")
    eng.add_argument("--gpus-per-job", type=int, help="default: 1 where the partition (sinfo) or this machine has "
                     "GPUs, else 0; here each job gets its own, round robin")
    eng.add_argument("--mem-gb", type=int, help="memory per job (default: a measured run's peak for the job's "
                     "method, batch and replay, + 25%%); here it bounds the jobs at a time")
    eng.add_argument("--seeds-per-job", type=int, help="seeds of one task and method as one `sear.py --seeds` "
                     "process where the method allows (default: as many as this machine's GPU holds, at most 16; "
                     "4 on SLURM with GPUs, fewer where a node holds fewer; 1 without a GPU)")
    eng.add_argument("--partition", help="SLURM partition")
    eng.add_argument("--account", help="SLURM account")
    eng.add_argument("--slurm-array-parallelism", type=int, help="SLURM: array tasks at a time")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    try:
        args, unknown = build_parser().parse_known_args(argv[:cut])
        args.flags, args.argv = unknown + argv[cut + 1:], argv
        check_passthrough(args.flags)  # first: --stauts is a typo of --status, whatever else
        if not (args.status or args.report):
            args.out = args.out or "sweeps"
            args.sweep, specs, grid = plan(args, args.flags)
            return run(args, specs, grid and grid.metric, *pick_engine(args))
        specs, grid = submitted_sweep(args)
        if args.status:
            print(status_table(args.out, specs))
        else:
            report(args.out, args.sweep, specs, grid and grid.metric)
        return 0
    except (SweepError, cli.ConfigError) as e:
        print(f"sweep.py: error: {e}", file=sys.stderr)
        return 2


def submitted_sweep(args) -> tuple[list[JobSpec], Grid | None]:
    """--status / --report: the sweep --out and --name name, else the sweep folder this is run in."""
    if args.out is None and args.name is None and (os.path.exists(RECORD) or folder_specs(".")):
        args.out, args.name = os.path.split(os.getcwd())
    args.out, args.sweep = args.out or "sweeps", sweep_name(args)
    return find_sweep(args, "status" if args.status else "report")


def run(args, specs: list[JobSpec], metric: str | None, engine: str, why: str) -> int:
    """Run the jobs neither done nor running elsewhere, here or on SLURM; 1 if one run here failed."""
    sweep_dir = os.path.join(args.out, args.sweep)
    done, busy, todo = job_states(specs, sweep_dir)
    part = slurm_partition(args.partition) if engine == "slurm" else None
    gpus, where = job_gpus(args, engine, part)
    print(f"engine: {engine} ({why})")
    units, packing, mem_gb, parallel = resources(args, engine, part, gpus, todo, sweep_dir) \
        if todo else ([], "", args.mem_gb, 0)
    if engine == "local" and parallel:
        where = f"{parallel} at a time, {args.threads} thread(s) each, {where}"
    header(args, specs, (done, busy, todo), units, f"{engine}, {where}", packing)
    if args.dry_run:
        print("\n".join(f"{u.name}: sear.py {shlex.join(u.args)}" for u in units))
        return 0
    record_sweep(sweep_dir, args, specs, engine)
    if todo:
        return launch(args, specs, metric, engine, (units, gpus, mem_gb, parallel))
    if engine == "local" and not busy:
        report(args.out, args.sweep, specs, metric)
    return 0


def job_states(specs: list[JobSpec], sweep_dir: str) -> tuple[list, list, list]:
    """(done, running elsewhere, to run) of a sweep's jobs."""
    done = [s for s in specs if is_done(os.path.join(sweep_dir, s.name))]
    busy = [s for s in specs if s not in done
            and alive(read_json(os.path.join(sweep_dir, s.name, "lock"))) is not False]
    return done, busy, [s for s in specs if s not in done and s not in busy]


def header(args, specs: list[JobSpec], states: tuple, units: list[Pack], where: str, packing: str) -> None:
    """The line that says what the sweep holds, what runs where, and the seeds per job."""
    done, busy, todo = states
    shape = (f"{len({s.env for s in specs})} envs x {len({s.variant for s in specs})} methods x "
             f"{len({s.seed for s in specs})} seeds")
    grouped = f" in {len(units)} process{'es' if len(units) != 1 else ''}" \
        if any(len(u.specs) > 1 for u in units) else ""
    print(f"sweep {args.sweep}: {len(specs)} jobs ({shape}): {len(done)} done, {len(busy)} running elsewhere, "
          f"{len(todo)} to run{grouped} ({where})" + (f"; {packing}" if packing else ""), flush=True)


def launch(args, specs: list[JobSpec], metric: str | None, engine: str, plan_: tuple) -> int:
    """The packs' jobs through submitit: one SLURM array (this process only submits), or here."""
    units, gpus, mem_gb, parallel = plan_
    sweep_dir = os.path.join(args.out, args.sweep)
    jobs = {u: new_job(sweep_dir, u, args.threads) for u in units}
    executor = submitit.AutoExecutor(folder=os.path.join(sweep_dir, ".submitit"), cluster=engine)
    params = dict(timeout_min=args.time_limit, name=f"sweep-{args.sweep}", mem_gb=mem_gb, cpus_per_task=args.threads,
                  # locally SearJob.devices gives each job its GPUs; submitit's gives all the same first ones
                  gpus_per_node=0 if engine == "local" else gpus or None,  # on SLURM none asked without GPUs
                  slurm_partition=args.partition, slurm_account=args.account,
                  slurm_array_parallelism=args.slurm_array_parallelism)
    executor.update_parameters(**{k: v for k, v in params.items() if v is not None})
    if SearJob.__module__ != "__main__":  # imported: ship this module's code with the jobs, so that they need
        import cloudpickle                # no `import sweep` from whatever their cwd is
        cloudpickle.register_pickle_by_value(sys.modules[SearJob.__module__])
    if engine != "local":
        return submit(executor, list(jobs.values()), mem_gb, engine, sweep_dir)
    return run_here(args, specs, metric, executor, jobs, job_devices(gpus, local_gpus(), parallel))


def run_here(args, specs: list[JobSpec], metric: str | None, executor, jobs: dict, devices: list[str]) -> int:
    """The jobs on this machine, then the report; 1 if one failed, 130 on Ctrl-C."""
    driver = whoami()
    for job_dir in (d for job in jobs.values() for d in job.state_dirs()):
        mark_queued(job_dir, driver)
    try:
        results = run_local(executor, jobs, devices)
    except KeyboardInterrupt:
        print("\ninterrupted: re-run the same command to continue (finished runs are kept, interrupted ones "
              "resume from their last snapshot)", file=sys.stderr)
        return 130
    outcomes = [r for u, r in results.items() for _ in u.specs]  # a pack's is each seed's
    failed = sum(r.startswith(("failed", "interrupted")) for r in outcomes)
    print(f"{len(outcomes) - failed} of {len(outcomes)} jobs finished"
          + (f"; {failed} failed (see --status)" if failed else ""))
    report(args.out, args.sweep, specs, metric)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
