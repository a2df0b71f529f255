"""sear.py's command line: the run settings (RunConfig), flags generated from the dataclasses (the algorithm's Config
is passed in), the recipes applied (harness/recipes.py), the checks that turn bad input into one line on stderr, the
saved config of --resume, --evaluate and --init-from, and sear.py's exit codes (main).

Every setting is declared once, as a dataclass field: `arg(default, doc, choices, **keys)`, the keys below (META).
The parser, --help and --help-all, the range checks and where each setting acts (its refusals, --drop-inapplicable,
what plot.py names a curve by) are read from there. Loads no numpy or torch at import: sweep.py and plot.py read
flags and configs through it without them.
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import difflib
import functools
import math
import operator
import os
import re
import sys
from dataclasses import dataclass, field

# What the rest of the project calls cli.X lives here or in these (which import nothing of cli):
from harness.files import (LOCK_FILE, ConfigError, StorageError, check_run_config, check_run_root,  # noqa: F401
                           first_sentence, flag, inherit_from_source, load_snapshot, lock_holder, storing,
                           torch_save, write_atomically)
from harness.process import (TERM, Terminated, TermSignal, configure_allocator, cxx_compiler,  # noqa: F401
                             default_threads, set_tf32, start_warnings, stop_cause, torch_threads)
from harness.recipes import DRM_MAX_PERTURB, DRM_TASKS, RECIPES, TASK_DEFAULTS  # noqa: F401


def arg(default, doc, choices=None, **keys):
    """A config field: its default, its one-line doc (--help), the values it takes if a fixed set, and META keys."""
    return field(default=default, metadata={"doc": doc, "choices": choices, **keys})


# The keys a field's arg() may carry (sear.py's arg() passes them on as they are):
#   group="budgets"         its --help group (GROUPS); without one, --help-all shows it
#   metavar="RUN_DIR"       what --help calls its value (else N, X or TEXT by its type)
#   low=0, above=0, high=1  its range: >= low, > above, <= high; why="..." says why
#   acts=("sear", "dear")   the --method values it acts with ("ae (2 x c1)": a note after the name),
#                           or a name of METHOD_SETS ("mask": the methods that use the robot mask)
#   envs="distracting"      the envs it acts on: a name of ENV_SETS
#   when="drm"              the runs it acts in: a setting that is set (--drm), or of CONDITIONS
#   resume_may_change=True  --resume may give it another value (evaluate_may_set: --evaluate may)
#   saved=False             a setting of this command only, never in config.json or a snapshot
# A field without acts, envs and when acts in every run. Those and the two *_may_* keys are literals: where a setting
# acts is asked without the classes (plot.py, sweep.py: no torch), and `declared` reads them from the source.
META = ("group", "metavar", "low", "above", "high", "why", "acts", "envs", "when", "resume_may_change",
        "evaluate_may_set", "saved")
STATIC = ("acts", "envs", "when", "resume_may_change", "evaluate_may_set")
GROUPS = ("what to run", "the method", "robot masks", "the suites", "budgets", "the process")  # --help's, in order

# Transfer (--init-from): which networks of another run's agent a new run starts from.
INIT_PARTS = {"encoder": ("encoder",), "encoder+decoders": ("encoder", "aux"),
              "all": ("encoder", "aux", "actor", "critic")}
_PROCESS = "the process"
_AUTO = ("auto", "on", "off")


@dataclass
class RunConfig:
    """How this process runs the experiment (sear.Config says what the experiment is): devices, files, logs, snapshots,
    transfer. Saved in config.json and snapshot.pt, all but the fields marked saved=False."""
    device: str = arg("auto", "auto (cuda when available, else cpu) | cpu | cuda | cuda:N", metavar="DEVICE",
                      group=_PROCESS, resume_may_change=True, evaluate_may_set=True)
    compile: str = arg("auto", "auto (on with CUDA) | on | off: the update through torch.compile (harness/speed.py); "
                               "equal to the plain update within rounding; its first update compiles (minutes)",
                       _AUTO, resume_may_change=True)
    cuda_graph: str = arg("auto", "auto (on with CUDA) | on | off: the update captured once as a CUDA graph and "
                                  "replayed (harness/speed.py)", _AUTO, resume_may_change=True)
    batch_seeds: str = arg("auto", "auto (on with CUDA) | on | off: with --seeds, every seed's update as one batched "
                                   "update (torch.func.vmap); off: one after another", _AUTO, resume_may_change=True)
    tf32: bool = arg(False, "CUDA: TF32 in float32 convolutions and matmuls (Ampere and newer: faster, ~3 fewer "
                            "significant digits); off: the reference arithmetic (DrQ-v2's curves ran on V100s, which "
                            "have none)", when="cuda", resume_may_change=True)
    replay_device: str = arg("auto", "where the replay ring lives: auto (the run's GPU when it fits there, else the "
                                     "host) | cpu | the run's device", metavar="DEVICE", resume_may_change=True)
    prefetch: str = arg("auto", "auto (on with CUDA and a replay on the host) | on | off: sample and copy the next "
                                "batch in a background thread while the current update runs", _AUTO, group=_PROCESS,
                        resume_may_change=True)
    threads: int = arg(0, "torch CPU threads; 0 = $OMP_NUM_THREADS, else every core this process may use. Several "
                          "runs on one machine: give each cores / runs", low=0, group=_PROCESS,
                       resume_may_change=True, evaluate_may_set=True)
    run_root: str = arg("runs", "folder that holds run directories", metavar="DIR", group=_PROCESS)
    resume: str = arg("", "run directory to continue from its last snapshot", metavar="RUN_DIR", group=_PROCESS,
                      resume_may_change=True)
    evaluate: str = arg("", "score this run directory's snapshot on its eval env, no training: mean return (and "
                            "success) over --eval-episodes with confidence intervals; writes nothing, but with "
                            "--save-video a new videos/evaluate_<frame>.mp4", metavar="RUN_DIR", group=_PROCESS,
                        saved=False, evaluate_may_set=True)
    recipe: str = arg("paper", "paper (the paper's hyper-parameter table) | authors (their released code where the "
                               "two differ: harness/recipes.py, docs/recipes.md); explicit flags win",
                      ("paper", "authors"), group="what to run")
    seeds: str = arg("", "several seeds in one process, e.g. 1-16 or 1,3,5: seed k writes the run directory --seed k "
                         "writes, inside one group folder (docs/speed.md)", metavar="SEEDS", group="what to run",
                     saved=False)
    save_buffer: bool = arg(False, "also snapshot the replay buffer: --resume then continues exactly", group=_PROCESS,
                            resume_may_change=True)
    save_video: bool = arg(False, "write each evaluation's first episode to videos/eval_<frame>.mp4: camera | true "
                                  "mask | predicted mask | reconstruction (the panels the method has)", group=_PROCESS,
                           resume_may_change=True, evaluate_may_set=True)
    init_from: str = arg("", "transfer: start from the snapshot.pt of this run directory (e.g. pre-trained on "
                             "metaworld-mt10); method and network sizes follow that run unless given",
                         metavar="RUN_DIR", group=_PROCESS)
    init_parts: str = arg("all", "with --init-from, what to copy: encoder | encoder+decoders (the method's auxiliary "
                                 "networks too) | all (also actor and critic: the authors' default, "
                                 "just_encoder_decoders false); the rest and the optimisers start fresh",
                          tuple(INIT_PARTS), when="init_from", group=_PROCESS)
    log_every: float = arg(10.0, "seconds between progress lines", resume_may_change=True)
    snapshot_minutes: float = arg(10.0, "minutes of wall time between snapshots, each written at the next episode "
                                        "end (0 = after every episode)", low=0, group=_PROCESS,
                                  resume_may_change=True)
    drop_inapplicable: bool = arg(False, "drop the flags given where they do nothing (their 'only for') with one "
                                         "line, instead of refusing them: sweep.py passes one set of flags to every "
                                         "method of a grid", saved=False)


class NonFinite(Exception):
    """A loss, Q or action that is no longer a finite number: the run diverged; it stops in one line (exit 1)."""


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


DRM_SUFFIX = "+drm"  # sweep.py's and the tables' name of a method run with --drm: drq+drm is DrM


def method_label(config) -> str:
    """'drq', or 'drq+drm' with --drm, of a Config or a saved config dict (one without 'drm' predates the flag)."""
    get = config.get if isinstance(config, dict) else lambda k: getattr(config, k, None)
    return f"{get('method')}{DRM_SUFFIX if get('drm') else ''}"


def split_method_label(label: str) -> tuple[str, tuple[str, ...]]:
    """('drq', ('--drm',)) for 'drq+drm'; (label, ()) for a plain method."""
    return (label[:-len(DRM_SUFFIX)], ("--drm",)) if label.endswith(DRM_SUFFIX) else (label, ())


def apply_recipe(cfg, recipe: str, explicit: set) -> list[str]:
    """Set the per-task rows (TASK_DEFAULTS), then the recipe's, except fields given explicitly and fields that do
    nothing in this run. Returns what changed."""
    changed = {}  # a recipe row may override a per-task row: report the value that stands
    for name, applies, value, source, *_ in (*TASK_DEFAULTS, *RECIPES.get(recipe, ())):
        if name in explicit or not applies(cfg) or not acts(name, vars(cfg)):  # never a value that does nothing
            continue
        setattr(cfg, name, value(cfg) if callable(value) else value)
        changed[name] = f"{name}={getattr(cfg, name)} ({source})"
    return list(changed.values())


# ------------------------------------------------------------------------------------------------ flags
class OneLineParser(argparse.ArgumentParser):
    def error(self, message):  # the caller prints it as one line, as every other bad input
        raise ConfigError(message)


def whole_number(text: str) -> int:
    """An int flag's value: an integer, or a float that is one (--frames 1e6, 2.5e5); else one line."""
    with contextlib.suppress(ValueError):
        return int(text)
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}'") from None
    if not value.is_integer():  # also inf and nan
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}' is not a whole number")
    return int(value)


