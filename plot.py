"""Learning curves from sear.py run directories: mean over seeds with a 95% confidence band.

Usage:  python plot.py runs/ --out curves.png
        python plot.py 'runs/walker-walk*' --group method,env --metric return --title "Walker"
        python plot.py runs/ --metric success --csv eval --out success.png --force
        python plot.py 'runs/metaworld-mt10*' --metric success --per-task --out mt10.png

Arguments are run directories (holding config.json), parent folders (every folder below holding a
config.json is a run) or globs. Runs are grouped by config keys (--group, default "method"); each
group is one line: the mean over its runs and, with 2+ runs, a shaded 95% t-interval of the mean
(mean +- t_{0.975, n-1} * std / sqrt(n)). With runs on several envs and env not a grouping key,
each env gets its own subplot.

Aligning runs of one group:
  eval.csv   the INTERSECTION of the runs' evaluation frames, so every plotted point is a real
             evaluation of every run (a run still in progress truncates its group).
  train.csv  episodes end at different frames in each run, so the curves are linearly
             INTERPOLATED onto the union of their frames, cut to the span all runs cover.

--per-task draws task-set runs (metaworld-mt3/-mt10/-mt50) one panel per task, from eval.csv's
per-task columns (success/<task>, return/<task>).

A markdown table (group, runs, last common frame, final mean +- CI) goes to stdout. A run without
the CSV (stopped before its first evaluation, or episode, ended) is skipped with one line on stderr.
Errors are one line on stderr, `plot.py: error: ...`, with exit code 2.
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import math
import os
import sys
from functools import reduce

import numpy as np

METRICS = ("return", "success")


class PlotError(Exception):
    """Bad input: reported as one line on stderr, exit code 2."""


class NoLogYet(PlotError):
    """A run without the CSV asked for: it stopped before writing its first row. Skipped, not fatal."""


# What a run has done when it first writes each log.
FIRST_ROW = {"eval": "its first evaluation", "train": "its first episode"}


# ---------------------------------------------------------------- finding and reading runs
def find_runs(paths: list[str]) -> list[str]:
    """Run directories named by `paths` (directories, parents of runs, or globs), sorted, unique."""
    runs = set()
    for pattern in paths:
        matches = glob.glob(pattern) or ([pattern] if os.path.exists(pattern) else [])
        if not matches:
            raise PlotError(f"no such file or directory: {pattern}")
        for path in matches:
            for root, dirs, files in os.walk(path):
                if "config.json" in files:
                    runs.add(os.path.normpath(root))
                    dirs.clear()  # a run's own subfolders (e.g. tensorboard) are not runs
                dirs.sort()
    if not runs:
        raise PlotError(f"no runs (folders with a config.json) found in: {' '.join(paths)}")
    return sorted(runs)


def load_run(run_dir: str, csv_name: str = "eval", metric: str = "return") -> dict:
    """{"dir", "config", "frames", "values"} of one run; frames sorted and unique."""
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            config = json.load(f)
    except (OSError, ValueError) as e:
        raise PlotError(f"{run_dir}/config.json: unreadable ({e})") from None
    path = os.path.join(run_dir, f"{csv_name}.csv")
    if not os.path.exists(path):
        raise NoLogYet(f"no {csv_name}.csv (the run stopped before {FIRST_ROW[csv_name]} ended)")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if not reader.fieldnames:
            raise PlotError(f"{path}: empty")
        if metric not in reader.fieldnames:
            raise PlotError(f"{path}: no '{metric}' column (has {','.join(reader.fieldnames)})")
        points = {}
        for row in reader:
            if row[metric] in ("", None):  # e.g. not logged yet: skip the cell, keep the run
                continue
            try:  # a repeated frame (e.g. after a resume) keeps its last row
                points[float(row["frame"])] = float(row[metric])
            except (KeyError, ValueError):
                raise PlotError(f"{path}: bad row {row}") from None
    if not points:
        raise PlotError(f"{path}: no rows with a '{metric}' value")
    frames = np.array(sorted(points))
    return {"dir": run_dir, "config": config, "frames": frames,
            "values": np.array([points[x] for x in frames])}


def task_columns(run_dir: str, metric: str) -> list[str]:
    """The tasks of a task-set run, from its eval.csv's <metric>/<task> columns (in their order)."""
    path = os.path.join(run_dir, "eval.csv")
    if not os.path.exists(path):
        raise NoLogYet(f"no eval.csv (the run stopped before {FIRST_ROW['eval']} ended)")
    with open(path, newline="") as f:
        header = next(csv.reader(f), [])
    tasks = [c[len(metric) + 1:] for c in header if c.startswith(metric + "/")]
    if not tasks:
        raise PlotError(f"{path}: no per-task columns ({metric}/<task>); --per-task needs task-set runs "
                        f"(metaworld-mt3, -mt10, -mt50)")
    return tasks


