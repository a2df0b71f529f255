"""sear.py's command line: the run settings (RunConfig), flags generated from the dataclasses (the
algorithm's Config is in sear.py, passed in), the paper and authors recipes, the checks that turn bad
input into one line on stderr (misspelled flags, run directories given as inputs and who owns one,
--evaluate's flags) and the start-up warnings, the saved config of --resume, --evaluate and
--init-from, and the process set-up (glibc's malloc, torch device and threads, SIGTERM).

Loads no numpy or torch at import: sweep.py and plot.py read flags and configs through it without them.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import errno
import json
import math
import os
import shutil
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field


def arg(default, doc, choices=None, saved=True):
    """A config field with its one-line doc (--help) and, for a fixed set of values, the choices.
    saved=False: a setting of this command only, never written to config.json or a snapshot."""
    return field(default=default, metadata={"doc": doc, "choices": choices, "saved": saved})


# Transfer (--init-from): which networks of another run's agent a new run starts from.
INIT_PARTS = {"encoder": ("encoder",), "encoder+decoders": ("encoder", "aux"),
              "all": ("encoder", "aux", "actor", "critic")}


@dataclass
class RunConfig:
    """How this process runs the experiment (sear.Config says what the experiment is): devices, files,
    logs, snapshots, transfer. Saved with the Config in config.json and snapshot.pt, all but the
    fields marked saved=False (--evaluate: a command, not a setting of the run)."""
    device: str = arg("auto", "auto (cuda when available, else cpu) | cpu | cuda | cuda:N")
    compile: str = arg("auto", "auto (on with CUDA) | on | off: the update through torch.compile (harness/speed.py); "
                               "equal to the plain update within rounding; its first update compiles (minutes)",
                       ("auto", "on", "off"))
    cuda_graph: str = arg("auto", "auto (on with CUDA) | on | off: the update captured once as a CUDA graph and "
                                  "replayed (harness/speed.py)", ("auto", "on", "off"))
    batch_seeds: str = arg("auto", "auto (on with CUDA) | on | off: with --seeds, every seed's update as one batched "
                                   "update (torch.func.vmap); off: one after another", ("auto", "on", "off"))
    tf32: bool = arg(False, "CUDA: TF32 in float32 convolutions and matmuls (Ampere and newer: faster, ~3 fewer "
                            "significant digits); off: the reference arithmetic (DrQ-v2's curves ran on V100s, which "
                            "have none)")
    replay_device: str = arg("auto", "where the replay ring lives: auto (the run's GPU when it fits there, else the "
                                     "host) | cpu | the run's device")
    prefetch: str = arg("auto", "auto (on with CUDA and a replay on the host) | on | off: sample and copy the next "
                                "batch in a background thread while the current update runs", ("auto", "on", "off"))
    threads: int = arg(0, "torch CPU threads; 0 = $OMP_NUM_THREADS, else every core this process may use. "
                          "Several runs on one machine: give each cores / runs")
    run_root: str = arg("runs", "folder that holds run directories")
    resume: str = arg("", "run directory to continue from its last snapshot")
    evaluate: str = arg("", "score this run directory's snapshot on its eval env, no training: mean return (and "
                            "success) over --eval-episodes with confidence intervals; writes nothing, but with "
                            "--save-video a new videos/evaluate_<frame>.mp4", saved=False)
    recipe: str = arg("paper", "paper (the paper's hyper-parameter table) | authors (their released code "
                               "where the two differ: RECIPES below, docs/recipes.md); explicit flags win",
                      ("paper", "authors"))
    save_buffer: bool = arg(False, "also snapshot the replay buffer: --resume then continues exactly")
    save_video: bool = arg(False, "write each evaluation's first episode to videos/eval_<frame>.mp4: camera | true "
                                  "mask | predicted mask | reconstruction (the panels the method has)")
    init_from: str = arg("", "transfer: start from the snapshot.pt of this run directory (e.g. pre-trained on "
                             "metaworld-mt10); method and network sizes follow that run unless given")
    init_parts: str = arg("all", "with --init-from, what to copy: encoder | encoder+decoders (the method's "
                                 "auxiliary networks too) | all (also actor and critic: the authors' default, "
                                 "just_encoder_decoders false); the rest and the optimisers start fresh",
                          tuple(INIT_PARTS))
    log_every: float = arg(10.0, "seconds between progress lines")
    snapshot_minutes: float = arg(10.0, "minutes of wall time between snapshots, each written at the next "
                                        "episode end (0 = after every episode)")
    drop_inapplicable: bool = arg(False, "drop the flags given where they do nothing (their 'only for') with one "
                                         "line, instead of refusing them: sweep.py passes one set of flags to every "
                                         "method of a grid", saved=False)


def parse_seeds(spec: str) -> list[int]:
    """--seeds: '1-16' -> [1, ..., 16]; '1,3,5' and '1-4,9' too. A bad spec is a ConfigError."""
    seeds = []
    try:
        for part in spec.split(","):
            lo, _, hi = part.partition("-")
            seeds += list(range(int(lo), int(hi or lo) + 1))
    except ValueError:
        raise ConfigError(f"--seeds takes seeds like 1-16 or 1,3,5, got '{spec}'") from None
    if len(seeds) < 2 or len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds takes two or more different seeds, got '{spec}'")
    return seeds


class ConfigError(ValueError):
    """Bad user input: reported as one line on stderr."""


class StorageError(Exception):
    """An OSError while writing a file the user keeps (a run directory's files, segment.py's model and
    label folders), as one line naming the file and the cause."""


# --- Storage errors: a full disk, a read-only or foreign folder is one line, never a traceback -----
def storage_message(path, err: OSError) -> str:
    """'cannot write PATH: No space left on device (ENOSPC)': the path being written and the system's
    reason (strerror, not str(err): imageio's and torch's messages run on for lines)."""
    if err.errno in (errno.EEXIST, errno.ENOTDIR):  # a file where a folder should be: say which
        for where in (path, *parents(path)):
            if os.path.lexists(where) and not os.path.isdir(where):
                return (f"cannot make the folder '{path}': a file of that name is in the way" if where == path
                        else f"cannot write '{path}': '{where}' is a file, not a folder")
    name = errno.errorcode.get(err.errno, "") if err.errno else ""
    reason = err.strerror or first_sentence(err) or type(err).__name__
    return f"cannot write '{path}': {reason}" + (f" ({name})" if name else "")


@contextlib.contextmanager
def storing(path):
    """Around every write of a run directory's or segment.py's files: an OSError becomes a StorageError
    naming `path`."""
    try:
        yield
    except OSError as e:
        raise StorageError(storage_message(path, e)) from None


class _WriteRecorder:
    """A file for torch.save that keeps the OSError of a failed write: torch turns it into
    'inline_container.cc ... unexpected pos', which names neither the file nor the cause."""

    def __init__(self, f):
        self.f, self.error = f, None

    def write(self, data):
        try:
            return self.f.write(data)
        except OSError as e:
            self.error = e
            raise

    def flush(self):
        self.f.flush()


def torch_save(obj, f):
    import torch  # here: cli loads no torch at import
    recorder = _WriteRecorder(f)
    try:
        torch.save(obj, recorder)
    except RuntimeError:
        if recorder.error is not None:
            raise recorder.error from None
        raise


def write_atomically(path, write, mode="wb"):
    """write(f) into PATH.tmp, then rename it onto PATH: a kill or a storage error mid-write leaves the
    previous file whole and no .tmp behind; an OSError is a StorageError naming PATH."""
    tmp = path + ".tmp"
    try:
        with storing(path):
            with open(tmp, mode, **({} if "b" in mode else {"newline": ""})) as f:
                write(f)
            os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):  # after the rename there is nothing left to remove
            os.remove(tmp)


class NonFinite(Exception):
    """A loss, Q or action that is no longer a finite number: the run diverged. It stops (exit 1) in
    one line that says where and what stands (experiment.RunDir adds the frame and the snapshot)."""


class Interrupted(Exception):
    """Ctrl-C or SIGTERM during training; the message says what was saved and how to continue."""

    def __init__(self, message, code=130):
        super().__init__(message)
        self.code = code


def warn(message):
    print(f"sear.py: warning: {message}", file=sys.stderr, flush=True)


def plural(n: int, word: str) -> str:
    """'1 episode', '10 episodes'."""
    return f"{n} {word}{'s' * (n != 1)}"


# ------------------------------------------------------------------------------------------------
# Recipes
# ------------------------------------------------------------------------------------------------
def _walker(cfg):
    return cfg.env.startswith("walker-")


def _humanoid(cfg):
    return cfg.env in ("humanoid-run", "humanoid-stand", "humanoid-walk")


def _manipulation(cfg):
    return cfg.env.split("-")[0] in ("metaworld", "kitchen", "adroit")


def _multitask(cfg):
    import envs  # imported late so --help needs no MuJoCo
    return envs.is_task_set(cfg.env)


def _dear(cfg):
    return cfg.method == "dear"


def _authors_discount(cfg):
    import envs  # the suite's default action repeat; imported late so --help needs no MuJoCo
    return round(0.99 ** (1 + (cfg.action_repeat or envs.default_action_repeat(cfg.env))), 6)


# Every value where the paper's hyper-parameter table and the authors' released code
# (github.com/sear-rl/sear-rl) differ: (field, applies to, authors' value, source). The Config defaults
# are the paper's values; --recipe authors replaces these unless the flag is given explicitly.
RECIPES = {"authors": (
    # (DEAR's c1 and c2 are its own under both recipes: TASK_DEFAULTS)
    ("recon_coef", lambda cfg: not _dear(cfg), 1.0, "sear/cfgs/agent/sear.yaml: reconstruction_loss_coeff"),
    ("mask_coef", lambda cfg: not _dear(cfg), 0.25, "sear/cfgs/agent/sear.yaml: mask_loss_coeff"),
    ("nstep", _walker, 1, "sear/cfgs/task/distracting_walker_walk.yaml: nstep (DrQ-v2's walker config)"),
    ("batch_size", _walker, 512, "sear/cfgs/task/distracting_walker_walk.yaml: batch_size"),
    ("lr", _humanoid, 8e-5, "sear/cfgs/task/humanoid_{run,stand,walk}.yaml: lr (DrQ-v2's)"),
    ("feature_dim", _humanoid, 100, "sear/cfgs/task/humanoid_{run,stand,walk}.yaml: feature_dim (DrQ-v2's)"),
    ("replay_size", lambda cfg: cfg.env == "quadruped-run", 100_000,
     "sear/cfgs/task/quadruped_run.yaml: replay_buffer_size (DrQ-v2's)"),
    # Their Meta-World / Kitchen / Adroit wrappers return discount 0.99 for every env step, and the
    # replay multiplies by 0.99 again per agent step: gamma = 0.99^(action repeat + 1) per step.
    ("discount", _manipulation, _authors_discount,
     "sear/environments/{metaworld,kitchen,adroit}_dm_env.py step(), sear/replay_buffer.py"),
    ("mask_downsample", _manipulation, "stride", "sear/environments/wrappers.py: SegmentationFilter [::3, ::3]"),
    # The paper's multi-task latent is 512 (TASK_DEFAULTS below); the authors' code keeps 4096 there too.
    ("latent_dim", lambda cfg: _multitask(cfg) and cfg.method != "ef", 4096,
     "sear/cfgs/agent/sear.yaml: latent_dim 4096 (no task cfg overrides it)"),
)}


def _drqv2_std_steps(cfg):
    import envs  # DrQ-v2's per-task table lives with the other suite facts; late so --help needs no MuJoCo
    return envs.exploration_std_steps(cfg.env)


# DrM's dm_control task configs (github.com/XuGW-Kevin/DrM at 317116a, cfgs/): what a --drm run on each
# task takes where it differs from this project's defaults. Every task: its cfgs/task/<task>.yaml (the
# `hard` group's exploration schedule, lr, feature_dim, batch_size, replay_buffer_size,
# agent.max_perturb_factor) over cfgs/config.yaml (replay_buffer_size 1000000). agent.target_lambda is 0.6
# in all of them (the --drm-lambda default); nstep is config.yaml's 3 everywhere (ours). docs/drm.md.
_DRM_HARD = {"std_steps": 2_000_000}                   # cfgs/task/hard.yaml: linear(1.0,0.1,2000000)
_DRM_BIG = {"lr": 8e-5, "feature_dim": 100}            # dog_* and humanoid_*
_DRM_REPLAY = {"replay_size": 1_000_000}               # cfgs/config.yaml: replay_buffer_size
DRM_TASKS = {
    "acrobot-swingup": {**_DRM_REPLAY},
    "acrobot-swingup_sparse": {**_DRM_REPLAY, **_DRM_HARD, "drm_max_perturb": 0.9},
    "cartpole-swingup_sparse": {**_DRM_REPLAY},
    "cheetah-run": {**_DRM_REPLAY},
    "dog-run": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "dog-stand": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "dog-trot": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.9},
    "dog-walk": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "hopper-hop": {**_DRM_REPLAY},
    "humanoid-run": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "humanoid-stand": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.9},
    "humanoid-walk": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.9},
    "manipulator-bring_ball": {**_DRM_REPLAY, **_DRM_HARD, "lr": 8e-5, "drm_max_perturb": 0.9},
    "quadruped-run": {"replay_size": 100_000},
    "quadruped-walk": {"replay_size": 100_000},
    "reacher-easy": {**_DRM_REPLAY},
    "reacher-hard": {**_DRM_REPLAY},
    "walker-run": {**_DRM_REPLAY, "batch_size": 512},
}
DRM_MAX_PERTURB = {env: task["drm_max_perturb"] for env, task in DRM_TASKS.items() if "drm_max_perturb" in task}
_DRM_SOURCE = {"std_steps": "cfgs/task/hard.yaml: stddev_schedule linear(1.0,0.1,2000000)",
               "lr": "cfgs/task/<task>.yaml: lr", "feature_dim": "cfgs/task/<task>.yaml: feature_dim",
               "batch_size": "cfgs/task/walker_run.yaml: batch_size",
               "replay_size": "cfgs/config.yaml: replay_buffer_size; cfgs/task/quadruped_{run,walk}.yaml",
               "drm_max_perturb": "cfgs/task/<task>.yaml: agent.max_perturb_factor"}


def _drm_row(name):
    """The TASK_DEFAULTS row of DrM's value of `name` (DRM_TASKS) for --drm runs on its tasks."""
    return (name, lambda cfg: cfg.drm and name in DRM_TASKS.get(cfg.env, {}), lambda cfg: DRM_TASKS[cfg.env][name],
            f"DrM's {_DRM_SOURCE[name]}")