def field_groups(Config) -> list:
    """[(title, defaults, fields)] of the flags: each dataclass Config is made of, then RunConfig."""
    groups = []
    for cls in (c for c in Config.__mro__ if dataclasses.is_dataclass(c)):
        own = cls.__dict__.get("__annotations__", {})
        module = "train" if cls.__module__ == "__main__" else cls.__module__  # `python sear.py` runs train.py so
        title = f"the experiment ({module.replace('.', '/')}.py {cls.__name__})"
        groups.append((title, cls(), [f for f in dataclasses.fields(cls) if f.name in own]))
    return groups + [("the run (harness/cli.py RunConfig)", RunConfig(), list(dataclasses.fields(RunConfig)))]


def help_text(f, defaults, methods: dict) -> str:
    """A flag's help: its doc, its default (and per-task defaults), and where it acts."""
    if f.name == "method":  # the METHODS table documents itself
        return "; ".join(f"{name}: {m.doc}" for name, m in methods.items()) + " (default: 'sear')"
    per_task = [row[4] for row in TASK_DEFAULTS if row[0] == f.name]
    text = f"{f.metadata['doc']} (default: {getattr(defaults, f.name)!r}"
    text += f"; per task: {'; '.join(per_task)})" if per_task else ")"
    where = scope(f.name)
    text += f"; only for {where[1]}" if where else ""
    return text.replace("%", "%%")  # argparse formats help with %: "0.8%" must reach it as "0.8%%"


