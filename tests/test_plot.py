"""Tests of plot.py on fake run directories with known returns."""
import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import plot

PLOT_PY = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plot.py")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def make_run(root, env, method, seed, frames=(0, 10000, 20000), success=False, base=0.0):
    """A run dir as sear.py writes it; return = base + 10 * seed + frame / 1000, exactly."""
    d = root / f"{env}__{method}__{seed}__20240101-000000"
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"env": env, "method": method, "seed": seed,
                                               "frames": max(frames)}))
    with open(d / "eval.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "step", "episode", "return", "wall_time"] + (["success"] if success else []))
        for i, fr in enumerate(frames):
            w.writerow([fr, fr // 2, i, base + 10 * seed + fr / 1000, 1.0 * i]
                       + ([float(seed >= 2)] if success else []))
    # a side file left by a resume must be ignored: its values would wreck the means
    (d / "eval.after_snapshot_20240101-000001.csv").write_text("frame,return\n30000,1e9\n")
    return d


@pytest.fixture
def runs(tmp_path):
    """2 methods x 3 seeds on one env; drq returns are 100 below sear's."""
    root = tmp_path / "runs"
    for method, base in (("drq", 0.0), ("sear", 100.0)):
        for seed in (1, 2, 3):
            make_run(root, "walker-walk", method, seed, base=base)
    return root


def run_main(capsys, *argv):
    """(exit code, stdout, stderr) of plot.main; argparse errors exit via SystemExit."""
    try:
        code = plot.main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


# ---------------------------------------------------------------- statistics
@pytest.mark.filterwarnings("ignore:random_state is deprecated:FutureWarning")  # arch's, on rliable's call
def test_the_band_is_rliables_percentile_bootstrap_of_the_mean_over_seeds():
    from rliable import library as rly
    values = np.array([3.0, 7.0, 8.0, 12.0, 20.0])
    frames, mean, ci = plot.aggregate([(np.array([0.0, 10.0]), np.array([v, 2 * v])) for v in values])
    np.testing.assert_allclose(mean, [10, 20])
    _, expected = rly.get_interval_estimates({"": np.stack([values, 2 * values], 1)[:, None]},
                                             lambda x: x.mean(axis=(0, 1)), reps=plot.BOOTSTRAP_REPS,
                                             random_state=np.random.RandomState(0))
    np.testing.assert_allclose(ci, expected[""])
    assert 3 < ci[0, 0] < 10 < ci[1, 0] < 20  # narrower than the seeds' range, around the mean


def test_a_band_never_leaves_the_range_of_the_runs_values(tmp_path, capsys, monkeypatch):
    """Returns that cannot be negative get no band below 0: at frame 10000 two seeds scored 0 and one
    30 (a t-interval of their mean reaches -33)."""
    import matplotlib.axes
    bands = []
    real = matplotlib.axes.Axes.fill_between
    monkeypatch.setattr(matplotlib.axes.Axes, "fill_between",
                        lambda ax, x, lo, hi, **k: bands.append((lo, hi)) or real(ax, x, lo, hi, **k))
    root = tmp_path / "runs"
    for seed, late in ((1, 0), (2, 0), (3, 30)):
        d = make_run(root, "walker-walk", "drq", seed)
        (d / "eval.csv").write_text(f"frame,return\n0,0\n10000,{late}\n")
    code, out, err = run_main(capsys, root, "--out", tmp_path / "x.png")
    assert code == 0, err
    ((lo, hi),) = bands
    np.testing.assert_allclose([lo, hi], [[0, 0], [0, 30]])
    assert "| walker-walk | drq | 3 | 10000 | 10 [0, 30] |" in out


def test_aggregate_mean_and_ci_by_hand(runs):
    groups = plot.group_runs([plot.load_run(d) for d in plot.find_runs([str(runs)])], ["method"])
    assert list(groups) == ["drq", "sear"] and all(len(g) == 3 for g in groups.values())
    frames, mean, ci = plot.aggregate([(r["frames"], r["values"]) for r in groups["drq"]])
    np.testing.assert_array_equal(frames, [0, 10000, 20000])
    # seeds 1,2,3 at frame f: 10+f/1000, 20+f/1000, 30+f/1000 -> mean 20+f/1000; with 3 seeds every
    # resample has a chance of 1/27 > 2.5% to be all one seed: the CI is the lowest and highest seed
    np.testing.assert_allclose(mean, [20, 30, 40])
    np.testing.assert_allclose(ci, [[10, 20, 30], [30, 40, 50]])
    _, mean, _ = plot.aggregate([(r["frames"], r["values"]) for r in groups["sear"]])
    np.testing.assert_allclose(mean, [120, 130, 140])


def test_aggregate_single_run_has_no_band():
    frames, mean, ci = plot.aggregate([(np.array([0.0, 5.0]), np.array([1.0, 2.0]))])
    np.testing.assert_allclose(mean, [1, 2])
    assert np.isnan(ci).all()


def test_aggregate_draws_each_run_to_its_own_end():
    a = (np.array([0.0, 10.0, 20.0]), np.array([0.0, 10.0, 20.0]))
    b = (np.array([0.0, 5.0, 10.0]), np.array([2.0, 4.0, 6.0]))
    # eval: every frame either run was evaluated at; the mean over the runs evaluated there
    frames, mean, ci = plot.aggregate([a, b])
    np.testing.assert_array_equal(frames, [0, 5, 10, 20])
    np.testing.assert_allclose(mean, [1, 4, 8, 20])
    np.testing.assert_array_equal(plot.coverage([a, b]), [2, 1, 2, 1])
    assert np.isnan(ci[:, [1, 3]]).all()  # no band over a single run
    np.testing.assert_allclose(ci[:, [0, 2]], [[0, 6], [2, 10]])  # two runs: their lower and higher
    # train: each run interpolated within its own span (a(5) = 5); b stops at 10
    frames, mean, _ = plot.aggregate([a, b], interpolate=True)
    np.testing.assert_array_equal(frames, [0, 5, 10, 20])
    np.testing.assert_allclose(mean, [1, 4.5, 8, 20])
    np.testing.assert_array_equal(plot.coverage([a, b], interpolate=True), [2, 2, 2, 1])
    frames, mean, _ = plot.aggregate([a, (np.array([1.0, 2.0]), np.array([5.0, 5.0]))])  # no frame in common
    np.testing.assert_array_equal(frames, [0, 1, 2, 10, 20])
    np.testing.assert_allclose(mean, [0, 5, 5, 10, 20])


# ---------------------------------------------------------------- finding and grouping runs
def test_find_runs_accepts_dirs_parents_and_globs(runs):
    all_runs = plot.find_runs([str(runs)])
    assert len(all_runs) == 6
    assert plot.find_runs([str(runs / "*__drq__*")]) == [r for r in all_runs if "__drq__" in r]
    assert plot.find_runs([all_runs[0], all_runs[0]]) == [all_runs[0]]  # no double counting


def test_group_by_method_and_env(runs):
    make_run(runs, "cheetah-run", "drq", 1)
    loaded = [plot.load_run(d) for d in plot.find_runs([str(runs)])]
    assert list(plot.group_runs(loaded, ["method"])) == ["drq", "sear"]
    assert list(plot.group_runs(loaded, ["method", "env"])) == [
        "drq / cheetah-run", "drq / walker-walk", "sear / walker-walk"]
    with pytest.raises(plot.PlotError, match="nosuchkey"):
        plot.group_runs(loaded, ["nosuchkey"])


def test_a_drm_run_is_its_own_line_named_method_plus_drm(runs):
    d = make_run(runs, "walker-walk", "drq", 4)
    config = json.loads((d / "config.json").read_text())
    (d / "config.json").write_text(json.dumps({**config, "drm": True}))  # sear.py --method drq --drm
    for r in plot.find_runs([str(runs)])[:3]:  # runs of a sear.py that has the flag record drm false
        path = os.path.join(r, "config.json")
        with open(path) as f:
            c = json.load(f)
        with open(path, "w") as f:
            json.dump({**c, "drm": False}, f)
    loaded = [plot.load_run(d) for d in plot.find_runs([str(runs)])]
    differ = plot.differing_settings(loaded, ["method"])  # drm is named with the method, not as a setting
    lines = {label: len(g) for name, group in plot.group_runs(loaded, ["method"]).items()
             for label, g in plot.split_by_config(name, group, differ).items()}
    assert lines == {"drq": 3, "drq+drm": 1, "sear": 3}


def test_any_train_csv_column_can_be_drawn(runs, tmp_path, capsys):
    """--csv train --metric NAME: e.g. --drm's dormant_ratio, interpolated over the episodes' frames."""
    for d in plot.find_runs([str(runs / "*__drq__*")]):
        with open(os.path.join(d, "train.csv"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["frame", "return", "dormant_ratio", "perturb_factor"])
            w.writerows([[1000, 1.0, 0.5, ""], [2000, 2.0, 0.3, 0.4], [3000, 3.0, 0.1, ""]])
    code, out, err = run_main(capsys, runs / "*__drq__*", "--csv", "train", "--metric", "dormant_ratio",
                              "--out", tmp_path / "d.png")
    assert code == 0, err
    assert "| walker-walk | drq | 3 | 3000 | 0.1 [0.1, 0.1] |" in out and (tmp_path / "d.png").read_bytes().startswith(PNG_MAGIC)
    code, out, err = run_main(capsys, runs / "*__drq__*", "--csv", "train", "--metric", "perturb_factor",
                              "--out", tmp_path / "p.png")  # an event column: only the episodes that have one
    assert code == 0 and "| walker-walk | drq | 3 | 2000 | 0.4 [0.4, 0.4] |" in out, err


# ---------------------------------------------------------------- CLI
def test_cli_subprocess_writes_png_and_table(runs, tmp_path):
    out = tmp_path / "curves.png"
    p = subprocess.run([sys.executable, PLOT_PY, str(runs), "--out", str(out)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    data = out.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 1000
    rows = [line for line in p.stdout.splitlines() if line.startswith("| walker-walk")]
    assert rows == ["| walker-walk | drq | 3 | 20000 | 40 [30, 50] |",
                    "| walker-walk | sear | 3 | 20000 | 140 [130, 150] |"]


def test_several_envs_and_success_metric(runs, tmp_path, capsys):
    for seed in (1, 2, 3):
        make_run(runs.parent / "mw", "mw-reach", "sear", seed, frames=(0, 10000), success=True)
    code, out, err = run_main(capsys, runs, runs.parent / "mw", "--out", tmp_path / "two.png")
    assert code == 0, err
    assert "| mw-reach | sear | 3 | 10000 |" in out and "| walker-walk | drq | 3 | 20000 |" in out
    code, out, err = run_main(capsys, runs.parent / "mw", "--metric", "success",
                              "--out", tmp_path / "s.png")
    assert code == 0, err  # success = 0, 1, 1 for seeds 1, 2, 3
    assert "| mw-reach | sear | 3 | 10000 | 0.6667 [0, 1] |" in out


def test_train_csv_with_empty_loss_cells(tmp_path, capsys):
    for seed in (1, 2):
        d = make_run(tmp_path / "runs", "walker-walk", "drq", seed)
        (d / "train.csv").write_text("frame,step,episode,return,length,critic_loss,fps,wall_time\n"
                                     f"1000,500,0,{seed},500,,10,1\n2000,1000,1,{2 * seed},500,0.5,10,2\n")
    code, out, err = run_main(capsys, tmp_path / "runs", "--csv", "train", "--out", tmp_path / "t.png")
    assert code == 0, err
    assert "| walker-walk | drq | 2 | 2000 | 3 [2, 4] |" in out


def test_success_metric_without_column_is_an_error(runs, tmp_path, capsys):
    code, out, err = run_main(capsys, runs, "--metric", "success", "--out", tmp_path / "x.png")
    assert code == 2 and not (tmp_path / "x.png").exists()
    assert err.count("\n") == 1 and err.startswith("plot.py: error:") and "'success'" in err


def test_no_runs_is_one_line_exit_2(tmp_path):
    (tmp_path / "empty").mkdir()
    p = subprocess.run([sys.executable, PLOT_PY, str(tmp_path / "empty"), "--out", str(tmp_path / "x.png")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and p.stderr.startswith("plot.py: error: no runs")
    assert "Traceback" not in p.stderr


def test_runs_without_the_csv_are_skipped_by_name_and_the_rest_drawn(runs, tmp_path):
    """A run stopped during its first evaluation has no eval.csv: skip it, draw the others."""
    stopped = sorted(runs.iterdir())[:2]  # two drq seeds
    for d in stopped:
        (d / "eval.csv").unlink()
    out = tmp_path / "curves.png"
    p = subprocess.run([sys.executable, PLOT_PY, str(runs), "--out", str(out)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert out.read_bytes().startswith(PNG_MAGIC)
    lines = p.stderr.splitlines()
    assert len(lines) == 2 and all(line.startswith("plot.py: skipping ") for line in lines), p.stderr
    assert [line.split()[2].rstrip(":") for line in lines] == [str(d) for d in stopped]
    assert "no eval.csv" in lines[0] and "first evaluation" in lines[0]
    assert "| walker-walk | drq | 1 | 20000 |" in p.stdout and "| walker-walk | sear | 3 | 20000 |" in p.stdout


def test_nothing_left_to_draw_is_one_line_exit_2(runs, tmp_path, capsys):
    for d in runs.iterdir():
        (d / "eval.csv").unlink()
    code, _, err = run_main(capsys, runs, "--out", tmp_path / "x.png")
    assert code == 2 and not (tmp_path / "x.png").exists()
    errors = [line for line in err.splitlines() if not line.startswith("plot.py: skipping ")]
    assert errors == ["plot.py: error: nothing to draw: none of the 6 runs found has written eval.csv yet"], err
    code, _, err = run_main(capsys, runs, "--csv", "train", "--out", tmp_path / "x.png")  # no train.csv either
    assert code == 2 and "first episode" in err and "has written train.csv" in err


@pytest.mark.parametrize("breakage", ["empty eval", "header only", "unknown metric", "bad flag", "no such path",
                                      "bad baseline"])
def test_bad_input_is_one_line_exit_2(runs, tmp_path, capsys, breakage):
    eval_csv = next(runs.iterdir()) / "eval.csv"
    argv = [runs, "--out", tmp_path / "x.png"]
    if breakage == "empty eval":
        eval_csv.write_text("")
    elif breakage == "header only":
        eval_csv.write_text("frame,step,episode,return,wall_time\n")
    elif breakage == "unknown metric":
        argv += ["--metric", "reward"]
    elif breakage == "bad flag":
        argv += ["--colour", "red"]
    elif breakage == "no such path":
        argv[0] = tmp_path / "nope"
    elif breakage == "bad baseline":
        argv += ["--baseline", "random"]
    code, _, err = run_main(capsys, *argv)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("plot.py: error:"), err
    assert not (tmp_path / "x.png").exists()


def test_baseline_is_drawn_as_a_labelled_line(runs, tmp_path, capsys, monkeypatch):
    import matplotlib.axes
    drawn = []
    real = matplotlib.axes.Axes.axhline
    monkeypatch.setattr(matplotlib.axes.Axes, "axhline",
                        lambda ax, y=0, *a, **k: drawn.append((y, k.get("label"))) or real(ax, y, *a, **k))
    code, _, err = run_main(capsys, runs, "--out", tmp_path / "x.png", "--baseline", "1.6:random policy")
    assert code == 0, err
    assert drawn == [(1.6, "random policy")]
    assert (tmp_path / "x.png").read_bytes().startswith(PNG_MAGIC)


def test_refuses_to_overwrite_without_force(runs, tmp_path, capsys):
    out = tmp_path / "curves.png"
    out.write_bytes(b"precious")
    code, _, err = run_main(capsys, runs, "--out", out)
    assert code == 2 and out.read_bytes() == b"precious"
    assert err.count("\n") == 1 and "--force" in err
    code, _, err = run_main(capsys, runs, "--out", out, "--force")
    assert code == 0, err
    assert out.read_bytes().startswith(PNG_MAGIC)


def test_load_run_skips_empty_cells(tmp_path):
    d = make_run(tmp_path, "walker-walk", "drq", 1)
    (d / "eval.csv").write_text("frame,step,episode,return,wall_time\n0,0,0,,1\n10000,5000,1,7.5,2\n")
    run = plot.load_run(str(d))
    np.testing.assert_array_equal(run["frames"], [10000])
    np.testing.assert_array_equal(run["values"], [7.5])


# ---------------------------------------------------------------- --reference: published curves
def write_published(path, rows, task_column=True):
    """A curve file as facebookresearch/drqv2 ships them (curves/dmc_<task>.csv): an index column,
    agent, task, seed, frame, episode_reward, hour. rows: (task, seed, frame, return)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["", "agent", *(["task"] if task_column else []), "seed", "frame", "episode_reward", "hour"])
        for i, (task, seed, frame, ret) in enumerate(rows):
            w.writerow([i, "DrQ-v2", *([task] if task_column else []), seed, frame, ret, frame / 4e5])
    return path


def published_rows(task="cartpole_balance_sparse"):
    """3 seeds at 0/20k/40k frames; seed 3 also has 60k, which the others lack."""
    values = {1: (50, 100, 1000), 2: (30, 400, 900), 3: (40, 700, 950)}
    rows = [(task, s, f, v) for s, vs in values.items() for f, v in zip((0, 20000, 40000), vs)]
    return rows + [(task, 3, 60000, 1000)]


def test_load_reference_mean_and_min_max_over_seeds_on_their_common_frames(tmp_path):
    path = write_published(tmp_path / "dmc_cartpole_balance_sparse.csv", published_rows())
    curves = plot.load_reference(str(path))
    assert list(curves) == ["cartpole_balance_sparse"]
    ref = curves["cartpole_balance_sparse"]
    np.testing.assert_array_equal(ref["frames"], [0, 20000, 40000])  # 60k: one seed only
    np.testing.assert_allclose(ref["mean"], [40, 400, 950])
    np.testing.assert_allclose(ref["min"], [30, 100, 900])
    np.testing.assert_allclose(ref["max"], [50, 700, 1000])
    assert ref["seeds"] == 3 and ref["label"] == "DrQ-v2 (published)"
    np.testing.assert_allclose(ref["values"], [[50, 100, 1000], [30, 400, 900], [40, 700, 950]])  # seed by seed
    assert plot.load_reference(str(path), "theirs")["cartpole_balance_sparse"]["label"] == "theirs"


def test_reference_without_task_column_takes_the_task_from_the_file_name(tmp_path):
    path = write_published(tmp_path / "dmc_walker_stand.csv", published_rows("walker_stand"), task_column=False)
    assert list(plot.load_reference(str(path))) == ["walker_stand"]


def test_parse_reference_label_and_paths_with_colons(tmp_path):
    assert plot.parse_reference("a/dmc_x.csv:DrQ-v2 paper") == ("a/dmc_x.csv", "DrQ-v2 paper")
    assert plot.parse_reference("a/dmc_x.csv") == ("a/dmc_x.csv", None)
    odd = tmp_path / "run:1.csv"
    odd.write_text("")
    assert plot.parse_reference(str(odd)) == (str(odd), None)


def test_reference_is_drawn_on_the_panel_of_its_task_only(tmp_path, capsys, monkeypatch):
    root = tmp_path / "runs"
    for seed in (1, 2):
        make_run(root, "walker-walk", "drq", seed)
        make_run(root, "cartpole-balance_sparse", "drq", seed, frames=(0, 10000, 20000, 30000))
    path = write_published(tmp_path / "dmc_cartpole_balance_sparse.csv", published_rows())
    drawn = []
    real = plot.draw_reference
    monkeypatch.setattr(plot, "draw_reference", lambda ax, ref, i=0, upto=None: drawn.append((ax.get_title(), ref, ax))
                        or real(ax, ref, i, upto))
    code, _, err = run_main(capsys, root, "--out", tmp_path / "x.png", "--reference", f"{path}:DrQ-v2 paper")
    assert code == 0, err
    assert [(title, ref["label"]) for title, ref, _ in drawn] == [("", "DrQ-v2 paper")]  # title is set after
    ax = drawn[0][2]
    assert ax.get_title() == "cartpole-balance_sparse"
    mean_line = next(line for line in ax.get_lines() if line.get_label().startswith("DrQ-v2 paper"))
    np.testing.assert_allclose(mean_line.get_ydata(), [40, 400])  # cut to the runs' 30k frames
    assert mean_line.get_label() == "DrQ-v2 paper (n=3: mean, min-max)"
    assert ax.get_xlim()[1] < 40000  # the runs' range (30k frames), not the published curve's
    assert (tmp_path / "x.png").read_bytes().startswith(PNG_MAGIC)


@pytest.mark.parametrize("breakage", ["no file", "no episode_reward", "other task", "two agents", "bad frame"])
def test_bad_reference_is_one_line_exit_2(runs, tmp_path, capsys, breakage):
    path = tmp_path / "dmc_walker_walk.csv"
    rows = published_rows("walker_walk")
    if breakage == "no episode_reward":
        path.write_text(",agent,task,seed,frame,return\n0,DrQ-v2,walker_walk,1,0,3.0\n")
    elif breakage == "other task":
        write_published(path, published_rows("cartpole_balance"))
    elif breakage in ("two agents", "bad frame"):
        write_published(path, rows)
        extra = "99,CURL,walker_walk,1,0,5.0,0" if breakage == "two agents" else "99,DrQ-v2,walker_walk,1,soon,5.0,0"
        path.write_text(path.read_text() + extra + "\n")
    code, _, err = run_main(capsys, runs, "--out", tmp_path / "x.png", "--reference", path)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("plot.py: error: --reference"), err
    assert not (tmp_path / "x.png").exists()


# ---------------------------------------------------------------- lines: settings, uneven ends, axes, task means
def set_config(run_dir, **values):
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, **values}))


def test_runs_that_differ_in_a_setting_are_separate_lines_named_by_it(tmp_path, capsys):
    root = tmp_path / "runs"
    for seed in (1, 2):
        set_config(make_run(root, "walker-walk", "sear", seed), mask_source="sim", device="cpu")
        set_config(make_run(root, "walker-walk", "sear", seed + 2, base=100.0), mask_source="learned:seg.pt",
                   device="cuda")  # the device is not a setting: it does not split a line
    code, out, err = run_main(capsys, root, "--out", tmp_path / "x.png")
    assert code == 0, err
    rows = [line for line in out.splitlines() if line.startswith("| walker-walk")]
    # learned: seeds 3, 4 -> 100 + 35 + 20 at frame 20000; sim: seeds 1, 2 -> 15 + 20
    assert rows == ["| walker-walk | sear mask_source=learned:seg.pt | 2 | 20000 | 155 [150, 160] |",
                    "| walker-walk | sear mask_source=sim | 2 | 20000 | 35 [30, 40] |"]


def test_a_key_older_runs_lack_does_not_split_them_from_newer_ones(tmp_path, capsys):
    root = tmp_path / "runs"
    set_config(make_run(root, "walker-walk", "sear", 1), kitchen_camera="fixed")  # a newer sear.py's key
    make_run(root, "walker-walk", "sear", 2)
    code, out, err = run_main(capsys, root, "--out", tmp_path / "x.png")
    assert code == 0, err
    assert [line.split(" | ")[1] for line in out.splitlines() if line.startswith("| walker-walk")] == ["sear"]


def test_not_a_setting_covers_what_a_resume_may_change():
    from harness import cli
    assert cli.RESUME_MAY_CHANGE <= plot.NOT_A_SETTING


def test_a_run_that_stopped_early_is_drawn_to_its_end_and_named(runs, tmp_path, capsys, monkeypatch):
    import matplotlib.axes
    drawn = []
    real = matplotlib.axes.Axes.plot
    monkeypatch.setattr(matplotlib.axes.Axes, "plot",
                        lambda ax, x, y, *a, **k: drawn.append((k.get("ls"), np.asarray(y))) or real(ax, x, y, *a, **k))
    short = sorted(runs.glob("*__drq__1__*"))[0]
    (short / "eval.csv").write_text("frame,step,episode,return,wall_time\n0,0,0,10,1\n10000,5000,1,20,2\n")
    code, out, err = run_main(capsys, runs, "--out", tmp_path / "x.png")
    assert code == 0, err
    assert err.splitlines() == ["plot.py: warning: drq (walker-walk): runs end at frames 10000, 20000 (x2); each is "
                                "drawn to its own end, the mean and CI at a frame are over the runs that reached it "
                                "(dashed where not all did)"]
    # drq's last frame: seeds 2 and 3 only (40 and 50 at frame 20000); the group is not cut to 10000
    assert "| walker-walk | drq | 3 (2 at the last frame) | 20000 | 45 [40, 50] |" in out
    assert "| walker-walk | sear | 3 | 20000 | 140 [130, 150] |" in out
    assert drawn[0][0] is None and drawn[1][0] == "--"  # drq: solid where all 3 runs are, then dashed
    np.testing.assert_allclose(drawn[0][1], [20, 30, np.nan])
    np.testing.assert_allclose(drawn[1][1], [np.nan, 30, 45])


def test_success_axes_stay_in_0_1(runs, tmp_path, capsys, monkeypatch):
    import matplotlib.figure
    limits = []
    real = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda fig, *a, **k: limits.extend(ax.get_ylim() for ax in fig.axes) or real(fig, *a, **k))
    root = tmp_path / "mw"
    for seed in (1, 2, 3):  # every success 0: matplotlib's own margins would reach -0.04
        d = make_run(root, "mw-reach", "sear", seed, success=True)
        (d / "eval.csv").write_text("frame,return,success\n0,1,0\n10000,2,0\n")
    code, _, err = run_main(capsys, root, "--metric", "success", "--out", tmp_path / "s.png")
    assert code == 0, err
    assert limits == [(0.0, 1.0)]
    code, _, err = run_main(capsys, root, "--metric", "return", "--out", tmp_path / "r.png")
    assert code == 0 and limits[1] != (0.0, 1.0)  # returns keep their own scale


def make_task_set_run(root, seed, per_task):
    """A metaworld-mt3-like run: eval.csv with success/<task> columns, per_task = {task: [values]}."""
    d = root / f"metaworld-mt3__sear__{seed}__20240101-000000"
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"env": "metaworld-mt3", "method": "sear", "seed": seed}))
    tasks = list(per_task)
    lines = ["frame,return,success," + ",".join(f"success/{t}" for t in tasks)]
    for i, frame in enumerate((0, 10000)):
        values = [per_task[t][i] for t in tasks]
        lines.append(f"{frame},0,{np.mean(values)}," + ",".join(str(v) for v in values))
    (d / "eval.csv").write_text("\n".join(lines) + "\n")


def test_per_task_adds_a_panel_with_the_mean_over_tasks(tmp_path, capsys):
    root = tmp_path / "runs"
    make_task_set_run(root, 1, {"hammer": [0.0, 0.2], "door-open": [0.0, 0.6]})
    make_task_set_run(root, 2, {"hammer": [0.0, 0.4], "door-open": [0.0, 1.0]})
    code, out, err = run_main(capsys, root, "--per-task", "--metric", "success", "--out", tmp_path / "t.png")
    assert code == 0, err
    rows = [line for line in out.splitlines() if line.startswith("| metaworld-mt3")]
    # per run the mean over the 2 tasks at frame 10000: 0.4 and 0.7 -> 0.55, CI [0.4, 0.7]
    assert rows[-1] == "| metaworld-mt3: mean over 2 tasks | sear | 2 | 10000 | 0.55 [0.4, 0.7] |"
    assert [r.split(" | ")[0] for r in rows] == ["| metaworld-mt3: hammer", "| metaworld-mt3: door-open",
                                                 "| metaworld-mt3: mean over 2 tasks"]


def test_a_reference_is_cut_to_the_frames_of_the_runs(tmp_path, capsys, monkeypatch):
    """A published curve goes on far beyond short runs: its later points must not set the y range."""
    root = tmp_path / "runs"
    for seed in (1, 2):
        make_run(root, "cartpole-balance_sparse", "drq", seed, frames=(0, 10000, 20000, 30000))
    later = [("cartpole_balance_sparse", s, f, 5000.0) for s in (1, 2, 3) for f in (100000, 500000)]
    path = write_published(tmp_path / "dmc_cartpole_balance_sparse.csv", published_rows() + later)
    figures = saved_figures(monkeypatch)
    code, _, err = run_main(capsys, root, "--out", tmp_path / "x.png", "--reference", path)
    assert code == 0, err
    (ax,) = [ax for ax in figures[0][0].axes if ax.get_lines()]
    ref = next(line for line in ax.get_lines() if "published" in line.get_label())
    assert ref.get_xdata().max() <= 30000 and list(ref.get_ydata()) == [40, 400]
    assert ax.get_ylim()[1] < 1000  # the band up to 700 at 20k frames, not the 5000 at 100k and beyond


# ---------------------------------------------------------------- labels and layout
def saved_figures(monkeypatch) -> list:
    """Every figure plot.py saves, with the renderer it was drawn with, for measuring after it is written."""
    import matplotlib.figure
    figures = []
    real = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda fig, *a, **k: (real(fig, *a, **k), figures.append((fig, fig.canvas.get_renderer()))))
    return figures


def inside(box, outer, slack=1.0) -> bool:
    return box.x0 >= outer.x0 - slack and box.y0 >= outer.y0 - slack and box.x1 <= outer.x1 + slack \
        and box.y1 <= outer.y1 + slack


def line_labels(out: str) -> list[str]:
    return [line.split(" | ")[1] for line in out.splitlines() if line.startswith("| walker-walk")]


def test_evaluation_and_logging_settings_do_not_split_lines(tmp_path, capsys):
    root = tmp_path / "runs"
    set_config(make_run(root, "walker-walk", "sear", 1), eval_every=10000, eval_episodes=10, threads=1)
    set_config(make_run(root, "walker-walk", "sear", 2), eval_every=5000, eval_episodes=2, threads=4,
               eval_episodes_per_task=3, log_every=1.0)
    code, out, err = run_main(capsys, root, "--out", tmp_path / "x.png")
    assert code == 0, err
    assert line_labels(out) == ["sear"]


def test_every_line_that_differs_from_another_says_so(tmp_path, capsys):
    """drq's runs agree among themselves but differ from sear's in batch_size: drq's line says so too.
    std_steps differs only between envs (a per-task default): it names no line."""
    root = tmp_path / "runs"
    for seed in (1, 2):
        set_config(make_run(root, "walker-walk", "sear", seed), batch_size=16, mask_source="sim")
        set_config(make_run(root, "walker-walk", "sear", seed + 2), batch_size=16, mask_source="learned:seg.pt")
        set_config(make_run(root, "walker-walk", "drq", seed), batch_size=256, mask_source="sim")
        set_config(make_run(root, "cheetah-run", "drq", seed), batch_size=256, mask_source="sim", std_steps=500000)
    code, out, err = run_main(capsys, root, "--out", tmp_path / "x.png", "--group", "method,env")
    assert code == 0, err
    assert line_labels(out) == ["drq / walker-walk batch_size=256",  # mask_source does nothing for drq
                                "sear / walker-walk batch_size=16 mask_source=learned:seg.pt",
                                "sear / walker-walk batch_size=16 mask_source=sim"]
    assert [line.split(" | ")[1] for line in out.splitlines() if line.startswith("| cheetah-run")] == [
        "drq / cheetah-run batch_size=256"]


@pytest.mark.parametrize("settings", [3, 6, 12])
def test_axes_keep_their_size_and_titles_fit_whatever_the_legend_holds(tmp_path, capsys, monkeypatch, settings):
    """The layout rule: with lines that differ in many settings, and a title longer than the figure is
    wide, the axes stay as wide and as tall as with plain labels, and the title and legend lie inside the
    figure."""
    figures = saved_figures(monkeypatch)
    plain = tmp_path / "plain"
    for seed in (1, 2):
        make_run(plain, "walker-walk", "sear", seed)
    code, _, err = run_main(capsys, plain, "--out", tmp_path / "plain.png")
    assert code == 0, err
    root = tmp_path / "runs"
    for line in range(4):
        for seed in (1, 2):
            set_config(make_run(root, "walker-walk", "sear", 10 * line + seed),
                       **{f"setting_{k:02d}": f"value-{line}" for k in range(settings)})
    title = "A title much longer than the figure is wide, as a sweep of many settings may well need " * 2
    code, out, err = run_main(capsys, root, "--out", tmp_path / "x.png", "--title", title)
    assert code == 0, err
    assert len(line_labels(out)) == 4
    sizes = []
    for fig, renderer in figures:
        (ax,) = [ax for ax in fig.axes if ax.get_lines()]
        box = ax.get_position()
        sizes.append((box.width * fig.get_figwidth(), box.height * fig.get_figheight(), box.width))
        assert inside(ax.title.get_window_extent(renderer), fig.bbox), ax.title.get_text()
        for legend in [*fig.legends, *(a.get_legend() for a in fig.axes if a.get_legend())]:
            assert inside(legend.get_window_extent(renderer), fig.bbox)
    (plain_w, plain_h, _), (w, h, width_share) = sizes
    assert w >= 0.95 * plain_w and h >= 0.95 * plain_h and h >= plot.AXES_HEIGHT - 0.01, sizes
    assert width_share >= 0.75, "the axes' share of the figure's width"