# Per-task (and per-method) defaults, applied under both recipes before the recipe's own rows; a later row
# wins over an earlier one. The paper's multi-task settings (its hyper-parameter table): the task sets
# (metaworld-mt3, -mt10, -mt50) train with a smaller latent and a 4x longer exploration schedule; the
# authors' code keeps latent 4096 there (its row in RECIPES). Plain dm_control tasks (the paper is silent)
# take DrQ-v2's exploration schedule by task. DEAR takes c1 (its cosine term) and c2 from its released
# dear.yaml (docs/dear.md). --drm runs on DrM's dm_control tasks take DrM's task config (DRM_TASKS).
TASK_DEFAULTS = (
    ("recon_coef", _dear, 1.0, "DEAR's dear/cfgs/agent/dear.yaml: reconstruction_loss_coeff (its cosine term)"),
    ("mask_coef", _dear, 0.25, "DEAR's dear/cfgs/agent/dear.yaml: mask_loss_coeff"),
    ("latent_dim", _multitask, 512, "paper, hyper-parameter table, multi-task"),
    ("latent_dim", lambda cfg: cfg.method == "ef", 2048, "efrl cfgs/agent/drqv2ef.yaml: hs_dim (docs/foresight.md)"),
    ("std_steps", _multitask, 2_000_000, "paper, hyper-parameter table, multi-task; the authors' "
                                         "multi-task task cfgs: stddev_schedule linear(1.0,0.1,2000000)"),
    ("std_steps", lambda cfg: _drqv2_std_steps(cfg) is not None, _drqv2_std_steps,
     "DrQ-v2's and the authors' cfgs/task/{easy,medium,hard}.yaml: stddev_schedule by task"),
    *map(_drm_row, _DRM_SOURCE),
)

