"""sweep.py: the paper's grids, bad input, a real local sweep killed midway and finished, failing
jobs, locks, resume-or-restart, GPUs per job, SLURM through stand-in srun/sinfo/squeue/sbatch commands
(what a one-node cluster cannot show: arrays over many nodes, GPUs, refusals) and through a real
one-node SLURM (SEAR_REAL_SLURM=1, .ci/run), and the report."""
import contextlib
import csv
import json
import os
import re
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import sweep

ROOT = Path(__file__).resolve().parents[1]
# Tiny sear.py runs: a few seconds each, mostly start-up. 60 frames rather than 40 because the kill
# test needs time between the first snapshot (frame 20) and the end of the run to stop it there.
TINY = ["--frames", "60", "--seed-frames", "20", "--eval-every", "20", "--eval-episodes", "1",
        "--max-episode-steps", "10", "--batch-size", "4", "--latent-dim", "64", "--hidden-dim", "32",
        "--feature-dim", "8", "--replay-size", "1000", "--render-quality", "fast",
        "--snapshot-minutes", "0",  # a snapshot at every episode end: the kill test needs an early one
        "--drop-inapplicable"]  # one set of flags for every method: --latent-dim does nothing for drq


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


def test_method_plus_drm_is_the_method_with_drm_in_a_grid_or_not():
    _, specs, _ = plan(["--envs", "cartpole-balance_sparse", "--methods", "drq", "drq+drm", "sear+drm"])
    assert [(s.variant, s.args[3], "--drm" in s.args) for s in specs] == [
        ("drq", "drq", False), ("drq+drm", "drq", True), ("sear+drm", "sear", True)]
    assert specs[0].key != specs[1].key and len({s.name for s in specs}) == 3
    assert "__drq+drm__1__" in specs[1].name
    _, specs, _ = plan(["--grid", "ablations", "--envs", "metaworld-hammer", "--seeds", "1",
                        "--methods", "sear-mask-noise+drm", "drq"])
    assert [(s.variant, s.args[-3:]) for s in specs] == [  # the grid's order, the variant's flags kept
        ("drq", ("--seed", "1", "--frames", "2500000")[-3:]),
        ("sear-mask-noise+drm", ("--mask-noise", "0.25", "--drm"))]
    with pytest.raises(sweep.SweepError, match="has no method curl-x.*each also as NAME[+]drm"):
        plan(["--grid", "kitchen", "--methods", "curl-x+drm"])


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
    (["--envs", "walker-walk", "--methods", "drq", "--frams", "40"], "no flag --frams; did you mean --frames?"),
    # a typo of sweep.py's own flag is named as such, not passed on to sear.py or answered with another line
    (["--stauts"], "no flag --stauts; did you mean --status?"),
    (["--grid", "kitchen", "--reprot"], "no flag --reprot; did you mean --report?"),
    (["--grid", "kitchen", "--methods", "sear", "--dry-rnu"], "no flag --dry-rnu; did you mean --dry-run?"),
    (["--grid", "kitchen", "--status", "--nmae", "k"], "no flag --nmae; did you mean --name?"),
    (["--grid", "kitchen", "--", "--status"], "--status is sweep.py's, not sear.py's: put it before --"),
    (["--envs", "walkr-walk", "--methods", "drq"], "sear.py rejects walkr-walk drq: unknown env 'walkr-walk'"),
    (["--envs", "walker-walk", "--methods", "dqr"], "invalid choice: 'dqr'"),
    (["--envs", "walker-walk", "--methods", "drq", "--", "--frames", "-5"], "--frames must be > 0, got -5"),
    (["--envs", "walker-walk", "--methods", "drq", "--seed", "3"], "--seed is set by sweep.py; use --seeds"),
    (["--envs", "walker-walk", "--methods", "drq", "--seeds", "3-1"], "the range '3-1' is empty"),
    (["--envs", "walker-walk"], "give --grid NAME, or --envs and --methods"),
    (["--grid", "transfer"], "grid 'transfer' is not available yet"),
    (["--grid", "kitchen", "--methods", "rgbm"], "grid 'kitchen' has no method rgbm"),
    (["--envs", "walker-walk", "--methods", "drq", "--engine", "local", "--partition", "gpu"],
     "--partition needs SLURM, but the engine is local (--engine local)"),
    (["--envs", "walker-walk", "--methods", "drq", "--account", "lab"],
     "--account needs SLURM, but the engine is local (default"),
    (["--envs", "walker-walk", "--methods", "drq", "--threads", "0"], "--threads must be >= 1, got 0"),
    (["--envs", "walker-walk", "--methods", "drq", "--seeds-per-job", "0"], "--seeds-per-job must be >= 1, got 0"),
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
            "--engine", "local", *extra, "--", *TINY]


@contextlib.contextmanager
def sweep_process(tmp_path, argv):
    """sweep.py in a process group of its own (its output in first.log), killed whole at the end."""
    with open(tmp_path / "first.log", "w") as log:
        p = subprocess.Popen([sys.executable, str(ROOT / "sweep.py"), *argv],
                             stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path, start_new_session=True,
                             env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
        p.log = tmp_path / "first.log"
        try:
            yield p
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def wait_for_files(p, folder, pattern, count=1):
    """Until `count` files under `folder` match `pattern`, while the sweep process `p` runs."""
    deadline = time.time() + 120
    while len(list(folder.glob(pattern))) < count:
        assert p.poll() is None, p.log.read_text()[-2000:]
        assert time.time() < deadline, f"no {pattern} in time"
        time.sleep(0.02)


def wait_for_text(p, folder, pattern, text):
    """Until a file under `folder` that matches `pattern` holds `text`, while the sweep process `p`
    runs."""
    deadline = time.time() + 120
    while not any(text in f.read_text(errors="replace") for f in folder.glob(pattern)):
        assert p.poll() is None, p.log.read_text()[-2000:]
        assert time.time() < deadline, f"no {text!r} in {pattern} in time"
        time.sleep(0.02)


def test_local_sweep_killed_midway_then_rerun_finishes_without_duplicates(tmp_path, capsys):
    out = tmp_path / "sweeps"
    folder = out / "custom"

    # A sweep one job at a time, killed whole (driver, submitit's processes, sear.py) once the first
    # job has written its snapshot at frame 20 (the one after its first updates).
    with sweep_process(tmp_path, sweep_args(out, "--jobs", "1")) as p:
        wait_for_text(p, folder, "walker-walk__drq__1__*/stdout.log", "snapshot at frame 20\n")
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
    assert (folder / "report.png").exists() and "| sear | 1 seed x 2 tasks | 60 |" in (folder / "report.md").read_text()

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
            "--engine", "local", "--jobs", "1", "--frames", "40"]
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
    argv = ["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "sear", "--seeds", "1", "--engine", "local",
            "--frames", "40"]
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


