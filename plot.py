"""Learning curves from sear.py run directories: mean over seeds with a 95% confidence band.

Usage:  python plot.py runs/ --out runs/curves.png
        python plot.py 'runs/walker-walk*' --group method,env --metric return --title "Walker"
        python plot.py runs/ --metric success --csv eval --out runs/success.png --force
        python plot.py 'runs/cartpole*' --csv train --metric dormant_ratio --out runs/dormant.png
        (any column) python plot.py 'runs/cartpole-balance_sparse*' --reference
        drqv2/curves/dmc_cartpole_balance_sparse.csv python plot.py 'runs/metaworld-mt10*' --metric
        success --per-task --out runs/mt10.png python plot.py maps RUN_A [RUN_B ...] --out
        runs/maps.png [--frames N]   (activation maps, below)

Arguments are run directories (holding config.json), parent folders (every folder below holding a
config.json is a run) or globs. Runs are grouped by config keys (--group, default "method"), and
split by every other config value in which runs on the same env differ (say --mask-source); every
line is then named by its values of all of them ("sear mask_source=learned:seg.pt"), so no line that
differs is labelled plainly. The seed, the budget, the device, logging and how often and how long
runs are evaluated (NOT_A_SETTING) never split a line. Each line is the mean over its runs and, with
2+ runs, a shaded 95% t-interval of the mean (mean +- t_{0.975, n-1} * std / sqrt(n)). With runs on
several envs and env not a grouping key, each env gets its own subplot. Success rates are drawn on a
[0, 1] axis. Layout (docs/figures.md): the axes keep their size whatever the legend holds; a short
legend stays inside a single panel, a long one (or one for several panels) goes to an empty slot of
the grid or below the panels with its labels wrapped; titles are wrapped to fit.

Each run is drawn to its own end: at every frame the mean and CI are over the runs that have a value
there (n per frame), the line is dashed where not all of them do, the table says how many reached
the last frame, and stderr warns which runs end early.
  eval.csv   the UNION of the runs' evaluation frames: every point averages real evaluations.
  train.csv  episodes end at different frames in each run, so each curve is linearly INTERPOLATED
             onto the union of the frames, within its own span.

--reference CSV[:LABEL] draws a published curve in DrQ-v2's format (curves/dmc_<task>.csv: seed,
frame, episode_reward, task): its mean over seeds and a min-max band, on each panel with runs on
that task (env cartpole-balance_sparse = task cartpole_balance_sparse), cut to the runs' last frame.

--per-task draws task-set runs (metaworld-mt3/-mt10/-mt50) one panel per task, from eval.csv's
per-task columns (success/<task>, return/<task>), and a last panel with each run's mean over tasks.

`plot.py maps` draws what the encoder's last convolution responds to, for runs on one env and on
the same frames (the paper's section 5), and measures each channel's share of activation on the
robot; its table (robot / environment channels per run) goes to stdout.

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
import textwrap
from functools import reduce

import numpy as np

from harness import cli  # the standard library only: the curves need neither torch nor MuJoCo


class PlotError(Exception):
    """Bad input: reported as one line on stderr, exit code 2."""


class NoLogYet(PlotError):
    """A run without the CSV asked for: it stopped before writing its first row. Skipped, not
    fatal."""


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
        raise PlotError(f"{path}: no per-task columns ({metric}/<task>); --per-task needs task-set "
                        f"runs (metaworld-mt3, -mt10, -mt50)")
    return tasks


def load_task_runs(run_dir: str, metric: str) -> list[dict]:
    """One load_run per task of a task-set run, each marked with its task."""
    return [{**load_run(run_dir, "eval", f"{metric}/{task}"), "task": task}
            for task in task_columns(run_dir, metric)]


# ---------------------------------------------------------------- statistics
def t_quantile(p: float, df: int) -> float:
    """Student-t quantile: the 95% interval of a mean over few seeds is wider than +-1.96
    sd/sqrt(n)."""
    from scipy import stats  # imported here: the rest of plot.py needs only numpy and matplotlib
    return float(stats.t.ppf(p, df))


def stack_curves(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False):
    """(frames, values): the union of the curves' frames, and each curve on them (NaN where it has
    no value). eval.csv: a value only at a curve's own evaluation frames, so every point is a real
    evaluation; train.csv (interpolate): linearly interpolated within the curve's own span."""
    if not curves:
        raise PlotError("no runs to average")
    grid = np.unique(np.concatenate([f for f, _ in curves]))
    ys = np.full((len(curves), len(grid)), np.nan)
    for row, (f, v) in zip(ys, curves):
        if interpolate:
            inside = (grid >= f[0]) & (grid <= f[-1])
            row[inside] = np.interp(grid[inside], f, v)
        else:
            row[np.isin(grid, f)] = v  # both sorted and unique: same order
    return grid, ys


def aggregate(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False):
    """(frames, mean, ci) of (frames, values) curves, each drawn to its own end: at every frame the
    mean and the 95% half-width over the curves that have it (coverage() counts them); ci is NaN
    where only one has."""
    grid, ys = stack_curves(curves, interpolate)
    n = np.sum(~np.isnan(ys), axis=0)
    mean = np.nanmean(ys, axis=0)
    ci = np.full_like(mean, np.nan)
    for k in np.unique(n[n > 1]):
        at = n == k
        ci[at] = t_quantile(0.975, k - 1) * np.nanstd(ys[:, at], axis=0, ddof=1) / math.sqrt(k)
    return grid, mean, ci


def coverage(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False) -> np.ndarray:
    """How many of the curves have a value at each of aggregate()'s frames."""
    return np.sum(~np.isnan(stack_curves(curves, interpolate)[1]), axis=0)


