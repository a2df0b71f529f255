"""benchmarks/published_curve.py: our runs against a published curve, table and verdict, on fake runs;
the rule's tests against scipy's on the recorded returns."""
import importlib.util
import itertools
import json
import os

import numpy as np
import pytest
from scipy import stats

from tests.test_plot import PNG_MAGIC, make_run, published_rows, write_published

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_spec = importlib.util.spec_from_file_location("published_curve",
                                               os.path.join(ROOT, "benchmarks", "published_curve.py"))
published_curve = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(published_curve)

COMMIT = "c0c650b76c6e5d22a7eb5f2edffd1440fe94f8ef"
FRAMES = (0, 10000, 20000, 30000, 40000)
# DrQ-v2's published seeds 1-10 (curves/dmc_cartpole_balance_sparse.csv at COMMIT), typed in by hand
PUBLISHED_20K = [159.6, 156.8, 235.5, 191.4, 305.8, 1000.0, 211.9, 1000.0, 171.1, 601.9]
PUBLISHED_40K = [1000.0] * 10
RESULTS = os.path.join(ROOT, "benchmarks", "published_curve_results.csv")


@pytest.fixture
def published(tmp_path):
    """A folder of copied curves with a README naming the commit (published 40k: 1000, 900, 950)."""
    d = tmp_path / "drqv2-curves"
    d.mkdir()
    write_published(d / "dmc_cartpole_balance_sparse.csv", published_rows())
    (d / "README").write_text(f"Copied from facebookresearch/drqv2 curves/ at commit {COMMIT}.\n")
    return d


def run_main(capsys, *argv):
    code = published_curve.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def table_row(out, frames):
    return next(line for line in out.splitlines() if line.startswith(f"| {frames} |")).split(" | ")


@pytest.mark.parametrize("base", [860.0, 840.0])
def test_table(tmp_path, published, capsys, base):
    """make_run's return is base + 10 * seed + frame / 1000."""
    runs = tmp_path / "runs"
    for seed in (1, 2, 3):
        make_run(runs, "cartpole-balance_sparse", "drq", seed, frames=FRAMES, base=base)
    make_run(runs, "walker-stand", "drq", 1, frames=FRAMES)  # another task: left out
    out_png = tmp_path / "fig.png"
    code, out, err = run_main(capsys, runs, "--published", published, "--out", out_png)
    assert code == 0, err
    assert f"commit {COMMIT}" in out
    row = table_row(out, "40k")
    assert row[1:5] == [f"{base + 60:.1f}", f"{base + 50:.1f}", f"{base + 60:.1f}", f"{base + 70:.1f}"]
    assert row[5:9] == ["", "not started", "not started", "not started"]  # sear: no runs yet
    assert row[9] == "950.0 (900.0-1000.0) |"
    assert table_row(out, "10k")[-1] == "no point |"  # published every 20k frames
    assert out_png.read_bytes().startswith(PNG_MAGIC)


def test_runs_in_progress_and_a_verdict_so_far(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES, base=900.0)  # 950 at 40k: not below
    d = make_run(runs, "cartpole-balance_sparse", "drq", 2, frames=(0, 10000))
    (d / "config.json").write_text('{"env": "cartpole-balance_sparse", "method": "drq", "seed": 2, "frames": 40000}')
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png")
    assert code == 0, err
    assert table_row(out, "20k")[1:5] == ["930.0 (1 of 3 seeds)", "930.0", "in progress", "not started"]
    assert "verdict: UNDECIDED so far (1 seed at 40k, 0 at the maximum" in out
    assert "left out, no evaluation at 40k: seed 2)" in out