# ------------------------------------------------------------------------------- SLURM stand-ins
def fake_slurm(tmp_path, monkeypatch, sinfo="gpu|gpu:4|64|256000\n", sbatch=None):
    """Stand-in srun (marks a SLURM machine), sinfo (prints `sinfo`: partition|gres|cpus|memory MB rows),
    squeue (every job pending) and sbatch (keeps the script it was given, or runs `sbatch` as its body), first
    on PATH whatever this machine has."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    scripts = {"srun": "exit 0",
               "sinfo": f"cat <<'EOF'\n{sinfo}EOF",
               "squeue": "echo PENDING",
               "sbatch": sbatch or f'cp "$1" {tmp_path}/submitted.sh\necho "Submitted batch job 4242"'}
    for tool, body in scripts.items():
        (bin_dir / tool).write_text(f"#!/bin/sh\n{body}\n")
        (bin_dir / tool).chmod(stat.S_IRWXU)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    return bin_dir


def test_engine_slurm_gets_one_array_with_the_cluster_flags(tmp_path, monkeypatch, capsys):
    fake_slurm(tmp_path, monkeypatch, sinfo="cpu*|(null)|64|256000\ngpu|gpu:a100:4(S:0-1)|32|128000\n")
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "cup-catch", "--methods", "drq", "--seeds", "1-2",
                       "--engine", "slurm", "--partition", "gpu", "--account", "lab", "--time-limit", "600",
                       "--threads", "2", "--slurm-array-parallelism", "3", "--seeds-per-job", "1",
                       "--frames", "40"]) == 0
    script = (tmp_path / "submitted.sh").read_text()
    for line in ("--partition=gpu", "--account=lab", "--time=600", "--cpus-per-task=2", "--gpus-per-node=1",
                 "--array=0-3%3"):
        assert f"#SBATCH {line}\n" in script, line
    assert "submitted 4 jobs (4242)" in capsys.readouterr().out
    states = [json.loads(p.read_text()) for p in sorted((out / "custom").glob("*/status.json"))]
    assert sorted(s["by"]["job"] for s in states) == ["4242_0", "4242_1", "4242_2", "4242_3"]
    assert sweep.main(["--out", str(out), "--status"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "4 jobs: 4 queued"


def test_a_partition_without_gpus_gets_no_gpu_request(tmp_path, monkeypatch, capsys):
    fake_slurm(tmp_path, monkeypatch, sinfo="cpu*|(null)|64|256000\ngpu|gpu:4|32|128000\n")
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--frames", "40",
                       "--engine", "slurm"]) == 0
    assert "(slurm, no GPU, as the default partition has none)" in capsys.readouterr().out
    script = (tmp_path / "submitted.sh").read_text()
    assert "--gpus" not in script and "--gres" not in script
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--frames", "40",
                       "--engine", "slurm", "--partition", "gpu", "--name", "g"]) == 0
    assert "#SBATCH --gpus-per-node=1\n" in (tmp_path / "submitted.sh").read_text()


@pytest.mark.parametrize("argv, sinfo, message", [
    (["--gpus-per-job", "1"], "cpu*|(null)|64|256000\n",
     "--gpus-per-job 1: the nodes of the default partition have no GPUs; --gpus-per-job 0 runs on their CPUs (sinfo)"),
    (["--gpus-per-job", "8", "--partition", "gpu"], "cpu*|(null)|64|256000\ngpu|gpu:v100:2,gpu:a100:2|32|128000\n",
     "--gpus-per-job 8: the nodes of partition gpu have at most 4 GPU(s) (sinfo)"),
    (["--partition", "gpus"], "cpu*|(null)|64|256000\ngpu|gpu:4|32|128000\n",
     "SLURM has no partition 'gpus' (sinfo lists cpu, gpu)"),
    (["--threads", "48", "--partition", "gpu"], "cpu*|(null)|64|256000\ngpu|gpu:4|32|128000\n",
     "--threads 48: the nodes of partition gpu have at most 32 CPUs (sinfo), so the jobs would never start"),
])
def test_what_slurm_cannot_give_fails_before_anything_is_created(tmp_path, monkeypatch, capsys, argv, sinfo, message):
    fake_slurm(tmp_path, monkeypatch, sinfo=sinfo)
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--frames", "40",
                       "--engine", "slurm", *argv]) == 2
    assert capsys.readouterr().err == f"sweep.py: error: {message}\n"
    assert not out.exists() and not (tmp_path / "submitted.sh").exists()


@pytest.mark.parametrize("sbatch, message", [
    ('echo "sbatch: error: Invalid generic resource (gres) specification" >&2; exit 1',
     "sbatch refused the 2 job(s): Invalid generic resource (gres) specification "
     "(--gpus-per-job 0 submits without a GPU request)"),
    ('echo "sbatch: error: Memory specification can not be satisfied" >&2\n'
     'echo "sbatch: error: Batch job submission failed: Requested node configuration is not available" >&2; exit 1',
     "sbatch refused the 2 job(s): Memory specification can not be satisfied; Batch job submission failed: "
     "Requested node configuration is not available (each job asks 3 GB: does a node have it? --mem-gb sets it)"),
    ('echo "sbatch: error: Batch job submission failed: Invalid account or account/partition combination" >&2; exit 1',
     "sbatch refused the 2 job(s): Batch job submission failed: Invalid account or account/partition combination"),
    ('echo "queued, no id"', 'sbatch refused the 2 job(s): Could not make sense of sbatch output "queued, no id"'),
])
def test_a_refused_submission_is_one_line_with_sbatchs_reason(tmp_path, monkeypatch, capsys, sbatch, message):
    fake_slurm(tmp_path, monkeypatch, sinfo="gpu*|gpu:1|8|32000\n", sbatch=sbatch)
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--seeds", "1-2",
                       "--engine", "slurm", "--seeds-per-job", "1", "--frames", "40"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sweep.py: error: {message}") and err.count("\n") == 1, err
    assert sweep.main(["--out", str(out), "--status"]) == 0  # nothing was queued
    assert capsys.readouterr().out.splitlines()[-1] == "2 jobs: 2 not started"


def test_no_sbatch_is_one_line(tmp_path, monkeypatch, capsys):
    bin_dir = fake_slurm(tmp_path, monkeypatch)
    (bin_dir / "sbatch").unlink()
    monkeypatch.setenv("PATH", str(bin_dir))  # srun and sinfo, but no sbatch anywhere
    assert sweep.main(["--out", str(tmp_path / "sweeps"), "--envs", "walker-walk", "--methods", "drq",
                       "--engine", "slurm", "--frames", "40"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sweep.py: error: sbatch refused the 1 job(s): [Errno 2] No such file or directory") \
        and err.count("\n") == 1, err


def line(printed: str, start: str) -> str:
    """The one printed line that starts with `start` (sear.py's recipe notes come first)."""
    (found,) = [ln for ln in printed.splitlines() if ln.startswith(start)]
    return found


def test_srun_on_the_path_does_not_send_a_sweep_to_slurm(tmp_path, monkeypatch, capsys):
    fake_slurm(tmp_path, monkeypatch, sinfo="debug*|(null)|8|32000\n")
    out = tmp_path / "sweeps"
    argv = ["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--frames", "40"]
    assert sweep.main([*argv, "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert line(printed, "engine: ") == ("engine: local (default; --engine slurm to submit to SLURM, whose srun is "
                                         "on the PATH)")
    assert "(local, " in line(printed, "sweep custom: ") and not (tmp_path / "submitted.sh").exists()
    assert sweep.main([*argv, "--engine", "slurm", "--dry-run"]) == 0
    assert line(capsys.readouterr().out, "engine: ") == "engine: slurm (--engine slurm)"


def test_a_sweep_submitted_to_slurm_stays_on_slurm(tmp_path, monkeypatch, capsys):
    bin_dir = fake_slurm(tmp_path, monkeypatch, sinfo="debug*|(null)|8|32000\n")
    out = tmp_path / "sweeps"
    argv = ["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--seeds", "1-2", "--frames", "40"]
    assert sweep.main([*argv, "--engine", "slurm"]) == 0
    assert "submitted 2 jobs" in capsys.readouterr().out
    assert json.loads((out / "custom" / "sweep.json").read_text())["engine"] == "slurm"
    record = f"{out / 'custom' / 'sweep.json'} records it"
    assert sweep.main([*argv, "--seeds", "1-3"]) == 0  # the same sweep, one more seed: SLURM again
    printed = capsys.readouterr().out
    assert line(printed, "engine: ") == f"engine: slurm ({record}; --engine local runs it here)"
    assert "submitted 3 jobs" in printed  # queued jobs hold no lock yet: each takes it when it starts
    assert sweep.main(["--out", str(out), "--status"]) == 0  # squeue: still pending
    assert capsys.readouterr().out.splitlines()[-1] == "3 jobs: 3 queued"
    # A folder from before the record named its engine: its jobs' status says SLURM.
    record_path = out / "custom" / "sweep.json"
    record_path.write_text(json.dumps({"sweeps": json.loads(record_path.read_text())["sweeps"]}))
    assert sweep.main([*argv, "--dry-run"]) == 0
    assert line(capsys.readouterr().out, "engine: ") == (f"engine: slurm (the jobs in {out / 'custom'} went to "
                                                         f"SLURM; --engine local runs it here)")
    (out / "new").mkdir()  # a folder told beforehand, as docs/sweeps.md says
    (out / "new" / "sweep.json").write_text('{"engine": "slurm"}')
    assert sweep.main([*argv, "--name", "new", "--dry-run"]) == 0
    assert line(capsys.readouterr().out, "engine: ") == (f"engine: slurm ({out / 'new' / 'sweep.json'} records it; "
                                                         f"--engine local runs it here)")
    (bin_dir / "srun").unlink()  # the folder copied to a machine without SLURM (this one may have it)
    (bin_dir / "cat").symlink_to(shutil.which("cat"))
    monkeypatch.setenv("PATH", str(bin_dir))
    assert sweep.main([*argv, "--dry-run"]) == 2
    assert capsys.readouterr().err == (f"sweep.py: error: engine slurm (the jobs in {out / 'custom'} went to SLURM; "
                                       f"--engine local runs it here), but srun is not on this machine's PATH\n")


def test_memory_per_job_comes_from_the_measured_peak_and_the_jobs_flags():
    cfg = sweep.sear_config(["--env", "walker-walk", "--method", "sear"], "walker-walk sear")
    peak, agent, held, how = sweep.run_memory(cfg)
    assert (round(peak, 2), agent, held) == (8.2, 2.66, 250_000)  # EXPERIMENTS.md, "Memory": about 8.2 GB
    assert how == ("sear: sear's measured peak at batch 256, 2.66 GB, + a replay of 250,000 transitions x 22 kB, "
                   "5.54 GB, + 25%")
    cfg = sweep.sear_config(["--env", "kitchen-kettle", "--method", "drq", "--batch-size", "512", "--frames",
                             "100000", "--replay-size", "1000000"], "kitchen-kettle drq")
    peak, agent, held, _ = sweep.run_memory(cfg)
    assert held == 100_000 and round(agent, 2) == round(0.89 + 2 * (2.01 - 0.89), 2)  # a replay it never fills
    import sear
    worst = sear.ReplayBuffer(1, (3, 84, 84), 28, frame_stack=3, nstep=3, discount=0.99).bytes_per_transition
    assert sweep.REPLAY_BYTES == worst  # Adroit's 28 actions: the most of any task


def test_slurm_asks_the_estimated_memory_and_refuses_what_no_node_holds(tmp_path, monkeypatch, capsys):
    fake_slurm(tmp_path, monkeypatch, sinfo="debug*|(null)|8|64000\n")
    out = tmp_path / "sweeps"
    argv = ["--out", str(out), "--envs", "walker-walk", "--methods", "sear", "drq", "--engine", "slurm"]
    assert sweep.main(argv) == 0
    assert line(capsys.readouterr().out, "memory: ") == (
        "memory: 11 GB per job (sear: sear's measured peak at batch 256, 2.66 GB, + a replay of 250,000 transitions "
        "x 22 kB, 5.54 GB, + 25%; --mem-gb sets it); a node of the default partition has at most 62.5 GB (sinfo)")
    assert "#SBATCH --mem=11GB\n" in (tmp_path / "submitted.sh").read_text()
    assert sweep.main([*argv, "--name", "small", "--mem-gb", "2"]) == 0  # --mem-gb wins
    assert line(capsys.readouterr().out, "memory: ").startswith("memory: 2 GB per job (--mem-gb; the estimate is "
                                                               "11 GB)")
    assert "#SBATCH --mem=2GB\n" in (tmp_path / "submitted.sh").read_text()

    (tmp_path / "x").mkdir()
    fake_slurm(tmp_path / "x", monkeypatch, sinfo="debug*|(null)|8|8000\n")  # a node of 7.8 GB
    for extra, message in (
            ([], "a job needs 11 GB (sear: sear's measured peak at batch 256, 2.66 GB, + a replay of 250,000 "
                 "transitions x 22 kB, 5.54 GB, + 25%), but a node of the default partition has at most 7.8 GB "
                 "(sinfo); --replay-size 132000 fits"),
            (["--mem-gb", "8"], "--mem-gb 8: a node of the default partition has at most 7.8 GB (sinfo)")):
        assert sweep.main([*argv, "--name", "refused", *extra]) == 2
        assert capsys.readouterr().err == f"sweep.py: error: {message}\n"
        assert not (out / "refused").exists()


def test_local_memory_bounds_the_jobs_at_a_time_and_refuses_a_job_too_big(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sweep, "usable_cores", lambda: 8)
    monkeypatch.setattr(sweep, "local_memory_gb", lambda: 24.0)
    argv = ["--out", str(tmp_path / "sweeps"), "--envs", "walker-walk", "--methods", "sear", "--seeds", "1-4",
            "--dry-run"]
    assert sweep.main(argv) == 0
    printed = capsys.readouterr().out
    assert line(printed, "memory: ").endswith("; this machine has 24.0 GB, room for 2 at a time")
    assert "(local, 2 at a time, 1 thread(s) each" in line(printed, "sweep custom: ")
    assert sweep.main([*argv, "--jobs", "4"]) == 0
    assert line(capsys.readouterr().out, "memory: ").endswith("; --jobs 4 x 11 GB is more than that")
    assert sweep.main([*argv, "--", "--frames", "2000", "--batch-size", "32"]) == 0  # small: cores bound it
    assert "(local, 8 at a time" in capsys.readouterr().out
    monkeypatch.setattr(sweep, "local_memory_gb", lambda: 6.0)
    assert sweep.main(argv) == 2
    assert capsys.readouterr().err.endswith("but this machine has 6.0 GB; --replay-size 96000 fits\n")
    assert sweep.main([*argv, "--", "--replay-size", "96000"]) == 0  # the hint fits
    assert line(capsys.readouterr().out, "memory: ").startswith("memory: 6 GB per job")


def test_a_job_requeued_at_its_time_limit_takes_its_own_lock_over_and_resumes(tmp_path, monkeypatch):
    """What a one-node cluster cannot show: the requeued job starts on another node while squeue still
    lists the job, so the old holder looks alive."""
    fake_slurm(tmp_path, monkeypatch)  # squeue: every job listed
    job, d = make_job(tmp_path)
    run = d / "run" / "walker-walk__drq__1__20260101-000000"
    run.mkdir(parents=True)
    (run / "snapshot.pt").write_bytes(b"stand-in")
    me = {**sweep.whoami(), "job": "4242_3", "cluster": "slurm"}
    monkeypatch.setattr(sweep, "whoami", lambda: me)
    sweep.write_json(str(d / "lock"), {"pid": 1, "host": "node-a", "job": "4242_7", "cluster": "slurm"})
    assert job().startswith("skipped: already running (pid 1 on node-a, slurm job 4242_7)")  # another job
    sweep.write_json(str(d / "lock"), {"pid": 1, "host": "node-a", "job": "4242_3", "cluster": "slurm"})
    again = job.checkpoint()  # what submitit calls at the time limit: the same call, requeued
    assert again.function is job and not again.args
    assert again.function() == "done"
    assert calls(tmp_path) == [["3", "--resume", str(run), "--device", "auto"]]


# ------------------------------------------------------------------------------- a real SLURM
# .ci/run brings up a one-node cluster (.ci/slurm_up.sh) and sets SEAR_REAL_SLURM=1: there this test
# must run. Elsewhere it is skipped: on a user's cluster its jobs could wait in a queue for hours.
REAL_SLURM = os.environ.get("SEAR_REAL_SLURM") == "1"


def slurm_answers() -> bool:
    if shutil.which("sinfo") is None or shutil.which("sbatch") is None:
        return False
    r = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True)
    return r.returncode == 0 and any(s.rstrip("*") in ("idle", "mixed", "allocated") for s in r.stdout.split())


def wait_for(what, test, seconds=600):
    deadline = time.time() + seconds
    while not test():
        assert time.time() < deadline, f"no {what} after {seconds} s"
        time.sleep(0.2)


def in_queue(job_id: str) -> bool:
    return bool(subprocess.run(["squeue", "-h", "-j", job_id], capture_output=True, text=True).stdout.strip())


@pytest.mark.skipif(not REAL_SLURM, reason="needs SEAR_REAL_SLURM=1 and a cluster up (.ci/slurm_up.sh)")
def test_real_slurm_sweep_cancelled_midway_resumes_and_then_submits_nothing(tmp_path, capsys):
    if not slurm_answers():
        pytest.fail("SEAR_REAL_SLURM=1 but SLURM does not answer (sinfo shows no idle node): run .ci/slurm_up.sh")
    out = tmp_path / "sweeps"
    folder = out / "real"
    # 300 frames: seconds between the first snapshot (frame 20) and the end, time enough to scancel.
    argv = ["--out", str(out), "--name", "real", "--envs", "walker-walk", "--methods", "drq", "--seeds", "1-2",
            "--engine", "slurm", "--threads", "1", "--mem-gb", "1", "--time-limit", "30",
            "--", *TINY, "--frames", "300", "--eval-every", "100"]
    assert sweep.main(argv) == 0
    printed = capsys.readouterr().out
    assert "engine: slurm (--engine slurm)\n" in printed  # never picked just because srun is on the PATH
    assert line(printed, "memory: ").startswith("memory: 1 GB per job (--mem-gb; the estimate is ")
    assert ("2 jobs (1 envs x 1 methods x 2 seeds): 0 done, 0 running elsewhere, 2 to run "
            "(slurm, no GPU, as the default partition has none)") in printed
    assert "submitted 2 jobs" in printed
    first, second = (next(folder.glob(f"walker-walk__drq__{seed}__*")) for seed in (1, 2))
    script = next((folder / ".submitit").glob("*_submission.sh")).read_text()
    assert "#SBATCH --array=0-1" in script and "--gpus" not in script  # the node has no GPU: none asked

    # Cancel the first job once it has written a snapshot.
    log = first / "stdout.log"  # the snapshot after its first updates (one at frame 0 comes first)
    wait_for("snapshot", lambda: log.exists() and "snapshot at frame 20\n" in log.read_text())
    job_id = sweep.read_json(str(first / "lock"))["job"]
    subprocess.run(["scancel", job_id], check=True)
    wait_for("end of the cancelled job", lambda: not in_queue(job_id))
    wait_for("second job", lambda: (second / "DONE").exists())
    assert not (first / "DONE").exists()
    assert sweep.main(["--out", str(out), "--name", "real", "--status"]) == 0
    states = {line.split()[0]: line.split()[1] for line in capsys.readouterr().out.splitlines()[1:-1]}
    assert states == {first.name: "interrupted", second.name: "done"}

    # The same sweep again: the cancelled job alone, resumed from its snapshot.
    assert sweep.main(argv) == 0
    printed = capsys.readouterr().out
    assert "1 done, 0 running elsewhere, 1 to run" in printed and "submitted 1 jobs" in printed
    wait_for("resumed job", lambda: (first / "DONE").exists())
    assert re.search(r"resumed at frame [1-9]\d*", (first / "stdout.log").read_text())
    assert attempts(first) == 2 and attempts(second) == 1
    for d in (first, second):
        (run,) = (d / "run").iterdir()
        assert column(run / "eval.csv", "frame") == [0, 100, 200, 300], d  # no evaluation twice
        frames = column(run / "train.csv", "frame")
        assert frames == sorted(set(frames)) and frames[-1] == 300, d

    # And again: everything is done, nothing is submitted.
    assert sweep.main(argv) == 0
    printed = capsys.readouterr().out
    assert "2 done, 0 running elsewhere, 0 to run" in printed and "submitted" not in printed


# ------------------------------------------------------------------------------- GPUs on this machine
RECORDS_ITS_GPUS = """import json, os, sys
with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "gpus.jsonl"), "a") as f:
    f.write(json.dumps([sys.argv[sys.argv.index("--env") + 1], os.environ.get("CUDA_VISIBLE_DEVICES")]) + "\\n")
"""


@pytest.mark.parametrize("visible, flag, expected", [
    (None, [], ["0", "1", "2"]),                      # one GPU per job, round robin
    ("4,6,7", [], ["4", "6", "7"]),                   # the GPUs this process was given, by their names
    (None, ["--gpus-per-job", "2"], ["0,1", "2,0", "1,2"]),
    (None, ["--gpus-per-job", "0"], ["", "", ""]),    # on the CPU
])
def test_local_jobs_get_their_own_gpus_round_robin(tmp_path, monkeypatch, capsys, visible, flag, expected):
    import torch
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 3)  # a machine with 3 GPUs
    if visible is None:
        monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    else:
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    fake = tmp_path / "fake_sear.py"
    fake.write_text(RECORDS_ITS_GPUS)
    monkeypatch.setattr(sweep, "SEAR_PY", str(fake))
    envs = ["walker-walk", "cup-catch", "cheetah-run"]
    assert sweep.main(["--out", str(tmp_path / "sweeps"), "--envs", *envs, "--methods", "drq", "--engine", "local",
                       "--jobs", "3", *flag, "--frames", "40"]) == 0
    got = dict(json.loads(line) for line in (tmp_path / "gpus.jsonl").read_text().splitlines())
    assert [got[e] for e in envs] == expected
    assert sweep.job_devices(1, ["0", "1"], 5) == ["0", "1", "0", "1", "0"]


def test_local_gpus_it_cannot_give_fail_up_front(tmp_path, monkeypatch, capsys):
    import torch
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    out = tmp_path / "sweeps"
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--engine", "local",
                       "--gpus-per-job", "1", "--frames", "40"]) == 2
    assert capsys.readouterr().err == ("sweep.py: error: --gpus-per-job 1: this machine has 0 GPU(s); "
                                       "--gpus-per-job 0 runs on the CPU\n")
    assert not out.exists()


