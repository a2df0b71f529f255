"""Our runs against DrQ-v2's published learning curve: the "published curve" rung of EXPERIMENTS.md.

    python benchmarks/published_curve.py runs/ --out docs/published_curve.png
    python benchmarks/published_curve.py --published ../drqv2 --task cartpole_balance runs/
    python benchmarks/published_curve.py runs/ --official 'runs/curve/official-*/'
    python benchmarks/published_curve.py --results benchmarks/published_curve_results.csv runs/ --record
    python benchmarks/published_curve.py --results part1.csv --results part2.csv --seeds 1 2 3 4 5 6 7 8
    python benchmarks/published_curve.py --power 3 8 16

--published is a checkout of facebookresearch/drqv2 (read in place: curves/dmc_<task>.csv, and the
commit from git), a folder holding dmc_<task>.csv (the commit from a 40-hex id in its README), or the
CSV itself; by default benchmarks/drqv2_curves, the copy of the cartpole_balance_sparse curve. The other
arguments are run directories, folders of runs or globs (as plot.py takes them); runs on other tasks are
left out. Prints the source commit; a table at --frames with each method's
mean over its seeds and every seed (planned seeds without a run or an evaluation yet say so), and the
published seeds' mean and min-max; the p-values of the rung's rule (EXPERIMENTS.md#the-verdict-rule) for every
method, and its verdict; each run's wall time. --power prints how often the rule finds a given collapse rate. Writes the
figure: each seed thin, each method's mean thick, the published mean with its min-max band.
Runs of benchmarks/drqv2_loader.py (a drqv2_loader.json in the run dir) are one more method,
"drq (drqv2 loader)", and so are runs with --drm ("drq+drm": DrM). --official adds runs of the official code
(facebookresearch/drqv2's train.py, run on this machine: hydra run dirs with .hydra/config.yaml and eval.csv)
as one more method, the check of the machine itself; the rule also runs on our DrQ and the official code's
seeds together.
--results is a results file (method, seed, task, frame, return, wall_time, source; one row per
evaluation) read as runs beside the run dirs: the evaluations of runs whose directories are gone. A run
dir and a results file's run of the same method and seed are one run: their returns must agree where
both have a frame, and the run dir's rows win. --record writes every run's evaluations back into the
results file, so that what the runs reached outlives their run directories, with each run's settings
(its config.json less where and how fast it ran: FREE_SETTINGS) in a "settings" column. --results may be
given again: the parts of a campaign run on separate machines (benchmarks/gpu_campaign.sh --first-seed),
one verdict on their union. Parts must hold different seeds and, where a method's runs carry settings,
the same settings.
Errors are one line on stderr, exit code 2.
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import os
import re
import subprocess
import sys

import numpy as np
from scipy import stats

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402
import plot  # noqa: E402

# The rung's rule (docs/published-curve.md#the-verdict-rule, its power), stated before the decisive run: our seeds against the
# published seeds, one-sided (the alternative: ours learn worse), at a family-wise ALPHA split over TESTS tests
# (Bonferroni):
# Fisher's exact test on the seeds at the task's maximum at LATE frames (>= SOLVED of 1000: the published
# files' solved seeds dip to 990.0-997.0 at later points), and the Mann-Whitney U test on the EARLY returns.
# NO MATCH: either p < ALPHA / TESTS. MATCH: neither, with at least MATCH_SEEDS of our seeds (the rule then
# finds a collapse rate of 50% about 4 times in 5: --power). UNDECIDED: neither, with fewer seeds. The
# Mann-Whitney test on the LATE returns is printed beside them and not counted: while every published seed
# is at the maximum there, it is Fisher's test again.
ALPHA, TESTS, SOLVED, EARLY, LATE, MATCH_SEEDS = 0.05, 2, 990.0, 20_000, 40_000, 16
VERDICT_METHOD = "drq"
DRQV2_CURVES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "drqv2_curves")  # a copy of the curve


class CurveError(Exception):
    """Bad input: one line on stderr, exit code 2."""


def find_published(path: str, task: str) -> tuple[str, str]:
    """(CSV path, source commit or 'unknown') of task's published curve under `path`."""
    if os.path.isfile(path):
        folder, candidates = os.path.dirname(os.path.abspath(path)), [path]
    else:
        folder = path
        candidates = [os.path.join(path, "curves", f"dmc_{task}.csv"), os.path.join(path, f"dmc_{task}.csv")]
    csv_path = next((c for c in candidates if os.path.isfile(c)), None)
    if csv_path is None:
        raise CurveError(f"--published {path}: no {' or '.join(candidates)} (a drqv2 checkout or a folder "
                         f"of its curves/dmc_<task>.csv files)")
    return csv_path, source_commit(folder)