def test_figure_legend_counts_seeds_and_dashes_the_mean_where_some_are_missing(tmp_path, published, capsys,
                                                                             monkeypatch):
    labels, figure = [], published_curve.figure
    monkeypatch.setattr(published_curve, "figure", lambda *a: labels.extend(figure(*a)))
    runs = tmp_path / "runs"
    for seed in (1, 2):
        make_run(runs, "cartpole-balance_sparse", "drq", seed, frames=FRAMES, base=900.0)
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "full.png")
    assert code == 0, err
    assert "drq, ours (2 seeds: mean, each seed thin)" in labels
    make_run(runs, "cartpole-balance_sparse", "drq", 3, frames=(0, 10000))
    labels.clear()
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "partial.png")
    assert code == 0, err
    assert "drq, ours (3 seeds: mean, each seed thin; dashed: fewer seeds)" in labels


def test_commit_from_a_git_checkout(tmp_path, capsys):
    import subprocess
    repo = tmp_path / "drqv2"
    (repo / "curves").mkdir(parents=True)
    write_published(repo / "curves" / "dmc_cartpole_balance_sparse.csv", published_rows())
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "curves"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    assert published_curve.find_published(str(repo), "cartpole_balance_sparse")[1] == head


@pytest.mark.parametrize("breakage", ["no csv", "out exists", "no runs of the task"])
def test_bad_input_is_one_line_exit_2(tmp_path, published, capsys, breakage):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse" if breakage != "no runs of the task" else "walker-stand", "drq", 1)
    out_png = tmp_path / "fig.png"
    argv = [runs, "--published", published, "--out", out_png]
    if breakage == "no csv":
        argv[2] = tmp_path
    elif breakage == "out exists":
        out_png.write_bytes(b"precious")
    code, _, err = run_main(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and err.startswith("published_curve.py: error:"), err
    assert (breakage == "out exists") == out_png.exists()
    if breakage == "out exists":
        assert out_png.read_bytes() == b"precious"


def make_official_run(root, seed, frames=(0, 10000, 20000), task="cartpole_balance_sparse"):
    """A run dir as the official drqv2 train.py (hydra) writes it: .hydra/config.yaml and an eval.csv
    with its columns; return = 500 + seed + frame / 100."""
    d = root / f"official-{seed}"
    (d / ".hydra").mkdir(parents=True)
    (d / ".hydra" / "config.yaml").write_text(f"frame_stack: 3\nseed: {seed}\ndevice: cpu\n"
                                              f"task_name: {task}\nnum_train_frames: 40002\n")
    rows = [f"{i},1000.0,{500 + seed + fr / 100},{fr},{fr // 2},{60.0 * (i + 1)}" for i, fr in enumerate(frames)]
    (d / "eval.csv").write_text("episode,episode_length,episode_reward,frame,step,total_time\n"
                                + "\n".join(rows) + "\n")
    return d


def test_official_runs_are_one_more_method(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES, base=900.0)
    make_official_run(runs, 1, frames=(20000, 0, 10000))  # rows out of order: sorted by frame
    make_official_run(runs, 4, frames=(0,))
    make_official_run(tmp_path / "other", 2, task="walker_stand")  # another task: left out
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png",
                              "--official", runs / "official-*", tmp_path / "other" / "official-2")
    assert code == 0, err
    head = next(line for line in out.splitlines() if line.startswith("| frames |")).split(" | ")
    assert head[-4:-1] == ["drqv2 official mean", "drqv2 official seed 1", "drqv2 official seed 4"]
    assert table_row(out, "20k")[-4:-1] == ["701.0 (1 of 2 seeds)", "701.0", "in progress"]
    assert table_row(out, "0")[-4:-1] == ["502.5", "501.0", "504.0"]
    assert "| drqv2 official | 1 | 20000 | 0.05 h |" in out  # its wall time: total_time of the last row
    assert "verdict: UNDECIDED (1 seed at 40k" in out
    assert "the same rule on drqv2 official: pending (no seed has evaluated at 40000 frames)" in out


