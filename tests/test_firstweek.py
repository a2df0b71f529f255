"""A researcher's first week, at the command line: one owner per run directory, storage
errors in one line, SIGTERM, resume and mask-model inputs, --evaluate, misspelled flags and start-up
warnings. Every test drives `python sear.py ...` (tiny budgets, CPU) and looks only at what a user
sees: exit codes, stderr, the files of the run directory."""
import csv
import hashlib
import json
import os
import queue
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--frames", "48", "--seed-frames", "12", "--batch-size", "4", "--eval-every", "24",
        "--eval-episodes", "1", "--max-episode-steps", "8", "--replay-size", "400",
        "--latent-dim", "64", "--hidden-dim", "32", "--render-quality", "fast", "--threads", "1"]
# 40-step episodes (80 frames), evaluations only at frame 0: a signal sent at step 3 lands mid-episode.
LONG_EPISODES = [*TINY, "--frames", "100000", "--max-episode-steps", "40", "--log-every", "0",
                 "--eval-every", "100000"]
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}


def run(args, cwd, timeout=600, **kwargs):
    return subprocess.run([sys.executable, str(ROOT / "sear.py"), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=ENV, **kwargs)


def one_line(r):
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    return lines[0]


def tree_digest(path):
    h = hashlib.sha256()
    for p in sorted(Path(path).rglob("*")):
        h.update(str(p.relative_to(path)).encode() + (p.read_bytes() if p.is_file() else b"/"))
    return h.hexdigest()


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def snapshot_step(run_dir):
    import torch
    return torch.load(Path(run_dir) / "snapshot.pt", weights_only=False)["counters"]["step"]


def only_dir(folder):
    dirs = sorted(Path(folder).iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


class Live:
    """A sear.py process whose stdout and stderr lines are read as they come."""

    def __init__(self, args, cwd):
        self.p = subprocess.Popen([sys.executable, str(ROOT / "sear.py"), *map(str, args)], cwd=cwd, env=ENV,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines, self.out, self.err = queue.Queue(), [], []
        for stream, seen in ((self.p.stdout, self.out), (self.p.stderr, self.err)):
            threading.Thread(target=self._read, args=(stream, seen), daemon=True).start()

    def _read(self, stream, seen):
        for line in stream:
            seen.append(line)
            self.lines.put(line)

    def wait_for(self, pattern, timeout=300):
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                line = self.lines.get(timeout=1)
            except queue.Empty:
                assert self.p.poll() is None, "".join(self.out[-20:] + self.err[-20:])
                continue
            if re.search(pattern, line):
                return line
        raise AssertionError(f"no line matching {pattern!r}: " + "".join(self.out[-20:] + self.err[-20:]))

    def finish(self, timeout=300):
        self.p.wait(timeout=timeout)
        time.sleep(0.2)  # the reader threads' last lines
        return self.p.returncode, "".join(self.out), "".join(self.err)

    def kill(self):
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()


def sigterm_when(args, cwd, pattern):
    """sear.py ARGS, sent one SIGTERM once a line matches `pattern`: (exit code, stdout, stderr)."""
    p = Live(args, cwd)
    try:
        p.wait_for(pattern)
        p.p.send_signal(signal.SIGTERM)
        return p.finish()
    finally:
        p.kill()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished tiny walker run (snapshot at frame 48, evaluations at 0, 24, 48); tests copy it."""
    root = tmp_path_factory.mktemp("finished")
    r = run(["--run-root", root / "runs", "--env", "walker-walk", *TINY], root)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "warning" not in r.stderr  # a sound config starts without warnings
    return only_dir(root / "runs")


@pytest.fixture
def a_run(finished_run, tmp_path):
    copy = tmp_path / "runs" / finished_run.name
    shutil.copytree(finished_run, copy)
    return copy


# ----------------------------------------------------------------------------- one owner per run dir
def test_a_run_directory_has_one_owner_and_a_dead_owner_never_blocks(tmp_path):
    first = Live(["--run-root", tmp_path / "runs", "--env", "walker-walk", *LONG_EPISODES, "--snapshot-minutes", "0"],
                 tmp_path)
    try:
        run_dir = Path(first.wait_for(r"^run dir: ").split(": ", 1)[1].strip())
        run_dir = run_dir if run_dir.is_absolute() else tmp_path / run_dir
        os.kill(first.p.pid, signal.SIGSTOP)
        r = run(["--resume", run_dir, "--frames", "96"], tmp_path)  # not "stopped before its first snapshot"
        assert r.returncode == 2 and one_line(r) == (f"sear.py: error: --resume: '{run_dir}' is in use by sear.py "
                                                     f"process {first.p.pid}, which has not written its first "
                                                     f"snapshot yet"), r.stderr
        os.kill(first.p.pid, signal.SIGCONT)
        first.wait_for(r"^snapshot at frame 80")
        os.kill(first.p.pid, signal.SIGSTOP)  # holds still (and holds its lock) while we look
        before = tree_digest(run_dir)
        r = run(["--resume", run_dir, "--frames", "96"], tmp_path)
        assert r.returncode == 2 and f"in use by sear.py process {first.p.pid}" in one_line(r), r.stderr
        assert tree_digest(run_dir) == before  # no rows, no snapshot, no side files
        os.kill(first.p.pid, signal.SIGKILL)  # dies holding the lock: the kernel releases it
    finally:
        first.kill()

    second = Live(["--resume", run_dir], tmp_path)  # the dead owner's lock file does not block
    try:
        second.wait_for(r"^resumed at frame 80")
        os.kill(second.p.pid, signal.SIGSTOP)
        before = tree_digest(run_dir)
        r = run(["--resume", run_dir, "--frames", "96"], tmp_path)  # --resume takes the lock too
        assert r.returncode == 2 and f"in use by sear.py process {second.p.pid}" in one_line(r), r.stderr
        assert tree_digest(run_dir) == before
    finally:
        second.kill()
    r = run(["--resume", run_dir, "--frames", "96"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]


# ------------------------------------------------------------------------------------------ SIGTERM
def test_sigterm_stops_at_the_next_episode_end_with_a_snapshot_and_exit_143(tmp_path):
    code, out, err = sigterm_when(["--run-root", tmp_path / "runs", "--env", "walker-walk", *LONG_EPISODES], tmp_path,
                                  r"\| ep 0 step 3$")
    run_dir = only_dir(tmp_path / "runs")
    assert code == 143, err
    assert err.strip().splitlines()[-1] == (f"sear.py: stopped by SIGTERM at frame 80 (between episodes): snapshot.pt "
                                            f"holds this frame; continue with: python sear.py --resume {run_dir}")
    assert "Traceback" not in err and snapshot_step(run_dir) == 40  # the episode was finished first

    # A second SIGTERM does not wait: the run stops at once, and the last snapshot stands.
    p = Live(["--resume", run_dir], tmp_path)
    try:
        p.wait_for(r"\| ep 1 step 3$")
        p.p.send_signal(signal.SIGTERM)
        p.wait_for(r"SIGTERM")
        p.p.send_signal(signal.SIGTERM)
        code, out, err = p.finish()
    finally:
        p.kill()
    assert code == 143, err
    assert re.fullmatch(r"sear.py: stopped by SIGTERM at frame \d+ \(mid-episode\): the last snapshot \(frame 80\) "
                        r"stands, the \d+ frames after it will be re-run; continue with: python sear.py --resume "
                        + re.escape(str(run_dir)), err.strip().splitlines()[-1]), err
    assert snapshot_step(run_dir) == 40


def test_sigterm_during_an_evaluation_stops_at_its_episode_end_and_the_resumed_run_evaluates_again(tmp_path):
    """The frame-0 evaluation of 3 episodes of 40 steps: a SIGTERM in its first episode stops the run
    when that episode ends (not after the evaluation and the training episode that follows), with a
    snapshot of frame 0 and no eval.csv row; the resumed run evaluates at frame 0 again."""
    code, out, err = sigterm_when(["--run-root", tmp_path / "runs", "--env", "walker-walk", *LONG_EPISODES,
                                   "--eval-episodes", "3"], tmp_path, r"\| eval 1/3 step 3 ")
    run_dir = only_dir(tmp_path / "runs")
    assert code == 143, err
    assert "eval 2/3" not in out and "| ep 0 step" not in out, out[-3000:]
    assert re.search(r"^evaluation at frame 0 stopped by SIGTERM after 1 of 3 episodes: no eval.csv row; a resume "
                     r"evaluates again$", out, re.M), out[-3000:]
    assert err.strip().splitlines()[-1] == (
        f"sear.py: stopped by SIGTERM at frame 0 (between episodes; its evaluation stopped after 1 of 3 episodes, "
        f"redone on resume): snapshot.pt holds this frame; continue with: python sear.py --resume {run_dir}")
    assert snapshot_step(run_dir) == 0
    assert not (run_dir / "eval.csv").exists() or rows(run_dir / "eval.csv") == []
    from harness import cli
    if hasattr(cli.TermSignal(), "waits_for"):  # cli.TermSignal prints what the run says it waits for
        line = next(line for line in err.splitlines() if line.startswith("sear.py: SIGTERM: "))
        assert re.fullmatch(r"sear.py: SIGTERM: stopping at the end of this evaluation episode \(not timed yet: the "
                            r"first of this process, at step \d+ after \d+s\), with a snapshot; the evaluation is "
                            r"redone on resume; another SIGTERM stops at once", line), line

    r = run(["--resume", run_dir, "--frames", "80"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "evaluating at frame 0 (3 episodes): the untrained policy, before any update" in r.stdout, r.stdout
    assert [row["frame"] for row in rows(run_dir / "eval.csv")] == ["0", "80"]
    assert not list(run_dir.glob("eval.after_snapshot_*.csv"))


def test_the_sigterm_line_says_what_it_waits_for_and_how_long_at_most_as_measured():
    """cli.TermSignal's line asks the run dir (cli.TERM.waits_for, set for the time of its block)."""
    import types
    from harness import cli
    from harness import experiment
    cfg = types.SimpleNamespace(frames=100_000, eval_every=10_000, discount=0.99, action_repeat=2)
    run = types.SimpleNamespace(resume="", log_every=0)
    with experiment.RunDir(cfg, run) as rundir:
        assert cli.TERM.waits_for == rundir.waits_for and rundir.waits_for().startswith("the end of the start-up")
    assert cli.TERM.waits_for is None

    console = experiment.Console(cfg, run, None)
    assert console.waits_for(0, False) == ("the next episode end (at most one episode, not timed yet in this "
                                           "process), with a snapshot")
    console.start_eval(0, 10, "the untrained policy")
    assert re.fullmatch(r"the end of this evaluation episode \(not timed yet: the first of this process, at step 0 "
                        r"after 0s\), with a snapshot; the evaluation is redone on resume", console.waits_for(0, False))
    # A snapshot's longest episodes: 1000 frames in 250.2 s; an evaluation episode of 61.3 s.
    console = experiment.Console(cfg, run, {"episode_frames": 1000, "episode_seconds": 250.2,
                                            "eval_episode_seconds": 61.3})
    assert console.waits_for(4000, True) == ("the next episode end (at most one episode: ~4m 11s, measured), with a "
                                             "snapshot")
    console.progress.saved["learning_fps"] = 2.0  # 1000 frames at 2 frames/s with updates
    assert "(at most one episode: ~8m 20s, measured)" in console.waits_for(4000, True)
    console.start_eval(10_000, 10, "")
    assert console.waits_for(10_000, False) == ("the end of this evaluation episode (at most ~1m 02s, measured), with "
                                                "a snapshot; the evaluation is redone on resume")
    assert console.waits_for(10_100, True) == (
        "the end of this evaluation episode (at most ~1m 02s, measured), then the end of the training episode "
        "under way (at most one episode: ~8m 20s, measured), with a snapshot; the evaluation is redone on resume")


def test_a_second_sigterm_stops_a_run_inside_one_long_native_call_within_seconds(tmp_path):
    """Python runs a signal handler between bytecodes only: a run inside one long torch call (here a
    deliberately long eigvals; --threads 64 on 2 cores sat in nn.init.orthogonal_) ignored both
    SIGTERMs until the call ended. The second now ends it within cli.TermSignal.GRACE (5 s), in one
    line, exit 143; the run had no snapshot, so its directory goes."""
    script = tmp_path / "stuck.py"
    script.write_text("import sys, torch, sear, train\n"
                      "real = sear.Agent.__init__\n"
                      "def stuck(self, *args):\n"
                      "    print('busy', flush=True)\n"
                      "    torch.linalg.eigvals(torch.randn(6000, 6000))  # one call of a minute or more\n"
                      "    real(self, *args)\n"
                      "sear.Agent.__init__ = stuck\n"
                      "sys.exit(train.main(sys.argv[1:]))\n")
    p = subprocess.Popen([sys.executable, str(script), "--run-root", str(tmp_path / "runs"), "--env", "walker-walk",
                          *TINY], cwd=tmp_path, env={**ENV, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        out = []
        while "busy" not in (line := p.stdout.readline()):
            assert line, "".join(out)
            out.append(line)
        time.sleep(1.0)  # well inside the call
        p.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        p.send_signal(signal.SIGTERM)
        sent = time.time()
        _, err = p.communicate(timeout=15)
        took = time.time() - sent
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 143 and took < 10, (p.returncode, took, err)
    assert re.fullmatch(r"sear.py: stopped by SIGTERM at once: the process did not answer it within 5 s \(inside a "
                        r"long native call\); " + re.escape(str(tmp_path / "runs"))
                        + r"/walker-walk__sear__1__\S+ had no snapshot yet and was removed",
                        err.strip().splitlines()[-1]), err
    assert list((tmp_path / "runs").iterdir()) == []


@pytest.mark.parametrize("how", ["--threads", "OMP_NUM_THREADS"])
def test_more_threads_than_cores_are_clamped_with_a_warning_and_the_run_finishes(tmp_path, how):
    """64 torch threads on 2 cores spun for over ten minutes in Agent.__init__ (nn.init.orthogonal_):
    clamped to the usable cores, the run goes on, and says so."""
    from harness import cli
    cores, n = len(os.sched_getaffinity(0)), max(64, 4 * len(os.sched_getaffinity(0)))
    assert cli.torch_threads(cli.RunConfig(threads=n)) == cores
    args = ["--run-root", tmp_path / "runs", "--env", "walker-walk", *TINY[:-2], "--frames", "16"]  # less --threads
    r = subprocess.run([sys.executable, str(ROOT / "sear.py"), *map(str, args), *(["--threads", str(n)] if how ==
                                                                                  "--threads" else [])],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env={**ENV, **({"OMP_NUM_THREADS": str(n)} if how != "--threads" else {})})
    assert r.returncode == 0, r.stderr[-3000:]
    given = f"--threads {n}" if how == "--threads" else f"OMP_NUM_THREADS={n}"
    assert one_line(r).startswith(f"sear.py: warning: {given} is more threads than the {cores} cores this process "
                                  f"may use; using {cores} "), r.stderr


# ------------------------------------------------------------------------------------ storage errors
@pytest.mark.parametrize("make", ["file", "file above"])
def test_a_file_where_the_run_root_should_be_is_one_line_before_anything(tmp_path, make):
    (tmp_path / "f").write_text("not a folder\n")
    root = tmp_path / "f" if make == "file" else tmp_path / "f" / "runs"
    r = run(["--run-root", root, "--env", "walker-walk", *TINY], tmp_path)
    assert r.returncode == 2 and "is a file, not a folder" in one_line(r) and "--run-root" in r.stderr
    assert (tmp_path / "f").read_text() == "not a folder\n" and sorted(os.listdir(tmp_path)) == ["f"]


def user_namespace_available():
    return shutil.which("unshare") and subprocess.run(
        ["unshare", "-rm", "sh", "-c", "mount -t tmpfs tmpfs /mnt"], capture_output=True).returncode == 0


def in_user_namespace(script, timeout=600):
    """Run a shell script as root of its own user and mount namespace: it may mount a tmpfs, which
    nothing outside sees, without privileges (where the kernel allows unprivileged namespaces)."""
    return subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, timeout=timeout,
                          env=ENV)


def sear_command(*args):
    return " ".join([sys.executable, str(ROOT / "sear.py"), *map(str, args)])


@pytest.mark.skipif(not user_namespace_available(), reason="needs unprivileged user namespaces (unshare -rm)")
def test_a_full_disk_is_one_line_and_the_last_snapshot_stands(tmp_path):
    """A 6 MB tmpfs: the snapshot at frame 16 (the networks: no update yet, so no Adam moments) and the
    one at frame 32 (3.7 MB, the moments made by the first step) fit, the next cannot (its .tmp beside
    the last)."""
    disk, copy = tmp_path / "disk", tmp_path / "copy"
    disk.mkdir()
    r = in_user_namespace(
        f"mount -t tmpfs -o size=6m tmpfs {disk} && cd {tmp_path} && "
        + sear_command("--run-root", disk / "runs", "--env", "walker-walk", *TINY, "--frames", "1000",
                       "--eval-every", "100000", "--snapshot-minutes", "0")
        + f"; echo exit $?; cp -a {disk}/runs {copy}")
    assert re.search(r"^exit 2$", r.stdout, re.M), r.stdout[-2000:] + r.stderr[-3000:]
    run_dir = only_dir(copy)
    warning, line = r.stderr.strip().splitlines()  # the start-up check saw it coming
    assert warning.startswith(f"sear.py: warning: {disk / 'runs' / run_dir.name}: 6.3 MB free, but this run's files "
                              f"need up to 7.3 MB more"), warning
    assert line.startswith(f"sear.py: error: cannot write '{disk / 'runs' / run_dir.name / 'snapshot.pt'}': "
                           f"No space left on device (ENOSPC); the last snapshot (frame 32) stands"), line
    assert not list(run_dir.rglob("*.tmp")) and snapshot_step(run_dir) == 16


def test_a_file_size_limit_during_a_snapshot_is_one_line_and_leaves_the_old_one(a_run, tmp_path):
    """The same failure without namespaces: a 1 MB RLIMIT_FSIZE (the snapshot is 3.8 MB) makes the
    kernel refuse the write (EFBIG) as a full disk would (ENOSPC)."""
    before = (a_run / "snapshot.pt").read_bytes()
    limit = 1 << 20
    r = run(["--resume", a_run, "--frames", "64"], tmp_path,
            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    assert r.returncode == 2, r.stderr[-3000:]
    assert one_line(r).startswith(f"sear.py: error: cannot write '{a_run / 'snapshot.pt'}': File too large (EFBIG); "
                                  f"the last snapshot (frame 48) stands"), r.stderr
    assert (a_run / "snapshot.pt").read_bytes() == before and not list(a_run.rglob("*.tmp"))


@pytest.mark.skipif(not user_namespace_available(), reason="needs unprivileged user namespaces (unshare -rm)")
def test_a_read_only_file_system_is_one_line_for_a_new_run_and_for_resume(finished_run, tmp_path):
    """A new run, and a resume that trains further (a finished run resumed as it is only says so)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    r = in_user_namespace(
        f"mount -t tmpfs tmpfs {ro} && mkdir {ro}/runs && cp -a {finished_run} {ro}/runs/ && "
        f"mount -o remount,ro {ro} && cd {tmp_path} && "
        + sear_command("--run-root", ro / "runs", "--env", "walker-walk", *TINY) + "; echo exit $?; "
        + sear_command("--resume", ro / "runs" / finished_run.name, "--frames", "64") + "; echo exit $?")
    assert re.findall(r"^exit (\d+)$", r.stdout, re.M) == ["2", "2"], r.stdout[-2000:] + r.stderr[-3000:]
    new, resume = r.stderr.strip().splitlines()
    assert new == f"sear.py: error: --run-root: cannot write in '{ro / 'runs'}': read-only file system"
    assert resume.startswith(f"sear.py: error: cannot write '{ro / 'runs' / finished_run.name}/") and \
        "Read-only file system (EROFS); the last snapshot (frame 48) stands" in resume, resume


def test_a_log_that_cannot_be_written_is_one_line(a_run, tmp_path):
    """EACCES on eval.csv, injected by a wrapper around the real sear.py (a test running as root
    could not make the kernel refuse it)."""
    wrapper = tmp_path / "no_eval_log.py"
    wrapper.write_text(
        "import builtins, errno, os, runpy, sys\n"
        "real = builtins.open\n"
        "def refuse_eval_log(file, mode='r', *args, **kwargs):\n"
        "    if str(file).endswith('eval.csv') and mode[0] in 'wa':\n"
        "        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(file))\n"
        "    return real(file, mode, *args, **kwargs)\n"
        "builtins.open = refuse_eval_log\n"
        f"sys.argv[0] = {str(ROOT / 'sear.py')!r}\n"
        "runpy.run_path(sys.argv[0], run_name='__main__')\n")
    r = subprocess.run([sys.executable, str(wrapper), "--resume", str(a_run), "--frames", "64"], capture_output=True,
                       text=True, timeout=600, cwd=tmp_path, env={**ENV, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2, r.stderr[-3000:]
    assert one_line(r).startswith(f"sear.py: error: cannot write '{a_run / 'eval.csv'}': Permission denied (EACCES)")


# ----------------------------------------------------------------------------- resume: what is a run
def test_resume_says_what_a_folder_is_when_it_is_not_a_run(a_run, tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "note.txt").write_text("x")
    started = tmp_path / "started"  # a run that stopped before its first snapshot
    started.mkdir()
    shutil.copy(a_run / "config.json", started)
    for folder, message in [(a_run.parent, f"'{a_run.parent}' is not a run directory (no config.json or snapshot.pt "
                                           f"in it); it holds 1 run directory, e.g. {a_run}"),
                            (tmp_path / "empty", "is not a run directory"),
                            (tmp_path / "note.txt", "is a file, not a run directory"),
                            (started, "has no snapshot.pt (the run stopped before its first snapshot")]:
        for flag in ("--resume", "--evaluate"):
            r = run([flag, folder], tmp_path)
            assert r.returncode == 2 and f"{flag}: " in one_line(r) and message in r.stderr, (flag, r.stderr)


def test_resume_refuses_an_unreadable_config_json_and_rewrites_a_missing_one(a_run, tmp_path):
    (a_run / "config.json").write_text('{"env": "walker-walk",')  # cut short
    before = tree_digest(a_run)
    r = run(["--resume", a_run], tmp_path)
    assert r.returncode == 2 and one_line(r) == (
        f"sear.py: error: --resume: cannot read '{a_run / 'config.json'}' (JSONDecodeError: Expecting property name "
        f"enclosed in double quotes: line 1 column 23 (char 22)); snapshot.pt holds the run's config: move "
        f"config.json aside and resume again to have it written from there")
    assert tree_digest(a_run) == before

    (a_run / "config.json").rename(tmp_path / "config.json.broken")  # what the message says to do
    r = run(["--resume", a_run, "--frames", "64"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    import torch
    saved = torch.load(a_run / "snapshot.pt", weights_only=False)["config"]
    config = json.loads((a_run / "config.json").read_text())
    assert config["env"] == "walker-walk" and config["latent_dim"] == 64 and config["seed"] == saved["seed"]


# ------------------------------------------------------------------------------- mask model inputs
def test_a_file_that_is_not_a_mask_model_says_so(a_run, tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("hello\n")
    for path in (text, a_run / "snapshot.pt"):  # a text file; a sear.py snapshot (a torch file of another kind)
        r = run(["--run-root", tmp_path / "new", "--env", "walker-walk", *TINY, "--mask-source", f"learned:{path}"],
                tmp_path)
        assert r.returncode == 2 and f"mask model '{path}' is not a segment.py model file" in one_line(r), r.stderr
        assert not (tmp_path / "new").exists()


def test_a_mask_model_knows_its_robot_and_warns_on_another(tmp_path):
    model = tmp_path / "cup.pt"
    r = subprocess.run([sys.executable, str(ROOT / "segment.py"), "train", "--env", "cup-catch", "--labels", "4",
                        "--steps", "2", "--channels", "4,8,16", "--threads", "1", "--out", str(model), "--force"],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path, env=ENV)
    assert r.returncode == 0, r.stderr[-3000:]
    sys.path.insert(0, str(ROOT))
    import segment
    meta = segment.load_model(str(model)).meta
    assert meta["source"]["env"] == "cup-catch" and meta["robot"] == "ball_in_cup"

    old = tmp_path / "old.pt"  # a model file from before the record: loads, and nothing is checked
    loaded = segment.load_model(str(model))
    segment.MaskModel(loaded.net, {"labels": 4}).save(str(old))
    for path, warned in ((model, True), (old, False)):
        r = run(["--run-root", tmp_path / "runs", "--env", "walker-walk", *TINY, "--frames", "16",
                 "--mask-source", f"learned:{path}"], tmp_path)
        assert r.returncode == 0, r.stderr[-3000:]
        # (--force wrote it below the IoU floor, and learned_mask_iou stays below it on walker: those
        # warnings are test_segment.py's subject)
        warnings = [line for line in r.stderr.splitlines() if "warning" in line and "IoU floor" not in line
                    and "learned_mask_iou has stayed below" not in line]
        if warned:
            assert len(warnings) == 1 and "trained on cup-catch (robot: ball_in_cup)" in warnings[0] \
                and "walker-walk's robot is walker" in warnings[0], r.stderr
        else:
            assert warnings == [], r.stderr


# -------------------------------------------------------------------------------------- --evaluate
def test_evaluate_scores_the_snapshot_and_writes_nothing_but_a_new_video(a_run, tmp_path):
    before = tree_digest(a_run)
    r = run(["--evaluate", a_run, "--eval-episodes", "2"], tmp_path)
    assert r.returncode == 0 and "warning" not in r.stderr, r.stderr[-3000:]
    m = re.search(r"^return (-?[\d.]+) \(95% CI (-?[\d.]+) to (-?[\d.]+), 2 episodes\)$", r.stdout, re.M)
    assert m and float(m[2]) <= float(m[1]) <= float(m[3]), r.stdout
    assert tree_digest(a_run) == before

    # One episode with the evaluations' own reset seed: eval.csv's row at the snapshot's frame again.
    last = rows(a_run / "eval.csv")[-1]
    videos, first_video = [], None
    for _ in range(2):
        r = run(["--evaluate", a_run, "--eval-episodes", "1", "--save-video"], tmp_path)
        assert r.returncode == 0, r.stderr[-3000:]
        assert f"return {float(last['return']):.1f} (1 episode" in r.stdout, r.stdout
        videos.append(Path(re.search(r"^video: (.+)$", r.stdout, re.M)[1]))
        first_video = first_video or videos[0].read_bytes()
    assert videos[0] != videos[1] and videos[0].read_bytes() == first_video  # never overwritten
    assert sorted(p.name for p in (a_run / "videos").iterdir()) == sorted(v.name for v in videos)
    assert all(v.stat().st_size > 0 for v in videos)
    shutil.rmtree(a_run / "videos")
    assert tree_digest(a_run) == before  # nothing else was written

    r = run(["--evaluate", a_run, "--frames", "10"], tmp_path)
    assert r.returncode == 2 and "--frames cannot be given with --evaluate" in one_line(r)


def test_evaluate_reports_success_where_the_suite_has_it(tmp_path):
    r = run(["--run-root", tmp_path / "runs", "--env", "metaworld-door-open", *TINY, "--frames", "8",
             "--seed-frames", "8", "--max-episode-steps", "4"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    r = run(["--evaluate", only_dir(tmp_path / "runs"), "--eval-episodes", "2"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    m = re.search(r"^success ([\d.]+) \(95% CI ([\d.]+) to ([\d.]+), 2 episodes\)$", r.stdout, re.M)
    assert m and 0 <= float(m[2]) <= float(m[1]) <= float(m[3]) <= 1 and float(m[3]) > float(m[2]), r.stdout


# ------------------------------------------------------------------------- flags and start warnings
@pytest.mark.parametrize("typo, flag", [("--frams", "--frames"), ("--save-vidoe", "--save-video"),
                                        ("--evalute=runs/x", "--evaluate")])
def test_a_misspelled_flag_gets_a_suggestion(tmp_path, typo, flag):
    r = run([typo, "10"] if "=" not in typo else [typo], tmp_path)
    assert r.returncode == 2 and one_line(r) == f"sear.py: error: no flag {typo.split('=')[0]}; did you mean {flag}?"


def test_oversubscribed_threads_and_a_small_replay_are_warned_at_start(tmp_path):
    cores = len(os.sched_getaffinity(0))
    r = run(["--run-root", tmp_path / "runs", "--env", "walker-walk", *TINY, "--frames", "16", "--threads", cores + 1,
             "--replay-size", "6", "--batch-size", "16"], tmp_path)  # 6: the seed phase's steps, where learning starts
    assert r.returncode == 0, r.stderr[-3000:]
    warnings = [line for line in r.stderr.splitlines() if line.startswith("sear.py: warning: ")]
    assert len(warnings) == 2, r.stderr
    assert f"--threads {cores + 1} is more threads than the {cores} cores this process may use; using {cores}" \
        in warnings[0]
    assert "--replay-size 6 is smaller than --batch-size 16" in warnings[1]