def source_commit(folder: str) -> str:
    """The drqv2 commit the curves come from: git's HEAD in a checkout, else the 40-hex id a README
    beside copied files names."""
    try:  # a checkout of its own, not a folder inside another repository (benchmarks/drqv2_curves)
        out = subprocess.run(["git", "-C", folder, "rev-parse", "--show-toplevel", "HEAD"], capture_output=True,
                             text=True)
        top, head = (out.stdout.split("\n") + ["", ""])[:2]
        if (out.returncode == 0 and os.path.realpath(top) == os.path.realpath(folder)
                and re.fullmatch(r"[0-9a-f]{40}", head)):
            return head
    except OSError:  # no git on this machine
        pass
    for readme in sorted(glob.glob(os.path.join(folder, "README*"))):
        with open(readme, errors="replace") as f:
            found = re.search(r"\b[0-9a-f]{40}\b", f.read())
        if found:
            return found.group(0)
    return "unknown"


def load_ours(paths: list[str], task: str) -> dict[str, dict[int, dict]]:
    """{method: {seed: run}} of the runs on `task`; each run as plot.load_run gives it, plus the wall
    time at each evaluation ("walls"). Runs that have not evaluated yet are kept with no frames."""
    ours = {}
    for d in plot.find_runs(paths):
        try:
            run = plot.load_run(d)
            wall = plot.load_run(d, "eval", "wall_time")
            wall_at = dict(zip(wall["frames"], wall["values"]))
            run["walls"] = [wall_at.get(f) for f in run["frames"]]
        except plot.NoLogYet:  # started, not evaluated yet: in the table all the same
            with open(os.path.join(d, "config.json")) as f:
                run = {"dir": d, "config": json.load(f), "frames": np.array([]), "values": np.array([]),
                       "walls": []}
        if plot.task_key(plot.env_of(run)) != task:
            continue
        method, seed = cli.method_label(run["config"]), int(run["config"].get("seed", 0))
        if os.path.isfile(os.path.join(d, LOADER_MARKER)):  # trained by benchmarks/drqv2_loader.py
            method += LOADER
        if seed in ours.get(method, {}):
            raise CurveError(f"two runs of {method} seed {seed} on {task}: {ours[method][seed]['dir']} and {d}")
        ours.setdefault(method, {})[seed] = run
    return ours


OFFICIAL = "drqv2 official"
LOADER, LOADER_MARKER = " (drqv2 loader)", "drqv2_loader.json"  # drqv2_loader.py's runs: a method of their own


def load_official(paths: list[str], task: str) -> dict[int, dict]:
    """{seed: run} of the official code's hydra run dirs on `task`, in the shape load_ours gives:
    seed, task and budget from .hydra/config.yaml, returns and wall time (total_time) from eval.csv."""
    runs = {}
    for pattern in paths:
        dirs = sorted(glob.glob(pattern)) or [pattern]
        for d in dirs:
            config_path = os.path.join(d, ".hydra", "config.yaml")
            try:
                with open(config_path) as f:
                    text = f.read()
            except OSError as e:
                raise CurveError(f"--official {d}: not a run of the official code ({config_path}: "
                                 f"{e.strerror or e})") from None
            fields = dict(re.findall(r"^(seed|task_name|num_train_frames): *(\S+)", text, re.MULTILINE))
            if plot.task_key(fields.get("task_name", "")) != task:
                continue
            seed, frames, values, walls = int(fields.get("seed", 0)), [], [], []
            eval_path = os.path.join(d, "eval.csv")
            if os.path.exists(eval_path):
                with open(eval_path, newline="") as f:
                    for row in csv.DictReader(f):
                        frames.append(float(row["frame"]))
                        values.append(float(row["episode_reward"]))
                        walls.append(float(row["total_time"]))
            order = np.argsort(frames, kind="stable")
            if seed in runs:
                raise CurveError(f"two official runs of seed {seed} on {task}: {runs[seed]['dir']} and {d}")
            runs[seed] = {"dir": d, "config": {"method": OFFICIAL, "seed": seed,
                                              "frames": float(fields.get("num_train_frames", 0))},
                          "frames": np.array(frames)[order], "values": np.array(values)[order],
                          "walls": [walls[i] for i in order]}
    if not runs:
        raise CurveError(f"--official: no runs of the official code on {task} in {' '.join(paths)}")
    return runs