def test_drqv2_loader_runs_are_a_method_of_their_own(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 2, frames=FRAMES, base=900.0)  # 1000 at 40k
    loader = make_run(tmp_path / "loader-2", "cartpole-balance_sparse", "drq", 2, frames=(0, 10000), base=100.0)
    (loader / "drqv2_loader.json").write_text('{"workers": 4}')
    code, out, err = run_main(capsys, runs, tmp_path / "loader-2", "--published", published,
                              "--out", tmp_path / "fig.png")
    assert code == 0, err  # the same method and seed twice, but one of them sampled as the official loader does
    head = next(line for line in out.splitlines() if line.startswith("| frames |")).split(" | ")
    assert head[-3:-1] == ["drq (drqv2 loader) mean", "drq (drqv2 loader) seed 2"]
    assert table_row(out, "10k")[-3:-1] == ["130.0", "130.0"]
    assert "verdict: UNDECIDED (1 seed at 40k" in out  # the rule is about our DrQ as sear.py trains it
    assert "the same rule on drq (drqv2 loader): pending" in out


def test_drm_runs_are_a_method_of_their_own(tmp_path, published, capsys):
    """sear.py --method drq --drm beside our DrQ of the same seed: "drq+drm", left out of the verdict."""
    import json
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 2, frames=FRAMES, base=900.0)
    d = make_run(tmp_path / "drm-2", "cartpole-balance_sparse", "drq", 2, frames=(0, 10000), base=100.0)
    (d / "config.json").write_text(json.dumps({**json.loads((d / "config.json").read_text()), "drm": True}))
    code, out, err = run_main(capsys, runs, tmp_path / "drm-2", "--published", published, "--out", tmp_path / "f.png")
    assert code == 0, err
    head = next(line for line in out.splitlines() if line.startswith("| frames |")).split(" | ")
    assert head[-3:-1] == ["drq+drm mean", "drq+drm seed 2"]
    assert table_row(out, "10k")[-3:-1] == ["130.0", "130.0"]
    assert "verdict: UNDECIDED (1 seed at 40k" in out


def test_official_dir_that_is_no_official_run_is_one_line(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES)
    code, _, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png",
                            "--official", runs)
    assert code == 2 and err.count("\n") == 1 and "not a run of the official code" in err, err


def test_recorded_results_outlive_the_run_dirs(tmp_path, published, capsys):
    """--record writes every run's evaluations into the results file; with the run dirs gone, the
    file alone gives the same table and verdict, and a run dir that goes on from a recorded run (the
    same returns where both have a frame) extends it."""
    import shutil
    runs, results = tmp_path / "runs", tmp_path / "results.csv"
    for seed in (1, 2):
        make_run(runs, "cartpole-balance_sparse", "drq", seed, frames=FRAMES, base=860.0)
    d = make_run(runs, "cartpole-balance_sparse", "drq", 3, frames=(0, 10000), base=860.0)
    (d / "config.json").write_text('{"env": "cartpole-balance_sparse", "method": "drq", "seed": 3, "frames": 40000}')
    make_official_run(runs, 1, frames=(0, 10000))
    results.write_text("method,seed,task,frame,return,wall_time,source\n"
                       "drq,1,walker_stand,0,5.0,,another rung\n")  # another task's rows are kept
    code, before, err = run_main(capsys, runs, "--official", runs / "official-1", "--published", published,
                                 "--results", results, "--record", "--out", tmp_path / "a.png")
    assert code == 0, err
    assert "recorded 14 evaluations of cartpole_balance_sparse" in before
    shutil.rmtree(runs)
    code, after, err = run_main(capsys, "--published", published, "--results", results, "--out", tmp_path / "b.png")
    assert code == 0, err
    assert table_row(after, "10k") == table_row(before, "10k")
    assert table_row(after, "40k")[:4] == table_row(before, "40k")[:4]
    assert table_row(before, "40k")[4] == "in progress" and table_row(after, "40k")[4] == "not recorded"
    assert "verdict: UNDECIDED so far (2 seeds at 40k" in after and "left out, no evaluation at 40k: seed 3)" in after
    assert "the same rule on drqv2 official: pending" in after
    assert "drq,1,walker_stand,0,5.0,,another rung" in results.read_text()
    # seed 3 resumed on another machine from the recorded evaluations: its new run dir goes on to 40k
    make_run(runs, "cartpole-balance_sparse", "drq", 3, frames=(10000, 20000, 30000, 40000), base=860.0)
    code, out, err = run_main(capsys, runs, "--published", published, "--results", results, "--record",
                              "--out", tmp_path / "c.png")
    assert code == 0, err
    assert table_row(out, "0")[4] == "890.0" and table_row(out, "40k")[4] == "930.0"
    assert "verdict: UNDECIDED (3 seeds at 40k" in out
    assert sum(line.startswith("drq,3,cartpole_balance_sparse,") for line in results.read_text().splitlines()) == 5


