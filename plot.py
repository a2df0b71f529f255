"""Learning curves from sear.py run directories: mean over seeds with a 95% confidence band.

Usage:  python plot.py runs/ --out runs/curves.png
        python plot.py 'runs/walker-walk*' --group method,env --metric return --title "Walker"
        python plot.py 'runs/cartpole*' --csv train --metric dormant_ratio --out runs/dormant.png
        python plot.py 'runs/cartpole*' --reference drqv2/curves/dmc_cartpole_balance_sparse.csv
        python plot.py 'runs/metaworld-mt10*' --metric success --per-task --out runs/mt10.png
        python plot.py maps RUN_A [RUN_B ...] --out runs/maps.png [--frames N]

Arguments are run directories (holding config.json), parent folders or globs. One line per --group value and
per setting in which runs on the same env differ, one panel per env (docs/figures.md); the band is rliable's
percentile-bootstrap 95% CI of the mean. A markdown table of the final values goes to stdout (docs/outputs.md);
`plot.py maps`: docs/inspection.md. Bad input is one line on stderr, exit code 2.
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
import warnings
from functools import reduce

import numpy as np

from harness import cli  # the standard library only: the curves need neither torch nor MuJoCo


class PlotError(Exception):
    """Bad input: reported as one line on stderr, exit code 2."""


class NoLogYet(PlotError):
    """A run without the CSV asked for (it stopped before its first row): skipped, not fatal."""


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


def read_csv(path: str, csv_name: str) -> tuple[list[str], list[dict]]:
    """(header, rows) of a run's log; NoLogYet when the run has not written it yet."""
    if not os.path.exists(path):
        first = {"eval": "its first evaluation", "train": "its first episode"}[csv_name]
        raise NoLogYet(f"no {csv_name}.csv (the run stopped before {first} ended)")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return reader.fieldnames or [], list(reader)


def load_run(run_dir: str, csv_name: str = "eval", metric: str = "return") -> dict:
    """{"dir", "config", "frames", "values"} of one run; frames sorted and unique (a repeated frame, say after a
    resume, keeps its last row); empty cells skipped."""
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            config = json.load(f)
    except (OSError, ValueError) as e:
        raise PlotError(f"{run_dir}/config.json: unreadable ({e})") from None
    path = os.path.join(run_dir, f"{csv_name}.csv")
    header, rows = read_csv(path, csv_name)
    if metric not in header:
        raise PlotError(f"{path}: " + (f"no '{metric}' column (has {','.join(header)})" if header else "empty"))
    points = {}
    for row in rows:
        try:
            if row[metric] not in ("", None):  # not logged there: skip the cell, keep the run
                points[float(row["frame"])] = float(row[metric])
        except (KeyError, ValueError):
            raise PlotError(f"{path}: bad row {row}") from None
    if not points:
        raise PlotError(f"{path}: no rows with a '{metric}' value")
    frames = np.array(sorted(points))
    return {"dir": run_dir, "config": config, "frames": frames, "values": np.array([points[x] for x in frames])}


def load_task_runs(run_dir: str, metric: str) -> list[dict]:
    """One load_run per task of a task-set run (its eval.csv's <metric>/<task> columns)."""
    path = os.path.join(run_dir, "eval.csv")
    tasks = [c[len(metric) + 1:] for c in read_csv(path, "eval")[0] if c.startswith(metric + "/")]
    if not tasks:
        raise PlotError(f"{path}: no per-task columns ({metric}/<task>); --per-task needs task-set runs "
                        f"(metaworld-mt3, -mt10, -mt50)")
    return [{**load_run(run_dir, "eval", f"{metric}/{task}"), "task": task} for task in tasks]


# ---------------------------------------------------------------- statistics
# Resamples of every bootstrap CI (plot.py's, sweep.py's report's). One method of a grid (5 seeds x 10 tasks x
# 250 evaluations) on 2 busy cores: rliable's default of 50,000 took 41 s, 10,000 10 s.
BOOTSTRAP_REPS = 10_000


def bootstrap(scores: dict, statistic) -> tuple[dict, dict]:
    """rliable's point estimates and stratified 95% percentile-bootstrap CIs ((2, ...) bounds) of `statistic` of each
    scores[k], (runs, tasks, frames), from a fixed seed: a figure is the same every time."""
    from rliable import library as rly
    with warnings.catch_warnings():  # arch's note on how rliable seeds it, not about these numbers
        warnings.simplefilter("ignore", FutureWarning)
        return rly.get_interval_estimates(scores, statistic, reps=BOOTSTRAP_REPS,
                                          random_state=np.random.RandomState(0))


def stack_curves(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False):
    """(frames, values): the union of the curves' frames, and each curve on them (NaN where it has no value):
    eval.csv's at its own frames only, train.csv's (interpolate) interpolated within its own span."""
    if not curves:
        raise PlotError("no runs to average")
    grid = np.unique(np.concatenate([f for f, _ in curves]))
    ys = np.full((len(curves), len(grid)), np.nan)
    for row, (f, v) in zip(ys, curves):
        inside = (grid >= f[0]) & (grid <= f[-1]) if interpolate else np.isin(grid, f)
        row[inside] = np.interp(grid[inside], f, v) if interpolate else v  # sorted: in order
    return grid, ys