RESULT_FIELDS = ["method", "seed", "task", "frame", "return", "wall_time", "source"]
SETTINGS = "settings"  # an optional column, written by --record: files recorded before it have none
# Config fields that change neither what a run learns nor how it is scored: plot.py's NOT_A_SETTING (the one
# list of them) less the budget and the evaluations, which runs read as one method (a campaign's parts) must share.
FREE_SETTINGS = plot.NOT_A_SETTING - {"frames", "eval_every", "eval_episodes", "eval_episodes_per_task"}
AGREE = 0.05  # returns of one run read twice: a results file may hold them rounded to 0.1


def load_results(path: str, task: str) -> dict[str, dict[int, dict]]:
    """{method: {seed: run}} of a results file's rows on `task`, in the shape load_ours gives; a run's
    "dir" is its rows' source (the run dir it was recorded from, or where its numbers were read)."""
    runs, rows, settings = {}, {}, {}
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            missing = [c for c in RESULT_FIELDS if c not in (reader.fieldnames or [])]
            if missing:
                raise CurveError(f"--results {path}: no {', '.join(missing)} column (a results file has "
                                 f"{', '.join(RESULT_FIELDS)})")
            for row in reader:
                if plot.task_key(row["task"]) != task:
                    continue
                try:
                    key = (row["method"], int(row["seed"]))
                    wall = float(row["wall_time"]) if row["wall_time"] else None
                    rows.setdefault(key, {})[float(row["frame"])] = (float(row["return"]), wall, row["source"])
                except ValueError:
                    raise CurveError(f"--results {path}: bad row {row}") from None
                settings.setdefault(key, set()).add(row.get(SETTINGS) or "")
    except OSError as e:
        raise CurveError(f"--results {path}: {e.strerror or e}") from None
    for (method, seed), points in rows.items():
        if len(settings[method, seed]) > 1:
            raise CurveError(f"--results {path}: {method} seed {seed} has rows of different settings")
        frames = sorted(points)
        runs.setdefault(method, {})[seed] = {
            "dir": points[frames[-1]][2], "config": {"method": method, "seed": seed, "frames": frames[-1],
                                                     "recorded": True},
            "frames": np.array(frames), "values": np.array([points[f][0] for f in frames]),
            "walls": [points[f][1] for f in frames], "sources": [points[f][2] for f in frames],
            "settings": settings[method, seed].pop(), "file": path}
    return runs


def load_parts(paths: list[str], task: str) -> dict[str, dict[int, dict]]:
    """The runs of several results files (a campaign's parts, run on separate machines) as one: each seed
    of a method in one part alone, and every run of a method with the same settings."""
    union = {}
    for path in paths:
        for method, runs in load_results(path, task).items():
            for seed, run in runs.items():
                other = union.get(method, {}).get(seed)
                if other is not None:
                    raise CurveError(f"{method} seed {seed} is in both {other['file']} and {path}: parts run "
                                     f"different seeds (gpu_campaign.sh --first-seed)")
                union.setdefault(method, {})[seed] = run
    for method, runs in union.items():
        check_settings(method, runs, every_known=len(paths) > 1)
    return union


def check_settings(method: str, runs: dict[int, dict], every_known: bool):
    """One verdict needs one experiment: refuse runs of `method` whose settings differ, and with
    `every_known` (parts to combine) runs whose settings are not known."""
    known = {s: r for s, r in sorted(runs.items()) if r["settings"]}
    if every_known and len(known) < len(runs):
        seed = next(s for s in sorted(runs) if s not in known)
        raise CurveError(f"{method} seed {seed} ({runs[seed]['file']}) has no settings: cannot tell whether it ran "
                         f"as the other parts (a results file that gpu_campaign.sh or --record writes has them)")
    if not known:
        return
    first, *rest = known.items()
    for seed, run in rest:
        if run["settings"] != first[1]["settings"]:
            try:
                a, b = json.loads(first[1]["settings"]), json.loads(run["settings"])
            except ValueError:
                raise CurveError(f"{method}: settings that are not JSON in {first[1]['file']} or {run['file']}") from None
            diff = ", ".join(f"{k} {a.get(k, '-')} against {b.get(k, '-')}" for k in sorted(set(a) | set(b))
                             if a.get(k) != b.get(k))
            raise CurveError(f"{method} seeds {first[0]} ({first[1]['file']}) and {seed} ({run['file']}) ran "
                             f"different settings ({diff}): the rule takes the seeds of one experiment")