# What --help says of the rows above: a field's default there is the value where no row applies.
_DRM_ON = "with --drm on DrM's tasks (cli.DRM_TASKS, docs/drm.md)"
TASK_DEFAULTS_HELP = {
    "latent_dim": "512 on the task sets (metaworld-mt3, -mt10, -mt50); 2048 with --method ef",
    "std_steps": "2000000 on the task sets; on dm_control tasks DrQ-v2's by task: 100000 (easy), 500000 (medium, and "
                 f"every task not in its table), 2000000 (hard: humanoid); 2000000 {_DRM_ON}: DrM's hard tasks",
    "recon_coef": "1.0 with --method dear", "mask_coef": "0.25 with --method dear",
    "drm_max_perturb": f"0.9 or 0.6 {_DRM_ON}",
    "lr": f"8e-05 {_DRM_ON}: dog-*, humanoid-*, manipulator-bring_ball",
    "feature_dim": f"100 {_DRM_ON}: dog-*, humanoid-*",
    "replay_size": f"1000000 {_DRM_ON}, 100000 on quadruped-run and -walk",
    "batch_size": f"512 {_DRM_ON}: walker-run",
}
DRM_SUFFIX = "+drm"  # sweep.py's and the tables' name of a method run with --drm: drq+drm is DrM


def method_label(config) -> str:
    """A run's method as run directories, sweep.py and plot tables name it: 'drq', or 'drq+drm' with
    --drm. `config` is a Config or a saved config dict (one without 'drm' predates the flag)."""
    get = config.get if isinstance(config, dict) else lambda k: getattr(config, k, None)
    return f"{get('method')}{DRM_SUFFIX if get('drm') else ''}"


def split_method_label(label: str) -> tuple[str, tuple[str, ...]]:
    """('drq', ('--drm',)) for 'drq+drm'; (label, ()) for a plain method."""
    return (label[:-len(DRM_SUFFIX)], ("--drm",)) if label.endswith(DRM_SUFFIX) else (label, ())


def apply_recipe(cfg, recipe: str, explicit: set) -> list[str]:
    """Set the per-task rows (TASK_DEFAULTS), then the recipe's values on `cfg`, except fields the user
    gave explicitly and fields that do nothing in this run (APPLIES). Returns what changed."""
    changed = {}  # a recipe row may override a per-task row: report the value that stands
    for name, applies, value, source in (*TASK_DEFAULTS, *RECIPES.get(recipe, ())):
        if name in explicit or not applies(cfg) or not acts(name, vars(cfg)):  # never a value that does nothing
            continue
        setattr(cfg, name, value(cfg) if callable(value) else value)
        changed[name] = f"{name}={getattr(cfg, name)} ({source})"
    return list(changed.values())


# ------------------------------------------------------------------------------------------------
# Flags and checks
# ------------------------------------------------------------------------------------------------
class OneLineParser(argparse.ArgumentParser):
    def error(self, message):  # the caller prints it as one line, as every other bad input
        raise ConfigError(message)


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def whole_number(text: str) -> int:
    """An int flag's value: an integer, or a float that is one (--frames 1e6, 2.5e5); else one line."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}'") from None
    if not value.is_integer():  # also inf and nan
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}' is not a whole number")
    return int(value)


def field_groups(Config) -> list:
    """[(title, defaults, fields)] of the flags: Config's own fields, those of each dataclass it inherits
    (sear.Config, drm.DrMConfig, ...), then RunConfig's."""
    groups = []
    for cls in (c for c in Config.__mro__ if dataclasses.is_dataclass(c)):
        own = cls.__dict__.get("__annotations__", {})
        module = "train" if cls.__module__ == "__main__" else cls.__module__  # `python sear.py` runs train.py so
        title = f"the experiment ({module.replace('.', '/')}.py {cls.__name__})"
        groups.append((title, cls(), [f for f in dataclasses.fields(cls) if f.name in own]))
    return groups + [("the run (harness/cli.py RunConfig)", RunConfig(), list(dataclasses.fields(RunConfig)))]


# --help: the flags that matter (docs/flags.md), in these groups; --help-all: every flag, by the dataclass
# that holds it. Both are generated from the fields' docs, defaults, choices and APPLIES.
HELP_GROUPS = (
    ("what to run", ("env", "method", "drm", "recipe", "seed", "frames")),
    ("the method", ("recon_coef", "mask_coef", "curl_lr", "dear_feature", "std_steps", "precision")),
    ("robot masks", ("mask_noise", "mask_approx", "mask_source", "mask_downsample")),
    ("the suites", ("backgrounds", "difficulty", "camera_distraction", "color_distraction", "render_quality",
                    "pole_inertia", "kitchen_camera", "eval_episodes_per_task")),
    ("budgets", ("batch_size", "replay_size", "eval_every", "max_episode_steps")),
    ("the process", ("device", "threads", "prefetch", "run_root", "resume", "evaluate", "init_from", "init_parts",
                     "save_video", "save_buffer", "snapshot_minutes")),
)
METAVARS = {"env": "ENV", "resume": "RUN_DIR", "evaluate": "RUN_DIR", "init_from": "RUN_DIR", "run_root": "DIR",
            "device": "DEVICE", "replay_device": "DEVICE", "backgrounds": "davis|DIR",
            "mask_source": "sim|learned:PATH"}


def help_text(f, defaults, methods: dict) -> str:
    """A flag's help: its doc, its default (and per-task defaults), and where it acts (APPLIES)."""
    if f.name == "method":  # the METHODS table documents itself
        return "; ".join(f"{name}: {m.doc}" for name, m in methods.items()) + " (default: 'sear')"
    text = f"{f.metadata['doc']} (default: {getattr(defaults, f.name)!r}"
    text += f"; per task: {TASK_DEFAULTS_HELP[f.name]})" if f.name in TASK_DEFAULTS_HELP else ")"
    text += f"; only for {APPLIES[f.name][1]}" if f.name in APPLIES else ""
    return text.replace("%", "%%")  # argparse formats help with %: "0.8%" must reach it as "0.8%%"


def add_flag(group, f, help_text: str, methods: dict) -> None:
    """One field as one flag: --x / --no-x for booleans, a typed value otherwise (ints also as 1e6)."""
    if f.type in ("bool", bool):
        group.add_argument(flag(f.name), action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS,
                           help=help_text)
        return
    kind = f.type if isinstance(f.type, str) else f.type.__name__
    choices = list(methods) if f.name == "method" else f.metadata.get("choices")
    group.add_argument(flag(f.name), type={"int": whole_number, "float": float, "str": str}[kind], choices=choices,
                       default=argparse.SUPPRESS, help=help_text,
                       metavar=None if choices else METAVARS.get(f.name, {"int": "N", "float": "X"}.get(kind, "TEXT")))


class HelpAll(argparse.Action):
    """--help-all: the help of every flag (the parser `full()` builds), then exit."""

    def __init__(self, option_strings, dest, full=None, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)
        self.full = full

    def __call__(self, parser, namespace, values, option_string=None):
        self.full().print_help()
        parser.exit()


def help_sections(Config, full: bool) -> list:
    """[(title, field names)] of --help (HELP_GROUPS, then the rest untitled: parsed, not shown) or, full,
    of --help-all (every field by its dataclass)."""
    if full:
        return [(title, [f.name for f in fields]) for title, _, fields in field_groups(Config)]
    shown = {name for _, names in HELP_GROUPS for name in names}
    rest = [f.name for _, _, fields in field_groups(Config) for f in fields if f.name not in shown]
    return [*HELP_GROUPS, (None, rest)]


