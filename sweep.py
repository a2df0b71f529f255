"""Run the paper's grids (seeds x tasks x methods) with sear.py, on one machine or a SLURM cluster.

Every (env, method, seed, flags) is one job with its own deterministic directory, so a sweep can be
stopped and started again at any time: finished runs are skipped, interrupted ones resume from
their last snapshot, and no key ever runs twice at once.

Usage:
  python sweep.py --grid kitchen                        # a named grid of the paper (see --help)
  python sweep.py --envs walker-walk cup-catch --methods sear drq --seeds 1-5 -- --frames 100000
  python sweep.py --envs cartpole-balance_sparse --methods drq drq+drm sear sear+drm
                                                        # METHOD+drm: METHOD with --drm
  python sweep.py --grid kitchen --methods sear sear+drm    # a grid's variant, and with --drm
  python sweep.py --grid kitchen --status               # queued / running / done / failed (the
                                                        # flags the sweep ran with need not be
                                                        # repeated: sweep.json has them)
  python sweep.py --grid kitchen --report               # per task mean +- 95% CI; over tasks IQM
                                                        # (rliable)
  cd sweeps/kitchen && python ../../sweep.py --status   # inside a sweep's folder: that sweep
  python sweep.py --grid kitchen --engine slurm --partition gpu   # a SLURM array; re-runs of the
                                                        # sweep stay on SLURM (sweep.json); default:
                                                        # this machine

Flags that sweep.py does not know go to sear.py (after `--` or anywhere on the line); sear.py's
own parser checks them before anything is created, so a typo fails the whole sweep at once. A flag
neither has is named with the closest of both: "no flag --stauts; did you mean --status?".
Memory per job (SLURM's --mem; locally, how many run at once): a measured run's peak for the job's
method, batch and replay, plus 25% (--mem-gb sets it); a job that no node holds fails up front.

Sweep folder: <out>/<sweep>/ (--name; default the grid's name, else custom)
  sweep.json    the record of what was submitted there: per sweep (grid and sear.py flags) its
                jobs, so that --status and --report need only the folder (--name or --grid), not
                the flags again; and the engine the folder's sweeps ran on, which a re-run without
                --engine keeps
Job directory: <out>/<sweep>/<env>__<method>__<seed>__<hash of the other sear.py flags>/
  job.json      what the job is: the sear.py arguments of a fresh run and of a resume
  run/          sear.py's --run-root: exactly one run directory
  pack.json     only for a seed run in a pack: {"pack": its folder, "seeds", "seed"}; its run is then
                the seed's run in the pack's group folder, its status.json, lock and DONE the pack
                process's, its logs in the pack's folder
  stdout.log    sear.py's stdout, after a "=== attempt" header line at every start; stderr.log
                likewise
  status.json   queued | running | done | failed | interrupted, the exit code, the last stderr line
  lock          pid, host and job id of the process that runs the job (a dead holder is taken over)
  DONE          written after sear.py exits 0: a re-run skips the job
Pack directory: <out>/<sweep>/<env>__<method>__seeds<seeds>__<hash>/ (--seeds-per-job: seeds of one
  task and method in one `sear.py --seeds` process, group.py; default: as many as this machine's GPU
  holds, 4 on SLURM with GPUs, 1 without a GPU; a method group.py cannot batch runs one seed a job)
  run/          sear.py's --run-root: one group folder (group.json, a run directory per seed)
  stdout.log, stderr.log, status.json   the process's, as a job's; the lock and DONE are each seed's
  A seed keeps its pack when the sweep runs again (with any --seeds-per-job): the pack resumes with
  `sear.py --resume <group folder>`; a seed that ran alone stays alone.
A snapshot-less run that failed is moved, untouched, to <out>/<sweep>.aside/ before a clean restart
(a pack's group folder without every seed's snapshot too).

Sections: 1. the paper's grids  2. from flags to jobs  3. job directories: lock, status, the run
          4. the job  5. engines  6. status table  7. report  8. CLI
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
import warnings
from dataclasses import dataclass

import numpy as np
import submitit

HERE = os.path.dirname(os.path.abspath(__file__))
SEAR_PY = os.path.join(HERE, "sear.py")


# ================================================================================================
# 1. The paper's grids
# ================================================================================================
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
    flags: tuple[str, ...]     # budgets shared by every run of the grid
    metric: str                # what the report plots: success (manipulation suites) or return
    doc: str
    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)


def plain(*methods):
    return tuple(Variant(m, m) for m in methods)


def pick_variants(wanted: tuple[str, ...] | None, have: tuple[Variant, ...]) -> list[Variant]:
    """A grid's variants named in `wanted` (all if None), in the grid's order; NAME+drm is variant
    NAME run with --drm (drm.py: DrQ becomes DrM, SEAR becomes SEAR + DrM)."""
    from harness import cli  # stdlib only, as sear_config's imports: late
    picked = []
    for v in have:
        if wanted is None or v.label in wanted:
            picked.append(v)
        if wanted is not None and v.label + cli.DRM_SUFFIX in wanted:
            picked.append(Variant(v.label + cli.DRM_SUFFIX, v.method, (*v.flags, "--drm")))
    return picked


BASELINES = plain("sear", "drq", "ae", "mae", "curl")
DEAR = (Variant("dear", "dear"), Variant("dear-push", "dear", ("--dear-feature", "push")), *plain("sear", "drq"))
# The authors' task cfgs (sear/cfgs/task/{metaworld,kitchen,adroit,distracting}.yaml) all train for
# num_train_frames 2.5M with the exploration std decaying over 500k agent steps (sear.py's default).
# Every grid runs the paper's recipe; add `--recipe authors` for the authors' released values.
PAPER_FRAMES = ("--frames", "2500000")
# The authors' MT10_CUSTOMIZED (sear/environments/metaworld_custom_envs.py), in their order.
METAWORLD10 = ("button-press-topdown-wall", "door-open", "door-unlock", "door-lock", "button-press-wall",
               "assembly", "hammer", "handle-pull", "door-close", "coffee-button")
# The ablations run on the authors' 3-task subset of those (their MT3_CUSTOMIZED).
ABLATION_TASKS = ("button-press-topdown-wall", "door-open", "hammer")

GRIDS = {
    "metaworld10": Grid(
        envs=tuple(f"metaworld-{t}" for t in METAWORLD10), variants=BASELINES, flags=PAPER_FRAMES,
        metric="success", doc="10 Meta-World tasks (the authors' MT10-customized set)"),
    "kitchen": Grid(
        envs=("kitchen-kettle", "kitchen-light", "kitchen-slider"), variants=BASELINES,
        flags=PAPER_FRAMES, metric="success", doc="Franka Kitchen kettle, light, slider"),
    "adroit": Grid(
        envs=("adroit-door", "adroit-hammer", "adroit-pen", "adroit-relocate"), variants=BASELINES,
        flags=PAPER_FRAMES, metric="success", doc="the 4 Adroit hand tasks"),
    "distracting": Grid(
        envs=("walker-walk-distracting", "cup-catch-distracting"), variants=BASELINES,
        # distracting.yaml: difficulty medium, background distraction only (sear.py's defaults);
        # walker's 1-step returns and batch 512 are the authors' recipe (--recipe authors).
        flags=PAPER_FRAMES, metric="return",
        doc="Distracting Control walker-walk and cup-catch (add --backgrounds davis for the "
            "paper's DAVIS videos)"),
    "ablations": Grid(
        envs=tuple(f"metaworld-{t}" for t in ABLATION_TASKS), flags=PAPER_FRAMES, metric="success",
        variants=(Variant("sear", "sear"), Variant("drq", "drq"),
                  Variant("sear-mask-noise", "sear", ("--mask-noise", "0.25")),
                  Variant("sear-mask-approx", "sear", ("--mask-approx",)),
                  Variant("rgbm", "rgbm"), Variant("sear-nosplit", "sear-nosplit"),
                  # c1/c2 of Eq. 6: the authors' code's values, and each decoder switched off
                  Variant("sear-c-authors", "sear", ("--recon-coef", "1.0", "--mask-coef", "0.25")),
                  Variant("sear-no-recon", "sear", ("--recon-coef", "0")),
                  Variant("sear-no-mask", "sear", ("--mask-coef", "0"))),
        doc="noisy / approximate masks, rgbm, no split, c1/c2 on 3 Meta-World tasks"),
    # Beyond the paper: DEAR (Pore et al. 2024) on its two benchmarks, with both signs of its cosine
    # term (the released code pulls the halves together, its paper separates them: docs/dear.md).
    "dear": Grid(
        envs=("walker-walk-distracting", "cup-catch-distracting"), variants=DEAR, flags=PAPER_FRAMES,
        metric="return", doc="DEAR (both signs) beside SEAR and DrQ-v2 on Distracting Control "
                             "walker-walk, cup-catch"),
    "dear-kitchen": Grid(
        envs=("kitchen-kettle", "kitchen-light", "kitchen-slider"), variants=DEAR, flags=PAPER_FRAMES,
        metric="success", doc="DEAR (both signs) beside SEAR and DrQ-v2 on Franka Kitchen kettle, light, slider"),
    # What do the masks buy? SEAR learns the robot from simulator masks, Ego-Foresight (foresight.py) from its own
    # motion, DrQ-v2 not at all; EF at its release's latent (hs_dim 2048). One metric for both suites: return.
    "masks": Grid(
        envs=("walker-walk-distracting", "metaworld-door-open"), flags=PAPER_FRAMES, metric="return",
        variants=(Variant("sear", "sear"), Variant("ef", "ef", ("--latent-dim", "2048")), Variant("drq", "drq")),
        doc="SEAR (masks) beside Ego-Foresight (no masks) and DrQ-v2 on walker-walk-distracting, metaworld-door-open"),
}
# Named so that asking for them gives a clear answer instead of "unknown grid".
NOT_YET = {"transfer": "pre-training on metaworld-mt10 and then fine-tuning from it (--init-from) "
                       "are two dependent stages; run them with sear.py as EXPERIMENTS.md, "
                       "'Multi-task and transfer', shows"}


# ================================================================================================
# 2. From flags to jobs
# ================================================================================================
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
UNKEYED = {"env", "method", "seed", "run_root", "resume", "device", "threads", "log_every", "save_buffer", "compile",
           "cuda_graphs"}


def parse_seeds(tokens: list[str]) -> tuple[int, ...]:
    """'1-5', '1,3,7', '1-3 9' -> seeds in the order given, without repeats."""
    seeds = []
    for tok in re.split(r"[,\s]+", " ".join(tokens).strip()):
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", tok)
        if not m:
            raise SweepError(f"--seeds: '{tok}' is neither a seed nor a range like 1-5")
        lo, hi = int(m[1]), int(m[2] or m[1])
        if hi < lo:
            raise SweepError(f"--seeds: the range '{tok}' is empty")
        seeds += [s for s in range(lo, hi + 1) if s not in seeds]
    return tuple(seeds)


def parse_names(tokens: list[str]) -> tuple[str, ...]:
    names = []
    for tok in re.split(r"[,\s]+", " ".join(tokens).strip()):
        if tok and tok not in names:
            names.append(tok)
    return tuple(names)


def sear_classes():
    """(Config, METHODS) of the run sear.py starts (train.py's): the one place that names the module
    holding them."""
    import train
    return train.Config, train.METHODS


def sear_flag_names() -> set[str]:
    """Every flag sear.py's parser has: one per Config field, plus --no-X for booleans."""
    from harness import cli
    return cli.flag_names(sear_classes()[0])


def sweep_flag_names() -> set[str]:
    return {s for a in build_parser()._actions for s in a.option_strings if s.startswith("--")}


def check_passthrough(tokens: list[str]) -> None:
    """Exact sear.py flag names only: argparse would take an abbreviation such as --see for --seed.
    A name neither sweep.py nor sear.py has is answered with the closest of both: --stauts is a typo
    of --status, not a sear.py flag."""
    if not any(tok.startswith("--") for tok in tokens):
        return  # no sear.py import (torch) for --status / --report without flags
    known, ours = sear_flag_names(), sweep_flag_names()
    for tok in tokens:
        if not tok.startswith("--"):
            continue
        name = tok.split("=", 1)[0]
        if name in RESERVED:
            raise SweepError(f"{name} is set by sweep.py; use {RESERVED[name]}")
        if name in known:
            continue
        if name in ours:  # only after --: before it, sweep.py's parser takes its own flags
            raise SweepError(f"{name} is sweep.py's, not sear.py's: put it before --")
        from harness import cli
        raise SweepError(cli.no_such_flag(name, known | ours))


def sear_config(argv: list[str], what: str):
    """sear.py's own parser and checks on argv (nothing is created), and the env name by envs.py."""
    from harness import cli
    import envs
    Config, methods = sear_classes()
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):  # argparse prints its one-line error, then exits
            cfg, run, _ = cli.parse_args(argv, Config, methods)
        envs.default_action_repeat(cfg.env)    # unknown env names fail here, not hours later
    except SystemExit:
        raise SweepError(f"sear.py rejects {what}: "
                         f"{err.getvalue().strip().removeprefix('sear.py: error: ')}")
    except (cli.ConfigError, envs.EnvError) as e:
        raise SweepError(f"sear.py rejects {what}: {e}")
    # every setting, as config.json has them
    return types.SimpleNamespace(**cli.config_dict(cfg, run))