def settings_of(run: dict) -> str:
    """The run's settings as one JSON line (its config less FREE_SETTINGS); "" where not known (the
    official code's runs, a results file without them)."""
    if "settings" in run:
        return run["settings"]
    if run["config"].get("recorded") or run["config"].get("method") == OFFICIAL:
        return ""
    return json.dumps({k: v for k, v in run["config"].items() if k not in FREE_SETTINGS}, sort_keys=True)


def merge_runs(recorded: dict, live: dict) -> dict:
    """The runs of both, a live run dir's over the same method and seed's recorded run: one run read
    twice (a resume or a deterministic restart evaluates the same returns), so the returns must agree
    where both have a frame; frames only the record has are kept."""
    merged = {m: dict(runs) for m, runs in recorded.items()}
    for method, runs in live.items():
        for seed, run in runs.items():
            old = merged.setdefault(method, {}).get(seed)
            merged[method][seed] = run
            if old is None:
                continue
            for frame, value in zip(old["frames"], old["values"]):
                now = value_at(run, frame)
                if now is not None and abs(now - value) > AGREE:
                    raise CurveError(f"{method} seed {seed}: {run['dir']} returns {now:.1f} at {frame:.0f} frames, "
                                     f"the results file {value:.1f} ({old['dir']}): another run of that seed")
            points = {f: (v, w, old["sources"][i]) for i, (f, v, w) in
                      enumerate(zip(old["frames"], old["values"], old["walls"]))}
            points.update({f: (v, w, run["dir"]) for f, v, w in zip(run["frames"], run["values"], run["walls"])})
            frames = sorted(points)
            run.update(frames=np.array(frames), values=np.array([points[f][0] for f in frames]),
                       walls=[points[f][1] for f in frames], sources=[points[f][2] for f in frames])
            run["config"] = {**run["config"], "frames": max(run["config"].get("frames", 0), frames[-1])}
    return merged


def record_results(path: str, runs: dict, task: str):
    """Write every run's evaluations on `task` into the results file, keeping its rows of other tasks."""
    kept = []
    if os.path.exists(path):
        with open(path, newline="") as f:
            kept = [row for row in csv.DictReader(f) if plot.task_key(row["task"]) != task]
    rows = kept + [{"method": m, "seed": s, "task": task, "frame": f"{f:.0f}", "return": repr(float(v)),
                    "wall_time": "" if w is None else f"{w:.0f}", "source": src, SETTINGS: settings_of(r)}
                   for m, seeds in sorted(runs.items()) for s, r in sorted(seeds.items())
                   for f, v, w, src in zip(r["frames"], r["values"], r["walls"],
                                           r.get("sources") or [r["dir"]] * len(r["frames"]))]

    def write(f):
        w = csv.DictWriter(f, RESULT_FIELDS + [SETTINGS], lineterminator="\n", restval="")
        w.writeheader()
        w.writerows(rows)
    cli.write_atomically(path, write, "w")
    return len(rows) - len(kept)


def value_at(run: dict, frame: float) -> float | None:
    hit = np.flatnonzero(run["frames"] == frame)
    return float(run["values"][hit[0]]) if len(hit) else None


def seed_cell(run: dict | None, frame: float) -> str:
    if run is None:
        return "not started"
    value = value_at(run, frame)
    if value is not None:
        return f"{value:.1f}"
    if run["config"].get("recorded"):  # from a results file alone: whether it goes on is not known here
        return "not recorded"
    return "in progress" if run["config"].get("frames", 0) >= frame else "-"


def mean_cell(runs: dict[int, dict], seeds: list[int], frame: float) -> str:
    values = [v for v in (value_at(runs[s], frame) for s in seeds if s in runs) if v is not None]
    if not values:
        return ""
    partial = "" if len(values) == len(seeds) else f" ({len(values)} of {len(seeds)} seeds)"
    return f"{np.mean(values):.1f}{partial}"


