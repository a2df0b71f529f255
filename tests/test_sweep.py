"""sweep.py: the paper's grids, bad input, a real local sweep killed midway and finished, failing
jobs, locks, resume-or-restart, and a SLURM submission through stand-in sbatch/srun commands."""
import csv
import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

import sweep

ROOT = Path(__file__).resolve().parents[1]
# Tiny sear.py runs: a few seconds each, mostly start-up. 60 frames rather than 40 because the kill
# test needs time between the first snapshot (frame 20) and the end of the run to stop it there.
TINY = ["--frames", "60", "--seed-frames", "20", "--eval-every", "20", "--eval-episodes", "1",
        "--max-episode-steps", "10", "--batch-size", "4", "--latent-dim", "64", "--hidden-dim", "32",
        "--feature-dim", "8", "--replay-size", "1000", "--render-quality", "fast",
        "--snapshot-minutes", "0"]  # a snapshot at every episode end: the kill test needs an early one


def column(path, name):
    with open(path, newline="") as f:
        return [int(float(row[name])) for row in csv.DictReader(f)]


def attempts(job_dir):
    return (Path(job_dir) / "stdout.log").read_text().count("=== attempt ")


def plan(argv, passthrough=()):
    args, unknown = sweep.build_parser().parse_known_args(argv)
    return sweep.plan(args, [*unknown, *passthrough])


# ------------------------------------------------------------------------------- planning, bad input
def test_named_grids_hold_the_papers_tasks_methods_seeds_and_budgets():
    name, specs, grid = plan(["--grid", "metaworld10"])
    assert name == "metaworld10" and len(specs) == 10 * 5 * 5 and grid.metric == "success"
    assert list(dict.fromkeys(s.env for s in specs)) == [f"metaworld-{t}" for t in (
        "button-press-topdown-wall", "door-open", "door-unlock", "door-lock", "button-press-wall",
        "assembly", "hammer", "handle-pull", "door-close", "coffee-button")]
    assert list(dict.fromkeys(s.variant for s in specs)) == ["sear", "drq", "ae", "mae", "curl"]
    assert sorted({s.seed for s in specs}) == [1, 2, 3, 4, 5]
    assert {s.frames for s in specs} == {2_500_000}
    assert len({s.name for s in specs}) == len(specs)

    _, specs, _ = plan(["--grid", "distracting", "--seeds", "1"])
    walker = next(s for s in specs if s.env == "walker-walk-distracting")
    cup = next(s for s in specs if s.env == "cup-catch-distracting")
    assert "--nstep" not in walker.args and walker.name != cup.name  # the paper's recipe: sear.py's defaults

    _, specs, _ = plan(["--grid", "ablations", "--seeds", "1", "--envs", "metaworld-hammer"])
    keys = {s.variant: s.key for s in specs}
    assert set(keys) == {"sear", "drq", "sear-mask-noise", "sear-mask-approx", "rgbm", "sear-nosplit",
                         "sear-c-authors", "sear-no-recon", "sear-no-mask"}
    assert keys["sear"] == keys["drq"] != keys["sear-mask-noise"]  # the method is in the name, not the key

    # The user's flags come last and win over the grid's budget.
    _, specs, _ = plan(["--grid", "kitchen", "--seeds", "2", "--methods", "sear"], ["--frames", "1000"])
    assert [(s.env, s.seed, s.frames) for s in specs] == [
        ("kitchen-kettle", 2, 1000), ("kitchen-light", 2, 1000), ("kitchen-slider", 2, 1000)]


def test_job_key_depends_on_the_experiment_not_on_how_it_was_spelled():
    def key(*flags):
        return plan(["--envs", "walker-walk", "--methods", "sear"], flags)[1][0].key
    assert key("--frames", "40", "--batch-size", "4") == key("--batch-size", "4", "--frames", "40")
    assert key() == key("--frames", "1000000") == key("--device", "cpu", "--save-buffer")
    assert key() != key("--frames", "40") != key("--frames", "40", "--mask-noise", "0.1")


def test_seed_lists_and_ranges():
    assert sweep.parse_seeds(["1-5"]) == (1, 2, 3, 4, 5)
    assert sweep.parse_seeds(["1-3,7", "9", "2"]) == (1, 2, 3, 7, 9)