def config_key(cfg) -> str:
    """8 hex digits naming what differs from sear.py's defaults: new sear.py flags leave old keys
    alone."""
    from harness import cli
    defaults = cli.config_dict(sear_classes()[0](), cli.RunConfig())
    diff = {k: v for k, v in vars(cfg).items() if k not in UNKEYED and v != defaults[k]}
    return hashlib.sha1(json.dumps(diff, sort_keys=True).encode()).hexdigest()[:8]


def resume_flags(cfg) -> tuple[str, ...]:
    """The config values a resume may change (cli.RESUME_MAY_CHANGE), as flags."""
    from harness import cli
    flags = []
    for name in sorted(cli.RESUME_MAY_CHANGE - {"resume"}):
        flag, value = "--" + name.replace("_", "-"), getattr(cfg, name)
        if isinstance(value, bool):
            flags.append(flag if value else "--no-" + flag[2:])
        else:
            flags += [flag, str(value)]
    return tuple(flags)


def plural(n: int, word: str) -> str:
    return f"{n} {word}{'s' * (n != 1)}"


def sweep_name(args) -> str:
    """The sweep's folder under --out: --name, else the grid's name, else custom."""
    sweep = args.name or args.grid or "custom"
    if not SAFE_NAME.fullmatch(sweep) or sweep.endswith(".aside"):
        raise SweepError(f"--name '{sweep}' must be letters, digits, '.', '_', '+' or '-' (and not "
                         "end in .aside)")
    return sweep


def plan(args, passthrough: list[str]) -> tuple[str, list[JobSpec], Grid | None]:
    """(sweep name, jobs, grid) from the command line. Checks everything; creates nothing."""
    from harness import cli
    grid = None
    if args.grid:
        if args.grid in NOT_YET:
            raise SweepError(f"grid '{args.grid}' is not available yet: {NOT_YET[args.grid]}")
        if args.grid not in GRIDS:
            raise SweepError(f"unknown grid '{args.grid}'; choose from {', '.join(GRIDS)}")
        grid = GRIDS[args.grid]
    elif not (args.envs and args.methods):
        raise SweepError("give --grid NAME, or --envs and --methods")
    sweep = sweep_name(args)

    envs = parse_names(args.envs) if args.envs else None
    wanted = parse_names(args.methods) if args.methods else None
    seeds = parse_seeds(args.seeds) if args.seeds else (grid.seeds if grid else (1,))
    if grid:  # --envs and --methods pick from the grid's lists
        for given, have, what in ((envs, grid.envs, "env"), (wanted, [v.label for v in grid.variants], "method")):
            extra = [x for x in (given or ()) if x not in have and cli.split_method_label(x)[0] not in have]
            if extra:
                raise SweepError(f"grid '{args.grid}' has no {what} {extra[0]}; it has "
                                 f"{', '.join(have)}"
                                 + (" (each also as NAME+drm)" if what == "method" else ""))
        envs = envs or grid.envs
        variants = pick_variants(wanted, grid.variants)
    else:
        variants = [Variant(m, *cli.split_method_label(m)) for m in wanted]
    for v in variants:
        if not SAFE_NAME.fullmatch(v.label):
            raise SweepError(f"method '{v.label}' cannot name a directory")
    check_passthrough(passthrough)

    specs = []
    for env in envs:
        for v in variants:
            # Grid budgets first, then the variant's settings; the user's flags win.
            # a flag given for the grid that does nothing for this method is dropped (one line in its log)
            flags = [*(grid.flags if grid else ()), *v.flags, *passthrough]
            base = ["--env", env, "--method", v.method, "--drop-inapplicable"]
            cfg = sear_config([*base, "--seed", str(seeds[0]), *flags], f"{env} {v.label}")
            key, resume = config_key(cfg), resume_flags(cfg)
            for seed in seeds:
                specs.append(JobSpec(sweep, env, v.label, seed, key, cfg.frames,
                                     (*base, "--seed", str(seed), *flags), resume))
    return sweep, specs, grid


def seed_spec(seeds) -> str:
    """[1, 2, 3, 5] -> '1-3,5': sear.py's --seeds (group.parse_seeds reads it)."""
    parts, start = [], 0
    for i, seed in enumerate(seeds):
        if i + 1 == len(seeds) or seeds[i + 1] != seed + 1:
            parts.append(str(seeds[start]) if i == start else f"{seeds[start]}-{seed}")
            start = i + 1
    return ",".join(parts)


def with_seed(spec: JobSpec, seed: int) -> JobSpec:
    """The same job for another seed."""
    args = list(spec.args)
    args[args.index("--seed") + 1] = str(seed)
    return dataclasses.replace(spec, seed=seed, args=tuple(args))


@dataclass(frozen=True)
class Pack:
    """Seeds of one (env, variant, key) run as one `sear.py --seeds` process (group.py); each seed
    keeps its own job directory, the process has the pack's."""
    specs: tuple[JobSpec, ...]

    @property
    def seeds(self) -> list[int]:
        return [s.seed for s in self.specs]

    @property
    def name(self) -> str:
        s = self.specs[0]
        return f"{s.env}__{s.variant}__seeds{seed_spec(self.seeds)}__{s.key}"

    @property
    def args(self) -> tuple[str, ...]:
        args = list(self.specs[0].args)
        i = args.index("--seed")
        args[i:i + 2] = ["--seeds", seed_spec(self.seeds)]
        return tuple(args)


def pack_refusal(spec: JobSpec) -> str | None:
    """Why the job's configuration cannot run as a seed group (group.refusal), or None."""
    from harness import group
    with contextlib.redirect_stdout(io.StringIO()):  # the recipe's notes, printed once already by plan()
        cfg = sear_config(list(spec.args), spec.name)
    return group.refusal(cfg, cfg)


def packs(todo: list[JobSpec], k: int, sweep_dir: str) -> list:
    """The jobs to run: a Pack of each seed's recorded pack (pack.json), a JobSpec of each seed whose
    folder holds a single run, and the other seeds of each (env, variant, key) in order in packs of at
    most k (a pack of 1, or of a configuration group.refusal refuses: single jobs, with one line)."""
    units, fresh, refused = {}, {}, set()
    for spec in todo:
        recorded = read_json(os.path.join(sweep_dir, spec.name, PACK_FILE))
        if recorded:
            unit = Pack(tuple(with_seed(spec, s) for s in recorded["seeds"]))
            units.setdefault(unit.name, unit)
        elif run_dirs(os.path.join(sweep_dir, spec.name)) or k == 1:
            units[spec.name] = spec
        else:
            fresh.setdefault((spec.env, spec.variant, spec.key), []).append(spec)
            units[spec.name] = None  # its place in the order
    for (_, variant, _), specs in fresh.items():
        for i in range(0, len(specs), k):
            chunk = specs[i:i + k]
            why = pack_refusal(chunk[0]) if len(chunk) > 1 else None
            if why and variant not in refused:
                print(f"packing: {variant} runs one seed per job: {why}")
                refused.add(variant)
            unit = Pack(tuple(chunk)) if len(chunk) > 1 and not why else None
            for spec in chunk:
                units[spec.name] = unit or spec
    return list({id(u): u for u in units.values()}.values())