def published_cell(ref: dict, frame: float) -> str:
    hit = np.flatnonzero(ref["frames"] == frame)
    if not len(hit):
        return "no point"
    i = hit[0]
    return f"{ref['mean'][i]:.1f} ({ref['min'][i]:.1f}-{ref['max'][i]:.1f})"


def comparison_table(ours, ref, methods, seeds, frames) -> str:
    """seeds: {method: planned seeds}."""
    head = ["frames"]
    for m in methods:
        head += [f"{m} mean"] + [f"{m} seed {s}" for s in seeds[m]]
    head.append(f"DrQ-v2 published, {ref['seeds']} seeds: mean (min-max)")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for frame in frames:
        cells = [plot.short_frames(frame)]
        for m in methods:
            runs = ours.get(m, {})
            cells += [mean_cell(runs, seeds[m], frame)] + [seed_cell(runs.get(s), frame) for s in seeds[m]]
        cells.append(published_cell(ref, frame))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def mwu_less(x, y) -> float:
    """One-sided p-value of the Mann-Whitney U test that x is stochastically less than y, exact with ties:
    the share of the C(n + m, n) ways to split the pooled values into groups of n and m whose group-of-n
    rank sum (midranks) is at most x's. scipy.stats.mannwhitneyu(x, y, alternative="less", method=
    PermutationMethod(n_resamples=np.inf)) gives the same p by listing the splits (tests/test_published_curve.py),
    5.3M of them at 16 seeds against 10 (minutes); its "exact" ignores ties and its "asymptotic" gives 3 seeds
    against 10 tied ones a p 4.6 times too small. This counts the splits by rank sum in milliseconds."""
    ranks = np.rint(2 * stats.rankdata(np.concatenate([x, y]))).astype(int)  # doubled midranks: integers
    n, top = len(x), int(ranks.sum())
    ways = np.zeros((n + 1, top + 1))  # ways[j, s]: the subsets of j values whose doubled ranks sum to s
    ways[0, 0] = 1.0
    for r in ranks:
        ways[1:, r:] += ways[:-1, :top + 1 - r].copy()
    return float(ways[n, :ranks[:n].sum() + 1].sum() / ways[n].sum())


def published_at(ref: dict, frame: float) -> np.ndarray:
    hit = np.flatnonzero(ref["frames"] == frame)
    if not len(hit):
        raise CurveError(f"the published curve has no point at {frame:.0f} frames: the rule compares there")
    return ref["values"][:, hit[0]]


def rule_tests(early: list[float], late: list[float], ref: dict) -> dict:
    """The rule's p-values for our seeds' returns at EARLY and LATE frames (a seed without an EARLY
    evaluation is left out of that test alone) against the published seeds' there."""
    pub_early, pub_late = published_at(ref, EARLY), published_at(ref, LATE)
    solved, pub_solved = sum(v >= SOLVED for v in late), int((pub_late >= SOLVED).sum())
    table = [[solved, len(late) - solved], [pub_solved, len(pub_late) - pub_solved]]
    return {"seeds": len(late), "solved": solved, "fisher": stats.fisher_exact(table, alternative="less").pvalue,
            "mwu_early": mwu_less(early, pub_early) if early else np.nan, "mwu_late": mwu_less(late, pub_late)}


def decide(tests: dict) -> str:
    if np.nanmin([tests["fisher"], tests["mwu_early"]]) < ALPHA / TESTS:
        return "NO MATCH"
    return "MATCH" if tests["seeds"] >= MATCH_SEEDS else "UNDECIDED"


def seed_values(runs: dict, at: tuple[float, float]) -> tuple[list, list, list]:
    """(early returns, late returns, seeds left out) of the runs that have evaluated at the late frame."""
    late = {s: value_at(r, at[1]) for s, r in sorted(runs.items())}
    kept = [s for s, v in late.items() if v is not None]
    early = [v for v in (value_at(runs[s], at[0]) for s in kept) if v is not None]
    return early, [late[s] for s in kept], [s for s in late if s not in kept]


def rule_groups(ours: dict, methods: list[str]) -> list[tuple[str, dict]]:
    """(label, {seed key: run}) of every method the rule is applied to, and our DrQ with the official
    code's runs together (two implementations of one algorithm)."""
    groups = [(m, ours[m]) for m in methods if ours.get(m)]
    if ours.get(VERDICT_METHOD) and ours.get(OFFICIAL):
        both = {(m, s): r for m in (VERDICT_METHOD, OFFICIAL) for s, r in ours[m].items()}
        groups.append((f"{VERDICT_METHOD} and {OFFICIAL} together", both))
    return groups