def aggregate(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False):
    """(frames, mean, ci) of (frames, values) curves, each to its own end: at every frame the mean over the curves that
    have it and rliable's 95% CI over them, (2, frames) bounds, NaN where one curve has it. A resampled mean lies
    between the lowest and the highest value: the band never leaves the values' range."""
    grid, ys = stack_curves(curves, interpolate)
    ci = np.full((2, len(grid)), np.nan)
    present, which = np.unique(~np.isnan(ys), axis=1, return_inverse=True)  # frames by their runs
    for p, rows in enumerate(present.T):
        at = np.ravel(which) == p
        if rows.sum() > 1:
            _, bounds = bootstrap({"": ys[rows][:, at][:, None]}, lambda x: x.mean(axis=(0, 1)))
            ci[:, at] = bounds[""]
    return grid, np.nanmean(ys, axis=0), ci


def coverage(curves: list[tuple[np.ndarray, np.ndarray]], interpolate: bool = False) -> np.ndarray:
    """How many of the curves have a value at each of aggregate()'s frames."""
    return np.sum(~np.isnan(stack_curves(curves, interpolate)[1]), axis=0)


def env_of(run: dict) -> str:
    return str(run["config"].get("env", "?"))


def group_runs(runs: list[dict], keys: list[str]) -> dict[str, list[dict]]:
    """{label: runs}, label the runs' config values of `keys` ("sear / walker-walk"), the method with its variant
    (drq+drm: --drm)."""
    groups = {}
    for run in runs:
        missing = [k for k in keys if k not in run["config"]]
        if missing:
            raise PlotError(f"{run['dir']}/config.json: no key {missing[0]!r} to group by")
        groups.setdefault(" / ".join(cli.method_label(run["config"]) if k == "method" else str(run["config"][k])
                                     for k in keys), []).append(run)
    return dict(sorted(groups.items()))


# Config values that do not change what a line means (docs/figures.md): the seed, the budget, where and how it is
# computed, what it writes, how often and how long it is evaluated. cli's RESUME_MAY_CHANGE is a subset.
NOT_A_SETTING = {"seed", "run_root", "frames", "device", "prefetch", "threads", "save_buffer", "save_video",
                 "log_every", "snapshot_minutes", "resume", "learned_mask_iou", "evaluate", "eval_every",
                 "eval_episodes", "eval_episodes_per_task", "compile", "cuda_graph", "cuda_graphs", "batch_seeds",
                 "tf32", "replay_device"}


def differing_settings(runs: list[dict], keys: list[str]) -> list[str]:
    """The settings that tell a panel's lines apart: those (but NOT_A_SETTING, the grouping keys and the env) that
    acted and differ between runs on the SAME env, so that a value set per task does not count; a key only some runs
    record differs only among them."""
    by_env = {}
    for r in runs:
        by_env.setdefault(env_of(r), []).append(cli.acting_settings(r["config"]))
    named = {*keys, "env", *(["drm"] if "method" in keys else [])}  # drm: in the method's label
    names = sorted({k for cs in by_env.values() for c in cs for k in c} - NOT_A_SETTING - named)
    return [k for k in names if any(differ(k, configs) for configs in by_env.values())]


def differ(key: str, configs: list[dict]) -> bool:
    """Whether the configs that record `key` hold more than one value of it."""
    return len({json.dumps(c[key], sort_keys=True) for c in configs if key in c}) > 1


def split_by_config(label: str, group: list[dict], differ: list[str]) -> dict[str, list[dict]]:
    """One line per setting: a group's runs split by `differ`, each named by its values of all of them."""
    lines = {}
    for run in group:
        acting = cli.acting_settings(run["config"]) if differ else {}
        values = " ".join(f"{k}={acting[k]}" for k in differ if k in acting)
        lines.setdefault(f"{label} {values}".rstrip(), []).append(run)
    return dict(sorted(lines.items()))


def task_mean_runs(task_runs: list[dict]) -> list[dict]:
    """--per-task: per run, its mean over its tasks at the frames every task has, as a task."""
    by_dir, means = {}, []
    for r in task_runs:
        by_dir.setdefault(r["dir"], []).append(r)
    for d, tasks in by_dir.items():
        frames = reduce(np.intersect1d, [t["frames"] for t in tasks])
        if len(frames):
            values = np.mean([t["values"][np.isin(t["frames"], frames)] for t in tasks], axis=0)
            means.append({"dir": d, "config": tasks[0]["config"], "frames": frames, "values": values,
                          "task": f"mean over {len(tasks)} tasks"})
    return means


# ---------------------------------------------------------------- plotting
def short_frames(x, _pos=None) -> str:
    return f"{x / 1e6:g}M" if abs(x) >= 1e6 else f"{x / 1e3:g}k" if abs(x) >= 1e3 else f"{x:g}"


def draw_mean(ax, frames, mean, full, color: str, label: str, dashed: dict | None = None, **solid) -> bool:
    """A mean solid where `full` (every run has the frame), dashed elsewhere, joined to the solid part at its
    neighbouring points. True if some part is dashed."""
    ax.plot(frames, np.where(full, mean, np.nan), color=color, label=label, **solid)
    partial = ~np.asarray(full)
    if partial.any():
        joined = partial | np.convolve(partial, [1, 1, 1], mode="same").astype(bool)
        ax.plot(frames, np.where(joined, mean, np.nan), color=color, ls="--", **(dashed or {"lw": 1}))
    return bool(partial.any())