def add_flag(group, f, help_text: str, methods: dict) -> None:
    """One field as one flag: --x / --no-x for booleans, a typed value otherwise (ints also as 1e6)."""
    if f.type in ("bool", bool):
        group.add_argument(flag(f.name), action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS,
                           help=help_text)
        return
    kind = f.type if isinstance(f.type, str) else f.type.__name__
    choices = list(methods) if f.name == "method" else f.metadata.get("choices")
    metavar = f.metadata.get("metavar", {"int": "N", "float": "X"}.get(kind, "TEXT"))
    group.add_argument(flag(f.name), type={"int": whole_number, "float": float, "str": str}[kind],
                       choices=choices, default=argparse.SUPPRESS, help=help_text,
                       metavar=None if choices else metavar)


class HelpAll(argparse.Action):
    """--help-all: the help of every flag (the parser `full()` builds), then exit."""

    def __init__(self, option_strings, dest, full=None, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)
        self.full = full

    def __call__(self, parser, namespace, values, option_string=None):
        self.full().print_help()
        parser.exit()


def help_sections(Config, full: bool) -> list:
    """[(title, field names)] of --help (GROUPS, then the rest untitled: parsed, not shown) or, full, of --help-all
    (every field by its dataclass)."""
    if full:
        return [(title, [f.name for f in group]) for title, _, group in field_groups(Config)]
    sections = {title: [] for title in (*GROUPS, None)}
    for f in (f for _, _, group in field_groups(Config) for f in group):
        group = f.metadata.get("group")
        sections[group if group in GROUPS else None].append(f.name)
    return list(sections.items())