def rule_report(ours: dict, ref: dict, methods: list[str], at=(EARLY, LATE)) -> str:
    """The p-values beside the table, then the verdict line of each group (ours first)."""
    level = ALPHA / TESTS
    late_k = plot.short_frames(at[1])  # where ours are read: LATE but in a reduced run's check
    lines = [f"rule (EXPERIMENTS.md#the-verdict-rule): one-sided, ours worse; alpha {ALPHA:g} over {TESTS} tests, "
             f"each at {level:g}; "
             f"at the maximum: >= {SOLVED:g} at {plot.short_frames(LATE)}; MATCH needs {MATCH_SEEDS} seeds", "",
             f"| runs | seeds at {late_k} | at the maximum | Fisher p ({late_k}) | Mann-Whitney p "
             f"({plot.short_frames(at[0])}) | Mann-Whitney p ({late_k}, not counted) | verdict |", "|---|---|---|---|---|---|---|"]
    verdicts = []
    pub_late = published_at(ref, LATE)
    for label, runs in rule_groups(ours, methods):
        early, late, left_out = seed_values(runs, at)
        head = "verdict" if label == VERDICT_METHOD else f"the same rule on {label}"
        if not late:
            verdicts.append(f"{head}: pending (no seed has evaluated at {at[1]:.0f} frames)")
            continue
        t = rule_tests(early, late, ref)
        outcome = decide(t)
        lines.append(f"| {label} | {t['seeds']} | {t['solved']} | {t['fisher']:.3g} | {t['mwu_early']:.3g} | "
                     f"{t['mwu_late']:.3g} | {outcome} |")
        why = {"NO MATCH": f"below {level:g}", "MATCH": f"neither below {level:g}, with {t['seeds']} seeds",
               "UNDECIDED": f"neither below {level:g}; MATCH needs {MATCH_SEEDS} seeds at {late_k}: "
                            f"{MATCH_SEEDS - t['seeds']} more"}[outcome]
        named = ", ".join(f"{k[0]} seed {k[1]}" if isinstance(k, tuple) else f"seed {k}" for k in left_out)
        note = f"; left out, no evaluation at {plot.short_frames(at[1])}: {named}" if left_out else ""
        check = ("" if tuple(at) == (EARLY, LATE) else f"; ours at {at[0]:.0f} and {at[1]:.0f} frames against the "
                 f"published {EARLY} and {LATE}: a check of the pipeline, not a verdict")
        so_far = " so far" if left_out else ""  # more seeds can change any outcome
        seeds = f"{t['seeds']} seed{'s' * (t['seeds'] != 1)}"
        verdicts.append(f"{head}: {outcome}{so_far} ({seeds} at {late_k}, {t['solved']} at the maximum: Fisher p = "
                        f"{t['fisher']:.3g}, Mann-Whitney p ({plot.short_frames(at[0])}) = {t['mwu_early']:.3g}: "
                        f"{why}{note}{check})")
    lines.append(f"| DrQ-v2 published | {len(pub_late)} | {int((pub_late >= SOLVED).sum())} | | | | |")
    return "\n".join(lines + [""] + verdicts)