@pytest.mark.parametrize("argv, message", [
    (["--envs", "walker-walk", "--methods", "drq", "--frams", "40"],
     "sear.py has no flag --frams; did you mean --frames?"),
    (["--envs", "walkr-walk", "--methods", "drq"], "sear.py rejects walkr-walk drq: unknown env 'walkr-walk'"),
    (["--envs", "walker-walk", "--methods", "dqr"], "invalid choice: 'dqr'"),
    (["--envs", "walker-walk", "--methods", "drq", "--", "--frames", "-5"], "--frames must be > 0, got -5"),
    (["--envs", "walker-walk", "--methods", "drq", "--seed", "3"], "--seed is set by sweep.py; use --seeds"),
    (["--envs", "walker-walk", "--methods", "drq", "--seeds", "3-1"], "the range '3-1' is empty"),
    (["--envs", "walker-walk"], "give --grid NAME, or --envs and --methods"),
    (["--grid", "transfer"], "grid 'transfer' is not available yet"),
    (["--grid", "kitchen", "--methods", "rgbm"], "grid 'kitchen' has no method rgbm"),
    (["--envs", "walker-walk", "--methods", "drq", "--engine", "local", "--partition", "gpu"],
     "--partition needs SLURM, but the engine is local"),
    (["--envs", "walker-walk", "--methods", "drq", "--threads", "0"], "--threads must be >= 1, got 0"),
])
def test_bad_input_fails_the_whole_sweep_up_front(tmp_path, capsys, argv, message):
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sweep.py: error: ") and message in err, err
    assert not out.exists()


# ------------------------------------------------------------------------------- a real local sweep
def sweep_args(out, *extra):
    return ["--envs", "walker-walk", "cup-catch", "--methods", "drq", "sear", "--seeds", "1", "--out", str(out),
            *extra, "--", *TINY]