STOPPED_BY_SIGTERM = """import os, signal
os.kill(os.getpid(), signal.SIGTERM)
"""


def test_a_run_stopped_by_sigterm_is_interrupted_not_failed(tmp_path):
    job, d = make_job(tmp_path)
    (tmp_path / "record.py").write_text(STOPPED_BY_SIGTERM)
    assert job() == "interrupted: stopped by SIGTERM (killed by signal 15); re-run the sweep to resume"
    assert sweep.job_state(str(d)) == ("interrupted", "stopped by SIGTERM (killed by signal 15); re-run the sweep "
                                                      "to resume")
    assert not (d / "DONE").exists()


# ------------------------------------------------------------------------------- seeds packed into one process
def dry_run(capsys, *argv):
    """The jobs a --dry-run prints, {name: sear.py command}, and all it printed."""
    printed = capsys.readouterr().out
    return {ln.split(": sear.py ")[0]: ln.split(": sear.py ")[1] for ln in printed.splitlines()
            if ": sear.py " in ln}, printed


def test_seeds_per_job_packs_each_tasks_and_methods_seeds_in_order(tmp_path, capsys):
    out = tmp_path / "sweeps"
    argv = ["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "drq+drm", "--seeds", "1-5",
            "--engine", "local", "--dry-run", "--", "--frames", "40"]
    assert sweep.main(["--seeds-per-job", "2", *argv]) == 0
    jobs, printed = dry_run(capsys)
    key = next(iter(jobs)).rsplit("__", 1)[1]
    drq = {n: c for n, c in jobs.items() if n.startswith("walker-walk__drq__")}
    assert drq == {f"walker-walk__drq__{name}__{key}":
                   f"--env walker-walk --method drq --drop-inapplicable {flag} --frames 40"
                   for name, flag in (("seeds1-2", "--seeds 1-2"), ("seeds3-4", "--seeds 3-4"), ("5", "--seed 5"))}
    drm = [n for n in jobs if "drq+drm" in n]  # --seeds takes every method, --drm too
    assert [n.split("__")[2] for n in drm] == ["seeds1-2", "seeds3-4", "5"] and all("--drm" in jobs[n] for n in drm)
    assert "10 to run in 6 processes (" in printed and "packing:" not in printed
    assert line(printed, "sweep custom: ").endswith("; 2 seeds per job (--seeds-per-job 2)")
    assert "x 2 seeds a job; --mem-gb sets it" in line(printed, "memory: ")
    assert not out.exists()

    # Without a GPU the default is one seed a job, as before.
    assert sweep.main(argv) == 0
    jobs, printed = dry_run(capsys)
    assert len(jobs) == 10 and all("--seed " in c for c in jobs.values())
    assert "1 seed per job (no GPU: one process per seed uses the cores as well; --seeds-per-job packs them)" \
        in line(printed, "sweep custom: ")

    # Run again: a seed that ran alone stays alone, a seed of a pack stays in it; only the others are packed.
    (out / "custom" / f"walker-walk__drq__1__{key}" / "run" / "a-single-run").mkdir(parents=True)
    for seed in (4, 5):
        (out / "custom" / f"walker-walk__drq__{seed}__{key}").mkdir()
        sweep.write_json(str(out / "custom" / f"walker-walk__drq__{seed}__{key}" / "pack.json"),
                         {"pack": f"walker-walk__drq__seeds4-5__{key}", "seeds": [4, 5], "seed": seed})
    assert sweep.main(["--seeds-per-job", "3", *argv]) == 0
    jobs, printed = dry_run(capsys)
    assert [n.split("__")[2] for n in jobs if n.startswith("walker-walk__drq__")] == ["1", "seeds2-3", "seeds4-5"]