def power_table(ref: dict, seeds=(3, 8, 16), rates=(0.0, 0.1, 0.2, 0.3, 0.5), draws=4000, seed=0) -> str:
    """How often the rule says NO MATCH when each of our seeds collapses with probability `rate` (its EARLY
    return below every published seed's, as the collapsed runs' 79.8 and 10.2 were; below the maximum at
    LATE) and otherwise learns as a published seed (its EARLY return one of the published ones, drawn
    uniformly; the maximum at LATE); the published seeds stay as published. Rate 0: the false alarms of a
    copy of the published seeds; 0.1-0.2: of a correct implementation whose seeds collapse as DrQ-v2's own
    do; 0.3 and 0.5: the power to find a defect that collapses that many. One set of draws for every rate."""
    pub_early = published_at(ref, EARLY)
    lines = [f"P(NO MATCH) by the rule (alpha {ALPHA:g}, each test at {ALPHA / TESTS:g}) against the {len(pub_early)} "
             f"published seeds, by our seeds' collapse rate; {draws} draws per cell (standard error <= "
             f"{0.5 / np.sqrt(draws):.3f}), seed {seed}", "",
             "| our seeds | " + " | ".join(f"collapse rate {q:g}" for q in rates) + " |", "|---|" + "---|" * len(rates)]
    for n in seeds:
        rng = np.random.default_rng(seed)
        u, pick = rng.random((draws, n)), rng.integers(0, len(pub_early), (draws, n))
        low_early, low_late = pub_early.min() - 1.0 - np.arange(n), SOLVED - 1.0 - np.arange(n)
        cache, cells = {}, []
        for q in rates:
            no_match = 0
            for collapsed, i in zip(u < q, pick):
                k, healthy = int(collapsed.sum()), sorted(pub_early[i[~collapsed]])
                if (k, *healthy) not in cache:
                    early, late = [*low_early[:k], *healthy], [*low_late[:k]] + [1000.0] * (n - k)
                    cache[k, *healthy] = decide(rule_tests(early, late, ref)) == "NO MATCH"
                no_match += cache[k, *healthy]
            cells.append(f"{no_match / draws:.3f}")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def wall_time_table(ours) -> str:
    lines = ["| run | method | seed | last evaluation (frames) | wall time to it |", "|---|---|---|---|---|"]
    for m, runs in sorted(ours.items()):
        for s, r in sorted(runs.items()):
            last = f"{r['frames'][-1]:.0f}" if len(r["frames"]) else "none yet"
            walls = [w for w in r["walls"] if w is not None]  # counted on across resumes: the largest is the last
            wall = f"{max(walls) / 3600:.2f} h" if walls else ""
            lines.append(f"| {r['dir']} | {m} | {s} | {last} | {wall} |")
    return "\n".join(lines)