def test_local_sweep_killed_midway_then_rerun_finishes_without_duplicates(tmp_path, capsys):
    out = tmp_path / "sweeps"
    folder = out / "custom"

    # A sweep one job at a time, killed whole (driver, submitit's processes, sear.py) once the first
    # job has written its first snapshot.
    with open(tmp_path / "first.log", "w") as log:
        p = subprocess.Popen([sys.executable, str(ROOT / "sweep.py"), *sweep_args(out, "--jobs", "1")],
                             stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path, start_new_session=True,
                             env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
        try:
            deadline = time.time() + 120
            while not list(folder.glob("walker-walk__drq__1__*/run/*/snapshot.pt")):
                assert p.poll() is None, (tmp_path / "first.log").read_text()[-2000:]
                assert time.time() < deadline, "no snapshot in time"
                time.sleep(0.05)
        finally:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    first = next(folder.glob("walker-walk__drq__1__*"))
    assert not (first / "DONE").exists()

    assert sweep.main(["--out", str(out), "--status"]) == 0
    rows = [re.split(r"\s{2,}", line) for line in capsys.readouterr().out.splitlines()[1:-1]]
    assert sorted((row[0].split("__1__")[0], row[1]) for row in rows) == [
        ("cup-catch__drq", "not started"), ("cup-catch__sear", "not started"),
        ("walker-walk__drq", "interrupted"), ("walker-walk__sear", "not started")]

    assert sweep.main(sweep_args(out, "--jobs", "2")) == 0
    printed = capsys.readouterr().out
    assert "4 jobs (2 envs x 2 methods x 1 seeds): 0 done, 0 running elsewhere, 4 to run" in printed
    assert "\n4 of 4 jobs finished\n" in printed
    jobs = sorted(d for d in folder.iterdir() if d.is_dir() and not d.name.startswith("."))
    stamps = {}
    for d in jobs:
        runs = list((d / "run").iterdir())
        assert (d / "DONE").exists() and len(runs) == 1, d  # exactly one run per key
        assert column(runs[0] / "eval.csv", "frame") == [0, 20, 40, 60], d  # no evaluation twice; the last at the end
        frames = column(runs[0] / "train.csv", "frame")
        assert frames == sorted(set(frames)) and frames[-1] == 60, d
        assert attempts(d) == (2 if d == first else 1), d
        stamps[d] = (runs[0] / "eval.csv").stat().st_mtime_ns
    assert "resumed at frame 20" in (first / "stdout.log").read_text()
    assert (folder / "report.png").exists() and "mean over 2 tasks" in (folder / "report.md").read_text()

    # The same sweep again: everything is finished, nothing starts.
    assert sweep.main(sweep_args(out)) == 0
    assert "4 done, 0 running elsewhere, 0 to run" in capsys.readouterr().out
    for d in jobs:
        assert attempts(d) == (2 if d == first else 1)
        assert next(d.glob("run/*/eval.csv")).stat().st_mtime_ns == stamps[d]


# ------------------------------------------------------------------------------- failures, locks, resume
FAILS_ON_CUP = """import sys
if "cup-catch" in sys.argv:
    print("UserWarning: nothing to worry about", file=sys.stderr)
    print("RuntimeError: the simulator exploded", file=sys.stderr)
    sys.exit(1)
print("done: a stand-in run")
"""


def test_a_failing_job_is_reported_with_its_error_and_the_others_still_run(tmp_path, monkeypatch, capsys):
    fake = tmp_path / "fake_sear.py"
    fake.write_text(FAILS_ON_CUP)
    monkeypatch.setattr(sweep, "SEAR_PY", str(fake))
    out = tmp_path / "sweeps"
    argv = ["--out", str(out), "--envs", "cup-catch", "walker-walk", "--methods", "drq", "sear", "--seeds", "1",
            "--jobs", "1", "--frames", "40"]
    assert sweep.main(argv) == 1  # the cup-catch jobs run first and fail; the walker ones run anyway
    printed = capsys.readouterr().out
    assert printed.count("failed: exit code 1: RuntimeError: the simulator exploded") == 2
    assert "2 of 4 jobs finished; 2 failed" in printed

    assert sweep.main(["--out", str(out), "--status"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split() == ["job", "state", "frames", "note"] and table[-1] == "4 jobs: 2 done, 2 failed"
    for line in table[1:-1]:
        if line.startswith("cup-catch"):
            assert " failed " in line and line.endswith("exit code 1: RuntimeError: the simulator exploded")
        else:
            assert line.startswith("walker-walk") and " done " in line and "-/40" in line


RECORDS_ITS_ARGS = """import json, os, sys
with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "calls.jsonl"), "a") as f:
    f.write(json.dumps([os.environ["OMP_NUM_THREADS"], *sys.argv[1:]]) + "\\n")
"""


def make_job(tmp_path, name="walker-walk__drq__1__abcd1234"):
    script = tmp_path / "record.py"
    script.write_text(RECORDS_ITS_ARGS)
    d = tmp_path / "sweeps" / "s" / name
    d.mkdir(parents=True)
    return sweep.SearJob(str(d), ["--env", "walker-walk"], ["--device", "auto"], 3, script=str(script)), d


def calls(tmp_path):
    """The stand-in sear.py's arguments, each call's after the torch thread count it was given."""
    path = tmp_path / "calls.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_a_live_lock_is_respected_and_a_dead_one_taken_over(tmp_path):
    job, d = make_job(tmp_path)
    me = sweep.whoami()
    sweep.write_json(str(d / "lock"), me)  # held by this (live) process
    assert job().startswith(f"skipped: already running (pid {os.getpid()} on ")
    assert sweep.job_state(str(d))[0] == "running" and calls(tmp_path) == []

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    sweep.write_json(str(d / "lock"), {**me, "pid": gone.pid, "start": None})  # its holder died
    assert sweep.job_state(str(d))[0] == "not started"
    assert job() == "done"
    assert calls(tmp_path) == [["3", "--env", "walker-walk", "--run-root", str(d / "run")]]
    assert not (d / "lock").exists() and (d / "DONE").exists()
    assert job() == "done" and len(calls(tmp_path)) == 1  # finished: never started again


def test_the_sweep_never_starts_a_key_that_is_running(tmp_path, capsys):
    out = tmp_path / "sweeps"
    argv = ["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "sear", "--seeds", "1", "--frames", "40"]
    _, specs, _ = plan(argv)
    busy = out / "custom" / specs[0].name
    busy.mkdir(parents=True)
    sweep.write_json(str(busy / "lock"), sweep.whoami())  # a live process runs this key
    (out / "custom" / specs[1].name).mkdir()
    (out / "custom" / specs[1].name / "DONE").write_text("")
    assert sweep.main(argv) == 0
    assert "2 jobs (1 envs x 2 methods x 1 seeds): 1 done, 1 running elsewhere, 0 to run" in capsys.readouterr().out
    assert sorted(p.name for p in busy.iterdir()) == ["lock"]  # nothing submitted, nothing written


def test_an_interrupted_run_resumes_from_its_snapshot_or_moves_aside_without_one(tmp_path):
    job, d = make_job(tmp_path, "walker-walk__drq__1__00000001")
    run = d / "run" / "walker-walk__drq__1__20260101-000000"
    run.mkdir(parents=True)
    (run / "snapshot.pt").write_bytes(b"stand-in")
    assert job() == "done"
    assert calls(tmp_path)[-1] == ["3", "--resume", str(run), "--device", "auto"]

    job, d = make_job(tmp_path, "walker-walk__drq__1__00000002")
    run = d / "run" / "walker-walk__drq__1__20260101-000000"
    run.mkdir(parents=True)
    (run / "config.json").write_text('{"note": "the user\'s"}')
    assert job() == "done"
    assert calls(tmp_path)[-1] == ["3", "--env", "walker-walk", "--run-root", str(d / "run")]
    aside = tmp_path / "sweeps" / "s.aside" / d.name / run.name / "config.json"
    assert aside.read_text() == '{"note": "the user\'s"}' and not run.exists()
    assert "moved the snapshot-less run" in (d / "stdout.log").read_text()


# ------------------------------------------------------------------------------- SLURM
def test_slurm_is_detected_and_gets_one_array_with_the_cluster_flags(tmp_path, monkeypatch, capsys):
    bin_dir = tmp_path / "bin"  # stand-ins: srun marks a SLURM machine, sbatch keeps what it was given
    bin_dir.mkdir()
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "sbatch").write_text(f'#!/bin/sh\ncp "$1" {tmp_path}/submitted.sh\necho "Submitted batch job 4242"\n')
    for tool in ("srun", "sbatch"):
        (bin_dir / tool).chmod(stat.S_IRWXU)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "cup-catch", "--methods", "drq", "--seeds", "1-2",
                       "--partition", "gpu", "--account", "lab", "--time-limit", "600", "--threads", "2",
                       "--slurm-array-parallelism", "3", "--frames", "40"]) == 0
    script = (tmp_path / "submitted.sh").read_text()
    for line in ("--partition=gpu", "--account=lab", "--time=600", "--cpus-per-task=2", "--gpus-per-node=1",
                 "--array=0-3%3"):
        assert f"#SBATCH {line}\n" in script, line
    assert "submitted 4 jobs (4242)" in capsys.readouterr().out
    states = [json.loads(p.read_text()) for p in sorted((out / "custom").glob("*/status.json"))]
    assert sorted(s["by"]["job"] for s in states) == ["4242_0", "4242_1", "4242_2", "4242_3"]
    assert sweep.main(["--out", str(out), "--status"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "4 jobs: 4 queued"


# ------------------------------------------------------------------------------- report
def test_report_averages_each_seed_over_the_tasks_then_the_seeds(tmp_path, capsys):
    out, specs = tmp_path / "sweeps", []
    for env, scale in (("metaworld-hammer", 0.1), ("metaworld-door-open", 0.3)):
        for seed in (1, 2, 3, 4):
            spec = sweep.JobSpec("g", env, "sear", seed, "k", 10, (), ())
            specs.append(spec)
            run = out / "g" / spec.name / "run" / "r"
            run.mkdir(parents=True)
            (run / "config.json").write_text(json.dumps({"env": env, "method": "sear", "seed": seed}))
            (run / "eval.csv").write_text(f"frame,return,success\n0,0,0\n10,1,{scale * seed}\n")
            if seed < 4:  # seed 4 is still running: left out
                (out / "g" / spec.name / "DONE").write_text("")
    table = sweep.report(str(out), "g", specs, None)
    # success at frame 10 per seed: hammer 0.1 s, door-open 0.3 s; their mean 0.2 s over seeds 1-3
    # -> 0.4 +- t(0.975, 2) * 0.2 / sqrt(3) = 0.4 +- 0.497
    assert "| mean over 2 tasks | sear | 3 | 10 | 0.4 ± 0.497 |" in table
    assert "| metaworld-hammer | sear | 3 | 10 | 0.2 ± 0.248 |" in table
    assert (out / "g" / "report.png").exists()
    assert "6 of 8 jobs finished" in (out / "g" / "report.md").read_text()