def test_the_header_says_how_many_seeds_each_job_runs(tmp_path, monkeypatch, capsys):
    """The largest pack that runs, not the number asked for: 4 seeds make one pack of 4 whatever
    --seeds-per-job asks; curl packs as every method does; a pack this machine cannot hold is one line."""
    argv = ["--out", str(tmp_path / "sweeps"), "--envs", "walker-walk", "--seeds", "1-4", "--engine", "local",
            "--dry-run", "--frames", "40"]
    assert sweep.main([*argv, "--methods", "drq", "--seeds-per-job", "100000"]) == 0
    jobs, printed = dry_run(capsys)
    assert [n.split("__")[2] for n in jobs] == ["seeds1-4"]
    assert line(printed, "sweep custom: ").endswith(
        "no GPU); 4 seeds per job (--seeds-per-job 100000; at most 4 seeds of a task and method to run)")
    assert sweep.main([*argv, "--methods", "curl", "--seeds-per-job", "2"]) == 0
    jobs, printed = dry_run(capsys)
    assert [n.split("__")[2] for n in jobs] == ["seeds1-2", "seeds3-4"] and "packing:" not in printed
    assert line(printed, "sweep custom: ").endswith("no GPU); 2 seeds per job (--seeds-per-job 2)")
    from harness import group
    monkeypatch.setattr(group, "PEAK_BYTES_PER_SEED", 1e15)  # a machine that holds one seed at a time
    assert sweep.main([*argv, "--methods", "drq", "--seeds-per-job", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sweep.py: error: walker-walk__drq__seeds1-2__") and "--seeds: 2 seeds do not fit" in err
    assert err.count("\n") == 1


def test_the_default_seeds_per_job_comes_from_the_gpus_memory_here_and_is_4_on_slurm(tmp_path, monkeypatch, capsys):
    import types
    import torch
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)  # one 40 GB GPU
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda i: types.SimpleNamespace(total_memory=40 * 2**30))
    monkeypatch.setattr(sweep, "local_memory_gb", lambda: 256.0)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    argv = ["--out", str(tmp_path / "sweeps"), "--envs", "walker-walk", "--methods", "sear", "--seeds", "1-5",
            "--dry-run"]
    assert sweep.main([*argv, "--engine", "local"]) == 0  # a default run: 8.2 GB + 25% a seed
    jobs, printed = dry_run(capsys)
    assert [n.split("__")[2] for n in jobs] == ["seeds1-3", "seeds4-5"]
    assert line(printed, "sweep custom: ").endswith(
        "; 3 seeds per job (as many as a GPU's 40 GB and this machine's 256 GB hold at 10.3 GB a seed, at most 16; "
        "--seeds-per-job sets it)")
    assert "(local, 1 at a time" in printed  # the packed job fills its GPU
    assert line(printed, "memory: ").startswith("memory: 31 GB per job")

    fake_slurm(tmp_path, monkeypatch)  # GPUs whose memory the submitting machine cannot see
    assert sweep.main([*argv, "--engine", "slurm"]) == 0
    jobs, printed = dry_run(capsys)
    assert [n.split("__")[2] for n in jobs] == ["seeds1-4", "5"]
    assert line(printed, "sweep custom: ").endswith(
        "; 4 seeds per job (the GPUs' memory is not visible at submission, so a conservative default; "
        "--seeds-per-job sets it)")
    (tmp_path / "small").mkdir()
    fake_slurm(tmp_path / "small", monkeypatch, sinfo="gpu*|gpu:1|8|32000\n")  # nodes of 31 GB: 3 seeds
    assert sweep.main([*argv, "--engine", "slurm", "--name", "small"]) == 0
    jobs, printed = dry_run(capsys)
    assert [n.split("__")[2] for n in jobs] == ["seeds1-3", "seeds4-5"]
    assert "; a node of the default partition holds 3 at 10.3 GB a seed;" in line(printed, "sweep small: ")