# The layout rule (docs/figures.md): axes keep AXES_HEIGHT inches (the figure grows instead); a legend stays inside a
# single panel's axes with at most LEGEND_INSIDE entries of at most LABEL_INSIDE characters, else serves all panels.
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
    """One legend for every panel: in the grid's empty slot (`spare`) if it fits there, else below the panels (the
    figure grows); as many columns as fit, labels wrapped to a column."""
    where = spare if spare is not None else fig
    width = 0.98 * where.get_window_extent(renderer).width
    loc = {"loc": "upper left", "frameon": False} if spare is not None else {"loc": "outside lower center"}
    legend = widest_legend(fig, where, entries, width, renderer, title=title, **loc)
    box = legend.get_window_extent(renderer)
    if spare is not None and box.height > spare.get_window_extent(renderer).height:
        legend.remove()  # too tall for the slot: below the panels instead
        spare.set_visible(False)
        return place_legend(fig, entries, title, None, renderer)
    if spare is None:  # room for it, or the layout would squeeze the axes to nothing
        fig.set_size_inches(fig.get_figwidth(), fig.get_figheight() + box.height / fig.dpi)
    return legend


def widest_legend(fig, where, entries: dict, width: float, renderer, **kwargs):
    """The legend in as many columns as fit `width` pixels, fewer columns before wrapped labels."""
    import matplotlib
    # characters per line at "small" (0.833 x the font size), about 0.6 em each
    per_line = int(width / fig.dpi * 72 / (0.6 * 0.833 * matplotlib.rcParams["font.size"]))
    for ncol in range(len(entries), 0, -1):
        chars = max(12, per_line // ncol - 6)  # room for the handle
        if chars < max(map(len, entries)) and ncol > 1:
            continue
        labels = [textwrap.fill(label, chars, break_long_words=False) for label in entries]
        legend = where.legend(list(entries.values()), labels, ncol=ncol, fontsize="small", title_fontsize="small",
                              **kwargs)
        if legend.get_window_extent(renderer).width <= width or ncol == 1:
            return legend
        legend.remove()


def plot(panels: dict, out: str, ylabel: str, title: str, baseline: tuple | None = None,
         references: dict | None = None, estimates: dict | None = None, ylabels: dict | None = None):
    """panels: {panel: {label: (frames, mean, ci, runs per frame, envs)}}. estimates: {panel: what its lines and bands
    are} where not "mean ± 95% CI" (the legend's title, or each panel's where they differ); ylabels: {panel: its
    y-label} where not `ylabel`; references: {panel: load_reference curves}."""
    import matplotlib
    matplotlib.use("Agg")  # files only: no display needed on a cluster node
    import matplotlib.pyplot as plt
    cols = min(len(panels), 3)
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(PANEL_SIZE[0] * cols, PANEL_SIZE[1] * rows), squeeze=False,
                             layout="constrained")
    texts, one = panel_texts(panels, title, ylabel, estimates or {}, ylabels or {})
    dashed, entries = draw_panels(axes.flat, panels, texts, baseline, references or {})
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    legend_title = "; ".join([*([one] if one else []), *(["dashed: fewer runs"] if dashed else [])])
    lay_out(fig, axes, len(panels), entries, legend_title or None, title if len(panels) > 1 else None)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def panel_texts(panels: dict, title: str, ylabel: str, estimates: dict, ylabels: dict):
    """({panel: (title, y-label)}, the estimate every panel shows, or None where they differ: then each panel's title
    says its own)."""
    what = {panel: estimates.get(panel, "mean ± 95% CI") for panel in panels}
    one = next(iter(what.values())) if len(set(what.values())) == 1 else None
    titles = {panel: panel if len(panels) > 1 else title for panel in panels}
    return {panel: (titles[panel] + ("" if one else f"\n{what[panel]}"), ylabels.get(panel, ylabel))
            for panel in panels}, one


def draw_panels(axes, panels: dict, texts: dict, baseline, references: dict) -> tuple[bool, dict]:
    """Each panel's lines (mean and band), baseline and references, then its (title, y-label). -> whether a line is
    dashed somewhere, and the legend's entries: the lines first, then the others."""
    colors = {label: f"C{i % 10}" for i, label in  # same line, same colour on every panel
              enumerate(sorted({label for curves in panels.values() for label in curves}))}
    dashed, entries, others = False, {}, {}
    for ax, (panel, curves) in zip(axes, panels.items()):
        for label, (frames, mean, ci, n, _env) in curves.items():
            dashed |= draw_mean(ax, frames, mean, n == n.max(), colors[label], f"{label} (n={n.max()})")
            if n.max() > 1:
                ax.fill_between(frames, ci[0], ci[1], color=colors[label], alpha=0.2, lw=0)
        entries.update(legend_entries(ax, entries))
        finish_panel(ax, baseline, references.get(panel, []), curves, texts[panel])
        others.update(legend_entries(ax, entries))
    return dashed, {**entries, **others}


def legend_entries(ax, known: dict) -> dict:
    """{label: handle} of the axes' artists not yet in `known`."""
    return {lb: h for h, lb in zip(*ax.get_legend_handles_labels()) if lb not in known}