def build_parser(Config, methods: dict, full=False) -> OneLineParser:
    """One flag per field of Config and RunConfig, shown by --help (GROUPS) or --help-all (full=True)."""
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
    """'--lr -1e-4' as '--lr=-1e-4': argparse's rule for negative numbers knows -1 and -1.5 but not -1e-4, takes it for
    a flag and says 'expected one argument' instead of what is wrong with it."""
    joined = []
    for token in argv:
        if joined and joined[-1].startswith("--") and "=" not in joined[-1] and token.startswith("-"):
            with contextlib.suppress(ValueError):
                float(token)
                joined[-1] += "=" + token
                continue
        joined.append(token)
    return joined


def flag_names(Config) -> set[str]:
    """Every flag sear.py's parser has: one per field, plus --no-X for booleans, and --help-all."""
    fields = (*dataclasses.fields(Config), *dataclasses.fields(RunConfig))
    return {"--help-all", *(flag(f.name) for f in fields),
            *("--no-" + flag(f.name)[2:] for f in fields if f.type in ("bool", bool))}


def no_such_flag(name, known: set[str]) -> str:
    """'no flag --frams; did you mean --frames?' (sweep.py says it of the flags it passes on)."""
    close = difflib.get_close_matches(name, sorted(known), n=1)
    return f"no flag {name}" + (f"; did you mean {close[0]}?" if close else "")


def unknown_arguments(extras: list[str], known: set[str]) -> str:
    """The parser's error for what it did not recognise: the first unknown flag, with a suggestion."""
    flags = [token.split("=", 1)[0] for token in extras if token.startswith("--")]
    return no_such_flag(flags[0], known) if flags else f"unrecognized arguments: {' '.join(extras)}"


# ------------------------------------------------------------------------------------------------ where settings act
# A flag given where it does nothing is refused (or, for sweep.py, dropped). The methods by what they read are named
# here (plot.py reads config.json without torch); tests check them against sear.METHODS (uses_mask, encoder).
MASK_METHODS = ("sear", "sear-nosplit", "rgbm", "dear")                   # Method.uses_mask
POOLED_METHODS = ("sear", "ae", "mae", "curl", "sear-nosplit", "dear", "ef")  # Method.encoder == "pooled"
TASK_SETS = ("mt3", "mt10", "mt50")  # metaworld-<set>; envs.py's _METAWORLD_SETS


def suite_of(env: str) -> str:
    """dmc | distracting | metaworld | task-set | kitchen | adroit: an env name's suite as envs.py names them, read
    from the name alone (no MuJoCo; tests check it against envs.py's parser)."""
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


# The named scopes a field's acts=, envs= and when= may use: (test, what a setting there is for).
METHOD_SETS = {"mask": (MASK_METHODS, "methods that use the robot mask (--method {})"),
               "pooled": (POOLED_METHODS, "SEAR's pooled encoder (--method {}; drq and rgbm flatten the feature map)")}