def build_parser(Config, methods: dict, full=False) -> OneLineParser:
    """One flag per field of Config and RunConfig. --help shows HELP_GROUPS' flags, --help-all (full=True)
    every flag by its dataclass; the others parse all the same."""
    fields = {f.name: (f, defaults) for _, defaults, group in field_groups(Config) for f in group}
    epilog = f"The flags that matter; all {len(fields)}: python sear.py --help-all. docs/flags.md has both."
    parser = OneLineParser(prog="sear.py", usage="%(prog)s [--env ENV] [--method METHOD] [--FLAG VALUE ...] | "
                                                 "--resume RUN_DIR | --evaluate RUN_DIR",
                           description="SEAR: Structured Environment-Agent Representations for visual RL (ICML 2023).",
                           epilog=None if full else epilog)
    parser.add_argument("--help-all", action=HelpAll, full=lambda: build_parser(Config, methods, full=True),
                        help=f"show all {len(fields)} flags and exit")
    for title, names in help_sections(Config, full):
        group = parser.add_argument_group(title) if title else parser
        for name in names:
            f, defaults = fields[name]
            add_flag(group, f, help_text(f, defaults, methods) if title else argparse.SUPPRESS, methods)
    return parser


def negative_numbers_as_values(argv: list[str]) -> list[str]:
    """'--lr -1e-4' as '--lr=-1e-4': argparse's rule for negative numbers knows -1 and -1.5 but not
    -1e-4, takes it for a flag and says 'expected one argument' instead of what is wrong with it."""
    joined = []
    for token in argv:
        if joined and joined[-1].startswith("--") and "=" not in joined[-1] and token.startswith("-"):
            try:
                float(token)
            except ValueError:
                pass
            else:
                joined[-1] += "=" + token
                continue
        joined.append(token)
    return joined


def flag_names(Config) -> set[str]:
    """Every flag sear.py's parser has: one per field, plus --no-X for booleans, and --help-all."""
    names = {"--help-all"}
    for f in (*dataclasses.fields(Config), *dataclasses.fields(RunConfig)):
        names.add(flag(f.name))
        if f.type in ("bool", bool):
            names.add("--no-" + flag(f.name)[2:])
    return names


def no_such_flag(name, known: set[str]) -> str:
    """'no flag --frams; did you mean --frames?' (sweep.py says it of the flags it passes on)."""
    close = difflib.get_close_matches(name, sorted(known), n=1)
    return f"no flag {name}" + (f"; did you mean {close[0]}?" if close else "")


def unknown_arguments(extras: list[str], known: set[str]) -> str:
    """The parser's error for what it did not recognise: the first unknown flag, with a suggestion."""
    flags = [token.split("=", 1)[0] for token in extras if token.startswith("--")]
    return no_such_flag(flags[0], known) if flags else f"unrecognized arguments: {' '.join(extras)}"


# ------------------------------------------------------------------------------------------------
# Where each setting acts: a flag given where it does nothing is refused (or, for sweep.py, dropped)
# ------------------------------------------------------------------------------------------------
# The methods by what they read, named here (plot.py reads config.json without torch); tests check them
# against sear.METHODS (uses_mask, encoder): a new method that uses the mask or the pooled encoder is added here.
MASK_METHODS = ("sear", "sear-nosplit", "rgbm", "dear")                   # Method.uses_mask
POOLED_METHODS = ("sear", "ae", "mae", "curl", "sear-nosplit", "dear", "ef")  # Method.encoder == "pooled"
TASK_SETS = ("mt3", "mt10", "mt50")  # metaworld-<set>; envs.py's _METAWORLD_SETS


def suite_of(env: str) -> str:
    """dmc | distracting | metaworld | task-set | kitchen | adroit: the suite of an env name as envs.py names
    them, read from the name alone (no MuJoCo; tests check it against envs.py's parser)."""
    prefix, _, rest = env.partition("-")
    if env.endswith("-distracting"):
        return "distracting"
    if prefix == "metaworld":
        return "task-set" if rest in TASK_SETS else "metaworld"
    return prefix if prefix in ("kitchen", "adroit") else "dmc"


def listing(names) -> str:
    """'a, b and c'."""
    names = list(names)
    return ", ".join(names[:-1]) + f" and {names[-1]}" if len(names) > 1 else "".join(names)


def only_methods(*names, text=None):
    """An APPLIES row: the setting acts with these --method values."""
    return lambda c: c.get("method", "sear") in names, text or f"--method {listing(names)}"


def only_suites(*suites, text):
    return lambda c: suite_of(c.get("env", "")) in suites, text


def _uses_mask(c) -> bool:
    return c.get("method", "sear") in MASK_METHODS


_MASK = f"methods that use the robot mask (--method {listing(MASK_METHODS)})"
_DRM = (lambda c: bool(c.get("drm")), "runs with --drm")
_DISTRACTING = only_suites("distracting", text="Distracting Control (*-distracting envs)")

# Where each setting acts, one row per field: (acts(settings), what it is for). `settings` is a run's
# config as config.json holds it (a dict: an old run's may lack later fields). A field without a row acts
# in every run and is listed in EVERYWHERE; tests/test_applies.py fails on a field in neither.
APPLIES = {
    "mask_noise": (_uses_mask, _MASK),
    "mask_approx": (_uses_mask, _MASK),
    "mask_source": (_uses_mask, _MASK),
    "learned_mask_iou": (lambda c: _uses_mask(c) and c.get("mask_source", "sim") != "sim",
                         "--mask-source learned:PATH, with one of the " + _MASK),
    "mask_downsample": (lambda c: _uses_mask(c) and suite_of(c.get("env", "")) in ("metaworld", "task-set", "kitchen",
                                                                                   "adroit"),
                        "the manipulation suites (metaworld-*, kitchen-*, adroit-*; dm_control renders masks at 84), "
                        "with one of the " + _MASK),
    "latent_dim": only_methods(*POOLED_METHODS, text=f"SEAR's pooled encoder (--method {listing(POOLED_METHODS)}; "
                                                     f"drq and rgbm flatten the feature map)"),
    "recon_coef": only_methods("sear", "sear-nosplit", "ae", "mae", "dear",
                               text="--method sear, sear-nosplit, ae (2 x c1), mae and dear (c1 of its cosine term)"),
    "mask_coef": only_methods("sear", "sear-nosplit", "dear"),
    "ae_latent_lambda": only_methods("ae"),
    "mae_ratio": only_methods("mae"),
    "mae_patch": only_methods("mae"),
    "curl_tau": only_methods("curl"),
    "curl_lr": only_methods("curl"),
    "dear_feature": only_methods("dear"),
    **dict.fromkeys(("ef_agent_dim", "ef_horizon", "ef_coef", "ef_babbling_steps"), only_methods("ef")),
    **dict.fromkeys(("drm_dormant_threshold", "drm_target_ratio", "drm_dormant_temp", "drm_lambda", "drm_lambda_temp",
                     "drm_perturb_every", "drm_min_perturb", "drm_max_perturb", "drm_perturb_rate", "drm_expectile"),
                    _DRM),
    **dict.fromkeys(("backgrounds", "difficulty", "camera_distraction", "color_distraction"), _DISTRACTING),
    "pole_inertia": (lambda c: suite_of(c.get("env", "")) in ("dmc", "distracting")
                     and c.get("env", "").startswith("cartpole-"),
                     "cartpole (cartpole-* and cartpole-*-distracting envs)"),
    "kitchen_camera": only_suites("kitchen", text="Kitchen (kitchen-* envs)"),
    "eval_episodes_per_task": only_suites("task-set", text="the task sets (metaworld-mt3, -mt10, -mt50)"),
    "eval_episodes": (lambda c: not (suite_of(c.get("env", "")) == "task-set" and c.get("eval_episodes_per_task")),
                      "runs other than a task set given --eval-episodes-per-task (which then sets every "
                      "task's episodes)"),
    "init_parts": (lambda c: bool(c.get("init_from")), "runs with --init-from"),
}
EVERYWHERE = frozenset((
    "env", "method", "drm", "seed", "frames", "action_repeat", "max_episode_steps", "eval_every", "precision",
    "frame_stack", "replay_size", "seed_frames", "exploration_steps", "nstep", "batch_size", "discount", "lr",
    "update_every", "critic_tau", "feature_dim", "hidden_dim", "std_start", "std_end", "std_steps", "std_clip",
    "render_quality",
    # RunConfig: how the process runs, whatever the experiment
    "device", "compile", "cuda_graph", "batch_seeds", "tf32", "replay_device", "prefetch", "threads", "run_root", "resume", "evaluate", "recipe",
    "save_buffer", "save_video", "init_from", "log_every", "snapshot_minutes", "drop_inapplicable"))