def finish_panel(ax, baseline, references: list, curves: dict, texts: tuple[str, str]) -> None:
    """A panel's baseline, reference curves (cut to its runs' last frame), title and axes; a success rate on [0, 1],
    whatever matplotlib's margins do."""
    from matplotlib.ticker import FuncFormatter
    if baseline is not None:  # e.g. a random policy's mean (benchmarks/random_policy.py)
        ax.axhline(baseline[0], color="0.4", ls="--", lw=1, label=baseline[1])
    for i, ref in enumerate(references):
        draw_reference(ax, ref, i, upto=max(c[0][-1] for c in curves.values()))
    ax.set(title=texts[0], xlabel="frames", ylabel=texts[1])
    ax.xaxis.set_major_formatter(FuncFormatter(short_frames))
    ax.grid(alpha=0.3)
    if texts[1].endswith("success rate"):
        ax.set_ylim(0.0, 1.0)


def lay_out(fig, axes, n: int, entries: dict, legend_title: str | None, suptitle: str | None):
    """The legend (inside a single panel when short, else in the grid's empty slot or below), titles wrapped to fit,
    and the n panels' axes grown (with the figure) to AXES_HEIGHT."""
    used, renderer = list(axes.flat[:n]), fig.canvas.get_renderer()
    suptitle = fig.suptitle(suptitle) if suptitle is not None else None
    if n == 1 and len(entries) <= LEGEND_INSIDE and max(map(len, entries)) <= LABEL_INSIDE:
        used[0].legend(fontsize="small", title=legend_title, title_fontsize="small")
    else:
        fig.canvas.draw()  # the layout: the empty slot's size
        place_legend(fig, entries, legend_title, axes.flat[n] if n < axes.size else None, renderer)
    fig.canvas.draw()
    for ax in used:
        fit_text(ax.title, ax.get_window_extent(renderer).width, renderer)
    if suptitle is not None:
        fit_text(suptitle, 0.98 * fig.get_figwidth() * fig.dpi, renderer)
    keep_axes_height(fig, used, axes.shape[0])


def keep_axes_height(fig, used: list, rows: int) -> None:
    """Grow the figure until its shortest axes is AXES_HEIGHT inches tall (the layout runs again on each draw)."""
    for _ in range(4):
        fig.canvas.draw()
        short = AXES_HEIGHT - min(ax.get_position().height for ax in used) * fig.get_figheight()
        if short <= 0.01:
            return
        fig.set_size_inches(fig.get_figwidth(), fig.get_figheight() + short * rows + 0.05)


def summary_table(panels: dict, metric: str) -> str:
    """One row per line: its runs (and how many reached its last frame, if not all), its final mean and CI."""
    lines = [f"| env | group | seeds | last frame | final {metric} (mean [95% CI]) |", "|---|---|---|---|---|"]
    for curves in panels.values():
        for label, (frames, mean, ci, n, env) in curves.items():
            seeds = f"{n.max()}" + (f" ({n[-1]} at the last frame)" if n[-1] < n.max() else "")
            final = f"{mean[-1]:.4g}" + ("" if n[-1] == 1 else f" [{ci[0][-1]:.4g}, {ci[1][-1]:.4g}]")
            lines.append(f"| {env} | {label} | {seeds} | {frames[-1]:.0f} | {final} |")
    return "\n".join(lines)


# ---------------------------------------------------------------- --reference: published curves
# DrQ-v2's format (facebookresearch/drqv2, curves/dmc_<task>.csv): one row per seed and evaluation, columns seed,
# frame, episode_reward, task and agent; without a task column, the file name says the task.
REFERENCE_COLUMNS = ("seed", "frame", "episode_reward")


def task_key(name: str) -> str:
    """Our env names and DrQ-v2's on one key: cartpole-balance_sparse = cartpole_balance_sparse."""
    return name.strip().lower().replace("-", "_")


def parse_reference(spec: str) -> tuple[str, str | None]:
    """--reference PATH[:LABEL] -> (path, label or None); a path that exists keeps its colons."""
    path, sep, label = spec.rpartition(":")
    return (spec, None) if os.path.exists(spec) or not sep or not path else (path, label or None)


def load_reference(path: str, label: str | None = None) -> dict[str, dict]:
    """{task key: {"label", "frames", "mean", "min", "max", "seeds", "values"}} of a published curve file: per task its
    seeds on the frames they all have, values (seeds, frames)."""
    curves = {}
    for task, (by_seed, agents) in read_reference(path).items():
        if len(agents) > 1:
            raise PlotError(f"--reference {path}: {task} has curves of several agents "
                            f"({', '.join(sorted(agents))}); give one agent per file")
        frames = reduce(np.intersect1d, [np.array(sorted(points)) for points in by_seed.values()])
        if len(frames) == 0:
            raise PlotError(f"--reference {path}: the seeds of {task} share no frames")
        ys = np.array([[points[x] for x in frames] for points in by_seed.values()])
        curves[task] = {"label": label or f"{agents.pop() or os.path.basename(path)} (published)",
                        "frames": frames, "mean": ys.mean(axis=0), "values": ys, "min": ys.min(axis=0),
                        "max": ys.max(axis=0), "seeds": len(by_seed)}
    return curves


