"""benchmarks/official_compare.py: the checks of a curve that does not match (replay contents, a
snapshot's policy, bad input), on fake official runs and a tiny run of ours."""
import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "official_compare.py"
TINY = ["--frames", "48", "--seed-frames", "12", "--batch-size", "4", "--eval-every", "24",
        "--eval-episodes", "1", "--max-episode-steps", "8", "--replay-size", "400",
        "--latent-dim", "64", "--hidden-dim", "32", "--render-quality", "fast", "--threads", "1"]


def run(*args, cwd):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True, timeout=600,
                          cwd=cwd, env=env)


def official_run(folder, episodes):
    """An official run's buffer/: one <time>_<index>_<length>.npz per episode, its first step the reset's."""
    (folder / "buffer").mkdir(parents=True)
    for i, (actions, rewards) in enumerate(episodes):
        n = len(actions)
        np.savez(folder / "buffer" / f"20261201T1{i:05d}_{i}_{n}.npz",
                 observation=np.zeros((n + 1, 9, 2, 2), np.uint8),
                 action=np.array([[0.0], *[[a] for a in actions]], np.float32),
                 reward=np.array([[0.0], *[[r] for r in rewards]], np.float32),
                 discount=np.ones((n + 1, 1), np.float32))
    return folder


def our_run(folder, episodes):
    """Our run dir's buffer.npz: a `first` slot (the reset) before each episode's steps."""
    folder.mkdir(parents=True)
    actions, rewards, first = [], [], []
    for acts, rews in episodes:
        actions += [[0.0], *[[a] for a in acts]]
        rewards += [0.0, *rews]
        first += [True] + [False] * len(acts)
    n = len(first)
    np.savez(folder / "buffer.npz", t=n, frames=np.zeros((n, 3, 2, 2), np.uint8), masks=np.zeros((n, 1), np.uint8),
             actions=np.array(actions, np.float32), rewards=np.array(rewards, np.float32),
             terminal=np.zeros(n, bool), first=np.array(first))
    (folder / "config.json").write_text('{"method": "drq", "seed": 4}')
    return folder