ENV_SETS = {
    "distracting": (lambda env: suite_of(env) == "distracting", "Distracting Control (*-distracting envs)"),
    "kitchen": (lambda env: suite_of(env) == "kitchen", "Kitchen (kitchen-* envs)"),
    "task sets": (lambda env: suite_of(env) == "task-set", "the task sets (metaworld-mt3, -mt10, -mt50)"),
    "manipulation": (lambda env: suite_of(env) in ("metaworld", "task-set", "kitchen", "adroit"),
                     "the manipulation suites (metaworld-*, kitchen-*, adroit-*; dm_control renders masks at 84)"),
    "cartpole": (lambda env: env.startswith("cartpole-"),  # dm_control's, plain or distracting
                 "cartpole (cartpole-* and cartpole-*-distracting envs)"),
}
CONDITIONS = {  # c: a run's settings as config.json holds them (an old run's may lack later ones)
    "learned masks": (lambda c: c.get("mask_source", "sim") != "sim", "--mask-source learned:PATH"),
    "episodes not per task": (
        lambda c: not (c.get("eval_episodes_per_task") and suite_of(c.get("env", "")) == "task-set"),
        "runs other than a task set given --eval-episodes-per-task (which then sets every task's episodes)"),
    "cuda": (lambda c: c.get("device", "auto") != "cpu",  # torch_setup refuses auto without CUDA
             "CUDA devices (--device cuda, cuda:N, or auto on a machine with CUDA)"),
}
# The files of the classes train.Config is made of (RunConfig is here): `declared` reads them.
CONFIG_SOURCES = ("train.py", "sear.py", "methods/baselines.py", "methods/foresight.py", "methods/drm.py",
                  "harness/experiment.py")


def _source_keys(path: str) -> dict[str, dict]:
    """{field: its STATIC keys} of the `name: type = arg(...)` fields of the classes in one file."""
    with open(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), path)) as f:
        tree = ast.parse(f.read(), path)
    fields = (n for cls in tree.body if isinstance(cls, ast.ClassDef) for n in cls.body
              if isinstance(n, ast.AnnAssign) and isinstance(n.value, ast.Call))
    return {n.target.id: {k.arg: ast.literal_eval(k.value) for k in n.value.keywords if k.arg in STATIC}
            for n in fields if getattr(n.value.func, "id", None) == "arg"}


@functools.cache
def declared() -> dict[str, dict]:
    """{setting: its STATIC keys} of RunConfig's fields and, read from their source, those of CONFIG_SOURCES: the
    classes import torch, and plot.py and sweep.py ask where a setting acts without it (tests check both agree)."""
    keys = {f.name: {k: f.metadata[k] for k in STATIC if k in f.metadata} for f in dataclasses.fields(RunConfig)}
    for path in CONFIG_SOURCES:
        keys.update(_source_keys(path))
    return keys


def _methods_scope(acts, alone: bool) -> tuple:
    if isinstance(acts, str):
        names, text = METHOD_SETS[acts]
        text = text.format(listing(names)) if alone else "one of the " + text.format(listing(names))
    else:  # "ae (2 x c1)": the method ae, and a note for the text
        names, text = [m.split()[0] for m in acts], f"--method {listing(acts)}"
    return lambda c: c.get("method", "sear") in names, text


@functools.cache
def scope(name: str) -> tuple | None:
    """(acts(settings), what the setting is for) of one that acts only in some runs (its when=, envs=, acts=); None for
    one that acts in every run."""
    keys, parts = declared().get(name, {}), []
    if "when" in keys:  # of CONDITIONS, or a setting that is set
        when = keys["when"]
        parts.append(CONDITIONS.get(when) or (lambda c: bool(c.get(when)), f"runs with {flag(when)}"))
    if "envs" in keys:
        on_env, text = ENV_SETS[keys["envs"]]
        parts.append((lambda c: on_env(c.get("env", "")), text))
    if "acts" in keys:
        parts.append(_methods_scope(keys["acts"], alone=not parts))
    if not parts:
        return None
    return (lambda c: all(test(c) for test, _ in parts)), ", with ".join(text for _, text in parts)


def acts(name: str, settings: dict) -> bool:
    """Whether setting `name` acts in a run of these settings."""
    where = scope(name)
    return where is None or bool(where[0](settings))


def acting_settings(config: dict) -> dict:
    """A run's config.json less the settings that did nothing in it: what a plot may name a curve by (runs from before
    the rule recorded them: --method drq --dear-feature push ran as drq)."""
    return {name: value for name, value in config.items() if acts(name, config)}


def may(key: str) -> set[str]:
    """The settings whose field has `key` (resume_may_change, evaluate_may_set)."""
    return {name for name, keys in declared().items() if keys.get(key)}


