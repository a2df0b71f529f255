"""group.py (--seeds): N seeds of one configuration in one process. The batched update equals N single
updates on the same batches and draws; a group is ordinary run directories that resume as a group and
one by one; refused configurations are one line."""
import copy
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
import sear
import train
from tests.test_cli import ROOT, TINY, rows, run
from tests.test_sear import fake_batch, small_cfg

METHODS = [m for m in sear.METHODS if group.refusal(small_cfg(method=m), train.cli.RunConfig()) is None]


def test_the_methods_a_group_takes():
    assert set(METHODS) == set(sear.METHODS) - {"curl", "ef"}


@pytest.mark.parametrize("method", METHODS)
def test_the_batched_update_equals_single_updates(method, device):
    """Three seeds, each its own networks and batches, the same random draws (vmap's randomness "same"
    against a single update from the same torch seed): every metric and every weight after three updates
    equal the single seeds' to float32 rounding."""
    cfg = small_cfg(method=method)
    agents = []
    for seed in range(3):
        torch.manual_seed(seed)
        agents.append(train.make_agent(cfg, 2, device))
    singles = [copy.deepcopy(a) for a in agents]
    seeds = group.SeedGroup(agents, randomness="same")
    for u in range(3):
        batches = [fake_batch(seed=10 * u + i, device=device) for i in range(3)]
        torch.manual_seed(100 + u)
        got = seeds.update(batches, 5000 + 2 * u)
        for i, single in enumerate(singles):
            torch.manual_seed(100 + u)
            want = single.update(batches[i], 5000 + 2 * u)
            assert set(got[i]) == set(want)
            for k in want:
                assert float(got[i][k]) == pytest.approx(float(want[k]), rel=1e-4, abs=1e-5), (u, i, k)
    for a, single in zip(agents, singles):  # each agent's own parameters are views of the stacks
        for name in ("encoder", "actor", "critic", "critic_target"):
            for p, q in zip(getattr(a, name).parameters(), getattr(single, name).parameters()):
                torch.testing.assert_close(p, q, rtol=0, atol=2 * cfg.lr * 3)


def test_each_seed_draws_its_own_shifts_and_noise():
    """randomness "different" (the default): seeds with the same weights and batch still differ after an
    update, each with its own shifts and exploration noise."""
    cfg = small_cfg(method="drq")
    torch.manual_seed(0)
    agent = train.make_agent(cfg, 2, torch.device("cpu"))
    seeds = group.SeedGroup([agent, copy.deepcopy(agent)])
    metrics = seeds.update([fake_batch(seed=1)] * 2, 5000)
    assert float(metrics[0]["critic_loss"]) != float(metrics[1]["critic_loss"])


@pytest.mark.parametrize("argv, says", [
    (["--method", "curl"], "--seeds does not take --method curl"),
    (["--drm"], "--seeds does not take --drm"),
    (["--compile"], "--seeds does not take --compile"),
    (["--seeds", "3"], "--seeds takes two or more different seeds, got '3'"),
    (["--seeds", "1-x"], "--seeds takes seeds like 1-16 or 1,3,5, got '1-x'"),
])
def test_what_a_group_does_not_take_is_one_line(tmp_path, argv, says):
    args = ["--env", "cartpole-balance", "--seeds", "1-2", *TINY, *argv] if "--seeds" not in argv else \
        ["--env", "cartpole-balance", *TINY, *argv]
    r = run(args, tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and says in r.stderr, r.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


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


def test_a_group_resumes_exactly_and_each_seed_is_an_ordinary_run(tmp_path):
    """80 frames in one go equal 48 and a --resume of the group's folder to 80, seed by seed (train.csv,
    eval.csv, weights), a resume that a storage error stopped on the way included; the group's folder holds group.json and one ordinary run directory per seed, which
    plot.py reads; one seed's run directory resumes on its own as a single run."""
    straight, split = tmp_path / "straight", tmp_path / "split"
    for d in (straight, split):
        d.mkdir()
    r = run([*GROUP, "--frames", "80"], straight)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "group: 2 seeds (1..2) of sear on cartpole-balance" in r.stdout and "envs in 2 worker processes" in r.stdout
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
            assert [[x[c] for c in cols] for x in rows(a[seed] / csv_name)] == \
                [[x[c] for c in cols] for x in rows(b[seed] / csv_name)], (seed, csv_name)
        assert json.loads((a[seed] / "config.json").read_text())["seed"] == seed
        sa = torch.load(a[seed] / "snapshot.pt", weights_only=False)["agent"]
        sb = torch.load(b[seed] / "snapshot.pt", weights_only=False)["agent"]
        assert all(torch.equal(sa["encoder"][k], sb["encoder"][k]) for k in sa["encoder"])
    assert rows(a[1] / "train.csv")[-1]["critic_loss"] != rows(a[2] / "train.csv")[-1]["critic_loss"]
    r = resume(a[2], straight, "--frames", "96")  # one seed, on its own
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(rows(a[2] / "train.csv")[-1]["frame"]) == 96


def test_a_sigterm_stops_every_seed_at_an_episode_end_with_its_snapshot(tmp_path):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    p = subprocess.Popen([sys.executable, str(ROOT / "sear.py"), "--run-root", str(tmp_path / "runs"), *GROUP,
                          "--frames", "100000", "--snapshot-minutes", "1000"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 300
        while time.time() < deadline:
            path = tmp_path / "runs"
            if path.exists() and any(path.iterdir()) and (group_dir(tmp_path) / "group.json").exists() and \
                    all((d / "train.csv").exists() for d in seed_dirs(group_dir(tmp_path)).values()):
                break
            time.sleep(0.5)
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
    assert "envs in this process, one seed after another" in r.stdout