def read_reference(path: str) -> dict[str, tuple[dict, set]]:
    """{task key: ({seed: {frame: return}}, agent names)} of a published curve file."""
    if not os.path.isfile(path):
        raise PlotError(f"--reference {path}: no such file")
    header, rows = read_csv(path, "eval")
    missing = [c for c in REFERENCE_COLUMNS if c not in header]
    if missing:
        raise PlotError(f"--reference {path}: no {missing[0]!r} column (a published curve has columns "
                        f"{', '.join(REFERENCE_COLUMNS)}, and task or a dmc_<task>.csv name)")
    if not rows:
        raise PlotError(f"--reference {path}: no rows")
    file_task = os.path.splitext(os.path.basename(path))[0].removeprefix("dmc_")
    tasks = {}
    for row in rows:
        by_seed, agents = tasks.setdefault(task_key(row.get("task") or file_task), ({}, set()))
        try:
            by_seed.setdefault(row["seed"], {})[float(row["frame"])] = float(row["episode_reward"])
        except (TypeError, ValueError):
            raise PlotError(f"--reference {path}: bad row {row}") from None
        agents.add(row.get("agent") or "")
    return tasks


def references_for(panel_envs: dict[str, set], references: list[tuple[str, dict]]) -> dict:
    """{panel: the reference curves drawn on it}: each on every panel holding a run on its task; a reference that
    matches no panel is an error."""
    drawn = {panel: [] for panel in panel_envs}
    plotted = sorted({e for envs in panel_envs.values() for e in envs})
    for path, curves in references:
        if not {task_key(e) for e in plotted} & set(curves):
            raise PlotError(f"--reference {path}: its tasks ({', '.join(sorted(curves))}) match no plotted env "
                            f"({', '.join(plotted)})")
        for panel, envs in panel_envs.items():
            drawn[panel] += [curves[t] for t in sorted({task_key(e) for e in envs} & set(curves))]
    return drawn


def draw_reference(ax, ref: dict, i: int = 0, upto: float | None = None):
    """A published curve: the mean over its seeds and a min-max band, cut to frames <= `upto` (the runs' last frame:
    its later values would set the y range); the x range stays the runs'."""
    xlim = ax.get_xlim()
    keep = slice(None) if upto is None else ref["frames"] <= upto
    ax.plot(ref["frames"][keep], ref["mean"][keep], color="k", ls=(":", "-.", "--")[i % 3], lw=1.5, marker="x",
            ms=4, label=f"{ref['label']} (n={ref['seeds']}: mean, min-max)")
    ax.fill_between(ref["frames"][keep], ref["min"][keep], ref["max"][keep], color="k", alpha=0.08, lw=0)
    if xlim[1] >= 1:
        ax.set_xlim(xlim)


# ---------------------------------------------------------------- activation maps: plot.py maps
# The paper's recipe (section 5): the ReLU output of the encoder's last convolution (32 x 35 x 35), each channel
# resized to the image (84 x 84), normalised to [0, 1], coloured and blended over the image; beyond the paper,
# each channel's share of activation mass on the robot.
MAPS_STRIDE = 25  # agent steps between the frames shown
# Map unit j sees input pixels 2j .. 2j + 14 (3x3 stride 2, then three 3x3 stride 1, no padding), centred on 2j + 7;
# the overlays stretch the map over the image (the paper's resize) instead.
RF_STRIDE, RF_OFFSET = 2, 7
ROBOT, ENVIRONMENT = 2.0, 0.5  # share > 2x the mask fraction: a robot channel; < 0.5x: environment


def load_snapshot_run(run_dir: str):
    """(train.Config, snapshot) of a run directory; PlotError for anything that is not one."""
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
    import train
    agent = train.make_agent(cfg, action_dim, torch.device("cpu"))
    try:
        agent.load_state_dict(state["agent"])
    except (KeyError, RuntimeError) as e:
        raise PlotError(f"snapshot does not fit its config's networks: {cli.first_sentence(e)}") from None
    return agent


def map_frames(env, cfg, agent, n: int):
    """n observations (pixels, masks) of `env`, MAPS_STRIDE agent steps apart from the reset of the run's first
    evaluation episode, acting with `agent`'s mean action; and their steps (counted on across episodes)."""
    from harness import runenvs
    tasks = runenvs.eval_tasks(getattr(env.unwrapped, "tasks", None), cfg)

    def reset(i):
        options = None if tasks[i % len(tasks)] is None else {"task": tasks[i % len(tasks)]}
        return env.reset(seed=runenvs.episode_seed(cfg.seed + 100_000, i), options=options)[0]

    episode, t, pixels, masks, steps = 0, 0, [], [], []
    obs = reset(episode)
    while True:
        if t % MAPS_STRIDE == 0:
            pixels.append(obs["pixels"]), masks.append(obs["mask"]), steps.append(t)
            if len(pixels) == n:
                return np.stack(pixels), np.stack(masks).astype(bool), steps
        action = agent.act(obs["pixels"], obs["mask"], 0, eval_mode=True)
        obs, _, terminated, truncated, _ = env.step(action)
        t += 1
        if terminated or truncated:  # a short episode: the next evaluation episode goes on
            episode += 1
            obs = reset(episode)


