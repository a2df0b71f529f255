"""A run directory written by an older sear.py still resumes: what users have keeps working."""
import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Written by main at ca5eab9 (the last commit before the harness left sear.py) with
#   python sear.py --env walker-walk --seed 7 --save-buffer --frames 32 --seed-frames 12 --batch-size 4
#     --eval-every 16 --eval-episodes 1 --max-episode-steps 8 --replay-size 400 --latent-dim 16
#     --hidden-dim 32 --feature-dim 8 --render-quality fast --threads 1
# Two 8-step episodes; the final snapshot (frame 32) with its replay buffer, config.json and both CSVs.
FIXTURE = ROOT / "tests" / "fixtures" / "run_ca5eab9"


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_a_run_dir_from_ca5eab9_resumes_and_finishes(tmp_path):
    import torch
    old_snapshot = torch.load(FIXTURE / "snapshot.pt", weights_only=False)
    # before the agent had its own generator: torch's stream was it
    assert "rng" not in old_snapshot["agent"]
    run_dir = tmp_path / "run"
    shutil.copytree(FIXTURE, run_dir)  # a resume appends to the run: never to the fixture itself
    config = (run_dir / "config.json").read_text()
    r = subprocess.run([sys.executable, str(ROOT / "sear.py"), "--resume", str(run_dir), "--frames", "48"],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert r.returncode == 0, r.stderr[-2000:]
    assert "resumed at frame 32, episode 2" in r.stdout
    assert "refilling" not in r.stdout  # the saved buffer came back
    train, evals = rows(run_dir / "train.csv"), rows(run_dir / "eval.csv")
    assert [int(x["frame"]) for x in train] == [16, 32, 48]
    assert [int(x["frame"]) for x in evals] == [0, 16, 32, 48]
    assert list(train[0]) == list(train[-1]) and train[-1]["mask_loss"] != ""  # same columns; it learned
    # Exactly what the code of b67b6dd wrote resuming this run (its draws from torch's stream, now the
    # agent's generator's; its optimiser state as saved, stepped as then): to the last digit.
    assert [train[-1][k] for k in ("return", "critic_loss", "actor_loss", "q", "recon_loss", "mask_loss")] == [
        "1.5334639174104543", "1.6713802814483643", "-0.04434816958382726", "0.10671739093959332",
        "5117.735107421875", "14633.758056640625"]
    assert [evals[-1][k] for k in ("return", "mask_bce", "recon_psnr")] == [
        "2.7559330536329627", "0.6926234364509583", "10.981945037841797"]
    assert (run_dir / "config.json").read_text() == config
    snapshot = torch.load(run_dir / "snapshot.pt", weights_only=False)
    assert snapshot["counters"]["step"] == 24 and snapshot["counters"]["episode"] == 3
    assert "rng" in snapshot["agent"]  # saved as a snapshot is now: the agent's generator with it
    # The old run's values; a field added since takes its default, one removed since is gone (CURL's
    # curl_dim and curl_coef); and what a resume may change, changed.
    from harness import cli
    import sear
    import train
    now = cli.config_dict(train.Config(), cli.RunConfig())
    old = json.loads(config)
    saved = {**{k: old.get(k, v) for k, v in now.items()}, "frames": 48, "resume": str(run_dir)}
    assert snapshot["config"] == saved
