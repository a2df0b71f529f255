"""sear.py end to end on CPU with tiny budgets: outputs, snapshots, --resume, bad input."""
import csv
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Small networks and budgets: the full-size architecture is covered by test_sear.py.
TINY = ["--frames", "48", "--seed-frames", "12", "--batch-size", "4", "--eval-every", "24",
        "--eval-episodes", "1", "--max-episode-steps", "8", "--replay-size", "400",
        "--latent-dim", "64", "--hidden-dim", "32", "--render-quality", "fast"]


def run(args, tmp_path, timeout=600):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run([sys.executable, str(ROOT / "sear.py"), "--run-root", str(tmp_path / "runs"), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=tmp_path, env=env)


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def only_run_dir(tmp_path):
    dirs = sorted((tmp_path / "runs").iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


def tree_digest(path):
    h = hashlib.sha256()
    for p in sorted(Path(path).rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(path)).encode() + p.read_bytes())
    return h.hexdigest()


def test_smoke_run_writes_csvs_and_snapshot_then_resume_continues(tmp_path):
    r = run(["--env", "walker-walk", "--seed", "3", "--save-buffer", *TINY], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert run_dir.name.startswith("walker-walk__sear__3__")
    for name in ("train.csv", "eval.csv", "snapshot.pt", "config.json", "buffer.npz"):
        assert (run_dir / name).exists(), name
    train = rows(run_dir / "train.csv")
    evals = rows(run_dir / "eval.csv")
    assert [int(r["frame"]) for r in evals] == [0, 24]
    assert [int(r["frame"]) for r in train] == [16, 32, 48]  # 8-step episodes, action repeat 2
    assert {"return", "critic_loss", "actor_loss", "recon_loss", "mask_loss", "fps", "wall_time"} <= set(train[0])
    assert train[-1]["mask_loss"] != ""  # learning happened after the seed frames
    assert json.loads((run_dir / "config.json").read_text())["action_repeat"] == 2

    # Resume from the last snapshot (written at the end, frame 48) and train further.
    r = run(["--resume", str(run_dir), "--frames", "80"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "resumed at frame 48" in r.stdout
    assert "no saved replay buffer" not in r.stdout  # --save-buffer: the buffer came back
    evals = rows(run_dir / "eval.csv")
    assert [int(r["frame"]) for r in evals] == [0, 24, 48, 72]
    assert [int(r["frame"]) for r in rows(run_dir / "train.csv")] == [16, 32, 48, 64, 80]
    assert only_run_dir(tmp_path) == run_dir  # no second run directory

    # plot.py draws the real run's eval.csv
    r = subprocess.run([sys.executable, str(ROOT / "plot.py"), str(tmp_path / "runs"), "--out", str(tmp_path / "c.png")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "sear" in r.stdout


@pytest.mark.parametrize("args, message", [
    (["--env", "no-such-env"], "unknown env"),
    (["--batch-size", "0"], "--batch-size must be > 0"),
    (["--discount", "1.5"], "--discount must be in [0, 1]"),
    (["--method", "nope"], "invalid choice"),
    (["--frames", "ten"], "invalid int value"),
    (["--resume", "does/not/exist"], "no such run directory"),
    (["--env", "walker-walk-distracting", "--backgrounds", "does/not/exist"], "does not exist"),
    (["--mask-downsample", "every-other"], "--mask-downsample must be"),
])
def test_bad_input_is_one_line_and_creates_nothing(tmp_path, args, message):
    r = run(args, tmp_path)
    assert r.returncode != 0
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "runs").exists()


def test_unreadable_snapshot_is_reported_and_left_untouched(tmp_path):
    run_dir = tmp_path / "runs" / "walker-walk__sear__1__x"
    run_dir.mkdir(parents=True)
    (run_dir / "snapshot.pt").write_bytes(b"this is not a torch file")
    (run_dir / "train.csv").write_text("frame,return\n2,1.0\n")
    before = tree_digest(run_dir)
    r = run(["--resume", str(run_dir)], tmp_path)
    assert r.returncode != 0
    assert len(r.stderr.strip().splitlines()) == 1 and "cannot read" in r.stderr, r.stderr
    assert tree_digest(run_dir) == before


def test_resume_refuses_to_change_the_experiment(tmp_path):
    r = run(["--env", "cup-catch", *TINY, "--frames", "16", "--eval-every", "100"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    before = tree_digest(run_dir)
    r = run(["--resume", str(run_dir), "--method", "drq"], tmp_path)
    assert r.returncode != 0 and "cannot change on --resume" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert tree_digest(run_dir) == before


@pytest.mark.parametrize("env_name", ["walker-walk-distracting", "metaworld-door-open", "kitchen-kettle", "adroit-door"])
def test_smoke_run_on_every_suite(env_name, tmp_path):
    r = run(["--env", env_name, *TINY, "--frames", "16", "--seed-frames", "8", "--eval-every", "100"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    train = rows(run_dir / "train.csv")
    assert train and train[-1]["mask_loss"] != ""
    if not env_name.endswith("distracting"):  # the manipulation suites report success
        assert "success" in train[0] and "success" in rows(run_dir / "eval.csv")[0]


def test_resume_replays_exactly_what_an_uninterrupted_run_does(tmp_path):
    """Snapshots sit between episodes and every episode's reset seed follows from its number, so
    48 frames + resume to 80 must equal 80 frames in one go: same evaluations, losses, weights."""
    import torch

    common = ["--env", "walker-walk", "--seed", "5", "--save-buffer", *TINY]
    straight, split = tmp_path / "straight", tmp_path / "split"
    for d in (straight, split):
        d.mkdir()
    assert run([*common, "--frames", "80"], straight).returncode == 0
    assert run([*common, "--frames", "48"], split).returncode == 0
    split_dir = only_run_dir(split)
    r = run(["--resume", str(split_dir), "--frames", "80"], split)
    assert r.returncode == 0, r.stderr[-2000:]
    straight_dir = only_run_dir(straight)

    def table(run_dir, name, cols):
        return [[r[c] for c in cols] for r in rows(run_dir / name)]

    losses = ["frame", "return", "critic_loss", "actor_loss", "recon_loss", "mask_loss"]
    assert table(split_dir, "eval.csv", ["frame", "return"]) == table(straight_dir, "eval.csv", ["frame", "return"])
    assert table(split_dir, "train.csv", losses) == table(straight_dir, "train.csv", losses)
    a = torch.load(straight_dir / "snapshot.pt", weights_only=False)["agent"]["encoder"]
    b = torch.load(split_dir / "snapshot.pt", weights_only=False)["agent"]["encoder"]
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("action_repeat", [1, 2])
def test_training_loop_gives_the_agent_agent_steps(tmp_path, monkeypatch, action_repeat):
    """The std schedule, exploration phase and updates see the agent step (frame / action repeat)."""
    import sear
    seen = {"act": [], "update": []}
    act, update = sear.Agent.act, sear.Agent.update
    monkeypatch.setattr(sear.Agent, "act", lambda self, p, m, step, eval_mode: (
        None if eval_mode else seen["act"].append(step), act(self, p, m, step, eval_mode))[1])
    monkeypatch.setattr(sear.Agent, "update", lambda self, batch, step: (
        seen["update"].append(step), update(self, batch, step))[1])
    cfg, _ = sear.parse_args(["--env", "cartpole-swingup", "--method", "drq", "--action-repeat", str(action_repeat),
                              "--run-root", str(tmp_path / "runs"), "--threads", "1", *TINY])
    sear.train(cfg)
    first = cfg.seed_frames // action_repeat  # the first step after the random seed phase
    last = cfg.frames // action_repeat - 1
    assert seen["act"] == list(range(first, last + 1))
    assert seen["update"] and seen["update"][0] >= first and seen["update"][-1] <= last
    assert all(s % cfg.update_every == 0 for s in seen["update"])