def figure(ours, ref, methods, out: str, task: str, commit: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    budget = max(r["config"].get("frames", 0) for runs in ours.values() for r in runs.values())
    for i, m in enumerate(methods):
        runs = [r for _, r in sorted(ours.get(m, {}).items()) if len(r["frames"])]
        for r in runs:
            ax.plot(r["frames"], r["values"], color=f"C{i}", lw=0.8, alpha=0.4)
        if runs:
            curves = [(r["frames"], r["values"]) for r in runs]
            frames, mean, _ = plot.aggregate(curves)
            full = plot.coverage(curves) == len(runs)  # a mean over every seed; dashed: over those that got there
            who = "DrQ-v2's code, this machine" if m == OFFICIAL else f"{m}, ours"
            seeds = f"{len(runs)} seed{'s' if len(runs) > 1 else ''}"
            label = f"{who} ({seeds}: mean, each seed thin" + ("" if full.all() else "; dashed: fewer seeds") + ")"
            plot.draw_mean(ax, frames, mean, full, f"C{i}", label, dashed={"lw": 1.2, "marker": "o", "ms": 2},
                           lw=2, marker="o", ms=3)
    plot.draw_reference(ax, ref)
    ax.axhline(SOLVED, color="0.5", ls="--", lw=0.8, label=f"the task's maximum for the rule: >= {SOLVED:g}")
    ax.set_xlim(0, max(budget, LATE) * 1.02)
    ax.set_ylim(0, 1050)
    ax.xaxis.set_major_formatter(FuncFormatter(plot.short_frames))
    ax.set_xlabel("frames")
    ax.set_ylabel("eval return (10 episodes)")
    ax.set_title(f"{task}: ours vs DrQ-v2's published curve\n(facebookresearch/drqv2 {commit[:12]}, "
                 f"curves/dmc_{task}.csv)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.13))  # below: the curves fill the axes
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=120)
    labels = ax.get_legend_handles_labels()[1]
    plt.close(fig)
    return labels


def print_power(args) -> int:
    try:
        csv_path, commit = find_published(args.published, plot.task_key(args.task))
        ref = plot.load_reference(csv_path).get(plot.task_key(args.task))
        if ref is None:
            raise CurveError(f"{csv_path} has no curve of {args.task}")
        print(f"published: {csv_path}, facebookresearch/drqv2 commit {commit}\n")
        print(power_table(ref, args.power or (3, 8, 16), draws=args.power_draws))
    except (CurveError, plot.PlotError) as e:
        print(f"published_curve.py: error: {e}", file=sys.stderr)
        return 2
    return 0


def build_parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="*", help="run directories, folders of runs, or globs")
    p.add_argument("--published", default=DRQV2_CURVES, metavar="PATH",
                   help="a drqv2 checkout, a folder of its dmc_<task>.csv files, or one such CSV (default: "
                        "benchmarks/drqv2_curves, the copy of the cartpole_balance_sparse curve)")
    p.add_argument("--task", default="cartpole_balance_sparse",
                   help="DrQ-v2's task name (our env cartpole-balance_sparse)")
    p.add_argument("--methods", nargs="+", default=["drq", "sear"], help="methods of the table, in its order")
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3], help="planned seeds of each method")
    p.add_argument("--frames", nargs="+", type=float, default=[0, 10_000, 20_000, 30_000, 40_000, 60_000],
                   help="table rows; those beyond every run's budget are left out")
    p.add_argument("--official", nargs="+", default=[], metavar="DIR",
                   help="run dirs (or globs) of the official drqv2 train.py on this machine: one more method")
    p.add_argument("--results", metavar="CSV", action="append",
                   help="a results file: evaluations of runs whose dirs are gone; again for each part of a campaign "
                        "(different seeds, the same settings)")
    p.add_argument("--record", action="store_true",
                   help="write every run's evaluations into --results (made if missing)")
    p.add_argument("--out", default="published_curve.png", help="PNG to write")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--rule-frames", nargs=2, type=float, default=[EARLY, LATE], metavar=("EARLY", "LATE"),
                   help="frames at which the rule reads our seeds (the published ones at 20k and 40k whatever "
                        "these are: other frames check the pipeline of a reduced run, and the verdict says so)")
    p.add_argument("--power", nargs="*", type=int, metavar="SEEDS",
                   help="print how often the rule says NO MATCH at these numbers of our seeds (default 3 8 16) "
                        "by collapse rate, and exit (no runs needed)")
    p.add_argument("--power-draws", type=int, default=4000, help="simulated draws per cell of --power")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.power is not None:
        return print_power(args)
    task = plot.task_key(args.task)
    try:
        if os.path.exists(args.out) and not args.force:
            raise CurveError(f"{args.out} exists; refusing to overwrite it (use --force)")
        csv_path, commit = find_published(args.published, task)
        curves = plot.load_reference(csv_path, "DrQ-v2, published")
        if task not in curves:
            raise CurveError(f"{csv_path} has no curve of {task} (has {', '.join(sorted(curves))})")
        ref = curves[task]
        if args.record and not args.results:
            raise CurveError("--record writes into a results file: give it with --results")
        if args.record and len(args.results) > 1:
            raise CurveError("--record writes into one results file: give --results once")
        results = args.results or []
        recorded = load_parts(results, task) if results and (os.path.exists(results[0]) or not args.record) else {}
        ours = load_ours(args.runs, task) if args.runs else {}
        seeds = {m: args.seeds for m in args.methods}
        methods = list(args.methods)
        if args.official:
            ours[OFFICIAL] = load_official(args.official, task)
        ours = merge_runs(recorded, ours)
        if not ours:
            raise CurveError(f"no runs on {task} in {' '.join(args.runs + args.official + results)}".strip())
        for m in sorted(ours):  # the official code's, the loader's and --drm runs: one more method each
            if m not in methods and (m == OFFICIAL or m.endswith((LOADER, cli.DRM_SUFFIX))):
                methods.append(m)
                seeds[m] = sorted(ours[m])
        if OFFICIAL in methods:
            methods.append(methods.pop(methods.index(OFFICIAL)))
        budget = max(r["config"].get("frames", 0) for runs in ours.values() for r in runs.values())
        frames = [f for f in args.frames if f <= budget]
        report = rule_report(ours, ref, methods, tuple(args.rule_frames))
        figure(ours, ref, methods, args.out, task, commit)
        recorded_rows = record_results(results[0], ours, task) if args.record else None
    except (CurveError, plot.PlotError, cli.StorageError) as e:
        print(f"published_curve.py: error: {e}", file=sys.stderr)
        return 2
    print(f"published: {csv_path}, facebookresearch/drqv2 commit {commit}\n")
    print(comparison_table(ours, ref, methods, seeds, frames))
    spacing = np.unique(np.diff(ref["frames"]))
    if len(spacing) == 1:
        print(f"\n(the published curve has a point every {spacing[0]:.0f} frames: 'no point' in between)")
    print(f"\n{report}\n")
    print(wall_time_table(ours))
    print(f"\nwrote {args.out}")
    if recorded_rows is not None:
        print(f"recorded {recorded_rows} evaluations of {task} in {results[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