@pytest.mark.parametrize("breakage", ["another run of the seed", "no columns", "record without results"])
def test_bad_results_file_is_one_line_and_leaves_it_whole(tmp_path, published, capsys, breakage):
    runs, results = tmp_path / "runs", tmp_path / "results.csv"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES, base=860.0)  # 870 at frame 0
    results.write_text({"another run of the seed": "method,seed,task,frame,return,wall_time,source\n"
                                                   "drq,1,cartpole_balance_sparse,0,99.0,,old machine\n",
                        "no columns": "frame,return\n0,1.0\n"}.get(breakage, ""))
    before = results.read_text()
    argv = [runs, "--published", published, "--out", tmp_path / "fig.png", "--record"]
    argv += [] if breakage == "record without results" else ["--results", results]
    code, _, err = run_main(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and err.startswith("published_curve.py: error:"), err
    assert {"another run of the seed": "another run of that seed", "no columns": "no method, seed, task",
            "record without results": "give it with --results"}[breakage] in err
    assert results.read_text() == before


def make_returns_run(root, method, seed, returns: dict):
    """A run dir as sear.py writes it, with these returns ({frame: return})."""
    d = root / f"cartpole-balance_sparse__{method}__{seed}__20240101-000000"
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"env": "cartpole-balance_sparse", "method": method, "seed": seed,
                                               "frames": max(returns)}))
    (d / "eval.csv").write_text("frame,step,episode,return,wall_time\n" + "".join(
        f"{f},{f // 2},{i},{v},{i}.0\n" for i, (f, v) in enumerate(sorted(returns.items()))))
    return d


def scipy_mwu(x, y):
    """scipy's exact Mann-Whitney p, ties included: every split of the pooled values listed."""
    return stats.mannwhitneyu(x, y, alternative="less", method=stats.PermutationMethod(n_resamples=np.inf)).pvalue


@pytest.mark.parametrize("x, y", [
    ([330.7, 79.8, 1000.0], PUBLISHED_20K),  # our DrQ at 20k: ties with two published seeds at 1000
    ([1000.0, 179.9, 1000.0], PUBLISHED_40K),  # at 40k: every published seed tied at the maximum
    ([169.6, 10.2], PUBLISHED_20K),  # the official code here
    ([330.7, 79.8, 1000.0, 169.6, 10.2], PUBLISHED_20K),
    ([1000.0, 1000.0, 1000.0], PUBLISHED_40K),  # all tied: p = 1
    ([5.0, 6.0, 7.0, 8.0], [1.0, 2.0, 3.0]),  # x above every y
])
def test_mann_whitney_equals_scipys_exact_permutation_test(x, y):
    assert published_curve.mwu_less(x, y) == pytest.approx(scipy_mwu(x, y), rel=1e-12)