def load_task_runs(run_dir: str, metric: str) -> list[dict]:
    """One load_run per task of a task-set run, each marked with its task."""
    return [{**load_run(run_dir, "eval", f"{metric}/{task}"), "task": task}
            for task in task_columns(run_dir, metric)]


# ---------------------------------------------------------------- statistics
def t_quantile(p: float, df: int) -> float:
    """Student-t quantile: the 95% interval of a mean over few seeds is wider than +-1.96 sd/sqrt(n)."""
    from scipy import stats  # imported here: the rest of plot.py needs only numpy and matplotlib
    return float(stats.t.ppf(p, df))


def aggregate(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False):
    """(frames, mean, ci) of (frames, values) curves; ci is the 95% half-width, NaN for 1 curve."""
    if interpolate:
        lo, hi = max(f[0] for f, _ in curves), min(f[-1] for f, _ in curves)
        grid = np.unique(np.concatenate([f for f, _ in curves]))
        grid = grid[(grid >= lo) & (grid <= hi)]
        ys = np.stack([np.interp(grid, f, v) for f, v in curves])
    else:
        grid = reduce(np.intersect1d, [f for f, _ in curves])
        ys = np.stack([v[np.isin(f, grid)] for f, v in curves])
    if len(grid) == 0:
        raise PlotError("runs of one group share no frames: cannot average them")
    n = len(curves)
    mean = ys.mean(axis=0)
    ci = (t_quantile(0.975, n - 1) * ys.std(axis=0, ddof=1) / math.sqrt(n) if n > 1
          else np.full_like(mean, np.nan))
    return grid, mean, ci


def env_of(run: dict) -> str:
    return str(run["config"].get("env", "?"))


def group_runs(runs: list[dict], keys: list[str]) -> dict[str, list[dict]]:
    """{label: runs} where label joins the runs' config values of `keys`, e.g. "sear / walker-walk"."""
    groups = {}
    for run in runs:
        missing = [k for k in keys if k not in run["config"]]
        if missing:
            raise PlotError(f"{run['dir']}/config.json: no key {missing[0]!r} to group by")
        groups.setdefault(" / ".join(str(run["config"][k]) for k in keys), []).append(run)
    return dict(sorted(groups.items()))


# ---------------------------------------------------------------- plotting
def short_frames(x, _pos=None) -> str:
    return f"{x / 1e6:g}M" if abs(x) >= 1e6 else f"{x / 1e3:g}k" if abs(x) >= 1e3 else f"{x:g}"


def plot(panels: dict, out: str, ylabel: str, title: str, baseline: tuple[float, str] | None = None):
    import matplotlib
    matplotlib.use("Agg")  # files only: no display needed on a cluster node
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    labels = sorted({label for curves in panels.values() for label in curves})
    colors = {label: f"C{i % 10}" for i, label in enumerate(labels)}  # same group, same color
    cols = min(len(panels), 3)
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
    for ax, (panel, curves) in zip(axes.flat, panels.items()):
        for label, (frames, mean, ci, n, _env) in curves.items():
            ax.plot(frames, mean, color=colors[label], label=f"{label} (n={n})")
            if n > 1:
                ax.fill_between(frames, mean - ci, mean + ci, color=colors[label], alpha=0.2, lw=0)
        if baseline is not None:  # e.g. a random policy's mean (benchmarks/random_policy.py)
            ax.axhline(baseline[0], color="0.4", ls="--", lw=1, label=baseline[1])
        ax.set_title(panel if len(panels) > 1 else title)
        ax.set_xlabel("frames")
        ax.set_ylabel(ylabel)
        ax.xaxis.set_major_formatter(FuncFormatter(short_frames))
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small", title="mean ± 95% CI", title_fontsize="small")
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    if len(panels) > 1:
        fig.suptitle(title)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def summary_table(panels: dict, metric: str) -> str:
    lines = [f"| env | group | seeds | last frame | final {metric} (mean ± 95% CI) |",
             "|---|---|---|---|---|"]
    for curves in panels.values():
        for label, (frames, mean, ci, n, env) in curves.items():
            final = f"{mean[-1]:.4g}" + ("" if n == 1 else f" ± {ci[-1]:.3g}")
            lines.append(f"| {env} | {label} | {n} | {frames[-1]:.0f} | {final} |")
    return "\n".join(lines)


