"""Tests for toy_pointmass.py (fast: the whole file runs in well under a minute on 2 CPU cores)."""

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import toy_pointmass as tp  # noqa: E402

SCRIPT = ROOT / "toy_pointmass.py"


def _cfg(**kw):
    base = dict(train_episodes=300, eval_episodes=16, workers=1)
    base.update(kw)
    return tp.Config(**base)


def _data(sigma_r, sigma_e, seed=0, **kw):
    cfg = _cfg(**kw)
    rng = np.random.default_rng(seed)
    sensor = tp.Sensor(rng, cfg, sigma_r, sigma_e)
    return cfg, sensor, tp.collect(rng, sensor, cfg, cfg.train_episodes, cfg.train_steps)


def test_observation_shapes():
    cfg, sensor, data = _data(0.2, 0.2, obs_dim=37)
    n, t1 = cfg.train_episodes, cfg.train_steps + 1
    assert data["X"].shape == (n, t1, 37)
    assert data["X_R"].shape == (n, t1, 37)
    assert data["z_r"].shape == (n, t1, tp.Z_R_DIM)
    assert data["z_e"].shape == (n, t1, tp.Z_E_DIM)
    assert data["a"].shape == (n, cfg.train_steps, 2)
    # X_R is a projection of z_R alone: exactly rank 2, and exactly Q2 z_R
    assert np.linalg.matrix_rank(data["X_R"].reshape(-1, 37)) == 2
    np.testing.assert_allclose(data["X_R"], data["z_r"] @ sensor.Q2.T, atol=1e-9)
    # X = Q z + eps with eps ~ N(0, 1): the residual has unit variance
    z = np.concatenate([data["z_r"], data["z_e"]], axis=-1)
    assert abs((data["X"] - z @ sensor.Q.T).std() - 1.0) < 0.05


def test_latent_noise_follows_sigmas():
    _, _, data = _data(0.3, 1.7, seed=1)
    assert abs((data["z_r"] - data["P"]).std() - 0.3) < 0.02
    assert abs((data["z_e"][..., :2] - data["G"]).std() - 1.7) < 0.1


@pytest.mark.parametrize("sigma_r, sigma_e", [(0.2, 2.4), (2.4, 0.2)])
def test_zhat_r_recovers_z_r(sigma_r, sigma_e):
    cfg, _, data = _data(sigma_r, sigma_e)
    enc_r = tp.PCA(data["X_R"], tp.Z_R_DIM)
    assert tp.linear_r2(enc_r(data["X_R"]), data["z_r"]).min() > 0.99


def test_bottleneck_drops_agent_when_environment_noise_dominates():
    """The mechanism behind the table: with sigma_E >> sigma_R the 4-dim PCA of X loses the agent."""
    cfg, _, data = _data(0.2, 2.4)
    z_hat = tp.PCA(data["X"], cfg.latent_dim)(data["X"])
    assert tp.linear_r2(z_hat, data["z_r"]).mean() < 0.3
    cfg, _, data = _data(0.2, 0.2)
    z_hat = tp.PCA(data["X"], cfg.latent_dim)(data["X"])
    assert tp.linear_r2(z_hat, data["z_r"]).mean() > 0.9


def test_learned_latent_dynamics_is_exact_without_noise():
    cfg, sensor, data = _data(1e-6, 1e-6)
    enc_r = tp.PCA(data["X_R"], tp.Z_R_DIM)
    F = enc_r(data["X_R"])
    dyn = tp.LatentActionModel(F, data["a"])
    acts = np.random.default_rng(0).uniform(-1, 1, (5, 3, 4, 2))
    f0 = F[:5, 0]
    pred = dyn.rollout(f0, acts)
    p = data["P"][:5, 0][:, None, None] + cfg.step * np.cumsum(acts, axis=2)
    X_R = p @ sensor.Q2.T
    np.testing.assert_allclose(pred, enc_r(X_R), atol=1e-4)
    # the cheap projected rollout used by the planner equals the direct one
    W = np.random.default_rng(1).standard_normal((2, 7))
    F2, proj = dyn.rollout(f0, acts, W)
    np.testing.assert_allclose(proj, F2 @ W, rtol=1e-4, atol=1e-4)


