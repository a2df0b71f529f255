"""benchmarks/published_curve.py: our runs against a published curve, table and verdict, on fake runs."""
import importlib.util
import os

import pytest

from tests.test_plot import PNG_MAGIC, make_run, published_rows, write_published

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_spec = importlib.util.spec_from_file_location("published_curve",
                                               os.path.join(ROOT, "benchmarks", "published_curve.py"))
published_curve = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(published_curve)

COMMIT = "c0c650b76c6e5d22a7eb5f2edffd1440fe94f8ef"
FRAMES = (0, 10000, 20000, 30000, 40000)


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


@pytest.mark.parametrize("base, verdict", [(860.0, "verdict: MATCH"), (840.0, "verdict: NO MATCH")])
def test_table_and_verdict(tmp_path, published, capsys, base, verdict):
    """make_run's return is base + 10 * seed + frame / 1000: at 40k, base 860 gives 910/920/930 (all
    >= 900 and >= the lowest published seed, 900); base 840 gives 890/900/910 (2 of 3 >= 900, but 890
    is below the lowest published seed)."""
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
    assert f"\n{verdict} (" in out
    assert out_png.read_bytes().startswith(PNG_MAGIC)


def test_runs_in_progress_and_a_pending_verdict(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES, base=900.0)  # 950 at 40k: not below
    d = make_run(runs, "cartpole-balance_sparse", "drq", 2, frames=(0, 10000))
    (d / "config.json").write_text('{"env": "cartpole-balance_sparse", "method": "drq", "seed": 2, "frames": 40000}')
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png")
    assert code == 0, err
    assert table_row(out, "20k")[1:5] == ["930.0 (1 of 3 seeds)", "930.0", "in progress", "not started"]
    assert "verdict: pending (1 of 3 seeds have evaluated at 40000)" in out


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


def test_no_match_is_decided_by_one_seed_below_the_lowest_published(tmp_path, published, capsys):
    """The rule's 'none below the lowest published seed' fails with one seed: no need to wait for
    the others (published 40k lowest: 900; seed 1 at 40k: 810 + 40 + 10)."""
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES, base=810.0)
    make_run(runs, "cartpole-balance_sparse", "drq", 2, frames=(0, 10000))
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png")
    assert code == 0, err
    assert "verdict: NO MATCH with 1 of 3 seeds evaluated, whatever the others give (seed 1 860.0:" in out
    assert "below the lowest published seed: [1])" in out


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
    assert "verdict: pending (1 of 3" in out  # the rule is about our DrQ, not the official code
    assert "the same rule on drqv2 official: pending (0 of 3 seeds have evaluated at 40000)" in out


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
    assert "verdict: pending (1 of 3" in out  # the rule is about our DrQ as sear.py trains it


def test_the_same_rule_is_applied_to_the_official_code(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES, base=840.0)  # 890 at 40k: below 900
    for seed in (1, 2, 3):
        make_official_run(runs, seed, frames=FRAMES)  # 900 + seed at 40k
    code, out, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png",
                              "--official", runs / "official-*")
    assert code == 0, err
    lines = out.splitlines()
    ours = next(i for i, line in enumerate(lines) if line.startswith("verdict: NO MATCH"))
    assert "a defect to find" in lines[ours]
    assert lines[ours + 1].startswith("the same rule on drqv2 official: MATCH (seed 1 901.0, seed 2 902.0, "
                                      "seed 3 903.0); rule: at least 2 of 3 drqv2 official seeds >= 900")


def test_official_dir_that_is_no_official_run_is_one_line(tmp_path, published, capsys):
    runs = tmp_path / "runs"
    make_run(runs, "cartpole-balance_sparse", "drq", 1, frames=FRAMES)
    code, _, err = run_main(capsys, runs, "--published", published, "--out", tmp_path / "fig.png",
                            "--official", runs)
    assert code == 2 and err.count("\n") == 1 and "not a run of the official code" in err, err