def last_conv_maps(agent, pixels: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """The ReLU output of the encoder's last convolution, (N, 32, 35, 35), for uint8 observations, caught on the way
    through the encoder's own forward (its normalisation, its input channels)."""
    import torch
    from methods import baselines
    caught = []
    hook = agent.encoder.convs.register_forward_hook(lambda module, inputs, out: caught.append(out))
    try:
        with torch.no_grad():
            x = torch.as_tensor(pixels).float()
            if isinstance(agent, baselines.RGBMAgent):  # its masks are part of its input
                x = baselines.with_masks(x, torch.as_tensor(masks).float())
            agent.encoder(x)
    finally:
        hook.remove()
    return caught[0].float().numpy()


def overlay_maps(image: np.ndarray, maps: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Each channel of `maps` (C, h, w) as a jet heat map over `image` (H, W, 3) uint8: resized to H x W (bilinear),
    normalised to [0, 1] per channel, blended: (C, H, W, 3) uint8."""
    import torch
    import torch.nn.functional as F
    from matplotlib import colormaps
    up = F.interpolate(torch.as_tensor(maps)[None], size=image.shape[:2], mode="bilinear",
                       align_corners=False)[0].numpy()
    lo, hi = up.min(axis=(1, 2), keepdims=True), up.max(axis=(1, 2), keepdims=True)
    heat = colormaps["jet"]((up - lo) / np.where(hi > lo, hi - lo, 1.0))[..., :3]  # flat: 0
    return np.round(255 * ((1 - alpha) * image[None] / 255.0 + alpha * heat)).astype(np.uint8)


def channel_grid(tiles: np.ndarray, cols: int = 8, pad: int = 2) -> np.ndarray:
    """Tiles (C, H, W, 3) in rows of `cols` with white gaps of `pad` px, as one image."""
    c, h, w, _ = tiles.shape
    rows = math.ceil(c / cols)
    padded = np.pad(tiles, ((0, rows * cols - c), (0, pad), (0, pad), (0, 0)), constant_values=255)
    grid = padded.reshape(rows, cols, h + pad, w + pad, 3).swapaxes(1, 2)
    return grid.reshape(rows * (h + pad), cols * (w + pad), 3)[:-pad, :-pad]


def robot_units(masks: np.ndarray, side: int) -> np.ndarray:
    """The true mask at the centre of each map unit's receptive field, (N, side, side)."""
    centres = RF_OFFSET + RF_STRIDE * np.arange(side)
    return masks[:, centres][:, :, centres]


def robot_share(maps: np.ndarray, robot: np.ndarray) -> np.ndarray:
    """Per channel, the share of its activation mass (over all frames and units) on robot units, maps (N, C, h, w),
    robot (N, h, w); NaN for a channel that never fires."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return (maps * robot[:, None]).sum(axis=(0, 2, 3)) / maps.sum(axis=(0, 2, 3))


def maps_figure(out: str, frames: dict, runs: list[dict], mask_fraction: float):
    """One row per frame: the image (true mask outlined), then each run's 32 channels as a 4 x 8 grid, sorted by share
    on robot (highest first, number in the corner); below, the histogram of the shares per run."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n, (gh, gw), k = len(frames["images"]), runs[0]["grids"][0].shape[:2], len(runs)
    fig = plt.figure(figsize=((gh + gw * k) / 100 + 1, n * (gh / 100 + 0.4) + 3.2), layout="constrained")
    gs = fig.add_gridspec(n + 1, 1 + k, width_ratios=[gh] + [gw] * k, height_ratios=[gh] * n + [0.9 * gh])
    tile = (gh + 2) // 4  # 4 rows of tiles with 2-px gaps
    for i in range(n):
        ax = fig.add_subplot(gs[i, 0])
        ax.imshow(frames["images"][i])
        ax.contour(frames["masks"][i], levels=[0.5], colors="magenta", linewidths=0.7)
        ax.set_title(f"step {frames['steps'][i]} (robot outlined)", fontsize=8)
        ax.axis("off")
        for j, run in enumerate(runs):
            ax = fig.add_subplot(gs[i, 1 + j])
            ax.imshow(run["grids"][i])
            for rank, share in enumerate(run["share"][run["order"]]):
                ax.text(rank % 8 * tile + 2, rank // 8 * tile + 2, "dead" if np.isnan(share) else f"{share:.2f}",
                        color="white", fontsize=5, va="top")
            ax.axis("off")
            ax.set_title(run["label"] if i == 0 else "", fontsize=9)
    ax = fig.add_subplot(gs[n, 1:])
    for j, run in enumerate(runs):
        ax.hist(run["share"][~np.isnan(run["share"])], bins=np.linspace(0, 1, 41), histtype="step", lw=1.5,
                color=f"C{j}", label=f"{run['label']}: {run['robot']} robot, {run['environment']} environment "
                                     "channels")
    ax.axvline(mask_fraction, color="k", lw=1, label=f"mask fraction {mask_fraction:.3f}")
    for factor in (ROBOT, ENVIRONMENT):
        ax.axvline(factor * mask_fraction, color="k", lw=0.8, ls="--")
    ax.set(xlabel="share of a channel's activation on the robot (dashed: 0.5x and 2x the mask fraction)",
           ylabel="channels")
    ax.legend(fontsize=7)
    fig.suptitle("Last-convolution activation maps (ReLU, 32 x 35 x 35 resized to 84 x 84), channels sorted by "
                 "share on robot", fontsize=10)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def maps_table(runs: list[dict], mask_fraction: float) -> str:
    lines = [f"mask fraction (robot units of the 35x35 map, over the frames): {mask_fraction:.4f}", "",
             f"| run | method | trained frames | robot channels (share > {ROBOT:g}x) | environment channels (share "
             f"< {ENVIRONMENT:g}x) | dead | median share |", "|---|---|---|---|---|---|---|"]
    for r in runs:
        live = r["share"][~np.isnan(r["share"])]
        lines.append(f"| {r['dir']} | {r['method']} | {r['frame']} | {r['robot']} | {r['environment']} | "
                     f"{r['dead']} | {f'{np.median(live):.4f}' if len(live) else '-'} |")
    return "\n".join(lines)


def map_runs(run_dirs: list[str], n_frames: int) -> tuple[list[dict], float, dict]:
    """Each run's maps on the same frames (the first run's eval env with clean masks, rendered for every method, and
    its policy), its channels' shares on the robot and their order; the mask fraction; the frames."""
    import torch
    from harness import runenvs
    loaded = [(os.path.normpath(d), *load_snapshot_run(d)) for d in run_dirs]
    first = loaded[0][1]
    for d, cfg, _ in loaded[1:]:
        if (cfg.env, cfg.frame_stack) != (first.env, first.frame_stack):
            raise PlotError(f"{d} is on {cfg.env} (frame stack {cfg.frame_stack}), {loaded[0][0]} on {first.env} "
                            f"(frame stack {first.frame_stack}): maps compare runs on the same frames")
    torch.set_num_threads(cli.default_threads())
    try:
        env = runenvs.make_run_env(first, "eval", render_mask=True, mask_noise=0.0, mask_approx=False)
    except cli.ConfigError as e:
        raise PlotError(str(e)) from None
    agents = [trained_agent(cfg, state, env.action_space.shape[0]) for _, cfg, state in loaded]
    pixels, masks, steps = map_frames(env, first, agents[0], n_frames)
    env.close()
    frames = {"images": pixels[:, -3:].transpose(0, 2, 3, 1), "masks": masks[:, -1], "steps": steps}
    all_maps = [last_conv_maps(agent, pixels, masks) for agent in agents]
    robot = robot_units(frames["masks"], all_maps[0].shape[-1])
    frac, runs = float(robot.mean()), []
    for (d, cfg, state), maps in zip(loaded, all_maps):
        share = robot_share(maps, robot)
        order = np.argsort(-np.nan_to_num(share, nan=-1.0), kind="stable")
        frame = state["counters"]["step"] * cfg.action_repeat
        runs.append({"dir": d, "method": cfg.method, "frame": frame, "share": share, "order": order,
                     "label": f"{cfg.method} seed {cfg.seed}, {short_frames(frame)} frames",
                     "robot": int(np.sum(share > ROBOT * frac)), "dead": int(np.isnan(share).sum()),
                     "environment": int(np.sum(share < ENVIRONMENT * frac)),
                     "grids": [channel_grid(overlay_maps(img, m)[order]) for img, m in zip(frames["images"], maps)]})
    return runs, frac, frames


def refuse_overwrite(args) -> None:
    if os.path.exists(args.out) and not args.force:  # checked first: don't make the user wait
        raise PlotError(f"{args.out} exists; refusing to overwrite it (use --force)")


def maps_main(argv) -> int:
    parser = cli.OneLineParser(prog="plot.py maps", description="Activation maps of the encoder's last convolution "
                               "for runs on the same frames (the paper's section 5), and each channel's share of "
                               "activation on the robot.")
    parser.add_argument("runs", nargs="+", help="run directories (snapshot.pt), on one env")
    parser.add_argument("--out", default="runs/maps.png", help="PNG (default runs/maps.png)")
    parser.add_argument("--frames", type=int, default=2, help=f"{MAPS_STRIDE} agent steps apart")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    try:
        args = parser.parse_args(argv)
        refuse_overwrite(args)
        if args.frames < 1:
            raise PlotError(f"--frames must be >= 1, got {args.frames}")
        runs, frac, frames = map_runs(args.runs, args.frames)
        maps_figure(args.out, frames, runs, frac)
    except (PlotError, cli.ConfigError) as e:
        print(f"plot.py maps: error: {e}", file=sys.stderr)
        return 2
    print(f"{maps_table(runs, frac)}\n\nwrote {args.out}")
    return 0


# ---------------------------------------------------------------- CLI
def build_parser():
    p = cli.OneLineParser(prog="plot.py", description=__doc__.split("\n\n")[0],
                          formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", help="run directories, folders of runs, or globs")
    p.add_argument("--out", default="runs/curves.png", help="PNG (default runs/curves.png)")
    p.add_argument("--metric", default="return", help="return | success | any column of the CSV read (e.g. "
                   "--csv train --metric dormant_ratio)")
    p.add_argument("--csv", default="eval", choices=("eval", "train"), help="which log to read")
    p.add_argument("--group", default="method", help="config keys, comma separated: method,env")
    p.add_argument("--title", default=None)
    p.add_argument("--per-task", action="store_true",
                   help="task sets: one panel per task, from eval.csv's <metric>/<task> columns")
    p.add_argument("--baseline", default=None, metavar="VALUE[:LABEL]",
                   help="a dashed horizontal line, e.g. 1.6:random (benchmarks/random_policy.py)")
    p.add_argument("--reference", action="append", default=[], metavar="CSV[:LABEL]",
                   help="a published curve (DrQ-v2's curves/dmc_<task>.csv format): mean and min-max band over "
                        "its seeds, on the panels of its task; repeatable")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    return p


def checked_args(args) -> tuple[list, tuple[float, str] | None, list[str]]:
    """(--reference curves, --baseline (value, label) or None, --group keys), checked before any run is read."""
    references = [(path, load_reference(path, label)) for path, label in map(parse_reference, args.reference)]
    refuse_overwrite(args)
    keys = [k.strip() for k in args.group.split(",") if k.strip()]
    if not keys:
        raise PlotError("--group needs at least one config key, e.g. method")
    if args.per_task and args.csv != "eval":
        raise PlotError("--per-task reads eval.csv (per-task columns are written by evaluations)")
    return references, parse_baseline(args.baseline), keys


def parse_baseline(spec: str | None) -> tuple[float, str] | None:
    """--baseline VALUE[:LABEL] -> (value, label); None without one."""
    value, _, label = (spec or "0").partition(":")
    try:
        return None if spec is None else (float(value), label or "baseline")
    except ValueError:
        raise PlotError(f"--baseline must be VALUE[:LABEL], e.g. 1.6:random; got {spec!r}") from None


def load_runs(args) -> list[dict]:
    """The runs the paths name (with --per-task one per task, and their means); a run without the CSV yet is skipped
    with one line."""
    runs, found = [], find_runs(args.paths)
    for d in found:
        try:
            runs += load_task_runs(d, args.metric) if args.per_task else [load_run(d, args.csv, args.metric)]
        except NoLogYet as e:  # one run stopped early must not hide all the others
            print(f"plot.py: skipping {d}: {e}", file=sys.stderr)
    if not runs:
        raise PlotError(f"nothing to draw: none of the {len(found)} runs found has written {args.csv}.csv yet")
    return runs + (task_mean_runs(runs) if args.per_task else [])


def panel_runs(runs: list[dict], keys: list[str]) -> dict[str, list[dict]]:
    """{panel: runs}: one panel per env, unless env is a grouping key (or there is one); with --per-task one per task
    (and env)."""
    envs, keyed = sorted({env_of(r) for r in runs}), {}
    by_env = len(envs) > 1 and "env" not in keys
    for r in sorted(runs, key=env_of):  # stable: tasks keep their column order
        key = ": ".join(([env_of(r)] if by_env else []) + ([r["task"]] if "task" in r else []))
        keyed.setdefault(key or ", ".join(envs), []).append(r)
    return keyed


def panel_lines(panel: str, members: list[dict], keys: list[str], interpolate: bool) -> dict:
    """{label: (frames, mean, ci, runs per frame, envs)} of a panel's lines."""
    lines, differ = {}, differing_settings(members, keys)
    for label, group in (line for g in group_runs(members, keys).items()
                         for line in split_by_config(*g, differ).items()):
        warn(f"{label} ({panel})", label, group)
        curves = [(r["frames"], r["values"]) for r in group]
        envs = ", ".join(sorted({env_of(r) for r in group}))
        envs += f": {group[0]['task']}" if "task" in group[0] else ""  # --per-task: the task too
        lines[label] = (*aggregate(curves, interpolate), coverage(curves, interpolate), envs)
    return lines


def warn(where: str, label: str, group: list[dict]) -> None:
    """A line's repeated seeds, and its runs that end at different frames, each a line on stderr."""
    seeds, ends = [r["config"].get("seed") for r in group], [int(r["frames"][-1]) for r in group]
    if len(set(seeds)) < len(seeds):
        print(f"plot.py: warning: {label}: repeated seeds {seeds}", file=sys.stderr)
    if len(set(ends)) > 1:
        counts = ", ".join(f"{e}" + (f" (x{ends.count(e)})" if ends.count(e) > 1 else "") for e in sorted(set(ends)))
        print(f"plot.py: warning: {where}: runs end at frames {counts}; each is drawn to its own end, the mean and "
              "CI at a frame are over the runs that reached it (dashed where not all did)", file=sys.stderr)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    if argv[:1] == ["maps"]:  # a folder of runs named "maps" is given as ./maps
        return maps_main(argv[1:])
    try:
        args = build_parser().parse_args(argv)
        references, baseline, keys = checked_args(args)
        keyed = panel_runs(load_runs(args), keys)
        panels = {panel: panel_lines(panel, members, keys, args.csv == "train") for panel, members in keyed.items()}
        envs = {panel: {env_of(r) for r in members} for panel, members in keyed.items()}
        ylabel = f"{args.csv} {'success rate' if args.metric == 'success' else args.metric}"
        plot(panels, args.out, ylabel, args.title or default_title(ylabel, envs), baseline,
             references_for(envs, references))
    except (PlotError, cli.ConfigError) as e:
        print(f"plot.py: error: {e}", file=sys.stderr)
        return 2
    print(f"{summary_table(panels, args.metric)}\n\nwrote {args.out}")
    return 0


def default_title(ylabel: str, panel_envs: dict[str, set]) -> str:
    """The y-label, and the env where every run is on one."""
    envs = set().union(*panel_envs.values())
    return f"{ylabel} ({envs.pop()})" if len(envs) == 1 else ylabel


if __name__ == "__main__":
    sys.exit(main())
