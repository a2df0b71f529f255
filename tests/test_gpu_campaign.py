"""benchmarks/gpu_campaign.sh on the CPU, reduced: bad arguments, the budget's stop, and no run left behind.
CI runs the whole --quick form (.ci/run)."""
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "gpu_campaign.sh"


@pytest.fixture
def campaign():
    """Starts the script (in a process group of its own); whatever a failed test leaves is ended after it."""
    started = []

    def start(*args):
        env = {**os.environ, "PYTHON": sys.executable, "MUJOCO_GL": "egl"}
        started.append(subprocess.Popen(["bash", str(SCRIPT), *map(str, args)], cwd=ROOT, env=env, text=True,
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True))
        return started[-1]
    yield start
    for p in started:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def runs_of(out: Path) -> list[int]:
    """The processes whose command line names `out`: the campaign's sear.py runs."""
    pids = []
    for d in Path("/proc").iterdir():
        try:
            cmdline = (d / "cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if d.name.isdigit() and "sear.py" in cmdline and str(out) in cmdline:
            pids.append(int(d.name))
    return pids


@pytest.mark.parametrize("args, message", [
    (["--seeds", "0"], "--seeds must be a positive integer, got '0'"),
    (["--first-seed", "0"], "--first-seed must be a positive integer, got '0'"),
    (["--parallel", "all"], "--parallel must be a positive integer, got 'all'"),
    (["--frames", "ten"], "--frames must be a positive integer, got 'ten'"),
    (["--budget-minutes", "-1"], "--budget-minutes must be a positive number, got '-1'"),
    (["--render-quality", "nice"], "--render-quality must be paper or fast, got 'nice'"),
    (["--gpus", "2"], "unknown argument --gpus"),
    (["--out"], "--out needs a value"),
])
def test_bad_arguments_are_one_line_and_make_nothing(tmp_path, campaign, args, message):
    p = campaign("--quick", *args, "--out", tmp_path / "c") if args != ["--out"] else campaign("--quick", *args)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and err.count("\n") == 1 and err.startswith("gpu_campaign.sh: error:"), err
    assert message in err and not (tmp_path / "c").exists()


def test_an_existing_out_is_refused(tmp_path, campaign):
    (tmp_path / "c").mkdir()
    p = campaign("--quick", "--out", tmp_path / "c")
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and "exists; give another --out" in err


def test_the_budget_stops_the_runs_and_the_summary_says_so(tmp_path, campaign):
    """Runs far longer than a 45 s budget: each run started is stopped (SIGTERM: at its next episode end,
    with a snapshot), and the summary names it; nothing is left running."""
    out = tmp_path / "c"
    p = campaign("--quick", "--frames", 100000, "--budget-minutes", 0.75, "--out", out)
    stdout, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    summary = (out / "summary.md").read_text()
    assert summary.strip() in stdout
    assert "| drq-group (2 seeds) | stopped by the budget |" in summary  # two seeds: one sear.py --seeds group
    assert "one sear.py --seeds 1-2 group per method" in summary
    # the runs stop inside the budget; the rule after them may overrun it on a loaded machine (python's start)
    trained = re.search(r"\(training (\d+) s\), budget 45 s: (within|OVER)$", summary.strip().splitlines()[-1])
    assert trained and int(trained.group(1)) <= 45, summary.strip().splitlines()[-1]
    assert runs_of(out) == []


def test_a_sigterm_to_the_campaign_stops_every_run_it_started(tmp_path, campaign):
    out = tmp_path / "c"
    p = campaign("--quick", "--frames", 100000, "--out", out)
    deadline = time.time() + 90
    while not runs_of(out) and time.time() < deadline and p.poll() is None:
        time.sleep(0.5)
    assert runs_of(out), "no run started"
    os.kill(p.pid, signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143 and "SIGTERM: stopping the runs" in err, err
    assert runs_of(out) == []


def test_a_part_runs_its_seeds_and_leaves_its_small_files(tmp_path, campaign):
    """--first-seed 3: seed 3 alone (the other parts run the others), with every core the process may use;
    --copy-to gets the part's 4 small files, whose results file the rule on the union of the parts reads;
    the summary says what comes next."""
    out, copy = tmp_path / "c", tmp_path / "copy"
    p = campaign("--quick", "--first-seed", 3, "--seeds", 1, "--out", out, "--copy-to", copy)
    stdout, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    assert [d.name for d in (out / "runs").iterdir()] == ["drq-3"]
    assert sorted(f.name for f in copy.iterdir()) == [f"seeds3-3_{f}" for f in
                                                      ("curve.png", "logs.tar.gz", "results.csv", "summary.md")]
    rows = (copy / "seeds3-3_results.csv").read_text().splitlines()
    assert rows[0].endswith(",settings") and len(rows) == 4 and all(r.startswith("drq,3,") for r in rows[1:])
    summary = (copy / "seeds3-3_summary.md").read_text()
    assert "This part holds seeds 3-3 (1 of the 16 that MATCH needs" in summary
    cores = len(os.sched_getaffinity(0))  # all of them, though the script sets OMP_NUM_THREADS=1 for its runs
    assert f"1 at a time, {cores} torch threads each (cores {cores}," in summary and f", {cores} CPU cores," in summary
    assert "`benchmarks/gpu_campaign.sh --first-seed 4 --quick --seeds 1`" in summary
    assert "--results seeds3-3_results.csv --results seeds4-4_results.csv" in summary
    assert "--seeds $(seq 1 16) --frames 0 100 200" in summary
    p = campaign("--quick", "--first-seed", 3, "--seeds", 1, "--out", tmp_path / "d", "--copy-to", copy)
    _, err = p.communicate(timeout=60)  # a part's files are never overwritten
    assert p.returncode == 2 and "seeds3-3_summary.md exists" in err and not (tmp_path / "d").exists()