def packed_args(out, *extra):
    return ["--envs", "walker-walk", "--methods", "drq", "--seeds", "1-2", "--out", str(out), "--engine", "local",
            *extra, "--", *TINY]


def sear_pid(marker: str) -> int | None:
    """The pid of the sear.py process whose command line holds `marker`."""
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmd = (Path("/proc") / pid / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(part.endswith(b"sear.py") for part in cmd) and marker.encode() in b" ".join(cmd):
            return int(pid)
    return None


def test_a_packed_sweep_stopped_by_sigterm_resumes_its_group_and_finishes(tmp_path, capsys):
    """Two seeds in one process; SIGTERM after their first snapshots: both seeds interrupted; the sweep
    run again (now without --seeds-per-job) resumes the group folder; --status and --report read each
    seed's run; a third run has nothing to do."""
    out = tmp_path / "sweeps"
    folder = out / "custom"
    with sweep_process(tmp_path, packed_args(out, "--seeds-per-job", "2")) as p:
        wait_for_files(p, folder, "*__seeds1-2__*/run/*/*/snapshot.pt", count=2)
        # the group stops at its next episode end, every seed's snapshot kept
        os.kill(sear_pid("--seeds 1-2 --frames 60"), signal.SIGTERM)
        assert p.wait(timeout=120) == 1
    assert "0 of 2 jobs finished; 2 failed" in (tmp_path / "first.log").read_text()
    assert sweep.main(["--out", str(out), "--status"]) == 0
    rows = [re.split(r"\s{2,}", ln) for ln in capsys.readouterr().out.splitlines()[1:-1]]
    assert [(r[0].split("__")[2], r[1], r[3].split(" (")[0]) for r in rows] == [
        ("1", "interrupted", "stopped by SIGTERM"), ("2", "interrupted", "stopped by SIGTERM")]

    assert sweep.main(packed_args(out)) == 0
    printed = capsys.readouterr().out
    assert "0 done, 0 running elsewhere, 2 to run in 1 process (" in printed and "\n2 of 2 jobs finished\n" in printed
    (pack,) = folder.glob("walker-walk__drq__seeds1-2__*")
    (group,) = (pack / "run").iterdir()
    assert f"--resume {group} " in (pack / "stdout.log").read_text().split("=== attempt 2 ")[1].splitlines()[0]
    for seed in (1, 2):
        (d,) = folder.glob(f"walker-walk__drq__{seed}__*")
        (run,) = sweep.run_dirs(str(d))
        assert Path(run).parent == group and (d / "DONE").exists()
        frames = column(Path(run) / "eval.csv", "frame")  # an evaluation SIGTERM cut short is redone later
        assert frames == sorted(set(frames)) and frames[0] == 0 and frames[-1] == 60  # none twice
        assert json.loads((d / "pack.json").read_text()) == {"pack": pack.name, "seeds": [1, 2], "seed": seed}
    assert "| drq | 2 seeds x 1 task | 60 |" in (folder / "report.md").read_text()
    assert sweep.main(["--out", str(out), "--status"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[-1] == "2 jobs: 2 done" and all(" 60/60" in ln for ln in table[1:-1])
    assert sweep.main(["--out", str(out), "--report"]) == 0
    assert "2 of 2 jobs finished" in capsys.readouterr().out
    assert sweep.main(packed_args(out, "--seeds-per-job", "2")) == 0
    assert "2 done, 0 running elsewhere, 0 to run" in capsys.readouterr().out
    assert attempts(pack) == 2


def test_a_pack_takes_every_seeds_lock_and_writes_every_seeds_status(tmp_path):
    script = tmp_path / "record.py"
    script.write_text(RECORDS_ITS_ARGS)
    sweep_dir = tmp_path / "sweeps" / "s"
    seeds = [sweep_dir / f"walker-walk__drq__{k}__abcd1234" for k in (1, 2)]
    pack = sweep_dir / "walker-walk__drq__seeds1-2__abcd1234"
    for d in (*seeds, pack):
        d.mkdir(parents=True)
    job = sweep.SearJob(str(pack), ["--env", "walker-walk", "--seeds", "1-2"], ["--device", "auto"], 3,
                        script=str(script), seed_dirs=[str(d) for d in seeds])
    sweep.write_json(str(seeds[1] / "lock"), sweep.whoami())  # seed 2 runs elsewhere
    assert job().startswith(f"skipped: already running (pid {os.getpid()} on ")
    assert not (seeds[0] / "lock").exists() and calls(tmp_path) == []  # seed 1's lock given back
    (seeds[1] / "lock").unlink()

    group = pack / "run" / "walker-walk__drq__seeds1-2__20260101-000000"  # died before its snapshots
    (group / "walker-walk__drq__1__x").mkdir(parents=True)
    sweep.write_json(str(group / "group.json"), {"seeds": [1, 2], "runs": {"1": "walker-walk__drq__1__x"}})
    assert job() == "done"
    assert calls(tmp_path) == [["3", "--env", "walker-walk", "--seeds", "1-2", "--run-root", str(pack / "run")]]
    assert (tmp_path / "sweeps" / "s.aside" / pack.name / group.name / "group.json").exists() and not group.exists()
    assert all((d / "DONE").exists() and sweep.job_state(str(d)) == ("done", "") for d in seeds)
    assert not any((d / "lock").exists() for d in seeds)

    for d in seeds:
        (d / "DONE").unlink()
    script.write_text(FAILS_ON_CUP.replace('"cup-catch" in sys.argv', "True"))
    assert job() == "failed: exit code 1: RuntimeError: the simulator exploded"
    assert {sweep.job_state(str(d)) for d in (*seeds, pack)} == {
        ("failed", "exit code 1: RuntimeError: the simulator exploded")}


# ------------------------------------------------------------------------------- report
def fake_finished_runs(out, tasks, seeds=(1, 2, 3, 4), finished=(1, 2, 3), config=None):
    """Sweep job folders with one run each; tasks = {env: (eval.csv header, row(seed) -> list of rows)}."""
    specs = []
    for env, (header, rows) in tasks.items():
        for seed in seeds:
            spec = sweep.JobSpec("g", env, "sear", seed, "k", 10, (), ())
            specs.append(spec)
            run = out / "g" / spec.name / "run" / "r"
            run.mkdir(parents=True)
            (run / "config.json").write_text(json.dumps({"env": env, "method": "sear", "seed": seed,
                                                         "action_repeat": 2, "max_episode_steps": 0, **(config or {})}))
            (run / "eval.csv").write_text(header + "\n" + "".join(f"{r}\n" for r in rows(seed)))
            if seed in finished:  # the others are still running: left out
                (out / "g" / spec.name / "DONE").write_text("")
    return specs


def iqm(values):
    from rliable import metrics
    return metrics.aggregate_iqm(np.array(values)[None])


def aggregate_row(table, method):
    """(IQM, its CI, mean, its CI) of a method in the report's across-task table."""
    row = next(line for line in table.splitlines() if line.startswith(f"| {method} | ") and "[" in line)
    numbers = [float(x) for x in re.findall(r"-?\d+\.\d+", row.split(" | ", 3)[3])]
    return numbers[0], numbers[1:3], numbers[3], numbers[4:6]


def test_report_success_rates_per_task_and_rliable_over_tasks(tmp_path):
    out = tmp_path / "sweeps"
    specs = fake_finished_runs(out, {
        "metaworld-hammer": ("frame,return,success", lambda s: ["0,0,0", f"10,1,{0.1 * s}"]),
        "metaworld-door-open": ("frame,return,success", lambda s: ["0,0,0", f"10,1,{0.3 * s}"])})
    table = sweep.report(str(out), "g", specs, None)
    # per task: the mean over seeds 1-3 (seed 4 unfinished), its percentile-bootstrap CI: with 3 seeds, a
    # resample of one seed thrice has a chance of 1/27 > 2.5%, so the CI is the lowest and highest seed
    assert "| metaworld-hammer | sear | 3 | 10 | 0.2 [0.1, 0.3] |" in table
    # over the tasks: the 6 final success rates 0.1 0.2 0.3 | 0.3 0.6 0.9, as they are
    point, ci, mean, mean_ci = aggregate_row(table, "sear")
    assert point == pytest.approx(iqm([0.1, 0.2, 0.3, 0.3, 0.6, 0.9]), abs=5e-4) and point == pytest.approx(0.35)
    assert mean == pytest.approx(0.4, abs=5e-4)
    assert ci[0] < point < ci[1] and mean_ci[0] < mean < mean_ci[1]
    # stratified: seeds are resampled within each task, so the mean's CI stays inside what 3 draws per task allow
    assert mean_ci[0] >= (0.1 + 0.3) / 2 - 1e-9 and mean_ci[1] <= (0.3 + 0.9) / 2 + 1e-9
    assert "| sear | 3 seeds x 2 tasks | 10 |" in table
    assert "| metaworld-hammer | success rate, as it is |" in table
    md = (out / "g" / "report.md").read_text()
    assert "6 of 8 jobs finished" in md and "stratified-bootstrap" in md and "rliable" in md
    assert (out / "g" / "report.png").exists()


def test_report_figure_says_what_each_panel_shows_and_its_titles_fit(tmp_path, monkeypatch):
    """Per task a mean with its t-interval on the raw scores, over the tasks the IQM of normalised scores
    with its bootstrap CI: each panel's title and y-label say which, and every title lies inside the figure
    (with 2 tasks the aggregate panel is the third, at the figure's right edge)."""
    import matplotlib.figure
    saved = []
    real = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda fig, *a, **k: (real(fig, *a, **k), saved.append((fig, fig.canvas.get_renderer()))))
    out = tmp_path / "sweeps"
    specs = fake_finished_runs(out, {
        "metaworld-button-press-topdown-wall": ("frame,return,success", lambda s: ["0,0,0", f"10,1,{0.1 * s}"]),
        "metaworld-door-open": ("frame,return,success", lambda s: ["0,0,0", f"10,1,{0.3 * s}"])})
    sweep.report(str(out), "a-sweep-with-a-long-name", specs, None)
    ((fig, renderer),) = saved
    panels = {ax.get_title().split("\n")[0]: ax for ax in fig.axes if ax.get_lines()}
    assert list(panels) == ["metaworld-button-press-topdown-wall", "metaworld-door-open", "over 2 tasks"]
    for name in ("metaworld-button-press-topdown-wall", "metaworld-door-open"):
        assert panels[name].get_ylabel() == "eval success rate"
        assert "mean ± 95% CI" in panels[name].get_title()
    assert panels["over 2 tasks"].get_ylabel() == "IQM of normalised score"
    assert "IQM" in panels["over 2 tasks"].get_title() and "bootstrap 95% CI" in panels["over 2 tasks"].get_title()
    titles = [ax.title for ax in panels.values()] + [fig._suptitle]
    for title in titles:
        box = title.get_window_extent(renderer)
        assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1 and box.y1 <= fig.bbox.y1, title.get_text()
    for ax in panels.values():  # and no title runs over its neighbour's
        box, axes_box = ax.title.get_window_extent(renderer), ax.get_window_extent(renderer)
        assert box.x0 >= axes_box.x0 - 1 and box.x1 <= axes_box.x1 + 1, ax.get_title()
    legend = fig.legends[0] if fig.legends else next(ax.get_legend() for ax in fig.axes if ax.get_legend())
    assert [t.get_text() for t in legend.get_texts()] == ["sear (n=3)"]


def test_report_normalises_returns_by_the_tasks_max_or_min_max(tmp_path):
    out = tmp_path / "sweeps"
    specs = fake_finished_runs(out, {
        "walker-walk": ("frame,return", lambda s: ["0,0", f"10,{100 * s}"]),           # dm_control: / 1000
        "metaworld-hammer": ("frame,return", lambda s: [f"0,{-50 * s}", f"10,{500 * s}"])})  # min-max: -150..1500
    table = sweep.report(str(out), "g", specs, None)
    assert "| walker-walk | return / 1000 (dm_control's maximum: 1 per control step) |" in table
    assert "| metaworld-hammer | min-max over this sweep: (return - -150) / (1500 - -150) |" in table
    scores = [0.1, 0.2, 0.3, *((500 * s + 150) / 1650 for s in (1, 2, 3))]
    point, _, mean, _ = aggregate_row(table, "sear")
    assert point == pytest.approx(iqm(scores), abs=5e-4) and mean == pytest.approx(np.mean(scores), abs=5e-4)
    assert sweep.dm_control_max({"max_episode_steps": 10, "action_repeat": 2}) == 20
    assert sweep.dm_control_max({"max_episode_steps": 0, "action_repeat": 8}) == 1000


# ------------------------------------------------------------------------------- finding a sweep from its folder
FINISHES = """import json, os, sys
a = sys.argv[1:]
root, env, method, seed = (a[a.index(f) + 1] for f in ("--run-root", "--env", "--method", "--seed"))
run = os.path.join(root, f"{env}__{method}__{seed}__x")
os.makedirs(run)
with open(os.path.join(run, "config.json"), "w") as f:
    json.dump({"env": env, "method": method, "seed": int(seed), "action_repeat": 2}, f)
with open(os.path.join(run, "eval.csv"), "w") as f:
    f.write("frame,return\\n0,1\\n40,%d\\n" % (10 * int(seed)))
"""


@pytest.fixture
def finished_sweep(tmp_path, monkeypatch, capsys):
    """A sweep of 2 envs x 2 methods x 2 seeds with trailing sear.py flags, run to the end by a stand-in
    sear.py; -> (its --out, the sweep.py arguments without those flags, the flags)."""
    fake = tmp_path / "fake_sear.py"
    fake.write_text(FINISHES)
    monkeypatch.setattr(sweep, "SEAR_PY", str(fake))
    out = tmp_path / "sweeps"
    args = ["--out", str(out), "--envs", "walker-walk", "cup-catch", "--methods", "drq", "sear", "--seeds", "1-2"]
    flags = ["--frames", "40", "--batch-size", "8"]
    assert sweep.main([*args, "--engine", "local", "--jobs", "2", "--", *flags]) == 0
    assert "8 of 8 jobs finished" in capsys.readouterr().out
    return out, args, flags


def test_status_and_report_find_a_sweeps_runs_without_its_flags(finished_sweep, capsys):
    out, args, flags = finished_sweep
    for argv in (args, ["--out", str(out)], [*args, "--", *flags], ["--out", str(out), "--", "--frames=40",
                 "--batch-size=8"], [*args, "--", "--batch-size=8", "--frames=40"]):  # any spelling, any order
        assert sweep.main(["--status", *argv]) == 0, argv
        assert capsys.readouterr().out.splitlines()[-1] == "8 jobs: 8 done", argv
    record = json.loads((out / "custom" / "sweep.json").read_text())
    assert [(e["grid"], e["flags"], len(e["jobs"])) for e in record["sweeps"]] == [(None, flags, 8)]
    assert sweep.main([*args, "--methods", "sear", "--seeds", "2", "--status"]) == 0  # a subset of the record
    assert capsys.readouterr().out.splitlines()[-1] == "2 jobs: 2 done"
    (out / "custom" / "report.md").unlink()
    assert sweep.main([*args, "--report"]) == 0
    assert "8 of 8 jobs finished" in capsys.readouterr().out and (out / "custom" / "report.md").exists()


def test_status_and_report_work_inside_the_sweeps_folder(finished_sweep, monkeypatch, capsys):
    out, args, flags = finished_sweep
    monkeypatch.chdir(out / "custom")
    for argv in (["--status"], ["--methods", "sear", "--status"], ["--status", "--", *flags]):
        assert sweep.main(argv) == 0, argv
        assert capsys.readouterr().out.splitlines()[-1] == f"{8 if argv[0] != '--methods' else 4} jobs: " \
               f"{8 if argv[0] != '--methods' else 4} done", argv
    (out / "custom" / "report.md").unlink()
    assert sweep.main(["--report"]) == 0 and (out / "custom" / "report.md").exists()
    capsys.readouterr()
    (out / "custom" / "sweep.json").unlink()  # a folder from before the record: its jobs
    assert sweep.main(["--status"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "8 jobs: 8 done"
    monkeypatch.chdir(out.parent)  # and from elsewhere, with --out and --name
    assert sweep.main(["--out", str(out), "--name", "custom", "--status"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "8 jobs: 8 done"


def test_flags_that_disagree_with_the_record_are_one_line_naming_the_sweep(finished_sweep, capsys):
    out, args, flags = finished_sweep
    assert sweep.main([*args, "--status", "--", "--frames", "80"]) == 2
    err = capsys.readouterr().err
    shown = f"python sweep.py --out {out} --status -- --frames 40 --batch-size 8 (8 jobs)"
    assert err == f"sweep.py: error: {out / 'custom'} holds no sweep run with `-- --frames 80`; it holds: {shown}\n"
    assert sweep.main([*args, "--grid", "kitchen", "--name", "custom", "--report"]) == 2
    assert "holds no sweep of grid kitchen" in capsys.readouterr().err


def test_a_folder_with_several_sweeps_names_the_command_that_shows_each(finished_sweep, capsys):
    out, args, flags = finished_sweep
    assert sweep.main(["--out", str(out), "--envs", "walker-walk", "--methods", "drq", "--engine", "local",
                       "--", "--frames", "20"]) == 0
    assert f"note: {out / 'custom'} now holds 2 sweeps" in capsys.readouterr().out
    assert sweep.main(["--out", str(out), "--report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"sweep.py: error: {out / 'custom'} holds 2 sweeps, show one: ")
    commands = re.findall(r"(python sweep.py [^(;]*) \(", err)
    assert commands == [f"python sweep.py --out {out} --report -- --frames 40 --batch-size 8",
                        f"python sweep.py --out {out} --report -- --frames 20"]
    for command, jobs in zip(commands, (8, 1)):
        assert sweep.main([a.replace("--report", "--status") for a in shlex.split(command)[2:]]) == 0, command
        assert capsys.readouterr().out.splitlines()[-1] == f"{jobs} jobs: {jobs} done"
    # One run without sear.py flags: no flags pick it, and the line says what else the folder holds.
    assert sweep.main(["--out", str(out), "--envs", "cup-catch", "--methods", "sear", "--engine", "local"]) == 0
    capsys.readouterr()
    assert sweep.main(["--out", str(out), "--status"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith(f"note: {out / 'custom'} also holds: python sweep.py --out {out} --status "
                                 f"-- --frames 40")
    assert printed[-1] == "1 jobs: 1 done" and printed[-2].startswith("cup-catch__sear__1__")


def test_an_old_sweep_folder_without_the_record_shows_the_jobs_its_folders_hold(finished_sweep, capsys):
    """A sweep folder from before sweep.json: its jobs are those its job folders' job.json name (its
    flags, kept nowhere else, cannot pick among them); --envs, --methods and --seeds pick a subset, and
    one it does not hold is one line naming what it holds."""
    out, args, flags = finished_sweep
    (out / "custom" / "sweep.json").unlink(missing_ok=True)  # as sweep folders were before sweep.py kept it
    for argv in (["--out", str(out)], args, [*args, "--", *flags]):
        assert sweep.main(["--status", *argv]) == 0
        assert capsys.readouterr().out.splitlines()[-1] == "8 jobs: 8 done"
    assert sweep.main(["--out", str(out), "--methods", "sear", "--seeds", "2", "--status"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "2 jobs: 2 done"
    assert sweep.main(["--out", str(out), "--envs", "cheetah-run", "--status"]) == 2
    assert capsys.readouterr().err == (
        f"sweep.py: error: the sweep in {out / 'custom'} has none of these jobs: it has envs cup-catch, "
        "walker-walk; methods drq, sear; seeds 1, 2\n")
    assert sweep.main(["--out", str(out), "--grid", "kitchen", "--status"]) == 2  # never run: nothing to show
    assert capsys.readouterr().err == (f"sweep.py: error: no sweep in {out / 'kitchen'}; {out} holds custom: "
                                       f"python sweep.py --out {out} --status\n")


def test_every_grid_has_its_row_in_the_docs_table():
    """docs/sweeps.md's grid table names every --grid, its methods and its seeds."""
    table = (ROOT / "docs" / "sweeps.md").read_text().split("## The grids", 1)[1].split("\n\n", 2)[1]
    rows = {line.split("|")[1].strip(" `"): line for line in table.splitlines()[2:]}
    assert set(rows) == set(sweep.GRIDS), set(rows) ^ set(sweep.GRIDS)
    for name in sweep.GRIDS:
        _, specs, _ = plan(["--grid", name])
        assert f"{len({s.seed for s in specs})} ×" in rows[name], name
        methods = {s.variant.split("-")[0] for s in specs}
        assert all(m in rows[name] for m in methods) or "variants" in rows[name], name