def test_the_rule_on_the_recorded_runs_gives_scipys_p_values(tmp_path, capsys):
    """The results file's runs, against the copy of the published curve (the default --published): each
    p-value is scipy's on the returns typed in here (EXPERIMENTS.md's Rung PC table)."""
    code, out, err = run_main(capsys, "--results", RESULTS, "--out", tmp_path / "fig.png")
    assert code == 0, err
    assert f"commit {COMMIT}" in out  # from benchmarks/drqv2_curves/README.md, not this repository's HEAD
    recorded = {"drq": ([330.7, 79.8, 1000.0], [1000.0, 179.9, 1000.0]),
                "sear": ([15.4, 11.4, 491.9], [333.6, 184.5, 1000.0]),
                "drqv2 official": ([169.6, 10.2], [1000.0, 10.0])}
    recorded["drq and drqv2 official together"] = tuple(a + b for a, b in zip(recorded["drq"],
                                                                               recorded["drqv2 official"]))
    for label, (early, late) in recorded.items():
        solved = sum(v >= 990 for v in late)
        fisher = stats.fisher_exact([[solved, len(late) - solved], [10, 0]], alternative="less").pvalue
        row = next(line for line in out.splitlines() if line.startswith(f"| {label} |")).split(" | ")
        assert row[1:6] == [str(len(late)), str(solved), f"{fisher:.3g}", f"{scipy_mwu(early, PUBLISHED_20K):.3g}",
                            f"{scipy_mwu(late, PUBLISHED_40K):.3g}"], label
        assert row[6] == "UNDECIDED |"
    assert "\nverdict: UNDECIDED (3 seeds at 40k, 2 at the maximum: Fisher p = 0.231, Mann-Whitney p (20k) = 0.591: " \
           "neither below 0.025; MATCH needs 16 seeds at 40k: 13 more)" in out
    assert "the same rule on drq and drqv2 official together: UNDECIDED so far (5 seeds at 40k, 3 at the maximum: " \
           "Fisher p = 0.0952" in out  # the official seed 3 stopped at 10k: left out
    assert "| DrQ-v2 published | 10 | 10 | | | | |" in out


@pytest.mark.parametrize("seeds, collapsed, verdict", [
    (16, 0, "verdict: MATCH (16 seeds at 40k, 16 at the maximum"),
    # the rule's limit with 10 published seeds: 6 of 16 collapsed is not found worse, 7 is
    (16, 6, "verdict: MATCH (16 seeds at 40k, 10 at the maximum: Fisher p = 0.0348, Mann-Whitney p (20k) = 0.059"),
    (16, 7, "verdict: NO MATCH (16 seeds at 40k, 9 at the maximum: Fisher p = 0.0174"),
    (3, 0, "verdict: UNDECIDED (3 seeds at 40k, 3 at the maximum"),
    (3, 3, "verdict: NO MATCH (3 seeds at 40k, 0 at the maximum: Fisher p = 0.0035"),
])
def test_verdicts(tmp_path, capsys, seeds, collapsed, verdict):
    """A seed that learns returns a published seed's 20k return and 1000 at 40k; a collapsed one 50 and 150."""
    for seed in range(1, seeds + 1):
        dead = seed <= collapsed
        make_returns_run(tmp_path / "runs", "drq", seed, {0: 40.0, 20000: 50.0 if dead else PUBLISHED_20K[seed % 10],
                                                          40000: 150.0 if dead else 1000.0})
    code, out, err = run_main(capsys, tmp_path / "runs", "--out", tmp_path / "fig.png")
    assert code == 0, err
    assert verdict in out


def test_the_rule_reads_a_reduced_run_elsewhere_and_says_it_is_no_verdict(tmp_path, capsys):
    for seed in (1, 2):
        make_returns_run(tmp_path / "runs", "drq", seed, {0: 10.0, 100: 20.0, 200: 30.0})
    code, out, err = run_main(capsys, tmp_path / "runs", "--rule-frames", 100, 200, "--out", tmp_path / "fig.png")
    assert code == 0, err
    assert "verdict: NO MATCH (2 seeds at 200, 0 at the maximum: Fisher p = 0.0152, Mann-Whitney p (100) = 0.0152" in out  # 1 / C(12, 2)
    assert "ours at 100 and 200 frames against the published 20000 and 40000: a check of the pipeline, not a verdict" in out