def test_mpc_with_ground_truth_reaches_goal():
    cfg = _cfg()
    rng = np.random.default_rng(3)
    p0, g, o, rho = tp.sample_episodes(rng, 32, cfg)
    start = np.linalg.norm(p0 - g, axis=1)
    final = tp.oracle_mpc(rng, cfg, p0, g, o, rho)
    assert start.mean() > 2.0
    assert final.mean() < 0.4
    assert (final < 1.0).mean() >= 0.9


def test_random_policy_does_not_reach_goal():
    """Guards the previous test against a trivially easy task."""
    cfg = _cfg()
    rng = np.random.default_rng(3)
    p0, g, o, rho = tp.sample_episodes(rng, 32, cfg)
    final = tp.mpc_episodes(rng, cfg, p0, g, o, rho, lambda s, a: rng.random(a.shape[:2]), lambda r, p: p)
    assert final.mean() > 1.5


def _run(*args, cwd=None):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


def test_quick_run_prints_table_and_writes_csv(tmp_path):
    out = tmp_path / "out"
    res = _run("--quick", "--out", str(out))
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("|")]
    header = lines[0]
    assert "V(ẑ)" in header and "V(ẑ, ẑ_R)" in header
    body = "\n".join(lines[2:])
    for row in ("σ_E > σ_R", "σ_E = σ_R", "σ_E < σ_R"):
        assert row in body
    assert len(lines) == 5
    assert all("±" in ln for ln in lines[2:])
    files = list(out.glob("toy_table_*.csv"))
    assert len(files) == 1
    with open(files[0]) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3 * tp.QUICK["seeds"]
    assert {r["regime"] for r in rows} == {"σ_E > σ_R", "σ_E = σ_R", "σ_E < σ_R"}
    assert all(float(r["dist_z"]) >= 0 and float(r["dist_z+zR"]) >= 0 for r in rows)
    # a second run never overwrites the first
    res2 = _run("--quick", "--out", str(out), "--seeds", "2")
    assert res2.returncode == 0, res2.stderr
    assert len(list(out.glob("toy_table_*.csv"))) == 2
    with open(files[0]) as fh:
        assert len(list(csv.DictReader(fh))) == 3 * tp.QUICK["seeds"]


def test_quick_sweep_writes_png(tmp_path):
    res = _run("--quick", "--sweep", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    pngs = list(tmp_path.glob("toy_sweep_*.png"))
    assert len(pngs) == 1 and pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(list(tmp_path.glob("toy_sweep_*.csv"))) == 1


@pytest.mark.parametrize("args", [
    ("--seeds", "-3"),
    ("--seeds", "abc"),
    ("--sigma-lo", "2", "--sigma-hi", "1"),
    ("--sigma-r", "0.1"),
    ("--latent-dim", "7"),
    ("--no-such-flag",),
])
def test_bad_input_one_line_nonzero_exit(args, tmp_path):
    res = _run(*args, "--out", str(tmp_path / "o"))
    assert res.returncode != 0
    err = res.stderr.strip().splitlines()
    assert len(err) == 1, res.stderr
    assert err[0].startswith("toy_pointmass.py: error:")
    assert "Traceback" not in res.stderr
    assert not (tmp_path / "o").exists()


def test_unwritable_out_is_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = _run("--quick", "--out", str(blocker / "sub"))
    assert res.returncode != 0
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr


def test_cli_flags_generated_from_dataclass():
    import dataclasses

    cfg = tp.parse_args(["--seeds", "7", "--sigma-lo", "0.1", "--no-sweep"])
    assert cfg.seeds == 7 and cfg.sigma_lo == 0.1 and cfg.sweep is False
    # --quick fills in small values, explicit flags still win
    cfg = tp.parse_args(["--quick", "--seeds", "4"])
    assert cfg.seeds == 4 and cfg.eval_episodes == tp.QUICK["eval_episodes"]
    res = _run("--help")
    for f in dataclasses.fields(tp.Config):
        assert "--" + f.name.replace("_", "-") in res.stdout