# ================================================================================================
# 3. Job directories: lock, status, the run
# ================================================================================================
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


def proc_stat(pid: int) -> list[str]:
    """/proc/<pid>/stat after the command name (Linux; [] elsewhere): [0] is the state, [19] the
    start time in clock ticks since boot, which tells a reused pid apart."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return []


def process_start(pid: int) -> int | None:
    fields = proc_stat(pid)
    return int(fields[19]) if len(fields) > 19 else None


def whoami() -> dict:
    """This process as a lock holder: pid and host, plus the submitit job id inside a job."""
    me = {"pid": os.getpid(), "host": socket.gethostname(), "start": process_start(os.getpid()), "time": time.time()}
    try:
        env = submitit.JobEnvironment()
        me.update(job=env.job_id, cluster=env.cluster)
    except RuntimeError:  # not inside a submitit job (the sweep driver itself)
        pass
    return me


def slurm_job_alive(job_id: str) -> bool | None:
    if shutil.which("squeue") is None:
        return None
    r = subprocess.run(["squeue", "-h", "-j", job_id, "-o", "%T"], capture_output=True, text=True)
    return bool(r.stdout.strip()) if r.returncode == 0 or "Invalid job id" in r.stderr else None


def alive(owner: dict | None) -> bool | None:
    """True / False, or None when this machine cannot tell (another host, no squeue)."""
    if not owner:
        return False
    if owner.get("host") == socket.gethostname() and owner.get("pid"):
        try:
            os.kill(owner["pid"], 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # someone else's live process
            return True
        fields = proc_stat(owner["pid"])
        if fields[:1] == ["Z"]:  # killed, not yet reaped by its parent
            return False
        start = int(fields[19]) if len(fields) > 19 else None
        return start is None or owner.get("start") in (None, start)
    if owner.get("cluster") == "slurm" and owner.get("job"):
        return slurm_job_alive(owner["job"])
    return None


def describe(owner: dict) -> str:
    where = f"pid {owner['pid']} on {owner['host']}" if owner.get("pid") else ""
    job = f"{owner.get('cluster', '')} job {owner['job']}".strip() if owner.get("job") else ""
    return ", ".join(x for x in (where, job) if x) or "unknown"


@contextlib.contextmanager
def guard(job_dir: str):
    """Serialises lock take-overs: two processes that both see a stale lock cannot both win."""
    with open(os.path.join(job_dir, ".guard"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def take_lock(job_dir: str, me: dict) -> dict | None:
    """None if `me` now holds the job's lock, else the live holder. A holder that is dead, or
    this very SLURM job before a requeue, is taken over."""
    path = os.path.join(job_dir, "lock")
    with guard(job_dir):
        holder = read_json(path)
        requeued = holder and me.get("job") and holder.get("job") == me["job"]
        if holder and not requeued and alive(holder) is not False:
            return holder
        write_json(path, me)
    return None


def drop_lock(job_dir: str, me: dict) -> None:
    path = os.path.join(job_dir, "lock")
    with guard(job_dir):
        holder = read_json(path)
        if holder and holder.get("pid") == me["pid"] and holder.get("host") == me["host"]:
            os.remove(path)


# A seed's job directory run by a pack holds pack.json, {"pack": the pack's folder, "seeds": its
# seeds, "seed": this folder's}; its run is the seed's member of the group folder in the pack's run/.
PACK_FILE = "pack.json"
GROUP_FILE = "group.json"  # group.GROUP_FILE, read here without group.py's torch


def run_dirs(job_dir: str) -> list[str]:
    """The job's run directories: those in its run/, or, for a seed run by a pack, the seed's run
    inside the pack's group folder."""
    pack = read_json(os.path.join(job_dir, PACK_FILE))
    if pack:
        return member_runs(os.path.join(os.path.dirname(os.path.normpath(job_dir)), pack["pack"]), pack["seed"])
    root = os.path.join(job_dir, "run")
    if not os.path.isdir(root):
        return []
    return sorted(os.path.join(root, d) for d in os.listdir(root) if os.path.isdir(os.path.join(root, d)))


def member_runs(pack_dir: str, seed: int) -> list[str]:
    """The run directories of `seed` in the group folders of a pack's run/ (their group.json)."""
    runs = []
    for folder in run_dirs(pack_dir):
        members = (read_json(os.path.join(folder, GROUP_FILE)) or {}).get("runs", {})
        if str(seed) in members and os.path.isdir(os.path.join(folder, members[str(seed)])):
            runs.append(os.path.join(folder, members[str(seed)]))
    return runs