def __getattr__(name):  # cli.RESUME_MAY_CHANGE and cli.EVALUATE_MAY_SET (sweep.py), from the fields
    if name not in ("RESUME_MAY_CHANGE", "EVALUATE_MAY_SET"):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return may(name.lower())


def given_as(name: str, value) -> str:
    """A flag as it was typed: --mask-approx, --no-mask-approx, --recon-coef 1.0."""
    if isinstance(value, bool):
        return flag(name) if value else "--no-" + flag(name)[2:]
    return f"{flag(name)} {value}"


def refusal(idle: dict, given: dict, where: str) -> str:
    """'--x 1 does nothing in this run (drq on walker-walk): it is for ...', of one or several flags."""
    if len(idle) == 1:
        (name, text), = idle.items()
        return f"{given_as(name, given[name])} does nothing in this run ({where}): it is for {text}"
    return (f"{listing(given_as(name, given[name]) for name in idle)} do nothing in this run ({where}): "
            + "; ".join(f"{flag(name)} is for {text}" for name, text in idle.items()))


def check_applies(cfg, run: RunConfig, given: dict, resumed=False) -> set:
    """A flag given where it does nothing is one line, exit 2; with --drop-inapplicable (sweep.py: one set of flags for
    every method of a grid) it is dropped, back to its default (a resumed run keeps its saved value), in one line for
    all of them. Returns the names dropped."""
    settings = {**vars(cfg), **vars(run)}
    idle = {name: scope(name)[1] for name in given if not acts(name, settings)}
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


# ------------------------------------------------------------------------------------------------ values
# Seeds: numpy's legacy seeding (np.random.seed, dm_control's and Meta-World's RandomState) takes [0, 2^32), and the
# eval env's seed is the run's + 100000 (experiment.EVAL_SEED); episodes' reset seeds go to default_rng.
EVAL_SEED = 100_000
MAX_SEED = 2**32 - 1 - EVAL_SEED
DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")  # what a setting with metavar DEVICE takes
_BOUNDS = {"low": (">=", operator.ge), "above": (">", operator.gt), "high": ("<=", operator.le)}


def range_rule(keys) -> tuple | None:
    """(holds(value), what the value must be) of a field's low=, above=, high= (why=), or None."""
    bounds = [(sign, holds, keys[k]) for k, (sign, holds) in _BOUNDS.items() if k in keys]
    if not bounds:
        return None
    rule = (f"in [{keys['low']}, {keys['high']}]" if {"low", "high"} <= set(keys)
            else f"{bounds[0][0]} {bounds[0][2]}") + (f" ({keys['why']})" if "why" in keys else "")
    return (lambda v: all(holds(v, bound) for _, holds, bound in bounds)), rule


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
    (lambda cfg: cfg.mask_source != "sim" and not re.fullmatch("learned:.+", cfg.mask_source, re.S),
     lambda cfg: f"--mask-source must be sim or learned:PATH (a segment.py model file), got '{cfg.mask_source}'"),
)


def not_finite(cfg, run) -> str | None:
    for settings in (cfg, run):
        for f in dataclasses.fields(settings):
            value = getattr(settings, f.name)
            if isinstance(value, float) and not math.isfinite(value):  # inf passes every range, NaN none
                return f"{flag(f.name)} must be a finite number, got {value}"


def out_of_range(cfg, run) -> str | None:
    for settings in (cfg, run):
        for f in dataclasses.fields(settings):
            rule, value = range_rule(f.metadata), getattr(settings, f.name)
            if rule and not rule[0](value):
                return f"{flag(f.name)} must be {rule[1]}, got {value}"


def no_such_device(cfg, run) -> str | None:
    """A device's name (what is there to run on is torch_setup's to say)."""
    for f in dataclasses.fields(run):
        value = getattr(run, f.name)
        if f.metadata.get("metavar") == "DEVICE" and not DEVICE.fullmatch(value):
            return f"{flag(f.name)} must be auto, cpu, cuda or cuda:N, got '{value}'"


def bad_seeds(cfg, run) -> str | None:
    try:
        run.seeds and parse_seeds(run.seeds)
    except ConfigError as e:
        return str(e)


def unrelated(cfg, run) -> str | None:
    return next((say(cfg) for broken, say in RELATIONS if broken(cfg)), None)


