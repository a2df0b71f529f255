"""A single run keeps the results it had before sear.py's update became plain PyTorch and each agent drew
from a generator of its own: tests/fixtures/rows_b67b6dd holds train.csv and eval.csv of the command below
as commit b67b6dd wrote them. The draws are the same (the agent's generator continues torch's stream where
the networks' initialisation left it, in DrQ-v2's order), so every row before the first update is equal to
the bit and the frames, steps and episodes throughout; after it, torch's fused Adam rounds some steps
differently from the optimiser it replaced (at most 1 ulp a step), so losses and returns agree to 1e-5
relative (CLOSE): a different draw or a wrong update moves them by percents."""
import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "rows_b67b6dd"
COMMAND = ["--env", "walker-walk", "--method", "sear", "--seed", "3", "--frames", "96", "--seed-frames", "24",
           "--batch-size", "4", "--eval-every", "48", "--eval-episodes", "1", "--max-episode-steps", "12",
           "--replay-size", "400", "--hidden-dim", "32", "--feature-dim", "8", "--render-quality", "fast",
           "--threads", "1", "--exploration-steps", "20", "--latent-dim", "16"]
EXACT = ("frame", "step", "episode", "length")
# relative tolerance: a loss or return moves by ~1e-6 with the optimiser's rounding; the evaluation's
# PSNR of the reconstruction by ~1e-5 (its IoU of thresholded masks flips pixels: not compared)
CLOSE = {"return": 1e-5, "critic_loss": 1e-5, "actor_loss": 1e-5, "q": 1e-5, "recon_loss": 1e-5,
         "mask_loss": 1e-5, "recon_psnr": 1e-4}


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_a_single_run_keeps_its_rows(tmp_path):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    r = subprocess.run([sys.executable, str(ROOT / "sear.py"), *COMMAND, "--run-root", str(tmp_path / "runs")],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    (run_dir,) = (tmp_path / "runs").iterdir()
    for name in ("train.csv", "eval.csv"):
        old, new = rows(FIXTURE / name), rows(run_dir / name)
        assert len(old) == len(new), name
        for a, b in zip(old, new):
            assert [a[k] for k in EXACT if k in a] == [b[k] for k in EXACT if k in a], (name, a, b)
            for k in (k for k in CLOSE if a.get(k)):
                assert float(b[k]) == pytest.approx(float(a[k]), rel=CLOSE[k]), (name, a["frame"], k)
    before_updates = rows(FIXTURE / "train.csv")[0]
    assert rows(run_dir / "train.csv")[0]["return"] == before_updates["return"]