def acts(name: str, settings: dict) -> bool:
    """Whether setting `name` acts in a run of these settings (APPLIES; a field without a row always does)."""
    return name not in APPLIES or bool(APPLIES[name][0](settings))


def acting_settings(config: dict) -> dict:
    """A run's config.json less the settings that did nothing in it: what a plot may name a curve by. Runs
    from before APPLIES recorded them (--method drq --dear-feature push ran as drq)."""
    return {name: value for name, value in config.items() if acts(name, config)}


def given_as(name: str, value) -> str:
    """A flag as it was typed: --mask-approx, --no-mask-approx, --recon-coef 1.0."""
    if isinstance(value, bool):
        return flag(name) if value else "--no-" + flag(name)[2:]
    return f"{flag(name)} {value}"


def idle_flags(cfg, run: RunConfig, given: dict) -> dict:
    """{name: what it is for} of the flags given that do nothing in this run (APPLIES)."""
    settings = {**vars(cfg), **vars(run)}
    return {name: APPLIES[name][1] for name in given if not acts(name, settings)}


def refusal(idle: dict, given: dict, where: str) -> str:
    """'--x 1 does nothing in this run (drq on walker-walk): it is for ...', of one or several flags."""
    if len(idle) == 1:
        (name, text), = idle.items()
        return f"{given_as(name, given[name])} does nothing in this run ({where}): it is for {text}"
    return (f"{listing(given_as(name, given[name]) for name in idle)} do nothing in this run ({where}): "
            + "; ".join(f"{flag(name)} is for {text}" for name, text in idle.items()))


def check_applies(cfg, run: RunConfig, given: dict, resumed=False) -> set:
    """A flag given where it does nothing (APPLIES) is one line, exit 2. With --drop-inapplicable (sweep.py:
    one set of flags for every method of a grid) it is dropped instead: back to its default, which
    config.json then records (a resumed run keeps its saved value), in one line for all of them. Returns
    the names dropped."""
    idle = idle_flags(cfg, run, given)
    if not idle:
        return set()
    where = f"{method_label(cfg)} on {cfg.env}"
    if not run.drop_inapplicable:
        raise ConfigError(refusal(idle, given, where))
    defaults = {**vars(type(cfg)()), **vars(RunConfig())}
    for name in () if resumed else idle:
        setattr(cfg if hasattr(cfg, name) else run, name, defaults[name])
    warn(f"--drop-inapplicable: ignored what does nothing in this run ({where})"
         + ("" if resumed else ", config.json records the default") + ": "
         + "; ".join(f"{given_as(name, given[name])} (for {text})" for name, text in idle.items()))
    return set(idle)


# ------------------------------------------------------------------------------------------------
# Values: types (the parser), ranges, the rules between fields
# ------------------------------------------------------------------------------------------------
# Seeds: numpy's legacy seeding (np.random.seed, dm_control's and Meta-World's RandomState) takes [0, 2^32),
# and the eval env's seed is the run's + 100000 (experiment.EVAL_SEED). Episodes' reset seeds go to
# default_rng, which takes any non-negative integer.
EVAL_SEED = 100_000
MAX_SEED = 2**32 - 1 - EVAL_SEED

# The range of each numeric flag; the parser checks the types, `choices` the enums.
RANGES = (
    ("> 0", lambda v: v > 0, ("frames", "frame_stack", "replay_size", "nstep", "batch_size", "update_every",
                              "eval_episodes", "feature_dim", "latent_dim", "hidden_dim", "std_steps",
                              "eval_every", "mae_patch", "drm_perturb_every", "lr", "ef_agent_dim", "ef_horizon")),
    (">= 0", lambda v: v >= 0, ("action_repeat", "max_episode_steps", "seed_frames", "exploration_steps",
                                "recon_coef", "mask_coef", "ae_latent_lambda", "curl_lr", "std_end", "std_clip",
                                "eval_episodes_per_task", "snapshot_minutes", "threads", "drm_dormant_temp",
                                "drm_lambda_temp", "drm_perturb_rate", "ef_coef", "ef_babbling_steps")),
    ("in [0, 1]", lambda v: 0.0 <= v <= 1.0, ("discount", "critic_tau", "curl_tau", "mask_noise", "mae_ratio",
                                              "camera_distraction", "color_distraction", "drm_dormant_threshold",
                                              "drm_target_ratio", "drm_lambda", "drm_min_perturb", "drm_max_perturb",
                                              "drm_expectile")),
    (f"in [0, {MAX_SEED}] (numpy seeds below 2^32, and the eval env's is --seed + {EVAL_SEED})",
     lambda v: 0 <= v <= MAX_SEED, ("seed",)),
)


def _mask_source_ok(source: str) -> bool:
    return source == "sim" or (source.startswith("learned:") and len(source) > len("learned:"))


# The rules between fields: (broken(cfg), what to say).
RELATIONS = (
    (lambda cfg: cfg.method == "ef" and cfg.ef_agent_dim >= cfg.latent_dim,
     lambda cfg: f"--ef-agent-dim ({cfg.ef_agent_dim}) must be below --latent-dim ({cfg.latent_dim}): the rest of "
                 f"the latent is EF's scene part"),
    (lambda cfg: cfg.drm and cfg.drm_perturb_every % cfg.update_every,
     lambda cfg: f"--drm-perturb-every ({cfg.drm_perturb_every}) must be a multiple of --update-every "
                 f"({cfg.update_every}): DrM perturbs at the start of an update"),
    (lambda cfg: cfg.drm_min_perturb > cfg.drm_max_perturb,
     lambda cfg: f"--drm-min-perturb ({cfg.drm_min_perturb}) must not exceed --drm-max-perturb "
                 f"({cfg.drm_max_perturb})"),
    (lambda cfg: cfg.latent_dim % 2,
     lambda cfg: f"--latent-dim must be even (it is split in two halves), got {cfg.latent_dim}"),
    (lambda cfg: 84 % cfg.mae_patch, lambda cfg: f"--mae-patch must divide 84, got {cfg.mae_patch}"),
    (lambda cfg: not _mask_source_ok(cfg.mask_source),
     lambda cfg: f"--mask-source must be sim or learned:PATH (a segment.py model file), got '{cfg.mask_source}'"),
)


def not_finite(cfg, run) -> str | None:
    for settings in (cfg, run):
        for f in dataclasses.fields(settings):
            value = getattr(settings, f.name)
            if isinstance(value, float) and not math.isfinite(value):  # inf passes every range, NaN none
                return f"{flag(f.name)} must be a finite number, got {value}"


def out_of_range(cfg, run) -> str | None:
    for rule, holds, names in RANGES:
        for name in names:
            value = getattr(cfg, name) if hasattr(cfg, name) else getattr(run, name)
            if not holds(value):
                return f"{flag(name)} must be {rule}, got {value}"


def unrelated(cfg, run) -> str | None:
    return next((say(cfg) for broken, say in RELATIONS if broken(cfg)), None)


def no_video_writer(cfg, run) -> str | None:
    if run.save_video:
        try:
            import imageio_ffmpeg  # noqa: F401  (brings its own ffmpeg binary)
        except ImportError:
            return "--save-video needs imageio-ffmpeg: pip install -r requirements.txt"


CHECKS = (not_finite, out_of_range, unrelated, no_video_writer)