def env_of(run: dict) -> str:
    return str(run["config"].get("env", "?"))


def config_label(config: dict, key: str) -> str:
    """A config value as a line's label names it; the method with its variant: drq+drm (--drm)."""
    if key == "method":
        return cli.method_label(config)
    return str(config[key])


def group_runs(runs: list[dict], keys: list[str]) -> dict[str, list[dict]]:
    """{label: runs} where label joins the runs' config values of `keys`, e.g. "sear /
    walker-walk"."""
    groups = {}
    for run in runs:
        missing = [k for k in keys if k not in run["config"]]
        if missing:
            raise PlotError(f"{run['dir']}/config.json: no key {missing[0]!r} to group by")
        groups.setdefault(" / ".join(config_label(run["config"], k) for k in keys), []).append(run)
    return dict(sorted(groups.items()))


# Config values that do not change what a line means: the seed, the budget (each run is drawn to its
# own end), where the run lives and how it is computed (device, threads, the replay's device,
# prefetch, compilation, TF32), what it writes (logs, snapshots, videos, the buffer) and how often
# and how long it is evaluated (eval_every moves the points, eval_episodes makes each one less
# noisy: the curve is an estimate of the same thing). Runs that differ only in these are seeds of
# one line. cli's RESUME_MAY_CHANGE is a subset.
NOT_A_SETTING = {"seed", "run_root", "frames", "device", "prefetch", "threads", "save_buffer", "save_video",
                 "log_every", "snapshot_minutes", "resume", "learned_mask_iou", "evaluate",
                 "eval_every", "eval_episodes", "eval_episodes_per_task",
                 "compile", "cuda_graphs", "tf32", "replay_device"}


def differing_settings(runs: list[dict], keys: list[str]) -> list[str]:
    """The config keys that tell a panel's lines apart: those (apart from NOT_A_SETTING, the
    grouping keys and the env) in which runs on the SAME env differ, so a value set per task
    (std_steps, a recipe's per-task rows) does not count. A key only some runs record came with a
    later sear.py: only the runs that record it can differ in it."""
    by_env = {}
    for r in runs:  # only the settings that acted in the run (cli.APPLIES): a drq run's --dear-feature did not
        by_env.setdefault(env_of(r), []).append(cli.acting_settings(r["config"]))
    # config_label() names drm with the method
    named = set(keys) | ({"drm"} if "method" in keys else set())
    names = sorted({k for configs in by_env.values() for c in configs for k in c} - NOT_A_SETTING - named - {"env"})
    return [k for k in names if any(len({json.dumps(c[k], sort_keys=True) for c in configs if k in c}) > 1
                                    for configs in by_env.values())]


def split_by_config(label: str, group: list[dict], differ: list[str]) -> dict[str, list[dict]]:
    """One line per setting: a group's runs split by the panel's differing settings
    (differing_settings), every line named by its values of all of them, e.g. "sear
    mask_source=learned:seg.pt", so that no line that differs from another is labelled plainly."""
    if not differ:
        return {label: group}
    lines = {}
    for run in group:
        acting = cli.acting_settings(run["config"])
        values = " ".join(f"{k}={acting[k]}" for k in differ if k in acting)
        lines.setdefault(f"{label} {values}".rstrip(), []).append(run)
    return dict(sorted(lines.items()))


def warn_uneven_ends(label: str, group: list[dict]) -> None:
    """Runs of one line that stop at different frames are each drawn to their own end: say so."""
    ends = [int(r["frames"][-1]) for r in group]
    if len(set(ends)) > 1:
        counts = ", ".join(f"{e}" + (f" (x{ends.count(e)})" if ends.count(e) > 1 else "")
                           for e in sorted(set(ends)))
        print(f"plot.py: warning: {label}: runs end at frames {counts}; each is drawn to its own "
              "end, the mean and CI at a frame are over the runs that reached it (dashed where "
              "not all did)", file=sys.stderr)


def task_mean_runs(task_runs: list[dict]) -> list[dict]:
    """--per-task: per run, the mean over its tasks at the frames where every task has a value, as
    one more "task" (its own panel)."""
    by_dir = {}
    for r in task_runs:
        by_dir.setdefault(r["dir"], []).append(r)
    means = []
    for d, tasks in by_dir.items():
        frames = tasks[0]["frames"]
        for t in tasks[1:]:
            frames = np.intersect1d(frames, t["frames"])
        if len(frames) == 0:
            continue
        values = np.mean([t["values"][np.isin(t["frames"], frames)] for t in tasks], axis=0)
        means.append({"dir": d, "config": tasks[0]["config"], "frames": frames, "values": values,
                      "task": f"mean over {len(tasks)} tasks"})
    return means


# ---------------------------------------------------------------- plotting
def short_frames(x, _pos=None) -> str:
    return f"{x / 1e6:g}M" if abs(x) >= 1e6 else f"{x / 1e3:g}k" if abs(x) >= 1e3 else f"{x:g}"