def no_video_writer(cfg, run) -> str | None:
    if run.save_video:
        try:
            import imageio_ffmpeg  # noqa: F401  (brings its own ffmpeg binary)
        except ImportError:
            return "--save-video needs imageio-ffmpeg: pip install -r requirements.txt"


CHECKS = (not_finite, out_of_range, no_such_device, bad_seeds, unrelated, no_video_writer)


def validate(cfg, run: RunConfig) -> None:
    """What the parser's types and choices cannot see: CHECKS, in order; the first that fails is the one line."""
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


# ------------------------------------------------------------------------------------------------ saved configs
UNSAVED = {f.name for f in dataclasses.fields(RunConfig) if not f.metadata.get("saved", True)}


def config_dict(cfg, run: RunConfig) -> dict:
    """config.json and a snapshot's "config": every saved field of both, flat, as one --flag each."""
    return {**dataclasses.asdict(cfg), **{k: v for k, v in dataclasses.asdict(run).items() if k not in UNSAVED}}


def split_config(values: dict, Config) -> tuple:
    """The (Config, RunConfig) of a flat dict of settings: fields since removed are dropped, renamed ones carried over.
    """
    values = dict(values)
    if "std_frames" in values and "std_steps" not in values:  # snapshots from before std counted steps
        values["std_steps"] = max(1, values["std_frames"] // max(1, values.get("action_repeat") or 1))

    def build(cls):
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})
    return build(Config), build(RunConfig)


def evaluate_config(given: dict, Config) -> tuple:
    """--evaluate RUN_DIR: the run as it is (its saved config, without its own --save-video) with only the flags
    evaluate_may_set on top, and its snapshot."""
    if given.get("resume"):
        raise ConfigError("--evaluate scores a run, --resume trains it further: give one of them")
    snapshot = load_snapshot(given["evaluate"], "--evaluate")
    settable = may("evaluate_may_set")
    extra = sorted(set(given) - settable)
    if extra:
        flags = ", ".join(flag(name) for name in sorted(settable - {"evaluate"}))
        raise ConfigError(f"{flag(extra[0])} cannot be given with --evaluate (the run's config holds it); "
                          f"only {flags} can")
    cfg, run = split_config({**snapshot["config"], "save_video": False, **given}, Config)
    check_applies(cfg, run, given, resumed=True)  # --eval-episodes-per-task on a single task
    validate(cfg, run)
    return cfg, run, snapshot


def parse_args(argv, Config, methods: dict) -> tuple:
    """(Config, RunConfig, snapshot) from the flags; with --resume or --evaluate, the run's saved config (plus the few
    flags that may change) and its snapshot, else snapshot None."""
    parser = build_parser(Config, methods)
    argv = negative_numbers_as_values(sys.argv[1:] if argv is None else list(argv))
    namespace, extras = parser.parse_known_args(argv)
    if extras:
        parser.error(unknown_arguments(extras, flag_names(Config)))
    given = vars(namespace)
    if given.get("evaluate"):
        return evaluate_config(given, Config)
    if given.get("resume"):
        return resume_config(given, Config)
    cfg, run = split_config(given, Config)
    validate(cfg, run)
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


def resume_config(given: dict, Config) -> tuple:
    """--resume RUN_DIR: the run's saved config, with only the settings marked resume_may_change given otherwise, and
    its snapshot. A resumed config was resolved when the run started: no recipe again."""
    snapshot = load_snapshot(given["resume"])
    check_run_config(given["resume"])
    saved = snapshot["config"]
    cfg, run = split_config({**saved, **given}, Config)
    check_applies(cfg, run, given, resumed=True)
    changeable = may("resume_may_change")
    for k, v in given.items():
        if k not in changeable | UNSAVED and saved.get(k) != v:
            raise ConfigError(f"{flag(k)} cannot change on --resume (run has {saved.get(k)!r}); "
                              f"only {', '.join(sorted(changeable))} can")
    validate(cfg, run)
    return cfg, run, snapshot


GROUP_FILE = "group.json"  # harness/group.py's: a seed group's folder holds it, beside its runs