def validate(cfg, run: RunConfig, methods: dict = None) -> None:
    """What the parser's types and choices cannot see: finite numbers, ranges and the rules between fields
    (CHECKS, in order; the first that fails is the one line)."""
    message = next(filter(None, (check(cfg, run) for check in CHECKS)), None)
    if message:
        raise ConfigError(message)


def check_env(cfg) -> None:
    """An unknown --env is one line ("did you mean") before anything else is read of it."""
    import envs  # late: --help needs no MuJoCo
    try:
        envs.default_action_repeat(cfg.env)
    except envs.EnvError as e:
        raise ConfigError(str(e)) from None


def check_learning_starts(cfg) -> None:
    """Learning starts once the replay holds the seed frames' steps: a smaller replay never learns."""
    import envs
    repeat = cfg.action_repeat or envs.default_action_repeat(cfg.env)
    steps = cfg.seed_frames // repeat
    if cfg.replay_size < steps:
        raise ConfigError(f"--replay-size {cfg.replay_size} is smaller than the {steps} steps of --seed-frames "
                          f"{cfg.seed_frames} (action repeat {repeat}): learning would never start")


# ------------------------------------------------------------------------------------------------
# Saved configs: config.json, --resume, --init-from
# ------------------------------------------------------------------------------------------------
def config_dict(cfg, run: RunConfig) -> dict:
    """config.json and a snapshot's "config": every saved field of both, flat, as one --flag each."""
    unsaved = {f.name for f in dataclasses.fields(RunConfig) if not f.metadata["saved"]}
    return {**dataclasses.asdict(cfg), **{k: v for k, v in dataclasses.asdict(run).items() if k not in unsaved}}


def split_config(values: dict, Config) -> tuple:
    """The (Config, RunConfig) of a flat dict of settings: fields since removed are dropped, renamed
    ones carried over."""
    values = dict(values)
    if "std_frames" in values and "std_steps" not in values:  # snapshots from before std counted steps
        values["std_steps"] = max(1, values["std_frames"] // max(1, values.get("action_repeat") or 1))

    def build(cls):
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})
    return build(Config), build(RunConfig)


def first_sentence(text) -> str:
    """The first sentence of a message, on one line. Error lines end at a sentence boundary; a
    length cut would stop them mid-word (torch's archive errors run on for 400 characters)."""
    text = " ".join(str(text).split())
    end = text.find(". ")
    sentence = text[: end + 1] if end >= 0 else text
    return sentence if not sentence or sentence.endswith((".", "!", "?")) else sentence + "."


def load_snapshot(run_dir, flag="--resume", mmap=False):
    """A run's snapshot.pt; every problem is a ConfigError naming `flag` (if any). mmap=True maps the
    tensors instead of reading them (--init-from reads a snapshot twice: its config, then its weights)."""
    import torch
    path = os.path.join(run_dir, "snapshot.pt")
    check_run_dir(run_dir, flag)
    flag = f"{flag}: " if flag else ""
    if not os.path.exists(path):
        owner = lock_owner(run_dir)
        if owner:
            raise ConfigError(f"{flag}'{run_dir}' is in use by {owner}, which has not written its first snapshot yet")
        raise ConfigError(f"{flag}'{run_dir}' has no snapshot.pt (the run stopped before its first "
                          f"snapshot; see --snapshot-minutes)")
    try:
        return torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as e:  # corrupt or foreign file: say so in one line
        reason = first_sentence(e)
        what = f"{type(e).__name__}" + (f": {reason}" if reason else "")
        if isinstance(e, EOFError) or "failed finding central directory" in str(e):  # a zip without its end
            raise ConfigError(f"{flag}'{path}' is cut short ({what.rstrip('.')}): sear.py writes a snapshot whole or "
                              f"not at all, so this is a copy or move that did not finish; copy snapshot.pt again "
                              f"from the run's original folder, where its last snapshot stands (this folder keeps "
                              f"no other)") from None
        raise ConfigError(f"{flag}cannot read '{path}': {what}")


# ------------------------------------------------------------------------------------------------
# Run directories as inputs: --run-root, the RUN_DIR of --resume / --evaluate / --init-from, its owner
# ------------------------------------------------------------------------------------------------
def parents(path):
    """The folders above path, nearest first, as given (relative stays relative)."""
    while os.path.dirname(path) not in ("", path):
        path = os.path.dirname(path)
        yield path