def test_replay_table_gives_each_blocks_return_and_action_statistics(tmp_path):
    bang_bang = ([1.0, 1.0, -1.0, -1.0], [1.0, 0.0, 1.0, 1.0])  # return 3, |a| 1, all at the bound, 1 flip in 3
    dither = ([0.5, -0.5, 0.5, -0.5], [0.0, 0.0, 0.0, 0.0])      # return 0, |a| 0.5, none at the bound, 3 in 3
    official = official_run(tmp_path / "official-1", [bang_bang, dither])
    ours = our_run(tmp_path / "runs" / "drq-4", [dither, bang_bang])
    r = run(SCRIPT, "replay", official, ours, "--block", "1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "| episodes | official (official-1) | drq seed 4 |" in r.stdout
    assert "| 0–0 | 3 / 1.00 / 1.00 / 0.33 | 0 / 0.50 / 0.00 / 1.00 |" in r.stdout
    assert "| 1–1 | 0 / 0.50 / 0.00 / 1.00 | 3 / 1.00 / 1.00 / 0.33 |" in r.stdout
    r = run(SCRIPT, "replay", official, ours, cwd=tmp_path)  # one block of 5: both episodes together
    assert "| 0–4 | 2 / 0.75 / 0.50 / 0.67 | 2 / 0.75 / 0.50 / 0.67 |" in r.stdout


def test_policy_reproduces_the_runs_evaluation_and_samples(tmp_path):
    """The mean action on the eval env from the evaluation's reset seeds is the run's own evaluation."""
    r = run(ROOT / "sear.py", "--env", "cartpole-balance_sparse", "--save-buffer", "--run-root", tmp_path / "runs",
            *TINY, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    run_dir = next((tmp_path / "runs").iterdir())
    with open(run_dir / "eval.csv") as f:
        last = list(csv.DictReader(f))[-1]
    r = run(SCRIPT, "policy", run_dir, "--episodes", "1", "--stds", "0.5,1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert f"snapshot at frame {last['frame']}" in lines[0]
    assert re.match(rf"mean action, eval env .*: return {float(last['return']):.1f} ", lines[1]), lines[1]
    assert lines[2].startswith("mean action, train env")
    assert [line.split(":")[0] for line in lines[3:]] == [f"sampled with std {s}, train env (new reset seeds)"
                                                          for s in ("0.5", "1")]
    r = run(SCRIPT, "replay", official_run(tmp_path / "official", [([1.0] * 8, [0.0] * 8)]), run_dir, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "| 0–4 | 0 / 1.00 / 1.00 / 0.00 | " in r.stdout


def actor_run(root, seed, rows):
    """Our drq run dir with train.csv rows (frame, step, actor_saturated, action_spread)."""
    ours = root / f"drq-{seed}"
    ours.mkdir()
    (ours / "config.json").write_text(f'{{"method": "drq", "seed": {seed}}}')
    with open(ours / "train.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "step", "actor_saturated", "action_spread"])
        w.writerows(rows)
    return ours


def test_saturation_table_puts_the_official_probe_beside_our_train_csv(tmp_path):
    """Per block of frames: the official probe's per-update rows (a resumed step's last row counts;
    frame = step x action repeat) beside our episodes' means (an episode in the block it ran in)."""
    official = tmp_path / "official-1"
    official.mkdir()
    (official / "actor.csv").write_text("2000,0.0,0.5\n2100,1.0,0.0\n2100,0.5,0.25\n")
    ours = actor_run(tmp_path, 4, [[1000, 500, "", ""], [5000, 2500, 0.5, 0.1], [6000, 3000, 1.0, 0.3],
                                   [7000, 3500, 0.0, 0.2]])
    r = run(SCRIPT, "saturation", official, ours, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "| frames | official (official-1) | drq seed 4 |" in r.stdout
    assert "| 4k–6k | 0.25 / 0.375 | 0.75 / 0.2 |" in r.stdout
    assert "| 6k–8k |  | 0.00 / 0.2 |" in r.stdout
    assert "| 0k–2k" not in r.stdout and "| 2k–4k" not in r.stdout  # seed frames: no update, no row
    r = run(SCRIPT, "saturation", official, ours, "--block", "1000", "--action-repeat", "1", cwd=tmp_path)
    assert "| 2k–3k | 0.25 / 0.375 |  |" in r.stdout and "| 4k–5k |  | 0.50 / 0.1 |" in r.stdout


def test_a_drm_run_is_named_method_plus_drm_beside_the_same_seed_without(tmp_path):
    (tmp_path / "drm").mkdir()
    drq = actor_run(tmp_path, 2, [[5000, 2500, 0.98, 0.15]])
    drm = actor_run(tmp_path / "drm", 2, [[5000, 2500, 0.1, 0.6]])
    (drm / "config.json").write_text('{"method": "drq", "seed": 2, "drm": true}')  # sear.py --method drq --drm
    r = run(SCRIPT, "saturation", drq, drm, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "| frames | drq seed 2 | drq+drm seed 2 |" in r.stdout
    assert "| 4k–6k | 0.98 / 0.15 | 0.10 / 0.6 |" in r.stdout


def test_saturation_of_a_resumed_run_counts_a_repeated_frame_once(tmp_path):
    """A resume repeats the episodes after its snapshot in train.csv: the rows written last count."""
    ours = actor_run(tmp_path, 5, [[5000, 2500, 0.5, 0.1], [6000, 3000, 1.0, 0.9], [6000, 3000, 0.0, 0.3]])
    r = run(SCRIPT, "saturation", ours, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "| 4k–6k | 0.25 / 0.2 |" in r.stdout


@pytest.mark.parametrize("case", ["official run without buffer", "our run without buffer", "no run dir",
                                  "no checkout", "loader without checkout", "no such check",
                                  "saturation without actor data", "saturation block 0",
                                  "saturation from an empty probe"])
def test_bad_input_is_one_line_exit_2(tmp_path, case):
    empty = tmp_path / "empty"
    empty.mkdir()
    official = official_run(tmp_path / "official", [([1.0], [1.0])])
    (empty_probe := tmp_path / "official-killed").mkdir()
    (empty_probe / "actor.csv").write_text("")  # killed before its first update
    args = {"official run without buffer": ["replay", empty, our_run(tmp_path / "ours", [([1.0], [1.0])])],
            "our run without buffer": ["replay", official, empty],
            "no run dir": ["policy", tmp_path / "missing"],
            "no checkout": ["env", "--official", empty],
            "loader without checkout": ["loader", "--official", empty],
            "no such check": ["everything"],
            "saturation without actor data": ["saturation", empty],
            "saturation block 0": ["saturation", official, "--block", "0"],
            "saturation from an empty probe": ["saturation", empty_probe]}[case]
    r = run(SCRIPT, *args, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.startswith("official_compare.py: ") and r.stderr.count("\n") == 1, r.stderr
    assert "Traceback" not in r.stderr


def test_physics_record_and_compare(tmp_path):
    r = run(SCRIPT, "physics", "--episodes", "1", "--steps", "60", "--record", tmp_path / "a.npz", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = run(SCRIPT, "physics", "--episodes", "1", "--steps", "60", "--compare", tmp_path / "a.npz", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert re.search(r"episode 0 against mujoco \S+, dm-control \S+: largest state difference 0\.0e\+00, reward "
                     r"0\.0e\+00; pixels: largest 0, mean 0\.00", r.stdout), r.stdout
    r = run(SCRIPT, "physics", "--episodes", "1", "--steps", "40", "--compare", tmp_path / "a.npz", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "other --task/--episodes/--steps" in r.stderr
