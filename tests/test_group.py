"""--seeds: one loop (train.train) for several seeds in one process. Seed k of a group is the run
--seed k: the same train.csv and eval.csv, row for row, whatever the group it is in (on the CPU, with
the same --threads, where the seeds update one after another); a group is ordinary run directories
that resume as a group and one by one; what it cannot take, a damaged group.json and more seeds than
the machine holds are one line; its env workers end with it, silently."""
import json
import os
import resource
import signal
import subprocess
import sys
import time

import pytest
import torch

from harness import group
from tests.test_cli import ROOT, TINY, rows, run

SAME = ["frame", "step", "episode", "return", "length", "critic_loss", "actor_loss", "q", "recon_loss",
        "mask_loss", "expl_std"]
GROUP = ["--env", "cartpole-balance", "--method", "sear", "--seeds", "1-2", "--save-buffer", *TINY, "--threads", "1"]


def resume(path, cwd, *args, **kwargs):
    """sear.py --resume PATH (no --run-root: the run's own stands)."""
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run([sys.executable, str(ROOT / "sear.py"), "--resume", str(path), *args], capture_output=True,
                          text=True, timeout=600, cwd=cwd, env=env, **kwargs)


def group_dir(tmp_path):
    (path,) = (tmp_path / "runs").iterdir()
    return path


def seed_dirs(path):
    runs = json.loads((path / "group.json").read_text())["runs"]
    return {int(k): path / v for k, v in runs.items()}


def table(path, name, cols=SAME):
    return [[row.get(c) for c in cols] for row in rows(path / name)]


def test_seed_k_of_a_group_is_the_run_seed_k(tmp_path):
    """--seeds 1-3 and --seeds 2-3 against --seed 2 and --seed 3 alone: the same train.csv and eval.csv
    rows (every value but speed and wall time), whatever the group a seed lands in."""
    args = ["--env", "walker-walk", "--method", "sear", *TINY, "--threads", "1", "--frames", "64",
            "--exploration-steps", "20"]
    for name, extra in (("g13", ["--seeds", "1-3"]), ("g23", ["--seeds", "2-3"]), ("s2", ["--seed", "2"]),
                        ("s3", ["--seed", "3"])):
        (tmp_path / name).mkdir()
        r = run([*args, *extra], tmp_path / name)
        assert r.returncode == 0, (name, r.stderr[-2000:])
    alone = {k: next((tmp_path / f"s{k}" / "runs").iterdir()) for k in (2, 3)}
    for g in ("g13", "g23"):
        seeds = seed_dirs(group_dir(tmp_path / g))
        for k in (2, 3):
            for name in ("train.csv", "eval.csv"):
                cols = SAME if name == "train.csv" else ["frame", "step", "return", "mask_iou", "recon_psnr"]
                assert table(seeds[k], name, cols) == table(alone[k], name, cols), (g, k, name)
    assert table(seed_dirs(group_dir(tmp_path / "g13"))[1], "train.csv") != table(alone[2], "train.csv")