def check_run_root(run_root):
    """Before a new run directory is made: --run-root must be a folder this process can write, or
    one it can create (the nearest existing parent is then checked)."""
    existing = next(p for p in (run_root, *parents(run_root), ".") if os.path.lexists(p))
    if not os.path.isdir(existing):
        raise ConfigError(f"--run-root: '{run_root}' is a file, not a folder" if existing == run_root else
                          f"--run-root: cannot make '{run_root}': '{existing}' is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        read_only = os.statvfs(existing).f_flag & getattr(os, "ST_RDONLY", 0)
        raise ConfigError(f"--run-root: cannot write in '{existing}': "
                          + ("read-only file system" if read_only else "permission denied"))


def check_run_dir(run_dir, flag="--resume"):
    """A folder sear.py made (config.json or snapshot.pt in it), not a file, a typo or the folder of runs."""
    flag = f"{flag}: " if flag else ""
    if not os.path.exists(run_dir):
        raise ConfigError(f"{flag}no such run directory '{run_dir}'")
    if not os.path.isdir(run_dir):
        raise ConfigError(f"{flag}'{run_dir}' is a file, not a run directory")
    if not any(os.path.exists(os.path.join(run_dir, name)) for name in ("config.json", "snapshot.pt")):
        runs = []
        with contextlib.suppress(OSError):
            runs = sorted(d for d in os.listdir(run_dir) if os.path.isfile(os.path.join(run_dir, d, "config.json")))
        hint = (f"; it holds {len(runs)} run director{'y' if len(runs) == 1 else 'ies'}, e.g. "
                f"{os.path.join(run_dir, runs[0])}") if runs else ""
        raise ConfigError(f"{flag}'{run_dir}' is not a run directory (no config.json or snapshot.pt in it){hint}")


def check_run_config(run_dir):
    """--resume: config.json must be the JSON object the run wrote (plot.py and sweep.py read it). A
    broken one is not replaced silently: moved aside by the user, the resumed run writes it again
    from the snapshot's copy (experiment.RunDir)."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.lexists(path):
        return
    try:
        with open(path) as f:
            ok = isinstance(json.load(f), dict)
        reason = "not a JSON object"
    except (OSError, ValueError) as e:  # ValueError: JSONDecodeError, UnicodeDecodeError
        ok, reason = False, f"{type(e).__name__}: {first_sentence(getattr(e, 'strerror', None) or e).rstrip('.')}"
    if not ok:
        raise ConfigError(f"--resume: cannot read '{path}' ({reason}); snapshot.pt holds the run's config: move "
                          f"config.json aside and resume again to have it written from there")


# The owner's lock (experiment.RunLock takes it): an flock on this file, which holds "pid host".
LOCK_FILE = "run.lock"


def lock_holder(fd) -> str:
    """'sear.py process PID [on HOST]', as the owner wrote it into the lock file. The owner writes it
    right after taking the lock: a file still empty, or naming a dead process of this host (the
    previous owner's), is read again for up to 2 s."""
    for _ in range(40):
        pid, _, host = os.pread(fd, 256, 0).decode(errors="replace").strip().partition(" ")
        if pid.isdigit() and (host != socket.gethostname() or pid_alive(int(pid))):
            return f"sear.py process {pid}" + (f" on {host}" if host != socket.gethostname() else "")
        time.sleep(0.05)
    return "another sear.py process (pid unknown)"


def lock_owner(run_dir) -> str | None:
    """Who holds RUN_DIR's lock now (see lock_holder), or None; takes nothing and creates nothing."""
    try:
        import fcntl
        fd = os.open(os.path.join(run_dir, LOCK_FILE), os.O_RDONLY)
    except (ImportError, OSError):
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None
    except OSError:
        return lock_holder(fd)
    finally:
        os.close(fd)  # also drops the shared lock, if it was taken


def pid_alive(pid) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def init_fields(cfg, init_parts: str) -> tuple[str, ...]:
    """The config fields that fix the shapes of the parts --init-parts copies: they must be the
    source run's."""
    fields = ("method", "latent_dim", "frame_stack")
    if init_parts != "encoder" and cfg.method == "curl":
        fields += ("feature_dim",)  # CURL's W and key read the critic's feature
    if init_parts == "all":
        fields += ("feature_dim", "hidden_dim")
    return fields


def inherit_from_source(cfg, run: RunConfig, explicit: set, Config) -> set:
    """--init-from: the fields that fix the shapes of the copied networks (init_fields) come from the
    source run's config; given explicitly, they must equal it. Returns the fields taken."""
    state = load_snapshot(run.init_from, "--init-from", mmap=True)
    source, defaults = state["config"], Config()
    run.init_from = os.path.abspath(run.init_from)  # config.json names the source from anywhere
    taken = set()
    if "method" not in explicit:  # first: which fields matter depends on the method
        cfg.method = source["method"]
        taken.add("method")
    for name in init_fields(cfg, run.init_parts):
        value = source.get(name, getattr(defaults, name))
        if name in explicit and getattr(cfg, name) != value:
            raise ConfigError(f"--init-from: the source run has {flag(name)} {value} but this run "
                              f"{getattr(cfg, name)}; --init-parts {run.init_parts} copies networks of that size "
                              f"(leave {flag(name)} out to take the source's)")
        if name not in explicit:
            setattr(cfg, name, value)
            taken.add(name)
    frame = state["counters"]["step"] * source.get("action_repeat", 1)
    print(f"init-from {run.init_from} ({source['env']}, frame {frame}): copies {run.init_parts}; "
          + ", ".join(f"{k}={getattr(cfg, k)}" for k in init_fields(cfg, run.init_parts)) + " as the source run")
    return taken


RESUME_MAY_CHANGE = {"frames", "device", "threads", "save_buffer", "log_every", "resume", "snapshot_minutes",
                     "save_video", "compile", "cuda_graph", "batch_seeds", "replay_device", "tf32", "prefetch"}
# --evaluate scores the run as it is: only how many episodes, whether to film, and where to compute.
EVALUATE_MAY_SET = {"evaluate", "eval_episodes", "eval_episodes_per_task", "save_video", "device", "threads"}


def evaluate_config(given: dict, Config, methods: dict) -> tuple:
    """--evaluate RUN_DIR: the run's saved config with the few flags EVALUATE_MAY_SET on top (the run's
    own --save-video does not carry over), and its snapshot."""
    if given.get("resume"):
        raise ConfigError("--evaluate scores a run, --resume trains it further: give one of them")
    snapshot = load_snapshot(given["evaluate"], "--evaluate")
    extra = sorted(set(given) - EVALUATE_MAY_SET)
    if extra:
        may = ", ".join(flag(name) for name in sorted(EVALUATE_MAY_SET - {"evaluate"}))
        raise ConfigError(f"{flag(extra[0])} cannot be given with --evaluate (the run's config holds it); "
                          f"only {may} can")
    cfg, run = split_config({**snapshot["config"], "save_video": False, **given}, Config)
    check_applies(cfg, run, given, resumed=True)  # --eval-episodes-per-task on a single task
    validate(cfg, run, methods)
    return cfg, run, snapshot


def parse_args(argv, Config, methods: dict) -> tuple:
    """(Config, RunConfig, snapshot) from the flags; with --resume or --evaluate, the run's saved
    config (plus the few flags that may change) and its snapshot, else snapshot None."""
    parser = build_parser(Config, methods)
    argv = negative_numbers_as_values(sys.argv[1:] if argv is None else list(argv))
    namespace, extras = parser.parse_known_args(argv)
    if extras:
        parser.error(unknown_arguments(extras, flag_names(Config)))
    given = vars(namespace)
    if given.get("evaluate"):
        return evaluate_config(given, Config, methods)
    if given.get("resume"):
        return resume_config(given, Config, methods)
    cfg, run = split_config(given, Config)
    validate(cfg, run, methods)
    check_env(cfg)
    check_run_root(run.run_root)
    if cfg.mask_source.startswith("learned:"):  # config.json names the model from anywhere
        cfg.mask_source = "learned:" + os.path.abspath(cfg.mask_source[len("learned:"):])
    explicit = set(given)
    if run.init_from:  # the source run fixes the copied networks' sizes; the recipe may not change them
        explicit |= inherit_from_source(cfg, run, explicit, Config)
    explicit -= check_applies(cfg, run, given)  # after --init-from: the method may be the source run's
    changed = apply_recipe(cfg, run.recipe, explicit)
    check_learning_starts(cfg)
    if changed:
        print(f"recipe {run.recipe}: " + "; ".join(changed))
    return cfg, run, None


def resume_config(given: dict, Config, methods: dict) -> tuple:
    """--resume RUN_DIR: the run's saved config, with only RESUME_MAY_CHANGE given otherwise, and its
    snapshot. A resumed config was resolved when the run started: no recipe again."""
    snapshot = load_snapshot(given["resume"])
    check_run_config(given["resume"])
    saved = snapshot["config"]
    cfg, run = split_config({**saved, **given}, Config)
    check_applies(cfg, run, given, resumed=True)
    unsaved = {f.name for f in dataclasses.fields(RunConfig) if not f.metadata["saved"]}
    for k, v in given.items():
        if k not in RESUME_MAY_CHANGE | unsaved and saved.get(k) != v:
            raise ConfigError(f"{flag(k)} cannot change on --resume "
                              f"(run has {saved.get(k)!r}); only {', '.join(sorted(RESUME_MAY_CHANGE))} can")
    validate(cfg, run, methods)
    return cfg, run, snapshot


def main(argv, Config, methods: dict, train, evaluate) -> int:
    """sear.py's exit: 0 done, 2 bad input or a storage error (one line), 1 a run that diverged (one
    line), 130 Ctrl-C and 143 SIGTERM (one line saying what was saved). train(cfg, run, snapshot)
    trains; with --evaluate, evaluate(cfg, run, snapshot) scores the snapshot."""
    configure_allocator()
    with TERM.installed():
        try:
            cfg, run, snapshot = parse_args(argv, Config, methods)
            (evaluate if run.evaluate else train)(cfg, run, snapshot)
        except (ConfigError, StorageError) as e:
            print(f"sear.py: error: {e}", file=sys.stderr)
            return 2
        except NonFinite as e:
            print(f"sear.py: error: {e}", file=sys.stderr)
            return 1
        except Interrupted as e:
            print(f"\nsear.py: {e}", file=sys.stderr)
            return e.code
        except KeyboardInterrupt as stop:  # while reading the flags or the snapshot: nothing started
            cause, code = stop_cause(stop)
            print(f"\nsear.py: {cause} before training started; nothing was saved", file=sys.stderr)
            return code
    return 0


# ------------------------------------------------------------------------------------------------
# SIGTERM: how SLURM, timeout, docker stop and systemd stop a process
# ------------------------------------------------------------------------------------------------
class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt: the same handlers stop the run."""


class TermSignal:
    """SIGTERM stops a run as Ctrl-C does, at the next safe point when the grace allows. While a run
    trains (`defer`, set by experiment.RunDir), the first SIGTERM only asks it to stop there: before
    the run directory is made, or at the next episode end, where a snapshot holds the exact state
    (SLURM's --signal=TERM@SECONDS gives that grace before the time limit). Anywhere else (reading
    flags, --evaluate), or a second time, it stops at once. Exit code 143 (128 + 15).

    Python runs a signal handler in the main thread only, between bytecodes: while that thread is
    inside one long native call (a torch operation, a render) the handler waits for the call to
    end, and a SIGTERM seems ignored. So a watcher thread hears every SIGTERM too (set_wakeup_fd:
    the interpreter's C-level handler writes the signal's number into a pipe at once), and when one
    that stops at once has not ended the process GRACE seconds later, it ends it: one line saying
    what stands (`stands`, set by experiment.RunDir), exit 143, no Python code of the main thread."""

    GRACE = 5.0

    def __init__(self):
        self.defer, self.pending = False, False
        self.received = 0  # SIGTERMs the watcher heard: the handler sees two that came during one call as one
        self.stands = None  # () -> what a forced stop leaves, e.g. "the last snapshot (frame N) stands; ..."
        self.waits_for = None  # () -> what a first SIGTERM waits for, e.g. "the next episode end (...)"

    @contextlib.contextmanager
    def installed(self):
        """The handler and its watcher for the time of a command (main), then the handler before it again."""
        if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
            yield
            return
        self.received = 0
        previous = signal.signal(signal.SIGTERM, self.handle)
        read, write = os.pipe()
        os.set_blocking(write, False)  # set_wakeup_fd's rule: a signal handler never blocks
        previous_fd = signal.set_wakeup_fd(write)
        done = threading.Event()
        threading.Thread(target=self.watch, args=(read, done), daemon=True, name="sigterm-watcher").start()
        try:
            yield
        finally:
            done.set()
            signal.set_wakeup_fd(previous_fd)
            signal.signal(signal.SIGTERM, previous)
            os.close(write)  # the watcher reads the end of the pipe and closes its side

    def watch(self, fd, done: threading.Event):
        try:
            while data := os.read(fd, 64):  # blocks without the GIL
                for signum in data:
                    if signum != signal.SIGTERM:
                        continue
                    self.received += 1
                    if (self.received > 1 or not self.defer) and not done.wait(self.GRACE):
                        self.force_stop()
        finally:
            os.close(fd)

    def force_stop(self):
        try:
            stands = self.stands() if self.stands else "nothing was saved"
        except Exception:  # the last words must not fail
            stands = "the last snapshot, if any, stands"
        os.write(2, f"\nsear.py: stopped by SIGTERM at once: the process did not answer it within {self.GRACE:g} s "
                    f"(inside a long native call); {stands}\n".encode())
        os._exit(128 + signal.SIGTERM)

    def handle(self, signum, frame):
        if self.defer and not self.pending and self.received <= 1:
            self.pending = True
            waits = "the next safe point (an episode end, with a snapshot)"
            with contextlib.suppress(Exception):  # the line must not fail
                waits = self.waits_for() if self.waits_for else waits
            # os.write: print() here could re-enter a write the signal interrupted
            os.write(2, f"\nsear.py: SIGTERM: stopping at {waits}; another SIGTERM stops at once\n".encode())
            return
        raise Terminated


TERM = TermSignal()


def stop_cause(stop: KeyboardInterrupt) -> tuple[str, int]:
    """What stopped the process, as the messages say it, and its exit code."""
    return ("stopped by SIGTERM", 128 + signal.SIGTERM) if isinstance(stop, Terminated) else ("interrupted", 130)


# ------------------------------------------------------------------------------------------------
# The process: glibc's malloc, torch's threads and device
# ------------------------------------------------------------------------------------------------
# glibc's malloc at run time (mallopt): never mmap a block of its own (M_MMAP_MAX 0) and never give
# freed heap back to the OS (M_TRIM_THRESHOLD -1): the update's large activation buffers are then
# reused from one update to the next instead of being mapped, faulted in and unmapped each time.
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # <malloc.h>


def configure_allocator() -> bool:
    """Set glibc's malloc as above for the rest of this process; False where there is no glibc
    (other platforms, musl), which then keep their allocator. Why: on CPU the 84x84x32 decoder
    activations (tens of MB at batch 256) would otherwise be mapped and unmapped by glibc at every
    update: 0.9M minor page faults per SEAR update at batch 256, none once the heap keeps them
    (`benchmarks/bench_agent.py --compare-allocators`, docs/speed.md, "Allocator"). Called where a
    process starts (main): blocks allocated before it keep their mmap."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, -1) == 1


def usable_cores():
    """The cores this process may run on (taskset / cgroup affinity)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def default_threads():
    """OMP_NUM_THREADS when set (sweep.py sets it per job), else every core this process may run on.
    Several runs sharing cores should split them: with more busy threads than cores, torch's threads
    wait on each other and an update gets ~2x slower, not 1x."""
    if os.environ.get("OMP_NUM_THREADS", "").isdigit() and int(os.environ["OMP_NUM_THREADS"]) > 0:
        return int(os.environ["OMP_NUM_THREADS"])
    return usable_cores()


def torch_threads(run: RunConfig) -> int:
    """--threads, else $OMP_NUM_THREADS, else every usable core; never more than the usable cores.
    Clamped, not refused: more threads than cores cannot be faster, and torch's OpenMP threads then
    spin waiting for each other (64 on 2 cores: one nn.init.orthogonal_ of SEAR's encoder ran for
    minutes instead of 6 s), while an OMP_NUM_THREADS that a cluster or a sweep set for other jobs
    should not stop a run (start_warnings says it was clamped)."""
    return min(run.threads or default_threads(), usable_cores())


def start_warnings(cfg, run: RunConfig, training=True) -> list[str]:
    """Settings that run, but not as meant: more threads than cores (clamped), Distracting Control without
    the paper's DAVIS backgrounds, a replay smaller than a batch (one smaller than the seed phase, where
    learning would never start, is refused: check_learning_starts)."""
    warnings, threads, cores = [], run.threads or default_threads(), usable_cores()
    if threads > cores:
        given = f"--threads {run.threads}" if run.threads else f"OMP_NUM_THREADS={threads}"
        warnings.append(f"{given} is more threads than the {cores} cores this process may use; using {cores} "
                        f"(more would only wait on each other: torch's threads spin, and on 2 cores 64 of them "
                        f"took minutes for one operation)")
    if training and cfg.replay_size < cfg.batch_size:
        warnings.append(f"--replay-size {cfg.replay_size} is smaller than --batch-size {cfg.batch_size}: every "
                        f"batch holds the same transitions several times")
    if cfg.env.endswith("-distracting") and not cfg.backgrounds:  # a default that is not the paper's: said every run
        warnings.append(f"{cfg.env} runs on the built-in procedural backgrounds, not the paper's DAVIS-2017 videos; "
                        "for the paper's setting: python envs.py --fetch-davis, then --backgrounds davis")
    return warnings


def torch_setup(run: RunConfig):
    """The run's torch device (--device), and its CPU threads (--threads) set."""
    import torch
    if run.device == "auto":
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    else:
        try:
            device = torch.device(run.device)
        except RuntimeError:
            raise ConfigError(f"--device: unknown device '{run.device}'")
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError(f"--device {run.device}: CUDA is not available on this machine")
    if run.replay_device not in ("auto", "cpu") and torch.device(run.replay_device) != device:
        raise ConfigError(f"--replay-device must be auto, cpu or the run's device ({device}), got '{run.replay_device}'")
    set_tf32(run.tf32)
    if run.compile in ("on", True) and device.type == "cpu" and not cxx_compiler():
        raise ConfigError("--compile on the CPU needs a C++ compiler (inductor builds its kernels with one): no "
                          "g++, c++ or clang++ found; install one or leave --compile off")
    torch.set_num_threads(torch_threads(run))
    return device


def set_tf32(on: bool) -> None:
    """TF32 in CUDA's float32 convolutions and matmuls, on or off (torch turns it on for cuDNN's
    convolutions by default)."""
    import torch
    precision = "tf32" if on else "ieee"
    if hasattr(torch.backends.cudnn, "conv") and hasattr(torch.backends.cudnn.conv, "fp32_precision"):
        torch.backends.cuda.matmul.fp32_precision = torch.backends.cudnn.conv.fp32_precision = precision
    else:  # torch before 2.9
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = on


def cxx_compiler() -> str | None:
    """The C++ compiler inductor's CPU kernels would be built with ($CXX, else the first one found)."""
    return next(filter(None, map(shutil.which, (os.environ.get("CXX", ""), "g++", "c++", "clang++"))), None)