# ---------------------------------------------------------------- CLI
class OneLineParser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def main(argv=None) -> int:
    parser = OneLineParser(prog="plot.py", description=__doc__.split("\n\n")[0],
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="run directories, folders of runs, or globs")
    parser.add_argument("--out", default="curves.png", help="PNG to write (default curves.png)")
    parser.add_argument("--metric", default="return", help="return | success")
    parser.add_argument("--csv", default="eval", choices=("eval", "train"), help="which log to read")
    parser.add_argument("--group", default="method", help="config keys, comma separated: method,env")
    parser.add_argument("--title", default=None)
    parser.add_argument("--per-task", action="store_true",
                        help="task sets: one panel per task, from eval.csv's <metric>/<task> columns")
    parser.add_argument("--baseline", default=None, metavar="VALUE[:LABEL]",
                        help="a dashed horizontal line, e.g. 1.6:random (benchmarks/random_policy.py)")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    args = parser.parse_args(argv)
    try:
        baseline = None
        if args.baseline is not None:
            value, _, label = args.baseline.partition(":")
            try:
                baseline = (float(value), label or "baseline")
            except ValueError:
                raise PlotError(f"--baseline must be VALUE[:LABEL], e.g. 1.6:random; got {args.baseline!r}") from None
        if args.metric not in METRICS:
            raise PlotError(f"unknown metric {args.metric!r} (choose from {', '.join(METRICS)})")
        if os.path.exists(args.out) and not args.force:  # checked first: don't make the user wait
            raise PlotError(f"{args.out} exists; refusing to overwrite it (use --force)")
        keys = [k.strip() for k in args.group.split(",") if k.strip()]
        if not keys:
            raise PlotError("--group needs at least one config key, e.g. method")
        if args.per_task and args.csv != "eval":
            raise PlotError("--per-task reads eval.csv (per-task columns are written by evaluations)")
        runs = []
        found = find_runs(args.paths)
        for d in found:
            try:
                runs += load_task_runs(d, args.metric) if args.per_task else [load_run(d, args.csv, args.metric)]
            except NoLogYet as e:  # one run stopped early must not hide all the others
                print(f"plot.py: skipping {d}: {e}", file=sys.stderr)
        if not runs:
            raise PlotError(f"nothing to draw: none of the {len(found)} runs found has written {args.csv}.csv yet")
        envs = sorted({env_of(r) for r in runs})
        # One subplot per env, unless env is already told apart by the lines (or there is just one);
        # with --per-task one per task (and env).
        by_env = len(envs) > 1 and "env" not in keys
        keyed = {}
        for r in sorted(runs, key=env_of):  # stable: tasks keep their column order
            key = ": ".join(([env_of(r)] if by_env else []) + ([r["task"]] if "task" in r else []))
            keyed.setdefault(key or ", ".join(envs), []).append(r)
        panels = {}
        for panel, members in keyed.items():
            panels[panel] = {}
            for label, group in group_runs(members, keys).items():
                seeds = [r["config"].get("seed") for r in group]
                if len(set(seeds)) < len(seeds):
                    print(f"plot.py: warning: {label}: repeated seeds {seeds}", file=sys.stderr)
                curves = [(r["frames"], r["values"]) for r in group]
                envs_of_group = ", ".join(sorted({env_of(r) for r in group}))
                if "task" in group[0]:  # --per-task: the table names the task too
                    envs_of_group += f": {group[0]['task']}"
                panels[panel][label] = (*aggregate(curves, interpolate=args.csv == "train"),
                                        len(group), envs_of_group)
        ylabel = f"{args.csv} {'success rate' if args.metric == 'success' else 'return'}"
        title = args.title or (f"{ylabel} ({envs[0]})" if len(envs) == 1 else ylabel)
        plot(panels, args.out, ylabel, title, baseline)
    except PlotError as e:
        print(f"plot.py: error: {e}", file=sys.stderr)
        return 2
    print(summary_table(panels, args.metric))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