def band(mean: np.ndarray, ci: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of a line: ci is a half-width per frame, or (2, frames) bounds (a
    bootstrap's)."""
    ci = np.asarray(ci, dtype=float)
    return (ci[0], ci[1]) if ci.ndim == 2 else (mean - ci, mean + ci)


def draw_mean(ax, frames, mean, full, color: str, label: str, dashed: dict | None = None, **solid) -> bool:
    """A mean solid where `full` (every run has the frame), dashed elsewhere; the dashed part joins
    the solid one at its neighbouring points. True if some part is dashed."""
    ax.plot(frames, np.where(full, mean, np.nan), color=color, label=label, **solid)
    partial = ~np.asarray(full)
    if partial.any():
        joined = partial | np.convolve(partial, [1, 1, 1], mode="same").astype(bool)
        ax.plot(frames, np.where(joined, mean, np.nan), color=color, ls="--", **(dashed or {"lw": 1}))
    return bool(partial.any())


def draw_line(ax, frames, mean, ci, n, color: str, label: str) -> bool:
    """A group's mean and 95% band; dashed where not all of its runs have reached the frame (n: runs
    per frame, or one count). True if some part is dashed."""
    n = np.broadcast_to(np.asarray(n), np.shape(frames))
    partial = draw_mean(ax, frames, mean, n == n.max(), color, f"{label} (n={n.max()})")
    lo, hi = band(mean, ci)
    if n.max() > 1:
        ax.fill_between(frames, lo, hi, color=color, alpha=0.2, lw=0)
    return partial


def rate_axis(ax, ylabel: str) -> None:
    """A success rate lies in [0, 1]: no axis below 0 or above 1, whatever the band does."""
    if ylabel.endswith("success rate"):
        ax.set_ylim(0.0, 1.0)


# The layout rule: every panel's axes keep AXES_HEIGHT inches whatever its titles and legend need
# (the figure grows instead); a legend stays inside its axes only on a single panel with at most
# LEGEND_INSIDE entries of at most LABEL_INSIDE characters, else one legend serves all panels, in
# the grid's empty slot or below the panels, its labels wrapped to fit; titles are wrapped to their
# axes' width, the figure's title to the figure's.
PANEL_SIZE = (5.0, 3.6)      # inches per panel before titles and legends
AXES_HEIGHT = 2.6            # inches
LEGEND_INSIDE, LABEL_INSIDE = 6, 48


def fit_text(text, width_px: float, renderer) -> None:
    """Wrap a matplotlib Text at spaces until it is at most width_px wide."""
    paragraphs = text.get_text().split("\n")
    chars = max(map(len, paragraphs))
    while chars > 8 and text.get_window_extent(renderer).width > width_px:
        chars -= max(1, chars // 20)
        text.set_text("\n".join(textwrap.fill(p, chars, break_long_words=False) for p in paragraphs))


def place_legend(fig, entries: dict, title: str | None, spare, renderer):
    """One legend for every panel: in the grid's first empty slot (`spare`) if it fits there, else
    below the panels; as many columns as fit, labels wrapped to a column."""
    import matplotlib
    where = spare if spare is not None else fig
    width = 0.98 * where.get_window_extent(renderer).width
    # characters per line at "small" (0.833 x the font size), about 0.6 em each
    per_line = int(width / fig.dpi * 72 / (0.6 * 0.833 * matplotlib.rcParams["font.size"]))
    where_args = dict(loc="upper left", frameon=False) if spare is not None else dict(loc="outside lower center")
    longest = max(map(len, entries))
    for ncol in range(len(entries), 0, -1):
        chars = max(12, per_line // ncol - 6)  # room for the handle
        if chars < longest and ncol > 1:  # fewer columns before wrapped labels
            continue
        labels = [textwrap.fill(label, chars, break_long_words=False) for label in entries]
        legend = where.legend(list(entries.values()), labels, ncol=ncol, fontsize="small", title=title,
                              title_fontsize="small", **where_args)
        box = legend.get_window_extent(renderer)
        if box.width <= width or ncol == 1:
            break
        legend.remove()
    if spare is not None and box.height > spare.get_window_extent(renderer).height:
        legend.remove()  # too tall for the slot: below the panels instead
        spare.set_visible(False)
        return place_legend(fig, entries, title, None, renderer)
    if spare is None:  # room for it, or the layout would squeeze the axes to nothing
        fig.set_size_inches(fig.get_figwidth(), fig.get_figheight() + box.height / fig.dpi)
    return legend


def keep_axes_height(fig, axes: list, rows: int) -> None:
    """Grow the figure until its shortest axes is AXES_HEIGHT inches tall (the layout runs again on
    each draw)."""
    for _ in range(4):
        fig.canvas.draw()
        short = AXES_HEIGHT - min(ax.get_position().height for ax in axes) * fig.get_figheight()
        if short <= 0.01:
            return
        fig.set_size_inches(fig.get_figwidth(), fig.get_figheight() + short * rows + 0.05)


def plot(panels: dict, out: str, ylabel: str, title: str, baseline: tuple[float, str] | None = None,
         references: dict | None = None, estimates: dict | None = None, ylabels: dict | None = None):
    """estimates: {panel: what its lines and bands are} where not "mean ± 95% CI" (the legend's
    title, or the panels' titles where panels differ); ylabels: {panel: its y-label} where not
    `ylabel`. Each
    --reference curve is cut to the last frame of its panel's runs."""
    import matplotlib
    matplotlib.use("Agg")  # files only: no display needed on a cluster node
    import matplotlib.pyplot as plt

    cols = min(len(panels), 3)
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(PANEL_SIZE[0] * cols, PANEL_SIZE[1] * rows),
                             squeeze=False, layout="constrained")
    used = list(axes.flat[:len(panels)])
    what = {panel: (estimates or {}).get(panel, "mean ± 95% CI") for panel in panels}
    one_estimate = len(set(what.values())) == 1
    titles = {panel: (panel if len(panels) > 1 else title) + ("" if one_estimate else f"\n{what[panel]}")
              for panel in panels}
    dashed, entries = draw_panels(used, panels, titles, (ylabels or {}, ylabel), baseline, references or {})
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    legend_title = "; ".join([*([next(iter(what.values()))] if one_estimate else []),
                              *(["dashed: fewer runs"] if dashed else [])])
    lay_out(fig, axes, used, entries, legend_title or None, title if len(panels) > 1 else None)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def draw_panels(used: list, panels: dict, titles: dict, ylabels: tuple[dict, str], baseline,
                references: dict) -> tuple[bool, dict]:
    """Each panel's lines, baseline and --reference curves on its axes. Returns whether a line is
    dashed somewhere, and the legend's entries: the lines first, then baselines and references."""
    from matplotlib.ticker import FuncFormatter
    labels = sorted({label for curves in panels.values() for label in curves})
    colors = {label: f"C{i % 10}" for i, label in enumerate(labels)}  # same group, same color
    dashed, entries, others = False, {}, {}
    for ax, (panel, curves) in zip(used, panels.items()):
        for label, (frames, mean, ci, n, _env) in curves.items():
            dashed |= draw_line(ax, frames, mean, ci, n, colors[label], label)
        entries.update((label, h) for h, label in zip(*ax.get_legend_handles_labels()) if label not in entries)
        if baseline is not None:  # e.g. a random policy's mean (benchmarks/random_policy.py)
            ax.axhline(baseline[0], color="0.4", ls="--", lw=1, label=baseline[1])
        last = max((c[0][-1] for c in curves.values()), default=None)
        for i, ref in enumerate(references.get(panel, [])):  # --reference: published curves
            draw_reference(ax, ref, i, upto=last)
        ax.set_title(titles[panel])
        ax.set_xlabel("frames")
        ax.set_ylabel(ylabels[0].get(panel, ylabels[1]))
        ax.xaxis.set_major_formatter(FuncFormatter(short_frames))
        ax.grid(alpha=0.3)
        rate_axis(ax, ax.get_ylabel())
        others.update((label, h) for h, label in zip(*ax.get_legend_handles_labels()) if label not in entries)
    return dashed, {**entries, **others}


def lay_out(fig, axes, used: list, entries: dict, legend_title: str | None, suptitle: str | None):
    """The legend (inside a single panel when short, else in the grid's empty slot or below), titles
    wrapped to fit, and the axes kept AXES_HEIGHT tall."""
    suptitle = fig.suptitle(suptitle) if suptitle is not None else None
    renderer = fig.canvas.get_renderer()
    if len(used) == 1 and len(entries) <= LEGEND_INSIDE and max(map(len, entries), default=0) <= LABEL_INSIDE:
        used[0].legend(fontsize="small", title=legend_title, title_fontsize="small")
    elif entries:
        fig.canvas.draw()  # the layout: the empty slot's size
        spare = axes.flat[len(used)] if len(used) < axes.size else None
        place_legend(fig, entries, legend_title, spare, renderer)
    fig.canvas.draw()
    for ax in used:
        fit_text(ax.title, ax.get_window_extent(renderer).width, renderer)
    if suptitle is not None:
        fit_text(suptitle, 0.98 * fig.get_figwidth() * fig.dpi, renderer)
    keep_axes_height(fig, used, axes.shape[0])


def summary_table(panels: dict, metric: str) -> str:
    """One row per line: its runs (and how many reached its last frame, if not all) and its final
    value."""
    lines = [f"| env | group | seeds | last frame | final {metric} (mean ± 95% CI) |",
             "|---|---|---|---|---|"]
    for curves in panels.values():
        for label, (frames, mean, ci, n, env) in curves.items():
            n = np.broadcast_to(np.asarray(n), np.shape(frames))
            seeds = f"{n.max()}" + (f" ({n[-1]} at the last frame)" if n[-1] < n.max() else "")
            final = f"{mean[-1]:.4g}" + ("" if n[-1] == 1 else f" ± {ci[-1]:.3g}")
            lines.append(f"| {env} | {label} | {seeds} | {frames[-1]:.0f} | {final} |")
    return "\n".join(lines)


# ---------------------------------------------------------------- published reference curves:
# --reference A published learning curve in DrQ-v2's format (facebookresearch/drqv2,
# curves/dmc_<task>.csv): one row per seed and evaluation with columns seed, frame, episode_reward,
# and task and agent. A file without a task column holds the task its name says (dmc_<task>.csv).
REFERENCE_COLUMNS = ("seed", "frame", "episode_reward")


def task_key(name: str) -> str:
    """Our env names and DrQ-v2's task names on one key: cartpole-balance_sparse =
    cartpole_balance_sparse."""
    return name.strip().lower().replace("-", "_")


def parse_reference(spec: str) -> tuple[str, str | None]:
    """--reference PATH[:LABEL] -> (path, label or None); a path that exists as given keeps its
    colons."""
    path, sep, label = spec.rpartition(":")
    if os.path.exists(spec) or not sep or not path:
        return spec, None
    return path, label or None


def load_reference(path: str, label: str | None = None) -> dict[str, dict]:
    """{task key: {"label", "frames", "mean", "min", "max", "seeds", "values"}} of a published curve
    file. Per task its seeds are aligned on the frames they all have, as eval.csv runs are
    (aggregate)."""
    if not os.path.isfile(path):
        raise PlotError(f"--reference {path}: no such file")
    file_task = os.path.splitext(os.path.basename(path))[0].removeprefix("dmc_")
    seeds, agents = {}, {}  # task -> seed -> {frame: return}; task -> agent names
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in REFERENCE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise PlotError(f"--reference {path}: no {missing[0]!r} column (a published curve has "
                            f"columns {', '.join(REFERENCE_COLUMNS)}, and task or a dmc_<task>.csv "
                            "name)")
        for row in reader:
            task = task_key(row.get("task") or file_task)
            try:
                point = float(row["frame"]), float(row["episode_reward"])
            except (TypeError, ValueError):
                raise PlotError(f"--reference {path}: bad row {row}") from None
            seeds.setdefault(task, {}).setdefault(row["seed"], {})[point[0]] = point[1]
            agents.setdefault(task, set()).add(row.get("agent") or "")
    if not seeds:
        raise PlotError(f"--reference {path}: no rows")
    curves = {}
    for task, by_seed in seeds.items():
        if len(agents[task]) > 1:
            raise PlotError(f"--reference {path}: {task} has curves of several agents "
                            f"({', '.join(sorted(agents[task]))}); give one agent per file")
        frames = reduce(np.intersect1d, [np.array(sorted(points)) for points in by_seed.values()])
        if len(frames) == 0:
            raise PlotError(f"--reference {path}: the seeds of {task} share no frames")
        ys = np.array([[points[x] for x in frames] for points in by_seed.values()])
        agent = agents[task].pop() or os.path.basename(path)
        curves[task] = {"label": label or f"{agent} (published)", "frames": frames, "mean": ys.mean(axis=0),
                        "min": ys.min(axis=0), "max": ys.max(axis=0), "seeds": len(by_seed),
                        "values": ys}  # (seeds, frames): each seed's return, for tests against ours
    return curves


def references_for(panel_envs: dict[str, set], references: list[tuple[str, dict]]) -> dict[str, list[dict]]:
    """{panel: the reference curves drawn on it}: a reference goes on every panel holding a run on
    its task. `references` are (path, load_reference(path)); one that matches no panel is an
    error."""
    drawn = {panel: [] for panel in panel_envs}
    for path, curves in references:
        matched = False
        for panel, envs in panel_envs.items():
            for task in sorted({task_key(e) for e in envs} & set(curves)):
                drawn[panel].append(curves[task])
                matched = True
        if not matched:
            plotted = ", ".join(sorted({e for envs in panel_envs.values() for e in envs}))
            raise PlotError(f"--reference {path}: its tasks ({', '.join(sorted(curves))}) match no "
                            f"plotted env ({plotted})")
    return drawn


def draw_reference(ax, ref: dict, i: int = 0, upto: float | None = None):
    """A published curve: the mean over its seeds and a band from its lowest to its highest seed,
    cut to frames <= `upto` (the runs' last frame: a published curve usually goes on far beyond
    them, and its later values would set the y range). The x range stays the runs' (once they span
    any frames)."""
    xlim = ax.get_xlim()
    keep = slice(None) if upto is None else ref["frames"] <= upto
    frames = ref["frames"][keep]
    ax.plot(frames, ref["mean"][keep], color="k", ls=(":", "-.", "--")[i % 3], lw=1.5, marker="x", ms=4,
            label=f"{ref['label']} (n={ref['seeds']}: mean, min-max)")
    ax.fill_between(frames, ref["min"][keep], ref["max"][keep], color="k", alpha=0.08, lw=0)
    if xlim[1] >= 1:
        ax.set_xlim(xlim)


# ---------------------------------------------------------------- activation maps: plot.py maps
# The paper's recipe (section 5, "Visualizing Feature Maps"): the ReLU output of the encoder's last
# convolution (32 x 35 x 35), each channel resized to the image (84 x 84), normalised to [0, 1],
# coloured and blended over the image. Beyond the paper, each channel's share of activation mass on
# the robot, against the robot's share of the image.
MAPS_STRIDE = 25  # agent steps between the frames shown
# Where a unit of the 35 x 35 map looks: the trunk (3x3 stride 2, then three 3x3 stride 1, no
# padding) gives unit j the input pixels 2j .. 2j + 14, centred on 2j + 7. The overlays stretch the
# map over the whole image instead (the paper's resize), up to 7 px off at the borders.
RF_STRIDE, RF_OFFSET = 2, 7
# share > 2x the mask fraction: a robot channel; < 0.5x: an environment channel
ROBOT, ENVIRONMENT = 2.0, 0.5


def load_snapshot_run(run_dir: str):
    """(train.Config, snapshot) of a run directory; PlotError for anything that is not one."""
    import sear
    import train
    if not os.path.isfile(os.path.join(run_dir, "config.json")):
        raise PlotError(f"{run_dir} is not a run directory (no config.json)")
    try:
        state = cli.load_snapshot(run_dir, flag="")
        return cli.split_config(state["config"], train.Config)[0], state
    except cli.ConfigError as e:
        raise PlotError(str(e)) from None
    except (KeyError, TypeError) as e:  # a torch file, but not a sear.py snapshot
        raise PlotError(f"{run_dir}/snapshot.pt is not a sear.py snapshot ({type(e).__name__}: "
                        f"{cli.first_sentence(e)})") from None


def trained_agent(cfg, state, action_dim: int):
    import torch
    import sear
    import train
    agent = train.make_agent(cfg, action_dim, torch.device("cpu"))
    try:
        agent.load_state_dict(state["agent"])
    except (KeyError, RuntimeError) as e:
        raise PlotError(f"snapshot does not fit its config's networks: {cli.first_sentence(e)}") from None
    return agent


def open_env(cfg):
    """The run's eval env as sear.py builds it (same seeds, render settings, distractions), but with
    clean masks whatever the run's --mask-noise, and masks rendered for mask-free methods too."""
    from harness import experiment, runenvs
    try:
        return runenvs.make_run_env(cfg, "eval", render_mask=True, mask_noise=0.0, mask_approx=False)
    except cli.ConfigError as e:
        raise PlotError(str(e)) from None


def map_frames(env, cfg, agent, n: int):
    """n observations (pixels, masks) of `env`, MAPS_STRIDE agent steps apart, from the reset of the
    run's first evaluation episode (its seed, its task), acting with `agent`'s mean action; and the
    steps they were at (counted on across episodes, should one end first)."""
    from harness import experiment, runenvs
    tasks = runenvs.eval_tasks(getattr(env.unwrapped, "tasks", None), cfg)

    def reset(i):
        task = tasks[i % len(tasks)]
        options = None if task is None else {"task": task}
        return env.reset(seed=runenvs.episode_seed(cfg.seed + 100_000, i), options=options)[0]

    episode, t, pixels, masks, steps = 0, 0, [], [], []
    obs = reset(episode)
    while True:
        if t % MAPS_STRIDE == 0:
            pixels.append(obs["pixels"]), masks.append(obs["mask"]), steps.append(t)
            if len(pixels) == n:
                return np.stack(pixels), np.stack(masks).astype(bool), steps
        obs, _, terminated, truncated, _ = env.step(agent.act(obs["pixels"], obs["mask"], 0, eval_mode=True))
        t += 1
        if terminated or truncated:  # a short episode: the next evaluation episode goes on
            episode += 1
            obs = reset(episode)


def last_conv_maps(agent, pixels: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """The ReLU output of the encoder's last convolution, (N, 32, 35, 35), for uint8 observations:
    caught on the way through the encoder's own forward (its normalisation, its input channels)."""
    import torch
    caught = []
    hook = agent.encoder.convs.register_forward_hook(lambda module, inputs, output: caught.append(output))
    try:
        with torch.no_grad():
            from methods import baselines
            x = torch.as_tensor(pixels).float()
            if isinstance(agent, baselines.RGBMAgent):
                x = baselines.with_masks(x, torch.as_tensor(masks).float())
            agent.encode(x)
    finally:
        hook.remove()
    return caught[0].float().numpy()


def overlay_maps(image: np.ndarray, maps: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Each channel of `maps` (C, h, w) as a heat map over `image` (H, W, 3) uint8: resized to H x W
    (bilinear), normalised to [0, 1] per channel, coloured with jet, blended. -> (C, H, W, 3)
    uint8."""
    import torch
    import torch.nn.functional as F
    from matplotlib import colormaps
    h, w = image.shape[:2]
    up = F.interpolate(torch.as_tensor(maps)[None], size=(h, w), mode="bilinear", align_corners=False)[0].numpy()
    lo, hi = up.min(axis=(1, 2), keepdims=True), up.max(axis=(1, 2), keepdims=True)
    norm = (up - lo) / np.where(hi > lo, hi - lo, 1.0)  # a flat channel stays 0
    heat = colormaps["jet"](norm)[..., :3]
    return np.round(255 * ((1 - alpha) * image[None] / 255.0 + alpha * heat)).astype(np.uint8)


def channel_grid(tiles: np.ndarray, cols: int = 8, pad: int = 2) -> np.ndarray:
    """Tiles (C, H, W, 3) in rows of `cols`, white gaps of `pad` px -> one (R*H + (R-1)*pad,
    cols*W + (cols-1)*pad, 3) image."""
    c, h, w, _ = tiles.shape
    rows = math.ceil(c / cols)
    grid = np.full((rows * h + (rows - 1) * pad, cols * w + (cols - 1) * pad, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, k = divmod(i, cols)
        grid[r * (h + pad):r * (h + pad) + h, k * (w + pad):k * (w + pad) + w] = tile
    return grid


def robot_units(masks: np.ndarray, side: int) -> np.ndarray:
    """The true mask at the centre of each map unit's receptive field: (N, H, W) -> (N, side,
    side)."""
    centres = RF_OFFSET + RF_STRIDE * np.arange(side)
    return masks[:, centres][:, :, centres]


def robot_share(maps: np.ndarray, robot: np.ndarray) -> np.ndarray:
    """Per channel, the share of its activation mass (over all frames and units) that falls on robot
    units: sum(a * robot) / sum(a), maps (N, C, h, w), robot (N, h, w). NaN for a channel that never
    fires. A channel that fires evenly everywhere gets the robot's share of the units."""
    mass = maps.sum(axis=(0, 2, 3))
    on_robot = (maps * robot[:, None]).sum(axis=(0, 2, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return on_robot / mass


def maps_figure(out: str, frames: dict, runs: list[dict], mask_fraction: float):
    """One row per frame: the image (true mask outlined), then each run's 32 channels as a 4 x 8
    grid, sorted by share on robot (highest first, number in the corner); below, the histogram of
    the shares per run against the mask fraction."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(frames["images"])
    grid_h, grid_w = runs[0]["grids"][0].shape[:2]
    fig = plt.figure(figsize=((grid_h + grid_w * len(runs)) / 100 + 1, n * (grid_h / 100 + 0.4) + 3.2),
                     layout="constrained")
    gs = fig.add_gridspec(n + 1, 1 + len(runs), width_ratios=[grid_h] + [grid_w] * len(runs),
                          height_ratios=[grid_h] * n + [0.9 * grid_h])
    tile = (grid_h + 2) // 4  # 4 rows of tiles with 2-px gaps
    for i in range(n):
        ax = fig.add_subplot(gs[i, 0])
        ax.imshow(frames["images"][i])
        ax.contour(frames["masks"][i], levels=[0.5], colors="magenta", linewidths=0.7)
        ax.set_title(f"step {frames['steps'][i]} (robot outlined)", fontsize=8)
        ax.axis("off")
        for j, run in enumerate(runs):
            ax = fig.add_subplot(gs[i, 1 + j])
            ax.imshow(run["grids"][i])
            for rank, channel in enumerate(run["order"]):
                r, k = divmod(rank, 8)
                share = run["share"][channel]
                ax.text(k * tile + 2, r * tile + 2, "dead" if np.isnan(share) else f"{share:.2f}",
                        color="white", fontsize=5, va="top")
            ax.axis("off")
            if i == 0:
                ax.set_title(run["label"], fontsize=9)
    ax = fig.add_subplot(gs[n, 1:])
    bins = np.linspace(0, 1, 41)
    for j, run in enumerate(runs):
        live = run["share"][~np.isnan(run["share"])]
        ax.hist(live, bins=bins, histtype="step", lw=1.5, color=f"C{j}",
                label=f"{run['label']}: {run['robot']} robot, {run['environment']} environment "
                      "channels")
    ax.axvline(mask_fraction, color="k", lw=1, label=f"mask fraction {mask_fraction:.3f}")
    for factor in (ROBOT, ENVIRONMENT):
        ax.axvline(factor * mask_fraction, color="k", lw=0.8, ls="--")
    ax.set_xlabel("share of a channel's activation on the robot (dashed: 0.5x and 2x the mask "
                  "fraction)")
    ax.set_ylabel("channels")
    ax.legend(fontsize=7)
    fig.suptitle("Last-convolution activation maps (ReLU, 32 x 35 x 35 resized to 84 x 84), "
                 "channels sorted by share on robot", fontsize=10)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def maps_table(runs: list[dict], mask_fraction: float) -> str:
    lines = [f"mask fraction (robot units of the 35x35 map, over the frames): {mask_fraction:.4f}", "",
             f"| run | method | trained frames | robot channels (share > {ROBOT:g}x) | environment "
             f"channels (share < {ENVIRONMENT:g}x) | dead | median share |", "|---|---|---|---|---|---|---|"]
    for run in runs:
        live = run["share"][~np.isnan(run["share"])]
        median = f"{np.median(live):.4f}" if len(live) else "-"
        lines.append(f"| {run['dir']} | {run['method']} | {run['frame']} | {run['robot']} | "
                     f"{run['environment']} | {run['dead']} | {median} |")
    return "\n".join(lines)


def maps_main(argv) -> int:
    parser = cli.OneLineParser(prog="plot.py maps", description="Activation maps of the encoder's "
                                                                "last "
                               "convolution for one or more runs on the same frames (the paper's "
                               "section 5), and each channel's share of activation on the robot.")
    parser.add_argument("runs", nargs="+", help="run directories (config.json and snapshot.pt), "
                                                "all on one env")
    parser.add_argument("--out", default="runs/maps.png", help="PNG to write (default "
                                                               "runs/maps.png)")
    parser.add_argument("--frames", type=int, default=2, help=f"frames to show, {MAPS_STRIDE} "
                                                              "agent steps apart")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    args = parse(parser, argv)
    if args is None:
        return 2
    try:
        if os.path.exists(args.out) and not args.force:  # checked first: don't make the user wait
            raise PlotError(f"{args.out} exists; refusing to overwrite it (use --force)")
        if args.frames < 1:
            raise PlotError(f"--frames must be >= 1, got {args.frames}")
        loaded = [(os.path.normpath(d), *load_snapshot_run(d)) for d in args.runs]
        first = loaded[0][1]
        for d, cfg, _ in loaded[1:]:
            if (cfg.env, cfg.frame_stack) != (first.env, first.frame_stack):
                raise PlotError(f"{d} is on {cfg.env} (frame stack {cfg.frame_stack}), "
                                f"{loaded[0][0]} on {first.env} (frame stack {first.frame_stack}): "
                                "maps compare runs on the same frames")
        import torch
        torch.set_num_threads(cli.default_threads())
        env = open_env(first)
        agents = [trained_agent(cfg, state, env.action_space.shape[0]) for _, cfg, state in loaded]
        # The frames: the first run's env, config and policy; every run sees exactly these.
        pixels, masks, steps = map_frames(env, first, agents[0], args.frames)
        env.close()
        frames = {"images": pixels[:, -3:].transpose(0, 2, 3, 1), "masks": masks[:, -1], "steps": steps}
        all_maps = [last_conv_maps(agent, pixels, masks) for agent in agents]
        robot = robot_units(frames["masks"], all_maps[0].shape[-1])
        frac = float(robot.mean())
        runs = []
        for (d, cfg, state), maps in zip(loaded, all_maps):
            share = robot_share(maps, robot)
            order = np.argsort(-np.nan_to_num(share, nan=-1.0), kind="stable")
            frame = state["counters"]["step"] * cfg.action_repeat
            runs.append({
                "dir": d, "method": cfg.method, "frame": frame, "share": share, "order": order,
                "label": f"{cfg.method} seed {cfg.seed}, {short_frames(frame)} frames",
                "robot": int(np.sum(share > ROBOT * frac)), "environment": int(np.sum(share < ENVIRONMENT * frac)),
                "dead": int(np.isnan(share).sum()),
                "grids": [channel_grid(overlay_maps(img, m)[order]) for img, m in zip(frames["images"], maps)]})
        maps_figure(args.out, frames, runs, frac)
    except PlotError as e:
        print(f"plot.py maps: error: {e}", file=sys.stderr)
        return 2
    print(maps_table(runs, frac))
    print(f"\nwrote {args.out}")
    return 0


# ---------------------------------------------------------------- CLI
def build_parser(parser_class):
    parser = parser_class(prog="plot.py", description=__doc__.split("\n\n")[0],
                          formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="run directories, folders of runs, or globs")
    parser.add_argument("--out", default="runs/curves.png", help="PNG to write (default "
                                                                 "runs/curves.png)")
    parser.add_argument("--metric", default="return", help="return | success | any column of the "
                                                           "CSV read (e.g. --csv train --metric "
                                                           "dormant_ratio)")
    parser.add_argument("--csv", default="eval", choices=("eval", "train"), help="which log to "
                                                                                 "read")
    parser.add_argument("--group", default="method", help="config keys, comma separated: "
                                                          "method,env")
    parser.add_argument("--title", default=None)
    parser.add_argument("--per-task", action="store_true",
                        help="task sets: one panel per task, from eval.csv's <metric>/<task> "
                             "columns")
    parser.add_argument("--baseline", default=None, metavar="VALUE[:LABEL]",
                        help="a dashed horizontal line, e.g. 1.6:random "
                             "(benchmarks/random_policy.py)")
    parser.add_argument("--reference", action="append", default=[], metavar="CSV[:LABEL]",
                        help="a published curve (DrQ-v2's curves/dmc_<task>.csv format): mean and "
                             "min-max band over its seeds, on the panels of its task; repeatable")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    return parser


def parse(parser, argv):
    """The arguments, or None after one line on stderr (`<prog>: error: ...`:
    cli.OneLineParser's)."""
    try:
        return parser.parse_args(argv)
    except cli.ConfigError as e:
        print(f"{parser.prog}: error: {e}", file=sys.stderr)
        return None


def checked_args(args) -> tuple[list, tuple[float, str] | None, list[str]]:
    """(--reference curves, --baseline, --group keys), read and checked before any run is."""
    references = [(path, load_reference(path, label)) for path, label in map(parse_reference, args.reference)]
    baseline = None
    if args.baseline is not None:
        value, _, label = args.baseline.partition(":")
        try:
            baseline = (float(value), label or "baseline")
        except ValueError:
            raise PlotError("--baseline must be VALUE[:LABEL], e.g. 1.6:random; got "
                            f"{args.baseline!r}") from None
    if os.path.exists(args.out) and not args.force:  # checked first: don't make the user wait
        raise PlotError(f"{args.out} exists; refusing to overwrite it (use --force)")
    keys = [k.strip() for k in args.group.split(",") if k.strip()]
    if not keys:
        raise PlotError("--group needs at least one config key, e.g. method")
    if args.per_task and args.csv != "eval":
        raise PlotError("--per-task reads eval.csv (per-task columns are written by evaluations)")
    return references, baseline, keys


def load_runs(args) -> list[dict]:
    """The runs the paths name (with --per-task one per task, and their means); a run without the
    CSV yet is skipped with one line."""
    runs = []
    found = find_runs(args.paths)
    for d in found:
        try:
            runs += load_task_runs(d, args.metric) if args.per_task else [load_run(d, args.csv, args.metric)]
        except NoLogYet as e:  # one run stopped early must not hide all the others
            print(f"plot.py: skipping {d}: {e}", file=sys.stderr)
    if not runs:
        raise PlotError(f"nothing to draw: none of the {len(found)} runs found has written "
                        f"{args.csv}.csv yet")
    return runs + (task_mean_runs(runs) if args.per_task else [])


def panel_runs(runs: list[dict], keys: list[str]) -> dict[str, list[dict]]:
    """{panel: runs}: one panel per env, unless env is already told apart by the lines (or there is
    just one); with --per-task one per task (and env)."""
    envs = sorted({env_of(r) for r in runs})
    by_env = len(envs) > 1 and "env" not in keys
    keyed = {}
    for r in sorted(runs, key=env_of):  # stable: tasks keep their column order
        key = ": ".join(([env_of(r)] if by_env else []) + ([r["task"]] if "task" in r else []))
        keyed.setdefault(key or ", ".join(envs), []).append(r)
    return keyed


def panel_lines(panel: str, members: list[dict], keys: list[str], interpolate: bool) -> dict:
    """{label: (frames, mean, ci, runs per frame, envs)} of a panel's lines."""
    lines = {}
    differ = differing_settings(members, keys)
    for label, group in (line for g in group_runs(members, keys).items()
                         for line in split_by_config(*g, differ).items()):
        seeds = [r["config"].get("seed") for r in group]
        if len(set(seeds)) < len(seeds):
            print(f"plot.py: warning: {label}: repeated seeds {seeds}", file=sys.stderr)
        warn_uneven_ends(f"{label} ({panel})", group)
        curves = [(r["frames"], r["values"]) for r in group]
        envs_of_group = ", ".join(sorted({env_of(r) for r in group}))
        if "task" in group[0]:  # --per-task: the table names the task too
            envs_of_group += f": {group[0]['task']}"
        lines[label] = (*aggregate(curves, interpolate), coverage(curves, interpolate), envs_of_group)
    return lines


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    if argv[:1] == ["maps"]:  # a folder of runs named "maps" is given as ./maps
        return maps_main(argv[1:])
    args = parse(build_parser(cli.OneLineParser), argv)
    if args is None:
        return 2
    try:
        references, baseline, keys = checked_args(args)
        keyed = panel_runs(load_runs(args), keys)
        panels = {panel: panel_lines(panel, members, keys, args.csv == "train")
                  for panel, members in keyed.items()}
        envs = sorted({env_of(r) for members in keyed.values() for r in members})
        ylabel = f"{args.csv} {'success rate' if args.metric == 'success' else args.metric}"
        title = args.title or (f"{ylabel} ({envs[0]})" if len(envs) == 1 else ylabel)
        drawn = references_for({panel: {env_of(r) for r in members} for panel, members in keyed.items()},
                               references)
        plot(panels, args.out, ylabel, title, baseline, drawn)
    except PlotError as e:
        print(f"plot.py: error: {e}", file=sys.stderr)
        return 2
    print(summary_table(panels, args.metric))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