def finished(cfg, run: RunConfig, snapshot, group: str = "") -> str | None:
    """--resume of a run (or with `group`, of its seed group's folder) that has trained its --frames and was evaluated
    at its last frame: the line that says so, before any env or network is built. None for any other command, and for a
    run of a seed group resumed alone (its group resumes it)."""
    counters = (snapshot or {}).get("counters")
    if not run.resume or run.evaluate or not counters:
        return None
    if not group and os.path.isfile(os.path.join(os.path.dirname(os.path.abspath(run.resume)), GROUP_FILE)):
        return None
    run = dataclasses.replace(run, resume=group or run.resume)
    import envs  # the suite's action repeat, where the config holds 0
    frame = counters["step"] * (cfg.action_repeat or envs.default_action_repeat(cfg.env))
    evaluated = counters.get("last_eval_frame", counters.get("next_eval", 0) - 1)
    if frame < cfg.frames or evaluated != frame:
        return None
    return (f"{run.resume} is done: it trained to frame {frame} (--frames {cfg.frames}) and was evaluated there; its "
            f"results are in {run.resume} (eval.csv, train.csv); to train further: python sear.py --resume "
            f"{run.resume} --frames N, with N > {frame}")


def main(argv, Config, methods: dict, train, evaluate) -> int:
    """sear.py's exit: 0 done, 2 bad input or a storage error, 1 a run that diverged, 130 Ctrl-C and 143 SIGTERM, each
    in one line. train(cfg, run, snapshot) trains; with --evaluate, evaluate(cfg, run, snapshot) scores."""
    configure_allocator()
    with TERM.installed():
        try:
            cfg, run, snapshot = parse_args(argv, Config, methods)
            done = finished(cfg, run, snapshot)
            if done:
                print(done)
            else:
                (evaluate if run.evaluate else train)(cfg, run, snapshot)
        except (ConfigError, StorageError, NonFinite) as e:
            print(f"sear.py: error: {e}", file=sys.stderr)
            return 1 if isinstance(e, NonFinite) else 2
        except Interrupted as e:
            print(f"\nsear.py: {e}", file=sys.stderr)
            return e.code
        except KeyboardInterrupt as stop:  # while reading the flags or the snapshot: nothing started
            cause, code = stop_cause(stop)
            print(f"\nsear.py: {cause} before training started; nothing was saved", file=sys.stderr)
            return code
    return 0


def torch_setup(run: RunConfig):
    """The run's torch device (--device), checked with --replay-device, --tf32 and --compile against this machine, and
    its CPU threads (--threads) set."""
    import torch
    device = run_device(run.device)
    if run.replay_device not in ("auto", "cpu") and torch.device(run.replay_device) != device:
        raise ConfigError(f"--replay-device must be auto, cpu or the run's device ({device}), got "
                          f"'{run.replay_device}'")
    if run.tf32 and device.type != "cuda":
        no_tf32(run, device)
    set_tf32(run.tf32)
    if run.compile in ("on", True) and device.type == "cpu" and not cxx_compiler():
        raise ConfigError("--compile on the CPU needs a C++ compiler (inductor builds its kernels with one): no "
                          "g++, c++ or clang++ found; install one or leave --compile off")
    torch.set_num_threads(torch_threads(run))
    return device


def run_device(name: str):
    """--device's torch device on this machine (no_such_device checked its name with the flags)."""
    import torch
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: CUDA is not available on this machine")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise ConfigError(f"--device {name}: this machine has {plural(count, 'CUDA device')} "
                          f"(cuda:0 to cuda:{count - 1})")
    return device


def no_tf32(run: RunConfig, device) -> None:
    """--tf32 where there is no CUDA: refused as every flag that does nothing, or turned off with --drop-inapplicable;
    a run --evaluate scores keeps its saved --tf32, which it cannot set: off without a word."""
    if run.evaluate:
        run.tf32 = False
        return
    line = refusal({"tf32": scope("tf32")[1]}, {"tf32": True}, f"device {device}")
    if not run.drop_inapplicable:
        raise ConfigError(line + ("; --no-tf32 turns it off" if run.resume else ""))
    run.tf32 = False
    warn(f"--drop-inapplicable: ignored what does nothing in this run (device {device}): --tf32")