@pytest.mark.parametrize("argv, says", [
    (["--seeds", "3"], "--seeds takes two or more different seeds, got '3'"),
    (["--seeds", "1-x"], "--seeds takes seeds like 1-16 or 1,3,5, got '1-x'"),
    (["--seeds", "1-1000"], "--seeds: 1000 seeds do not fit this machine"),
])
def test_what_a_group_does_not_take_is_one_line_and_starts_nothing(tmp_path, argv, says):
    r = run(["--env", "cartpole-balance", *TINY, *argv], tmp_path, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and says in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_a_damaged_group_json_is_one_line_naming_it(tmp_path):
    folder = tmp_path / "runs" / "g"
    folder.mkdir(parents=True)
    (folder / "group.json").write_text('{"seeds": [1, 2], "runs": {"1": ')
    r = resume(folder, tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert str(folder / "group.json") in r.stderr and "damaged" in r.stderr and "Traceback" not in r.stderr


def test_every_method_runs_as_a_group(tmp_path):
    """Seeds updated one after another take every method: CURL's own step, EF's windows, DrM."""
    for name, extra in (("curl", ["--method", "curl"]), ("drm", ["--method", "drq", "--drm"])):
        (tmp_path / name).mkdir()
        args = ["--env", "cartpole-balance", "--seeds", "1-2", *TINY, "--threads", "1", *extra]
        if name == "drm":
            args = [a for a in args if a not in ("--latent-dim", "64")] + ["--drm-perturb-every", "100000"]
        r = run(args, tmp_path / name)
        assert r.returncode == 0, (name, r.stderr[-2000:])
        assert all(rows(d / "train.csv") for d in seed_dirs(group_dir(tmp_path / name)).values())


def test_a_group_resumes_exactly_and_each_seed_is_an_ordinary_run(tmp_path):
    """80 frames in one go equal 48 and a --resume of the group's folder to 80, seed by seed (train.csv,
    eval.csv, weights), a resume that a storage error stopped on the way included; the group's folder holds
    group.json and one ordinary run directory per seed; one seed's run directory resumes on its own."""
    straight, split = tmp_path / "straight", tmp_path / "split"
    for d in (straight, split):
        d.mkdir()
    r = run([*GROUP, "--frames", "80"], straight)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "group: 2 seeds (1..2) of sear on cartpole-balance" in r.stdout and "4 worker processes" in r.stdout
    assert run([*GROUP, "--frames", "48"], split).returncode == 0
    # a storage error on the way (a 1 MB file size limit: a seed's snapshot is 7 MB) is one line, the snapshots stand
    before = {p: p.read_bytes() for p in group_dir(split).glob("*/snapshot.pt")}
    limit = 1 << 20
    r = resume(group_dir(split), split, "--frames", "64",
               preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr[-2000:]
    assert r.stderr.startswith("sear.py: error: cannot write ") and r.stderr.strip().endswith(
        f"File too large (EFBIG); the last snapshot (frame 48) stands: fix that, then python sear.py --resume "
        f"{group_dir(split)}"), r.stderr
    assert {p: p.read_bytes() for p in group_dir(split).glob("*/snapshot.pt")} == before
    r = resume(group_dir(split), split, "--frames", "80")
    assert r.returncode == 0, r.stderr[-2000:]
    a, b = seed_dirs(group_dir(straight)), seed_dirs(group_dir(split))
    assert set(a) == set(b) == {1, 2}
    for seed in (1, 2):
        for csv_name, cols in (("train.csv", ["frame", "return", "critic_loss", "recon_loss"]),
                               ("eval.csv", ["frame", "return"])):
            assert table(a[seed], csv_name, cols) == table(b[seed], csv_name, cols), (seed, csv_name)
        assert json.loads((a[seed] / "config.json").read_text())["seed"] == seed
        sa = torch.load(a[seed] / "snapshot.pt", weights_only=False)["agent"]
        sb = torch.load(b[seed] / "snapshot.pt", weights_only=False)["agent"]
        assert all(torch.equal(sa["encoder"][k], sb["encoder"][k]) for k in sa["encoder"])
    assert rows(a[1] / "train.csv")[-1]["critic_loss"] != rows(a[2] / "train.csv")[-1]["critic_loss"]
    r = resume(a[2], straight, "--frames", "96")  # one seed, on its own
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(rows(a[2] / "train.csv")[-1]["frame"]) == 96


def wait_for_seeds(tmp_path, p, seconds=300):
    deadline = time.time() + seconds
    while time.time() < deadline and p.poll() is None:
        path = tmp_path / "runs"
        if path.exists() and any(path.iterdir()) and (group_dir(tmp_path) / "group.json").exists() and \
                all((d / "train.csv").exists() for d in seed_dirs(group_dir(tmp_path)).values()):
            return
        time.sleep(0.5)


def start_group(tmp_path, *extra):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.Popen([sys.executable, str(ROOT / "sear.py"), "--run-root", str(tmp_path / "runs"), *GROUP,
                             "--frames", "100000", "--snapshot-minutes", "1000", *extra], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def test_a_sigterm_stops_every_seed_at_an_episode_end_with_its_snapshot(tmp_path):
    p = start_group(tmp_path)
    try:
        wait_for_seeds(tmp_path, p)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=300)
    finally:
        p.kill()
    assert p.returncode == 143, err[-2000:]
    line = err.strip().splitlines()[-1]
    assert line.startswith("sear.py: stopped by SIGTERM at frame ") and "every seed's snapshot holds frame" in line
    assert line.endswith(f"continue with: python sear.py --resume {group_dir(tmp_path)}")
    frames = {torch.load(d / "snapshot.pt", weights_only=False)["counters"]["step"]
              for d in seed_dirs(group_dir(tmp_path)).values()}
    assert len(frames) == 1


def workers_of(pid) -> list[int]:
    """The processes whose parent is `pid` (Linux /proc)."""
    kids = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as f:
                if entry.isdigit() and int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                    kids.append(int(entry))
        except OSError:
            continue
    return kids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_env_workers_end_with_a_killed_group_silently(tmp_path):
    """kill -9 of a group: its env workers end within seconds and print nothing (no EOFError tracebacks)."""
    p = start_group(tmp_path)
    try:
        wait_for_seeds(tmp_path, p)
        kids = workers_of(p.pid)
        assert len(kids) >= 4, kids  # each seed's train and eval env
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=60)
        deadline = time.time() + 30
        while time.time() < deadline and any(os.path.exists(f"/proc/{k}") for k in kids):
            time.sleep(0.2)
        assert not [k for k in kids if os.path.exists(f"/proc/{k}")]
        err = p.stderr.read()
    finally:
        p.kill()
    assert "Traceback" not in err and "EOFError" not in err, err[-2000:]


def test_a_sigterm_in_the_groups_evaluation_stops_there_and_the_resumed_group_evaluates_again(tmp_path):
    """As a single run (tests/test_firstweek.py): a SIGTERM during the frame-0 evaluation stops the group when
    the evaluation episode it lands in ends, every seed's snapshot at frame 0 and no eval.csv row; the resumed group
    evaluates at frame 0 again."""
    from tests.test_firstweek import LONG_EPISODES, sigterm_when
    # an evaluation episode takes seconds: the signal lands in the second
    code, out, err = sigterm_when(["--run-root", tmp_path / "runs", "--env", "cartpole-balance", "--method", "sear",
                                   "--seeds", "1-2", *LONG_EPISODES, "--max-episode-steps", "200", "--eval-episodes",
                                   "3"], tmp_path, r"^eval 1/3 done")
    assert code == 143, err[-2000:]
    assert "eval 3/3 done" not in out and "eval @ frame" not in out, out[-2000:]
    seeds = seed_dirs(group_dir(tmp_path))
    for d in seeds.values():
        assert torch.load(d / "snapshot.pt", weights_only=False)["counters"]["step"] == 0
        assert not (d / "eval.csv").exists() or rows(d / "eval.csv") == []
    r = resume(group_dir(tmp_path), tmp_path, "--frames", "80")
    assert r.returncode == 0, r.stderr[-2000:]
    for d in seeds.values():
        assert [row["frame"] for row in rows(d / "eval.csv")] == ["0", "80"]


def test_envs_in_this_process_when_asked(tmp_path, monkeypatch):
    monkeypatch.setenv(group.WORKERS, "serial")
    r = run([*GROUP, "--frames", "24"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "envs in this process" in r.stdout


def test_a_finished_group_resumed_says_so_within_seconds(tmp_path):
    r = run([*GROUP, "--frames", "24"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    began = time.monotonic()
    r = resume(group_dir(tmp_path), tmp_path)
    assert r.returncode == 0 and r.stdout.strip().startswith(f"{group_dir(tmp_path)} is done: it trained to frame 24")
    assert "group:" not in r.stdout and time.monotonic() - began < 30, r.stdout