def test_power_is_one_when_every_seed_collapses_and_matches_enumeration_when_none_does(capsys):
    """With no seed collapsed, our 20k returns are published ones drawn uniformly: over the 1000 equally
    likely draws of 3 seeds, the share that the rule calls NO MATCH, against the simulation's estimate."""
    ref = published_curve.plot.load_reference(
        os.path.join(published_curve.DRQV2_CURVES, "dmc_cartpole_balance_sparse.csv"))["cartpole_balance_sparse"]
    draws = 2000
    table = published_curve.power_table(ref, seeds=(3,), rates=(0.0, 1.0), draws=draws)
    simulated, every = (float(c) for c in table.splitlines()[-1].strip("| ").split(" | ")[1:])
    assert every == 1.0  # Fisher p = 1 / 286 < 0.025
    exact = np.mean([published_curve.decide(published_curve.rule_tests(list(x), [1000.0] * 3, ref)) == "NO MATCH"
                     for x in itertools.product(PUBLISHED_20K, repeat=3)])
    assert 0 < exact < 0.05 and abs(simulated - exact) < 4 * np.sqrt(exact * (1 - exact) / draws)
    assert published_curve.main(["--power", "3", "--power-draws", "50"]) == 0
    assert "| 3 | " in capsys.readouterr().out


def record_part(tmp_path, capsys, published, name, seeds, frames=FRAMES, config=None):
    """A campaign's part as gpu_campaign.sh leaves it: its run dirs recorded into its own results file."""
    runs, results = tmp_path / name, tmp_path / f"{name}.csv"
    for seed in seeds:
        d = make_run(runs, "cartpole-balance_sparse", "drq", seed, frames=frames, base=860.0)
        (d / "config.json").write_text(json.dumps({"env": "cartpole-balance_sparse", "method": "drq", "seed": seed,
                                                   "frames": 40000, "device": f"cuda:{seed}", **(config or {})}))
    code, _, err = run_main(capsys, runs, "--published", published, "--results", results, "--record",
                            "--out", tmp_path / f"{name}.png")
    assert code == 0, err
    return results


def test_the_rule_on_the_union_of_a_campaigns_parts(tmp_path, published, capsys):
    """--results once per part (run on machines whose run dirs are gone): one verdict on every part's
    seeds; the device a run used is no setting."""
    parts = [record_part(tmp_path, capsys, published, f"part{k}", seeds)
             for k, seeds in enumerate([(1, 2), (3, 4), (5,)])]
    code, out, err = run_main(capsys, *sum((["--results", p] for p in parts), []), "--published", published,
                              "--seeds", 1, 2, 3, 4, 5, "--out", tmp_path / "union.png")
    assert code == 0, err
    assert table_row(out, "40k")[1:7] == ["930.0", "910.0", "920.0", "930.0", "940.0", "950.0"]
    assert "verdict: UNDECIDED (5 seeds at 40k" in out and "MATCH needs 16 seeds at 40k: 11 more)" in out


@pytest.mark.parametrize("breakage, message", [
    ("a seed in two parts", "drq seed 2 is in both"),
    ("other frames", "ran different settings (frames 40000 against 60000)"),
    ("a part without settings", "part2.csv) has no settings: cannot tell"),
    ("record into two", "--record writes into one results file"),
])
def test_parts_of_different_experiments_are_refused(tmp_path, published, capsys, breakage, message):
    first = record_part(tmp_path, capsys, published, "part1", (1, 2))
    second = record_part(tmp_path, capsys, published, "part2", (2, 3) if breakage == "a seed in two parts" else (3,),
                         config={"frames": 60000} if breakage == "other frames" else None)
    if breakage == "a part without settings":  # a results file recorded before the settings column
        second.write_text("\n".join(line.rsplit(",\"{", 1)[0].removesuffix(",settings")
                                    for line in second.read_text().splitlines()) + "\n")
    before = {p: p.read_text() for p in (first, second)}
    code, _, err = run_main(capsys, "--results", first, "--results", second, "--published", published,
                            "--out", tmp_path / "union.png", *(["--record"] if breakage == "record into two" else []))
    assert code == 2 and err.count("\n") == 1 and err.startswith("published_curve.py: error:"), err
    assert message in err
    assert {p: p.read_text() for p in (first, second)} == before and not (tmp_path / "union.png").exists()