def last_line(path: str, offset: int = 0) -> str:
    """The last non-empty line of a log from `offset` on: an error's last line is its message."""
    try:
        with open(path, errors="replace") as f:
            f.seek(offset)
            lines = [ln.strip() for ln in f.read().replace("\r", "\n").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""


def set_status(job_dir: str, state: str, **info) -> None:
    old = read_json(os.path.join(job_dir, "status.json")) or {}
    write_json(os.path.join(job_dir, "status.json"),
               {"state": state, "time": time.strftime("%Y-%m-%d %H:%M:%S"),
                "attempts": old.get("attempts", 0), **info})


def mark_queued(job_dir: str, by: dict) -> None:
    """Under the guard, and only while no live process holds the job: a job that has already
    started (its lock is taken under the same guard) keeps its own status."""
    with guard(job_dir):
        if alive(read_json(os.path.join(job_dir, "lock"))) is False:
            set_status(job_dir, "queued", by=by)


def is_done(job_dir: str) -> bool:
    return os.path.exists(os.path.join(job_dir, "DONE"))


# The sweep folder's record (sweep.json): {"engine", "sweeps": [{"grid", "flags", "command",
# "jobs"}]}, one entry per grid and sear.py flags submitted to the folder, its jobs the JobSpecs of
# every submission with them; "engine" (local or slurm) the one the folder's sweeps last ran on, and
# run on again unless --engine.
RECORD = "sweep.json"


def read_record(sweep_dir: str) -> list[dict]:
    return (read_json(os.path.join(sweep_dir, RECORD)) or {}).get("sweeps", [])


def recorded_engine(sweep_dir: str) -> tuple[str | None, str]:
    """(engine, where it is written) of a sweep folder: its record, else (folders from before the
    record named it) a job queued or run on SLURM; (None, "") for a new folder."""
    engine = (read_json(os.path.join(sweep_dir, RECORD)) or {}).get("engine")
    if engine in ("local", "slurm"):
        return engine, f"{os.path.join(sweep_dir, RECORD)} records it"
    for name in sorted(os.listdir(sweep_dir)) if os.path.isdir(sweep_dir) else []:
        status = read_json(os.path.join(sweep_dir, name, "status.json")) or {}
        if any((status.get(k) or {}).get("cluster") == "slurm" for k in ("by", "owner")):
            return "slurm", f"the jobs in {sweep_dir} went to SLURM"
    return None, ""


def record_sweep(sweep_dir: str, grid: str | None, flags: list[str], command: list[str], specs: list[JobSpec],
                 engine: str) -> int:
    """Add `specs` to the folder's record, under their grid and sear.py flags: the same sweep run
    again (say for more seeds) adds its jobs to its entry; other flags make a second entry. ->
    sweeps recorded."""
    os.makedirs(sweep_dir, exist_ok=True)
    with guard(sweep_dir):  # two drivers submitting to one folder at once both end up in the record
        sweeps = read_record(sweep_dir)
        entry = next((e for e in sweeps if e["grid"] == grid and e["flags"] == list(flags)), None)
        if entry is None:
            entry = {"grid": grid, "flags": list(flags), "jobs": []}
            sweeps.append(entry)
        entry["command"] = list(command)
        jobs = {j["name"]: j for j in entry["jobs"]}
        jobs.update({s.name: {"name": s.name, **dataclasses.asdict(s)} for s in specs})
        entry["jobs"] = list(jobs.values())
        write_json(os.path.join(sweep_dir, RECORD), {"engine": engine, "sweeps": sweeps})
    return len(sweeps)


def recorded_specs(entry: dict) -> list[JobSpec]:
    fields = [f.name for f in dataclasses.fields(JobSpec)]
    return [JobSpec(**{k: tuple(j[k]) if isinstance(j[k], list) else j[k] for k in fields}) for j in entry["jobs"]]


# ================================================================================================
# 4. The job: what runs inside each submitit job
# ================================================================================================
class SearJob(submitit.helpers.Checkpointable):
    """One sear.py run, started as a fresh process. Why a fresh process: sear.py renders with EGL,
    and a process that rendered must not fork a renderer child; a new interpreter is always safe.
    Checkpointable: a SLURM job that reaches its time limit is requeued, and this same call then
    resumes the run from its last snapshot."""

    def __init__(self, job_dir: str, args: list[str], resume_args: list[str], threads: int,
                 script: str, python: str = sys.executable, devices: str | None = None):
        self.job_dir, self.args, self.resume_args = job_dir, list(args), list(resume_args)
        self.threads, self.script, self.python = threads, script, python
        self.devices = devices  # CUDA_VISIBLE_DEVICES for sear.py; None: as given (SLURM sets it)

    def lock_dirs(self) -> list[str]:
        """The job directories whose locks the job takes, and DONE marks."""
        return [self.job_dir]

    def state_dirs(self) -> list[str]:
        """The directories whose status.json says what the job's process did."""
        return [self.job_dir]

    def __call__(self) -> str:
        me, taken = whoami(), []
        for job_dir in self.lock_dirs():
            holder = take_lock(job_dir, me)
            if holder is not None:
                for held in taken:
                    drop_lock(held, me)
                return f"skipped: already running ({describe(holder)})"
            taken.append(job_dir)
        try:
            return "done" if all(is_done(d) for d in self.lock_dirs()) else self.run(me)
        except KeyboardInterrupt:
            self.set_status("interrupted", error="interrupted; re-run the sweep to resume")
            raise
        finally:
            for held in taken:
                drop_lock(held, me)

    def set_status(self, state: str, **info) -> None:
        for job_dir in self.state_dirs():
            set_status(job_dir, state, **info)

    def resumable(self, run: str) -> bool:
        return os.path.exists(os.path.join(run, "snapshot.pt"))

    def run(self, me: dict) -> str:
        runs = run_dirs(self.job_dir)
        if len(runs) > 1:
            error = f"{os.path.join(self.job_dir, 'run')} holds {len(runs)} runs; move all but one out"
            self.set_status("failed", error=error)
            return f"failed: {error}"
        moved = ""
        if runs and self.resumable(runs[0]):
            argv = ["--resume", runs[0], *self.resume_args]
        else:
            if runs:  # died before its first snapshot: keep it, out of the way, and start clean
                moved = self.move_aside(runs[0])
            argv = [*self.args, "--run-root", os.path.join(self.job_dir, "run")]
        cmd = [self.python, self.script, *argv]
        attempt = (read_json(os.path.join(self.job_dir, "status.json")) or {}).get("attempts", 0) + 1
        self.set_status("running", attempts=attempt, owner=me)
        env = {**os.environ, "OMP_NUM_THREADS": str(self.threads), "MKL_NUM_THREADS": str(self.threads),
               "PYTHONUNBUFFERED": "1", **({} if self.devices is None else {"CUDA_VISIBLE_DEVICES": self.devices})}
        with open(os.path.join(self.job_dir, "stdout.log"), "a") as out, \
                open(os.path.join(self.job_dir, "stderr.log"), "a") as err:
            stamp = time.strftime("%Y-%m-%d %H:%M:%S")
            for f in (out, err):
                f.write(f"=== attempt {attempt} at {stamp}, {describe(me)}: {shlex.join(cmd)}\n")
                if moved and f is out:
                    f.write(f"moved the snapshot-less run {runs[0]} to {moved}\n")
                f.flush()
            offset = err.tell()
            code = subprocess.run(cmd, stdout=out, stderr=err, env=env, cwd=self.job_dir).returncode
        return self.settle(code, attempt, offset)

    def settle(self, code: int, attempt: int, offset: int) -> str:
        """DONE and status done after exit 0; interrupted after SIGTERM; else failed with the last
        stderr line."""
        if code == 0:
            for job_dir in self.lock_dirs():
                with open(os.path.join(job_dir, "DONE"), "w") as f:
                    f.write(time.strftime("%Y-%m-%d %H:%M:%S\n"))
            self.set_status("done", attempts=attempt, exit_code=0)
            return "done"
        how = f"exit code {code}" if code > 0 else f"killed by signal {-code}"
        if code in (-signal.SIGTERM, 128 + signal.SIGTERM):  # scancel, a time limit, a shutdown
            error = f"stopped by SIGTERM ({how}); re-run the sweep to resume"
            self.set_status("interrupted", attempts=attempt, exit_code=code, error=error)
            return f"interrupted: {error}"
        error = last_line(os.path.join(self.job_dir, "stderr.log"), offset) or how
        self.set_status("failed", attempts=attempt, exit_code=code, error=f"{how}: {error}")
        return f"failed: {how}: {error}"

    def move_aside(self, run: str) -> str:
        """<out>/<sweep>/<job>/run/<run> -> <out>/<sweep>.aside/<job>/<run>: outside the sweep's
        folder, so that plot.py on the sweep folder does not pick it up."""
        sweep_dir, job = os.path.split(os.path.normpath(self.job_dir))
        dest = base = os.path.join(f"{sweep_dir}.aside", job, os.path.basename(run))
        k = 1
        while os.path.exists(dest):  # an earlier start in the same second: never overwrite it
            dest, k = f"{base}~{k}", k + 1
        os.makedirs(os.path.dirname(dest), exist_ok=True)
        shutil.move(run, dest)
        return dest


class PackJob(SearJob):
    """Several seeds' jobs as one `sear.py --seeds` process (group.py), run from the pack's folder
    (its run/ holds the group folder; its logs and status.json the process's). It holds every seed's
    lock (one held by a live process: it takes none and skips), and every seed's status.json and
    DONE say what the process did. The group folder resumes (`--resume GROUP_DIR`) when every seed
    has its snapshot; a group folder without them is moved aside, as a single run's is."""

    def __init__(self, pack_dir: str, job_dirs: list[str], args: list[str], resume_args: list[str], threads: int,
                 script: str, python: str = sys.executable, devices: str | None = None):
        super().__init__(pack_dir, args, resume_args, threads, script, python, devices)
        self.job_dirs = list(job_dirs)

    def lock_dirs(self) -> list[str]:
        return self.job_dirs

    def state_dirs(self) -> list[str]:
        return [self.job_dir, *self.job_dirs]

    def resumable(self, run: str) -> bool:
        runs = (read_json(os.path.join(run, GROUP_FILE)) or {}).get("runs")
        return bool(runs) and all(os.path.exists(os.path.join(run, r, "snapshot.pt")) for r in runs.values())


# ================================================================================================
# 5. Engines: local (N jobs at a time) or a SLURM array
# ================================================================================================
def cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def pick_engine(args) -> tuple[str, str]:
    """(engine, why): --engine, else the one the sweep's folder records, else this machine. Never
    SLURM because srun happens to be on the PATH: that sent a login node's test sweep to a queue
    unasked."""
    srun = shutil.which("srun") is not None
    recorded, where = recorded_engine(os.path.join(args.out, args.sweep))
    if args.engine:
        engine, why = args.engine, f"--engine {args.engine}"
    elif recorded:
        other = "local runs it here" if recorded == "slurm" else "slurm submits it to SLURM"
        engine, why = recorded, f"{where}; --engine {other}"
    else:
        engine, why = "local", "default" + ("; --engine slurm to submit to SLURM, whose srun is on "
                                            "the PATH"
                                            if srun else "")
    if engine == "slurm" and not srun:
        raise SweepError(f"engine slurm ({why}), but srun is not on this machine's PATH")
    slurm_only = [f for f, v in (("--partition", args.partition), ("--account", args.account),
                                 ("--slurm-array-parallelism", args.slurm_array_parallelism)) if v is not None]
    if engine != "slurm" and slurm_only:
        raise SweepError(f"{slurm_only[0]} needs SLURM, but the engine is {engine} ({why})")
    for name in ("jobs", "threads", "time_limit", "gpus_per_job", "mem_gb", "slurm_array_parallelism",
                 "seeds_per_job"):
        value, least = getattr(args, name), 0 if name == "gpus_per_job" else 1
        if value is not None and value < least:
            raise SweepError(f"--{name.replace('_', '-')} must be >= {least}, got {value}")
    return engine, why


def gres_gpus(gres: str) -> int:
    """GPUs in one of sinfo's %G fields: 'gpu:4', 'gpu:a100:8(S:0-1)', 'gpu:a:2,gpu:b:2,mps:100',
    '(null)'."""
    return sum(int(n) for n in re.findall(r"(?:^|,)gpu(?::[^:,(]+)?:(\d+)", gres))


@dataclass(frozen=True)
class Partition:
    """What a node of a SLURM partition can give, as sinfo reports it."""
    name: str    # for messages: "partition gpu" or "the default partition"
    gpus: int    # the most GPUs one node has
    cpus: int    # the most CPUs one node has
    # the most memory one node has (RealMemory, MB as SLURM counts them: 1024 to its GB)
    mem_mb: int


def slurm_partition(partition: str | None) -> Partition | None:
    """`partition` (None: the cluster's default one) from sinfo; None when sinfo cannot tell."""
    if shutil.which("sinfo") is None:
        return None
    try:
        r = subprocess.run(["sinfo", "-h", "--all", "-o", "%P|%G|%c|%m"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    rows = [line.split("|") for line in r.stdout.splitlines() if line.count("|") == 3] if r.returncode == 0 else []
    if not rows:
        return None
    names = list(dict.fromkeys(row[0].rstrip("*") for row in rows))
    if partition is not None and partition not in names:
        raise SweepError(f"SLURM has no partition '{partition}' (sinfo lists {', '.join(names)})")
    mine = [row[1:] for row in rows if (row[0].rstrip("*") == partition if partition else row[0].endswith("*"))]
    if not mine:
        return None

    def most(values):  # '64', '64+' (nodes that differ), 'n/a': the number
        return max(int(re.match(r"\d*", v)[0] or 0) for v in values)
    return Partition(f"partition {partition}" if partition else "the default partition",
                     gpus=max(gres_gpus(g) for g, _, _ in mine), cpus=most(c for _, c, _ in mine),
                     mem_mb=most(m for _, _, m in mine))


def local_gpus() -> list[str]:
    """The GPUs this machine lets us use, as CUDA_VISIBLE_DEVICES names them."""
    import torch
    n = torch.cuda.device_count()
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    names = [d.strip() for d in visible.split(",") if d.strip()] if visible is not None else []
    return names[:n] if visible is not None else [str(i) for i in range(n)]


def job_gpus(args, engine: str, part: Partition | None) -> tuple[int, str]:
    """(GPUs per job, what the header says about them). The default is what this machine or the
    partition can give: 1 where there are GPUs, else none; an explicit count it cannot give fails
    here, before anything is created."""
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
    if asked is not None and asked > part.gpus:
        have = f"at most {part.gpus} GPU(s)" if part.gpus else "no GPUs; --gpus-per-job 0 runs on their CPUs"
        raise SweepError(f"--gpus-per-job {asked}: the nodes of {part.name} have {have} (sinfo)")
    gpus = min(1, part.gpus) if asked is None else asked
    return gpus, f"{gpus} GPU(s) per job" if part.gpus else f"no GPU, as {part.name} has none"


def check_cpus(args, part: Partition | None) -> None:
    """A job that asks for more CPUs than any node has would stay pending for ever."""
    if part is not None and part.cpus and args.threads > part.cpus:
        raise SweepError(f"--threads {args.threads}: the nodes of {part.name} have at most "
                         f"{part.cpus} CPUs (sinfo), so the jobs would never start")


# What one sear.py run holds, measured (EXPERIMENTS.md, "Memory": VmRSS of a default run on the
# CPU): 0.89 GB until the first update, 2.66 GB at the peak of SEAR's batch-256 updates, the replay
# still nearly empty; then the replay, ReplayBuffer.bytes_per_transition for each transition it
# holds. The DrQ encoder's methods (drq, rgbm) peak 0.65 GB lower (bench_agent.py's peak RSS at
# batch 256: drq 1.52, sear 2.17 GB); the other methods, unmeasured, count as SEAR. What the updates
# add scales with the batch.
START_GB = 0.89
PEAK_GB = {"pooled": 2.66, "drq": 2.66 - 0.65}  # by sear.METHODS' encoder, at batch 256
# per transition at 84x84 with Adroit's 28 actions, the most of any task (walker: 22,080)
REPLAY_BYTES = 22_168
# one run's peak; another task, renderer or allocator's slack moves it: a quarter more
HEADROOM = 1.25


def run_memory(cfg) -> tuple[float, float, int, str]:
    """(peak GB, of it the agent's, transitions the replay holds at most, how) of a sear.py run."""
    import envs
    encoder = sear_classes()[1][cfg.method].encoder
    agent = START_GB + (PEAK_GB[encoder] - START_GB) * cfg.batch_size / 256
    held = min(cfg.replay_size, cfg.frames // (cfg.action_repeat or envs.default_action_repeat(cfg.env)))
    scaled = "" if cfg.batch_size == 256 else f" scaled to batch {cfg.batch_size}"
    how = (f"{cfg.method}: {'drq' if encoder == 'drq' else 'sear'}'s measured peak at batch "
           f"256{scaled}, {agent:.2f} GB, + a replay of {held:,} transitions x "
           f"{REPLAY_BYTES / 1e3:.0f} kB, {held * REPLAY_BYTES / 1e9:.2f} GB, + {HEADROOM - 1:.0%}")
    return agent + held * REPLAY_BYTES / 1e9, agent, held, how


def local_memory_gb() -> float:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30


def job_memory(args, engine: str, part: Partition | None, specs: list[JobSpec],
               seeds: int = 1) -> tuple[int, float | None, str]:
    """(GB per job, GB of the largest node or None when unknown, the line that says both and why):
    --mem-gb, else the largest run's measured peak plus headroom, times the seeds a job runs. One
    that no node holds fails here, in one line."""
    distinct = {(s.env, s.variant, s.key): s for s in specs}.values()  # the seed changes nothing
    # the recipe's notes, printed once already by plan()
    with contextlib.redirect_stdout(io.StringIO()):
        peak, agent, held, how = max(run_memory(sear_config(list(s.args), s.name)) for s in distinct)
    need = max(1, math.ceil(peak * HEADROOM * seeds))
    how += f", x {seeds} seeds a job" if seeds > 1 else ""
    asked = args.mem_gb or need
    if engine == "local":
        node, where = local_memory_gb(), "this machine has"
    elif part is not None and part.mem_mb:
        node, where = part.mem_mb / 1024, f"a node of {part.name} has at most"
    else:
        node, where = None, ""
    have = (f"{where} {node:.1f} GB" + (" (sinfo)" if engine == "slurm" else "")) if node else ""
    if node is not None and asked > node:
        if args.mem_gb:
            raise SweepError(f"--mem-gb {asked}: {have}")
        # whole GB asked
        fits = int((math.floor(node) / HEADROOM / seeds - agent) * 1e9 / REPLAY_BYTES) // 1000 * 1000
        hint = f"; --replay-size {fits} fits" if 0 < fits < held else ""
        fewer = int(math.floor(node) // (peak * HEADROOM))
        hint = f"; --seeds-per-job {fewer} fits" if 1 <= fewer < seeds else hint
        raise SweepError(f"a job needs {need} GB ({how}), but {have}{hint}")
    why = f"--mem-gb; the estimate is {need} GB" if args.mem_gb else f"{how}; --mem-gb sets it"
    return asked, node, f"memory: {asked} GB per job ({why})" + (f"; {have}" if have else "")


def make_executor(args, engine: str, folder: str, gpus: int, mem_gb: int | None):
    executor = submitit.AutoExecutor(folder=folder, cluster=engine)
    # Locally each job gets its GPUs through CUDA_VISIBLE_DEVICES (SearJob.devices), not submitit's
    # (which would give every job the same first ones); on SLURM, no GPU request unless there are
    # GPUs.
    params = dict(timeout_min=args.time_limit, name=f"sweep-{args.sweep}", cpus_per_task=args.threads,
                  gpus_per_node=(gpus or None) if engine != "local" else 0, mem_gb=mem_gb,
                  slurm_partition=args.partition, slurm_account=args.account,
                  slurm_array_parallelism=args.slurm_array_parallelism)
    executor.update_parameters(**{k: v for k, v in params.items() if v is not None})
    return executor


def submit_array(executor, jobs: list, mem_gb: int) -> list:
    """One SLURM array; SweepError with sbatch's own reason (one line) if it refuses."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):  # submitit prints sbatch's stderr before raising it
            with executor.batch():
                submitted = [executor.submit(job) for job in jobs]
    except (submitit.core.utils.FailedJobError, submitit.core.utils.FailedSubmissionError, OSError) as e:
        lines = [ln.strip() for ln in (str(e) or err.getvalue()).splitlines() if ln.strip()]
        reason = "; ".join(ln.removeprefix("sbatch: error: ") for ln in lines) or type(e).__name__
        hint = ""
        if re.search(r"gres|gpu", reason, re.I):
            hint = " (--gpus-per-job 0 submits without a GPU request)"
        elif re.search(r"memory|node configuration", reason, re.I):
            hint = f" (each job asks {mem_gb} GB: does a node have it? --mem-gb sets it)"
        raise SweepError(f"sbatch refused the {len(jobs)} job(s): {reason[:300]}{hint}") from None
    return submitted


def job_devices(gpus: int, have: list[str], slots: int) -> list[str]:
    """CUDA_VISIBLE_DEVICES of each local job slot: `gpus` per job, round robin over `have`."""
    if not gpus:
        return [""] * slots  # --gpus-per-job 0 (or no GPU): every job on the CPU
    return [",".join(have[(s * gpus + i) % len(have)] for i in range(gpus)) for s in range(slots)]


def outcome(job) -> str:
    try:
        return job.result()
    except Exception as e:  # the job process itself failed (e.g. killed): its last line says why
        return "failed: " + (str(e).strip().splitlines() or [type(e).__name__])[-1][:300]


def run_local(executor, jobs: dict, parallel: int, devices: list[str]) -> dict:
    """Start the jobs `parallel` at a time, the one in slot k on devices[k]; {spec: outcome}."""
    pending, running, results = list(jobs), {}, {}
    started, free = {}, list(range(parallel))
    try:
        while pending or running:
            while pending and free:
                spec, slot = pending.pop(0), free.pop(0)
                jobs[spec].devices = devices[slot]
                running[spec], started[spec] = (executor.submit(jobs[spec]), slot), time.time()
            time.sleep(0.2)
            for spec, (job, slot) in list(running.items()):
                if job.done():
                    del running[spec]
                    free = sorted([*free, slot])
                    results[spec] = outcome(job)
                    print(f"[{len(results)}/{len(jobs)}] {spec.name}: {results[spec]} "
                          f"({time.time() - started[spec]:.0f} s)", flush=True)
    except KeyboardInterrupt:
        for job, _ in running.values():
            job.cancel(check=False)
        raise
    return results


# ================================================================================================
# 6. Status table
# ================================================================================================
def job_state(job_dir: str) -> tuple[str, str]:
    """(state, note): done / running / queued / failed / interrupted / not started."""
    if is_done(job_dir):
        return "done", ""
    holder = read_json(os.path.join(job_dir, "lock"))
    if holder and alive(holder) is not False:
        return "running", describe(holder)
    status = read_json(os.path.join(job_dir, "status.json")) or {}
    state = status.get("state")
    if state == "queued":
        by = status.get("by")
        if alive(by) is False:
            return "not started", f"its sweep ({describe(by)}) stopped first"
        return "queued", describe(by)
    if state == "running":  # status says running, but the lock holder is gone
        return "interrupted", "its process is gone; re-run the sweep to resume"
    if state in ("failed", "interrupted"):
        return state, status.get("error", "")
    return "not started", ""


def last_frame(job_dir: str) -> str:
    runs = run_dirs(job_dir)
    if not runs:
        return "-"
    try:
        with open(os.path.join(runs[-1], "train.csv"), newline="") as f:
            rows = list(csv.DictReader(f))
        return rows[-1]["frame"] if rows else "0"
    except (OSError, KeyError):
        return "0"


def status_table(out: str, specs: list[JobSpec]) -> str:
    rows = [("job", "state", "frames", "note")]
    counts = {}
    for spec in specs:
        d = os.path.join(out, spec.sweep, spec.name)
        state, note = job_state(d)
        counts[state] = counts.get(state, 0) + 1
        rows.append((spec.name, state, f"{last_frame(d)}/{spec.frames}", note))
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    lines = ["  ".join(r[i].ljust(widths[i]) for i in range(3)) + "  " + r[3] for r in rows]
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    return "\n".join([*(ln.rstrip() for ln in lines), f"{len(specs)} jobs: {summary}"])


# ================================================================================================
# 7. Report: per task plot.py's mean +- 95% CI over seeds; over the tasks rliable's IQM and mean
# ================================================================================================
# Stratified-bootstrap resamples of the across-task CIs. For one method of a grid (5 seeds x 10
# tasks x 250 evaluations) on 2 busy cores, rliable's default of 50,000 took 41 s, 10,000 took 10 s.
BOOTSTRAP_REPS = 10_000
DM_CONTROL_STEPS = 1000  # control steps of a dm_control episode, each rewarded in [0, 1]


def dm_control_max(config: dict) -> float:
    """The highest return of a dm_control episode: 1 per control step (--max-episode-steps cuts
    them)."""
    steps = config.get("max_episode_steps") or 0
    return float(min(DM_CONTROL_STEPS, steps * config.get("action_repeat", 1)) if steps else DM_CONTROL_STEPS)


def normalisation(env: str, runs: list[dict], metric: str) -> tuple[list[tuple[float, float]], str]:
    """(low, high) of each run's scores, so that (score - low) / (high - low) compares across tasks,
    and what the report says: success rates as they are, dm_control returns by the task's maximum,
    any other return min-max over this sweep's evaluations of the task."""
    import envs
    if metric == "success":
        return [(0.0, 1.0)] * len(runs), "success rate, as it is"
    if envs._parse_name(env)[0] in ("dmc", "distracting"):
        highs = [dm_control_max(r["config"]) for r in runs]
        return [(0.0, h) for h in highs], (f"return / {' or '.join(f'{h:g}' for h in sorted(set(highs)))} "
                                           f"(dm_control's maximum: 1 per control step)")
    values = np.concatenate([r["values"] for r in runs])
    lo, hi = float(values.min()), float(values.max())
    if hi == lo:
        return [(lo, lo + 1.0)] * len(runs), f"min-max over this sweep, but every return is {lo:.4g}: all 0"
    return [(lo, hi)] * len(runs), f"min-max over this sweep: (return - {lo:.4g}) / ({hi:.4g} - {lo:.4g})"


def across_tasks(scores: dict[str, np.ndarray]) -> dict[str, dict]:
    """rliable's IQM and mean with stratified-bootstrap 95% CIs (runs resampled within each task),
    at every frame: scores[method] is (seeds, tasks, frames) of normalised scores. -> {method:
    {"iqm", "iqm_ci", "mean", "mean_ci"}}, the CIs (2, frames) bounds."""
    from rliable import library as rly

    def iqm_and_mean(x):
        # rliable's metrics.aggregate_iqm (scipy's trim_mean, 25% off each end) and aggregate_mean
        # at every frame at once: trim_mean's own checks cost 2 ms a call, times 10,000 resamples.
        flat = np.sort(x.reshape(-1, x.shape[-1]), axis=0)
        cut = int(0.25 * len(flat))
        return np.concatenate([flat[cut:len(flat) - cut].mean(axis=0), flat.mean(axis=0)])
    with warnings.catch_warnings():  # arch's note on how rliable seeds it, not about these numbers
        warnings.simplefilter("ignore", FutureWarning)
        point, ci = rly.get_interval_estimates(scores, iqm_and_mean, reps=BOOTSTRAP_REPS,
                                               random_state=np.random.RandomState(0))
    out = {}
    for m, x in scores.items():
        f = x.shape[-1]
        out[m] = {"iqm": point[m][:f], "iqm_ci": ci[m][:, :f], "mean": point[m][f:], "mean_ci": ci[m][:, f:]}
    return out


def report(out: str, sweep: str, specs: list[JobSpec], metric: str | None) -> str | None:
    """Per task: mean +- 95% CI over seeds for each method (raw scores). Over the tasks: IQM and
    mean of the scores normalised per task (normalisation()), with rliable's stratified-bootstrap
    95% CIs over the seeds finished on every task. Only finished runs count. Writes
    <out>/<sweep>/report.png and report.md; returns the tables."""
    import plot
    finished = [(spec, run_dirs(d)[0]) for spec, d in ((s, os.path.join(out, s.sweep, s.name)) for s in specs)
                if is_done(d) and len(run_dirs(d)) == 1]
    if not finished:
        print("report: no finished runs yet")
        return None
    metric, runs = finished_runs(finished, metric)
    envs = [e for e in dict.fromkeys(s.env for s in specs) if any(k[0] == e for k in runs)]
    variants = list(dict.fromkeys(s.variant for s in specs))
    if not envs:
        return None
    panels = {env: {v: (*plot.aggregate(curves), plot.coverage(curves), env) for v in variants
                    if (curves := [(r["frames"], r["values"]) for r in runs.get((env, v), {}).values()])}
              for env in envs}
    how, normalised = normalise(runs, envs, metric)
    overall = f"over {plural(len(envs), 'task')}"
    aggregate_rows = across_task_lines(normalised, envs, variants, panels, overall)
    ylabel = f"eval {'success rate' if metric == 'success' else 'return'}"
    png = os.path.join(out, sweep, "report.png")
    # Per task the raw scores; over the tasks the IQM of the normalised ones (report.md says how
    # each task is).
    plot.plot(panels, png, ylabel, f"{sweep}: {ylabel} per task; over the tasks, the IQM of scores "
                                   f"normalised per task to 0-1 (report.md says how)",
              ylabels={overall: "IQM of normalised score"},
              estimates={**{e: "mean ± 95% CI over seeds" for e in envs},
                         overall: "IQM, stratified-bootstrap 95% CI"})
    per_task = plot.summary_table({e: panels[e] for e in envs}, metric)
    norm_rows = ["| task | normalised score |", "|---|---|", *(f"| {e} | {how[e]} |" for e in envs)]
    tables = "\n\n".join([per_task, "\n".join(aggregate_rows), "\n".join(norm_rows)])
    note = (f"{len(finished)} of {len(specs)} jobs finished; only finished runs count. Per task: "
            "mean ± 95% t-interval over seeds, raw scores. Over the tasks: IQM and mean of the "
            "scores normalised per task (last table), with 95% stratified-bootstrap CIs over the "
            f"seeds finished on every task (rliable, {BOOTSTRAP_REPS} resamples).")
    with open(os.path.join(out, sweep, "report.md"), "w") as f:
        f.write(f"# {sweep}\n\n{note}\n\n![curves](report.png)\n\n{tables}\n")
    print(f"{tables}\n\n{note}\nwrote {png} and report.md")
    return tables


def finished_runs(finished: list[tuple[JobSpec, str]], metric: str | None) -> tuple[str, dict]:
    """The metric (None: a success rate where every run has one, else the return) and the finished
    runs' eval.csv curves, {(env, variant): {seed: plot.load_run()}}; a run that cannot be read is
    skipped with one line."""
    import plot
    if metric is None:
        metric = "success" if all(has_column(run, "success") for _, run in finished) else "return"
    runs = {}
    for spec, run in finished:
        try:
            runs.setdefault((spec.env, spec.variant), {})[spec.seed] = plot.load_run(run, "eval", metric)
        except plot.PlotError as e:
            print(f"report: skipping {spec.name}: {e}")
    return metric, runs


def normalise(runs: dict, envs: list[str], metric: str) -> tuple[dict, dict]:
    """Per task, how its scores are normalised (every method's runs of the task together), and
    {(env, variant): {seed: (frames, normalised scores)}}."""
    how, normalised = {}, {}
    for env in envs:
        members = [(k, seed, r) for k, by_seed in runs.items() if k[0] == env for seed, r in by_seed.items()]
        bounds, how[env] = normalisation(env, [r for _, _, r in members], metric)
        for (k, seed, r), (lo, hi) in zip(members, bounds):
            normalised.setdefault(k, {})[seed] = (r["frames"], (r["values"] - lo) / (hi - lo))
    return how, normalised


def across_task_lines(normalised: dict, envs: list[str], variants: list[str], panels: dict,
                      overall: str) -> list[str]:
    """The IQM over the tasks of every method with runs on all of them: its panel (`overall`, added
    to `panels`) and its rows of the aggregate table (returned)."""
    scores, seeds_of = {}, {}
    for v in variants:
        seeds = sorted(set.intersection(*(set(normalised.get((e, v), {})) for e in envs)))
        if not seeds:
            continue
        frames = normalised[(envs[0], v)][seeds[0]][0]
        for e in envs:
            for s in seeds:
                frames = np.intersect1d(frames, normalised[(e, v)][s][0])
        if len(frames) == 0:
            print(f"report: {v}: its runs share no evaluation frame; left out of the aggregate")
            continue
        scores[v] = np.array([[normalised[(e, v)][s][1][np.isin(normalised[(e, v)][s][0], frames)]
                               for e in envs] for s in seeds])
        seeds_of[v] = (seeds, frames)
    rows = ["| method | runs | last frame | IQM [95% CI] | mean [95% CI] |", "|---|---|---|---|---|"]
    if scores:
        panels[overall] = {}
        for v, est in across_tasks(scores).items():
            seeds, frames = seeds_of[v]
            panels[overall][v] = (frames, est["iqm"], est["iqm_ci"], len(seeds), overall)
            iqm, mean = (f"{est[k][-1]:.3f} [{est[k + '_ci'][0, -1]:.3f}, "
                         f"{est[k + '_ci'][1, -1]:.3f}]"
                         for k in ("iqm", "mean"))
            runs_of = f"{plural(len(seeds), 'seed')} x {plural(len(envs), 'task')}"
            rows.append(f"| {v} | {runs_of} | {frames[-1]:.0f} | {iqm} | {mean} |")
    return rows


def has_column(run: str, name: str) -> bool:
    try:
        with open(os.path.join(run, "eval.csv"), newline="") as f:
            return name in (next(csv.reader(f), None) or [])
    except OSError:
        return False


# ================================================================================================
# 8. CLI
# ================================================================================================
def build_parser() -> argparse.ArgumentParser:
    """sweep.py's flags; a bad one is a cli.ConfigError (one line)."""
    from harness import cli  # stdlib only, as sear_config's imports: late
    grids = "; ".join(f"{name}: {g.doc}" for name, g in GRIDS.items())
    # no abbreviations: --seed is sear.py's
    p = cli.OneLineParser(prog="sweep.py", allow_abbrev=False,
                          description=__doc__.split("\nJob directory")[0],
                          formatter_class=argparse.RawDescriptionHelpFormatter,
                          epilog="Unknown flags, and everything after --, go to sear.py.")
    what = p.add_argument_group("what to run")
    what.add_argument("--grid", help=f"a named grid of the paper: {grids}; transfer: not available "
                                     "yet")
    what.add_argument("--envs", nargs="+", help="tasks (with --grid: a subset of the grid's)")
    what.add_argument("--methods", nargs="+", help="sear.py methods (with --grid: a subset of its "
                                                   "variants); "
                                                    "METHOD+drm runs METHOD with --drm (drq+drm is "
                                                    "DrM)")
    what.add_argument("--seeds", nargs="+", help="seeds: 1-5, 1,3,7 or 1-3 9 (default: the grid's, "
                                                 "else 1)")
    what.add_argument("--name", help="sweep folder under --out (default: the grid's name, else "
                                     "custom)")
    what.add_argument("--out", help="folder of sweeps (default: sweeps; --status and --report "
                                    "inside a sweep's "
                                   "folder: that folder)")
    do = p.add_argument_group("what to do (default: run what is not finished)")
    do.add_argument("--status", action="store_true", help="print a table of the jobs' states and "
                                                          "exit")
    do.add_argument("--report", action="store_true", help="draw report.png / report.md and exit")
    do.add_argument("--dry-run", action="store_true", help="print the jobs and their sear.py "
                                                           "commands, run nothing")
    eng = p.add_argument_group("engine (submitit: this machine, or a SLURM array)")
    eng.add_argument("--engine", choices=("local", "slurm"),
                     help="default: the one the sweep's folder records (sweep.json), else local")
    eng.add_argument("--jobs", type=int, help="local: jobs at a time (default: cores // --threads)")
    eng.add_argument("--threads", type=int, default=1, help="torch threads per job "
                                                            "(OMP_NUM_THREADS; default 1)")
    eng.add_argument("--time-limit", type=int, default=4300, help="minutes per job (default 4300, "
                                                                  "the authors')")
    eng.add_argument("--gpus-per-job", type=int, help="default: 1 where the partition (sinfo) or "
                                                      "this machine "
                     "has GPUs, else 0; locally each job gets its own, round robin "
                     "(CUDA_VISIBLE_DEVICES)")
    eng.add_argument("--mem-gb", type=int, help="memory per job (default: a measured run's peak "
                                                "for the job's "
                     "method, batch and replay, + 25%%); SLURM asks it, locally it bounds the jobs "
                     "at a time")
    eng.add_argument("--seeds-per-job", type=int, help="seeds of one task and method per job, run as one "
                     "`sear.py --seeds` process (group.py) where the method allows (default: as many as this "
                     "machine's GPU holds, at most 16; 4 on SLURM with GPUs, fewer where a node holds fewer; "
                     "1 without a GPU)")
    eng.add_argument("--partition", help="SLURM partition")
    eng.add_argument("--account", help="SLURM account")
    eng.add_argument("--slurm-array-parallelism", type=int, help="SLURM: array tasks at a time")
    return p


def folder_specs(sweep_dir: str) -> list[JobSpec]:
    """The jobs a sweep folder holds, from their job.json (folders from before sweep.json)."""
    specs = []
    for name in sorted(os.listdir(sweep_dir)) if os.path.isdir(sweep_dir) else []:
        data = read_json(os.path.join(sweep_dir, name, "job.json"))
        if data:
            specs.append(JobSpec(**{f.name: data[f.name] for f in dataclasses.fields(JobSpec)}))
    return specs


def show_command(args, verb: str, sweep: str, grid: str | None, flags: list[str]) -> str:
    """The sweep.py line that shows one sweep of a folder: --status or --report with its flags."""
    line = ["python", "sweep.py", *(["--out", args.out] if args.out != "sweeps" else []),
            *(["--grid", grid] if grid else []), *(["--name", sweep] if sweep != (grid or "custom") else []),
            f"--{verb}", *(["--", *flags] if flags else [])]
    return shlex.join(line)


def other_sweeps(args, verb: str) -> str:
    """What else --out holds, as the commands that show it."""
    names = sorted(n for n in os.listdir(args.out) if os.path.isdir(os.path.join(args.out, n))
                   and (read_record(os.path.join(args.out, n)) or folder_specs(os.path.join(args.out, n)))) \
        if os.path.isdir(args.out) else []
    if not names:
        return f"{args.out} holds no sweep yet"
    return f"{args.out} holds {', '.join(names)}: " + "; ".join(show_command(args, verb, n, None, []) for n in names)


def spelled_out(flags: list[str]) -> list[str]:
    """--frames=40 as --frames 40: one spelling of the same flags."""
    return [part for flag in flags for part in (flag.split("=", 1) if flag.startswith("--") else [flag])]


def listed(args, verb: str, sweep: str, entries: list[dict]) -> str:
    return "; ".join(f"{show_command(args, verb, sweep, e['grid'], e['flags'])} "
                     f"({plural(len(e['jobs']), 'job')})"
                     for e in entries)


def find_sweep(args, flags: list[str], verb: str) -> tuple[list[JobSpec], Grid | None]:
    """--status / --report: the jobs of the sweep that --name / --grid names, from the folder's
    record (sweep.json): its flags need not be given again. Where the folder holds several, the
    flags (none: the one run without any) or --grid pick one. Flags that match none of its sweeps,
    several left, or no sweep at all: SweepError naming the folder's sweeps and the command that
    shows each."""
    sweep = sweep_name(args)
    folder = os.path.join(args.out, sweep)
    entries = read_record(folder)
    if not entries:
        return unrecorded_sweep(args, flags, verb, sweep, folder)
    if args.grid and not any(e["grid"] == args.grid for e in entries):
        raise SweepError(f"{folder} holds no sweep of grid {args.grid}; it holds: "
                         f"{listed(args, verb, sweep, entries)}")
    chosen = [e for e in entries if e["grid"] == args.grid] if args.grid else entries
    same = [e for e in chosen if spelled_out(e["flags"]) == spelled_out(flags)]
    # the same flags spelled otherwise
    if flags and not same and (args.grid or (args.envs and args.methods)):
        names = {s.name for s in plan(args, flags)[1]}
        same = [e for e in chosen if names & {j["name"] for j in e["jobs"]}]
    if flags and not same:
        raise SweepError(f"{folder} holds no sweep run with `-- {shlex.join(flags)}`; it holds: "
                         f"{listed(args, verb, sweep, chosen)}")
    if len(chosen) > 1 and len(same) != 1:
        raise SweepError(f"{folder} holds {len(chosen)} sweeps, show one: "
                         f"{listed(args, verb, sweep, chosen)}")
    if len(chosen) > 1:
        print(f"note: {folder} also holds: "
              f"{listed(args, verb, sweep, [e for e in chosen if e is not same[0]])}")
    entry = same[0] if same else chosen[0]
    return select(args, recorded_specs(entry), folder), GRIDS.get(entry["grid"])


def select(args, specs: list[JobSpec], folder: str) -> list[JobSpec]:
    """The jobs --envs / --methods / --seeds pick from a recorded sweep."""
    envs = parse_names(args.envs) if args.envs else None
    methods = parse_names(args.methods) if args.methods else None
    seeds = parse_seeds(args.seeds) if args.seeds else None
    picked = [s for s in specs if (envs is None or s.env in envs) and (methods is None or s.variant in methods)
              and (seeds is None or s.seed in seeds)]
    if not picked:
        def have(values):
            return ", ".join(map(str, dict.fromkeys(values)))
        raise SweepError(f"the sweep in {folder} has none of these jobs: it has envs "
                         f"{have(s.env for s in specs)}; methods {have(s.variant for s in specs)}; "
                         f"seeds {have(s.seed for s in specs)}")
    return picked


def unrecorded_sweep(args, flags: list[str], verb: str, sweep: str, folder: str):
    """A folder without sweep.json: made before sweep.py recorded its sweeps, or never submitted
    to."""
    held = folder_specs(folder)
    if not held:
        raise SweepError(f"no sweep in {folder}; {other_sweeps(args, verb)}")
    if not (args.grid or args.envs or args.methods or flags):
        return held, None
    _, specs, grid = plan(args, flags)
    if not {s.name for s in specs} & {s.name for s in held}:
        raise SweepError(f"{folder} holds {len(held)} jobs, none of those these arguments name, "
                         f"and no {RECORD} (the record of its flags, which older sweeps lack): "
                         "give the sweep's own flags after --, or show all of its jobs: "
                         f"{show_command(args, verb, sweep, None, [])}")
    return specs, grid


def main(argv: list[str] | None = None) -> int:
    from harness import cli
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, after = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    try:
        args, unknown = build_parser().parse_known_args(ours)
    except cli.ConfigError as e:
        print(f"sweep.py: error: {e}", file=sys.stderr)
        return 2
    args.flags, args.argv = unknown + after, argv
    try:
        # first: --stauts is a typo of --status, whatever else is on the line
        check_passthrough(args.flags)
        if args.status or args.report:  # a sweep already submitted: its record knows the flags
            inside_sweep(args)
            args.sweep = sweep_name(args)
            specs, grid = find_sweep(args, args.flags, "status" if args.status else "report")
        else:
            args.out = args.out or "sweeps"
            args.sweep, specs, grid = plan(args, args.flags)
        if args.status:
            print(status_table(args.out, specs))
            return 0
        if args.report:
            report(args.out, args.sweep, specs, grid.metric if grid else None)
            return 0
        return run(args, specs, grid, *pick_engine(args))
    except SweepError as e:
        print(f"sweep.py: error: {e}", file=sys.stderr)
        return 2


def inside_sweep(args) -> None:
    """--status / --report in a sweep's folder (it holds sweep.json, or job folders): that folder,
    unless
    --out or --name say which."""
    if args.out is None and args.name is None and (os.path.exists(RECORD) or folder_specs(".")):
        args.out, args.name = os.path.split(os.getcwd())
    args.out = args.out or "sweeps"


def run(args, specs: list[JobSpec], grid: Grid | None, engine: str, why: str) -> int:
    """The jobs neither done nor running elsewhere: run here (then the report) or submitted to
    SLURM;
    --dry-run prints them. 0 when every job run here finished, 1 if one failed."""
    sweep_dir = os.path.join(args.out, args.sweep)
    dirs = {spec: os.path.abspath(os.path.join(sweep_dir, spec.name)) for spec in specs}
    done = [s for s in specs if is_done(dirs[s])]
    busy = [s for s in specs if s not in done and alive(read_json(os.path.join(dirs[s], "lock"))) is not False]
    todo = [s for s in specs if s not in done and s not in busy]
    gpus, mem_gb, parallel, where, units, packing = resources(args, engine, why, todo, sweep_dir)
    shape = f"{len({s.env for s in specs})} envs x {len({s.variant for s in specs})} methods x " \
            f"{len({s.seed for s in specs})} seeds"
    grouped = f" in {len(units)} process{'es' * (len(units) != 1)}" if any(isinstance(u, Pack) for u in units) else ""
    print(f"sweep {args.sweep}: {len(specs)} jobs ({shape}): {len(done)} done, {len(busy)} running "
          f"elsewhere, {len(todo)} to run{grouped} ({where}); {packing}", flush=True)
    if args.dry_run:
        for u in units:
            print(f"{u.name}: sear.py {shlex.join(u.args)}")
        return 0
    held = record_sweep(sweep_dir, args.grid, args.flags, args.argv, specs, engine)
    if held > 1:
        print(f"note: {sweep_dir} now holds {held} sweeps (other grids or sear.py flags); --status "
              f"and --report then need the sweep's flags after -- to pick one")
    metric = grid.metric if grid else None
    if not todo:
        if engine == "local" and not busy:
            report(args.out, args.sweep, specs, metric)
        return 0
    jobs = {u: new_job(sweep_dir, u, args.threads) for u in units}
    executor = make_executor(args, engine, os.path.join(sweep_dir, ".submitit"), gpus, mem_gb)
    if SearJob.__module__ != "__main__":  # imported: ship this module's code with the jobs, so that
        import cloudpickle                # they need no `import sweep` from whatever their cwd is
        cloudpickle.register_pickle_by_value(sys.modules[SearJob.__module__])
    if engine != "local":  # one SLURM array; this process only submits
        return submit(executor, jobs, mem_gb, engine, sweep_dir)
    driver = whoami()
    for job in jobs.values():
        for job_dir in job.state_dirs():
            mark_queued(job_dir, driver)
    try:
        results = run_local(executor, jobs, parallel, job_devices(gpus, local_gpus(), parallel))
    except KeyboardInterrupt:
        print("\ninterrupted: re-run the same command to continue (finished runs are kept, "
              "interrupted ones resume from their last snapshot)", file=sys.stderr)
        return 130
    return finished_here(args, specs, metric, results)


def finished_here(args, specs: list[JobSpec], metric: str | None, results: dict) -> int:
    """After the jobs run here: how many finished, and the report. 1 if one failed."""
    # a pack's outcome is each of its seeds'
    results = {s: r for u, r in results.items() for s in (u.specs if isinstance(u, Pack) else (u,))}
    failed = [s for s, r in results.items() if r.startswith(("failed", "interrupted"))]
    print(f"{len(results) - len(failed)} of {len(results)} jobs finished"
          + (f"; {len(failed)} failed (see --status)" if failed else ""))
    report(args.out, args.sweep, specs, metric)
    return 1 if failed else 0


def new_job(sweep_dir: str, unit: JobSpec | Pack, threads: int) -> SearJob:
    """A job's folder with its job.json, and the job; for a pack, each seed's folder, with its
    pack.json too, and the pack's folder."""
    for spec in unit.specs if isinstance(unit, Pack) else (unit,):
        job_dir = os.path.abspath(os.path.join(sweep_dir, spec.name))
        os.makedirs(job_dir, exist_ok=True)
        write_json(os.path.join(job_dir, "job.json"), dataclasses.asdict(spec))
        if isinstance(unit, Pack):
            write_json(os.path.join(job_dir, PACK_FILE), {"pack": unit.name, "seeds": unit.seeds, "seed": spec.seed})
    job_dir = os.path.abspath(os.path.join(sweep_dir, unit.name))
    if not isinstance(unit, Pack):
        return SearJob(job_dir, unit.args, unit.resume_args, threads, script=SEAR_PY)
    os.makedirs(job_dir, exist_ok=True)
    seeds = [os.path.abspath(os.path.join(sweep_dir, spec.name)) for spec in unit.specs]
    return PackJob(job_dir, seeds, unit.args, unit.specs[0].resume_args, threads, script=SEAR_PY)


def resources(args, engine: str, why: str, todo: list[JobSpec], sweep_dir: str) -> tuple:
    """(GPUs per job, memory per job in GB, jobs at a time here, where they run, the jobs: JobSpecs
    and Packs, seeds per job and why) of the seeds to run, after the lines that say which engine and
    how much memory."""
    part = slurm_partition(args.partition) if engine == "slurm" else None
    check_cpus(args, part)
    gpus, gpu_note = job_gpus(args, engine, part)
    k, pack_note, slots = seeds_per_job(args, engine, gpus, part, todo)
    print(f"engine: {engine} ({why})")
    units = packs(todo, k, sweep_dir)
    most = max([len(u.specs) for u in units if isinstance(u, Pack)], default=1)
    mem_gb, node_gb, mem_line = job_memory(args, engine, part, todo, most) if todo else (args.mem_gb, None, "")
    parallel = args.jobs or min(max(1, cpu_count() // args.threads), slots or math.inf)
    if engine == "local" and node_gb and parallel * mem_gb > node_gb:
        fit = max(1, int(node_gb // mem_gb))  # job_memory refused a job that fits nowhere
        if args.jobs:
            mem_line += f"; --jobs {args.jobs} x {mem_gb} GB is more than that"
        else:
            mem_line, parallel = mem_line + f", room for {fit} at a time", fit
    if mem_line:
        print(mem_line)
    where = f"{engine}, {parallel} at a time, {args.threads} thread(s) each" if engine == "local" else engine
    return gpus, mem_gb, parallel, f"{where}, {gpu_note}", units, f"{plural(k, 'seed')} per job ({pack_note})"


# Seeds per job on SLURM with GPUs, where the GPU's memory cannot be seen at submission: few enough
# for any GPU a partition of the paper's runs has (4 default runs: about 33 GB by run_memory).
SLURM_SEEDS_PER_JOB = 4
MOST_SEEDS_PER_JOB = 16


def seeds_per_job(args, engine: str, gpus: int, part: Partition | None,
                  todo: list[JobSpec]) -> tuple[int, str, int | None]:
    """(seeds per job, why, jobs at a time the GPUs hold or None): --seeds-per-job; else 1 without a
    GPU (one process per seed uses the cores as well); on SLURM SLURM_SEEDS_PER_JOB, or fewer where a
    node's memory holds fewer; here, as many as the GPU's and this machine's memory hold at a run's
    measured need (run_memory, + 25%), at most MOST_SEEDS_PER_JOB, each packed job then on GPUs of its
    own."""
    if args.seeds_per_job:
        return args.seeds_per_job, "--seeds-per-job", None
    if not gpus:
        return 1, "no GPU: one process per seed uses the cores as well; --seeds-per-job packs them", None
    if max(collections.Counter((s.env, s.variant, s.key) for s in todo).values(), default=0) < 2:
        return 1, "one seed of each task and method to run", None
    distinct = {(s.env, s.variant, s.key): s for s in todo}.values()
    with contextlib.redirect_stdout(io.StringIO()):  # the recipe's notes, printed once already by plan()
        need = max(run_memory(sear_config(list(s.args), s.name))[0] for s in distinct) * HEADROOM
    if engine != "local":
        node_gb = part.mem_mb / 1024 if part is not None and part.mem_mb else None
        k = max(1, min(SLURM_SEEDS_PER_JOB, int(node_gb // need) if node_gb else SLURM_SEEDS_PER_JOB))
        held = f"; a node of {part.name} holds {k} at {need:.1f} GB a seed" if k < SLURM_SEEDS_PER_JOB else ""
        return k, (f"the GPUs' memory is not visible at submission, so a conservative default{held}; "
                   "--seeds-per-job sets it"), None
    import torch
    gpu_gb = min(torch.cuda.get_device_properties(i).total_memory for i in range(len(local_gpus()))) / 2**30
    host_gb = local_memory_gb()
    k = max(1, min(MOST_SEEDS_PER_JOB, int(min(gpu_gb, host_gb) // need)))
    return k, (f"as many as a GPU's {gpu_gb:.0f} GB and this machine's {host_gb:.0f} GB hold at {need:.1f} GB "
               f"a seed, at most {MOST_SEEDS_PER_JOB}; --seeds-per-job sets it"), \
        max(1, len(local_gpus()) // gpus) if k > 1 else None


def submit(executor, jobs: dict, mem_gb, engine: str, sweep_dir: str) -> int:
    """The jobs as one SLURM array; each job folder records its array task."""
    submitted = submit_array(executor, list(jobs.values()), mem_gb)
    for job, task in zip(jobs.values(), submitted):
        for job_dir in job.state_dirs():
            mark_queued(job_dir, {"cluster": engine, "job": task.job_id})
    print(f"submitted {len(submitted)} jobs ({submitted[0].job_id.split('_')[0]}); follow them "
          f"with --status, draw the curves with --report; logs in {sweep_dir}/<job>/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
