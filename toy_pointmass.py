"""SEAR toy experiment: why separating agent from environment helps (paper appendix "Toy Experiment").

Run ``python toy_pointmass.py`` (the table; ~45 s of CPU spread over 2 worker processes) or
``python toy_pointmass.py --sweep`` (table + sweep of the gap against log(sigma_E / sigma_R) + PNG).
``--help`` lists all flags; measured numbers and their discussion are in EXPERIMENTS.md (rung 0).

World
    2D point mass, no walls, no collisions. Per episode: goal g and start p_0 uniform in
    [-A, A]^2 (A = ``arena``), a circular obstacle with centre o uniform in [-A/2, A/2]^2 and radius
    rho uniform in [rho_min, rho_max] (start/goal are resampled until they lie outside the obstacle).
    Dynamics p' = p + step * clip(a, -1, 1). The obstacle is a *reward* obstacle (no contact
    physics), so the dynamics stay exactly linear.
    Ground-truth reward  r = exp(-|p - g| / goal_scale) - obstacle_weight * exp(-|p - o| / rho).
    Metric: |p_T - g| after ``horizon`` steps, averaged over evaluation episodes, then over seeds.

Observations (the agent never sees p, g, o, rho)
    z_R ~ N(mu_R, sigma_R^2 I), mu_R = p                       (2 dims)
    z_E ~ N(mu_E, sigma_E^2 I), mu_E = (g, o, rho)             (5 dims)
    X   = Q z + eps, z = [z_R, z_E], Q in R^{obs_dim x 7}, eps ~ N(0, I)
    X_R = Q2 z_R (the "mask": a projection of the agent part alone, no extra noise, as the study sets it)
    z is resampled at *every* step; Q, Q2 are fixed per seed (entries N(0, 1)).

Representations (fit per seed on random-action data)
    z_hat   = top-``latent_dim`` PCA of X   (PCA = the optimal linear autoencoder). latent_dim = 4 < 7:
              the bottleneck keeps the four largest-variance directions of z.
    z_hat_R = top-2 PCA of X_R (X_R is exactly rank 2, so this recovers z_R up to a linear map).
    Features are standardised with the training mean/std.

Why the claim shows up mechanistically
    Per-coordinate variance in the collected data is Var(mu) + sigma^2. Positions of agent and goal
    spread over the whole arena, the obstacle centre over a quarter of it, the radius hardly varies.
    * sigma_E ~ sigma_R (small): the 4 largest directions are agent + goal -> z_hat is sufficient
      for the attraction term and V(z_hat) ~ V(z_hat, z_hat_R) is expected (we measure a small
      residual gap in favour of V(z_hat, z_hat_R); see EXPERIMENTS.md).
    * sigma_E >> sigma_R: goal, obstacle centre (and radius) all get +sigma_E^2, overtake the agent
      coordinates, and the bottleneck drops the agent position: z_hat carries (almost) no information
      about where the agent is, actions have (almost) no predicted effect, and V(z_hat) cannot steer.
      z_hat_R still carries the agent, so V(z_hat, z_hat_R) can.
    * sigma_E << sigma_R: agent + goal are still the top directions; both models see the same,
      now very noisy, agent position -> both equally (and worse) off.
    A large sigma_E also makes the goal estimate noisy for *both* models (z is resampled every step
    and the agent only sees the current observation; there is no filtering over time). In practice
    this costs V(z_hat, z_hat_R) little: the planner re-plans every step towards a jittering goal
    estimate whose mean is right.

Predictive models (numpy only, fit on the same random-action data, identical for both variants)
    Data: ``train_episodes`` (3000) random-action episodes of ``train_steps`` (10) steps per seed, i.e.
        33k observations from 3000 different layouts (many short episodes: the reward model needs
        many goal/obstacle layouts more than long trajectories).
    Reward model V(f): ridge regression (closed form) of the ground-truth reward on
        [1, f, quadratic terms f_i f_j, random Fourier features cos(W f + b)], W ~ N(0, 1/rff_bandwidth^2),
        f = z_hat (4 dims) or f = [z_hat, z_hat_R] (6 dims).
    Dynamics: a *learned* linear latent action model  f_{t+1} - f_t = B a_t + c, least squares on
        the collected transitions. Exact in expectation for a point mass (the state part drops out);
        because the per-step latent noise is independent of a_t the estimate of B is unbiased,
        whereas a full f_{t+1} = A f_t + B a_t fit would be attenuated by the noise. Nothing about
        which coordinates are "agent" is given to the model: if f holds no agent information, B ~ 0.
        (No privileged state is used anywhere by the learned agent: not for the encoder, the
        dynamics, or the planner; the ground-truth reward is only the regression target.)
    Planner: random-shooting MPC. Each step, ``candidates`` uniform action sequences of length
        ``plan_horizon`` are rolled out with the linear model from the current observed f, scored
        by the sum of V along the rollout, and the first action of the best sequence is executed.
    Hyper-parameters (data size, RFF length scale, candidates) were chosen once, on a handful of
    settings, by planning quality at *near-zero* noise (sigma_R = sigma_E = 0.05) and compute, never
    on the table rows; ``oracle_mpc`` (true state, dynamics and reward) is the planner sanity check.
    Diagnostics in the table/CSV: R^2 of the agent position from z_hat (linear fit), and held-out R^2
    of each reward model. ``--control`` adds a third, diagnostic-only column V(z_hat, L z_hat), where
    L z_hat is a linear read-out of the agent position from z_hat fit *with state labels*: it adds
    no information to z_hat, only makes the agent coordinates explicit (separates "information"
    from "presentation" effects; see EXPERIMENTS.md).

Table: rows sigma_E > sigma_R, =, <; columns V(z_hat), V(z_hat, z_hat_R); mean final distance over
seeds with a 95% t-interval across seeds. The three rows lie on the line sigma_R * sigma_E = const:
(sigma_lo, sigma_hi), (sqrt(lo*hi), sqrt(lo*hi)), (sigma_hi, sigma_lo). The sweep moves along that
same line. Both models of a seed share data, projections and evaluation episodes, so gaps are paired.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

if __name__ == "__main__":  # one BLAS thread per process; parallelism comes from the worker pool
    for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402


def _f(default, help):  # noqa: A002 - one-line doc per field, used for --help
    return field(default=default, metadata={"help": help})


@dataclass
class Config:
    seeds: int = _f(20, "number of seeds per table cell (each seed: new Q, Q2, data, models, eval episodes)")
    sigma_lo: float = _f(0.2, "the small latent-noise std of the unequal rows")
    sigma_hi: float = _f(2.4, "the large latent-noise std of the unequal rows (equal row uses sqrt(lo*hi))")
    sigma_r: float = _f(0.0, "optional extra table row: its sigma_R (needs --sigma-e too; 0 = no extra row)")
    sigma_e: float = _f(0.0, "optional extra table row: its sigma_E (needs --sigma-r too; 0 = no extra row)")
    latent_dim: int = _f(4, "PCA bottleneck of z_hat (z has 7 dims; must be < 7)")
    obs_dim: int = _f(50, "dimension of the observation X and of the mask X_R")
    arena: float = _f(3.0, "start and goal uniform in [-arena, arena]^2")
    rho_min: float = _f(0.3, "minimum obstacle radius")
    rho_max: float = _f(0.8, "maximum obstacle radius")
    step: float = _f(0.3, "max displacement per step and axis (p' = p + step * clip(a, -1, 1))")
    horizon: int = _f(40, "steps per evaluation episode (the metric is the distance after the last one)")
    goal_scale: float = _f(2.0, "length scale of the attraction term exp(-|p-g|/goal_scale)")
    obstacle_weight: float = _f(1.0, "weight of the repulsion term exp(-|p-o|/rho)")
    train_episodes: int = _f(3000, "random-action episodes collected per seed to fit PCA, V and dynamics")
    train_steps: int = _f(10, "steps per random-action training episode (many short episodes = many layouts)")
    eval_episodes: int = _f(20, "evaluation episodes per seed and model")
    rff: int = _f(256, "number of random Fourier features of the reward model")
    rff_bandwidth: float = _f(3.0, "RFF length scale in standardised feature units")
    ridge: float = _f(1e-3, "ridge penalty of the reward model")
    candidates: int = _f(32, "random-shooting action sequences per MPC step")
    plan_horizon: int = _f(5, "length of the planned action sequences")
    workers: int = _f(2, "worker processes (seeds are distributed over them)")
    sweep: bool = _f(False, "also run the sweep of the gap against log(sigma_E/sigma_R) and write a PNG")
    sweep_points: int = _f(9, "number of sigma ratios in the sweep")
    control: bool = _f(False, "diagnostic 3rd column V(ẑ, Lẑ): ẑ plus a linear read-out of the agent position from ẑ (uses state labels)")
    quick: bool = _f(False, "tiny fast run for tests (few seeds/episodes; numbers are not meaningful)")
    out: str = _f("runs/toy", "directory for the CSV/PNG (files are timestamped, never overwritten)")


QUICK = dict(seeds=3, train_episodes=300, eval_episodes=6, rff=128, candidates=16, horizon=30, sweep_points=3, workers=1)

Z_R_DIM, Z_E_DIM = 2, 5
Z_DIM = Z_R_DIM + Z_E_DIM


# --------------------------------------------------------------------------------------------- world
def sample_episodes(rng: np.random.Generator, n: int, cfg: Config):
    """Return start p0 (n,2), goal g (n,2), obstacle centre o (n,2), radius rho (n,)."""
    A = cfg.arena
    o = rng.uniform(-A / 2, A / 2, (n, 2))
    rho = rng.uniform(cfg.rho_min, cfg.rho_max, n)

    def outside():
        pts = rng.uniform(-A, A, (n, 2))
        for _ in range(100):
            bad = np.linalg.norm(pts - o, axis=1) < rho + 0.1
            if not bad.any():
                break
            pts[bad] = rng.uniform(-A, A, (bad.sum(), 2))
        return pts

    return outside(), outside(), o, rho


def true_reward(p, g, o, rho, cfg: Config):
    """Ground-truth reward; p, g, o (..., 2), rho (...)."""
    dg = np.linalg.norm(p - g, axis=-1)
    do = np.linalg.norm(p - o, axis=-1)
    return np.exp(-dg / cfg.goal_scale) - cfg.obstacle_weight * np.exp(-do / rho)


def latent(rng, p, g, o, rho, sigma_r, sigma_e):
    """z = [z_R, z_E] with per-step Gaussian noise around mu_R = p, mu_E = (g, o, rho)."""
    mu_e = np.concatenate([g, o, rho[..., None]], axis=-1)
    z_r = p + sigma_r * rng.standard_normal(p.shape)
    z_e = mu_e + sigma_e * rng.standard_normal(mu_e.shape)
    return z_r, z_e


class Sensor:
    """Fixed random projections: X = Q z + eps, X_R = Q2 z_R."""

    def __init__(self, rng, cfg: Config, sigma_r: float, sigma_e: float):
        self.Q = rng.standard_normal((cfg.obs_dim, Z_DIM))
        self.Q2 = rng.standard_normal((cfg.obs_dim, Z_R_DIM))
        self.sigma_r, self.sigma_e = sigma_r, sigma_e

    def observe(self, rng, p, g, o, rho):
        z_r, z_e = latent(rng, p, g, o, rho, self.sigma_r, self.sigma_e)
        z = np.concatenate([z_r, z_e], axis=-1)
        X = z @ self.Q.T + rng.standard_normal(z.shape[:-1] + (self.Q.shape[0],))
        X_R = z_r @ self.Q2.T
        return X, X_R, z_r, z_e


def collect(rng, sensor: Sensor, cfg: Config, n_episodes: int, steps: int):
    """Random-action rollouts. Returns dict of arrays shaped (episodes, steps+1, ...)/(episodes, steps, 2)."""
    p, g, o, rho = sample_episodes(rng, n_episodes, cfg)
    acts = rng.uniform(-1, 1, (n_episodes, steps, 2))
    P = np.empty((n_episodes, steps + 1, 2))
    P[:, 0] = p
    for t in range(steps):
        P[:, t + 1] = P[:, t] + cfg.step * acts[:, t]
    G = np.broadcast_to(g[:, None], P.shape)
    O = np.broadcast_to(o[:, None], P.shape)
    R = np.broadcast_to(rho[:, None], P.shape[:2])
    X, X_R, z_r, z_e = sensor.observe(rng, P, G, O, R)
    return dict(X=X, X_R=X_R, z_r=z_r, z_e=z_e, P=P, G=G, O=O, rho=R, a=acts,
                r=true_reward(P, G, O, R, cfg))


# ------------------------------------------------------------------------------------------ learning
class PCA:
    """Linear autoencoder = PCA with a k-dim bottleneck; outputs standardised codes."""

    def __init__(self, X, k):
        X = X.reshape(-1, X.shape[-1])
        self.mean = X.mean(0)
        Xc = X - self.mean
        evals, evecs = np.linalg.eigh(Xc.T @ Xc)  # ascending; same subspace as the SVD, much cheaper
        self.V = evecs[:, ::-1][:, :k]
        self.explained = (evals[::-1] / evals.sum())[:k]
        codes = (X - self.mean) @ self.V
        self.scale = codes.std(0) + 1e-12

    def __call__(self, X):
        return ((X - self.mean) @ self.V) / self.scale


class RewardModel:
    """Ridge regression on [1, f, upper-triangular f f^T, cos(W f + b)] (quadratic + random Fourier features)."""

    def __init__(self, F, r, cfg: Config, rng):
        d = F.shape[-1]
        self.iu = np.triu_indices(d)
        self.W = (rng.standard_normal((d, cfg.rff)) / cfg.rff_bandwidth).astype(np.float32)
        self.b = rng.uniform(0, 2 * np.pi, cfg.rff).astype(np.float32)
        Phi = self._phi(F.reshape(-1, d).astype(np.float32))
        A = (Phi.T @ Phi).astype(np.float64) + cfg.ridge * len(Phi) * np.eye(Phi.shape[1])
        self.w = np.linalg.solve(A, (Phi.T @ r.reshape(-1).astype(np.float32)).astype(np.float64)).astype(np.float32)
        nq = len(self.iu[0])
        self.w0, self.wl = self.w[0], self.w[1:1 + d]
        self.Wq = np.zeros((d, d), np.float32)
        self.Wq[self.iu] = self.w[1 + d:1 + d + nq]
        self.wc = self.w[1 + d + nq:]

    def _phi(self, F):
        quad = (F[..., :, None] * F[..., None, :])[..., self.iu[0], self.iu[1]]
        return np.concatenate([np.ones(F.shape[:-1] + (1,), F.dtype), F, quad, np.cos(F @ self.W + self.b)], axis=-1)

    def __call__(self, F, proj=None):
        """V(F) for F (..., d). proj: optional precomputed F @ W (the planner gets it cheaply, see rollout)."""
        F = F.astype(np.float32)
        out = self.w0 + F @ self.wl + ((F @ self.Wq) * F).sum(-1)
        if len(self.wc):
            if proj is None:
                proj = F @ self.W
            proj += self.b
            out = out + np.cos(proj, out=proj) @ self.wc
        return out


class LatentActionModel:
    """Learned linear latent dynamics f_{t+1} = f_t + B a_t + c (least squares)."""

    def __init__(self, F, a):
        dF = (F[:, 1:] - F[:, :-1]).reshape(-1, F.shape[-1])
        A = np.concatenate([a.reshape(-1, a.shape[-1]), np.ones((len(dF), 1))], axis=1)
        coef, *_ = np.linalg.lstsq(A, dF, rcond=None)
        self.B, self.c = coef[:-1], coef[-1]  # B: (2, d)

    def rollout(self, f0, actions, W=None):
        """f0 (E, d), actions (E, N, H, 2) -> predicted features (E, N, H, d) after each action.

        With W (d, M) also returns the predicted features projected by W, computed as
        f0 W + S (B W) + h (c W) (rank-2 update; much cheaper than F @ W for a skinny d)."""
        S = np.cumsum(actions, axis=2)
        h = np.arange(1, actions.shape[2] + 1, dtype=np.float64)[:, None]
        F = f0[:, None, None, :] + S @ self.B + h * self.c
        if W is None:
            return F
        BW, cW = (self.B @ W).astype(np.float32), (h * (self.c @ W)).astype(np.float32)
        proj = (S.reshape(-1, 2).astype(np.float32) @ BW).reshape(S.shape[:-1] + (W.shape[1],))
        proj += cW
        proj += (f0 @ W).astype(np.float32)[:, None, None, :]
        return F, proj


def r2(y, yhat):
    y, yhat = y.reshape(len(y), -1), yhat.reshape(len(yhat), -1)
    return 1.0 - ((y - yhat) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)


def linear_r2(F, Y):
    """R^2 (per output) of the best affine map F -> Y."""
    F = F.reshape(-1, F.shape[-1])
    Y = Y.reshape(-1, Y.shape[-1])
    A = np.concatenate([F, np.ones((len(F), 1))], axis=1)
    coef, *_ = np.linalg.lstsq(A, Y, rcond=None)
    return r2(Y, A @ coef)


# ------------------------------------------------------------------------------------------ planning
def mpc_episodes(rng, cfg: Config, p0, g, o, rho, score_fn, first_features):
    """Random-shooting MPC over a batch of episodes.

    score_fn(state, actions) -> (E, N) predicted return of each candidate sequence.
    first_features(rng, p) -> per-step planner state (observation-derived or ground truth).
    Returns the final distance to the goal per episode.
    """
    E = len(p0)
    p = p0.copy()
    for _ in range(cfg.horizon):
        state = first_features(rng, p)
        acts = rng.uniform(-1, 1, (E, cfg.candidates, cfg.plan_horizon, 2))
        best = np.argmax(score_fn(state, acts), axis=1)
        p = p + cfg.step * acts[np.arange(E), best, 0]
    return np.linalg.norm(p - g, axis=1)


def oracle_mpc(rng, cfg: Config, p0, g, o, rho):
    """Same planner with the true state, true dynamics and ground-truth reward (planner sanity check)."""

    def score(p, acts):
        P = p[:, None, None, :] + cfg.step * np.cumsum(acts, axis=2)
        return true_reward(P, g[:, None, None], o[:, None, None], rho[:, None, None], cfg).sum(-1)

    return mpc_episodes(rng, cfg, p0, g, o, rho, score, lambda rng, p: p)


def run_seed(cfg: Config, sigma_r: float, sigma_e: float, seed: int) -> dict:
    """Train both variants on shared data and evaluate them on the same episodes."""
    rng = np.random.default_rng([seed, int(round(sigma_r * 1e6)), int(round(sigma_e * 1e6))])
    sensor = Sensor(rng, cfg, sigma_r, sigma_e)
    data = collect(rng, sensor, cfg, cfg.train_episodes, cfg.train_steps)
    enc = PCA(data["X"], cfg.latent_dim)
    enc_r = PCA(data["X_R"], Z_R_DIM)
    readout = None
    if cfg.control:  # diagnostic only: a linear read-out of the agent position from z_hat, fit with state labels
        Fz = enc(data["X"]).reshape(-1, cfg.latent_dim)
        coef, *_ = np.linalg.lstsq(np.c_[Fz, np.ones(len(Fz))], data["P"].reshape(-1, 2), rcond=None)
        ro = np.c_[Fz, np.ones(len(Fz))] @ coef
        mu, sd = ro.mean(0), ro.std(0) + 1e-12

        def readout(f):
            return (np.concatenate([f, np.ones(f.shape[:-1] + (1,))], axis=-1) @ coef - mu) / sd

    def build(name, X, X_R):
        f = enc(X)
        if name == "z":
            return f
        return np.concatenate([f, enc_r(X_R) if name == "z+zR" else readout(f)], axis=-1)

    names = ["z", "z+zR"] + (["z+Lz"] if cfg.control else [])
    feats = {n: build(n, data["X"], data["X_R"]) for n in names}
    out = {"seed": seed, "sigma_r": sigma_r, "sigma_e": sigma_e,
           "agent_r2_z": float(linear_r2(feats["z"], data["P"]).mean()),
           "agent_r2_z+zR": float(linear_r2(feats["z+zR"], data["P"]).mean())}
    held = collect(rng, sensor, cfg, max(50, cfg.train_episodes // 10), cfg.train_steps)
    ep = sample_episodes(rng, cfg.eval_episodes, cfg)
    eval_seed = int(rng.integers(2**31))
    for name, F in feats.items():
        V = RewardModel(F, data["r"], cfg, rng)
        dyn = LatentActionModel(F, data["a"])
        out[f"reward_r2_{name}"] = float(r2(held["r"].reshape(-1),
                                            V(build(name, held["X"], held["X_R"])).reshape(-1))[0])

        def features(rng_, p, _name=name):
            X, X_R, _, _ = sensor.observe(rng_, p, ep[1], ep[2], ep[3])
            return build(_name, X, X_R)

        def score(f0, acts, V=V, dyn=dyn):
            return V(*dyn.rollout(f0, acts, V.W)).sum(-1)

        # same eval rng for both variants: same action candidates / noise stream start
        dist = mpc_episodes(np.random.default_rng(eval_seed), cfg, *ep, score, features)
        out[f"dist_{name}"] = float(dist.mean())
    return out


# ---------------------------------------------------------------------------------------- experiment
MODELS = (("z", "V(ẑ)"), ("z+zR", "V(ẑ, ẑ_R)"))
CONTROL = (("z+Lz", "control V(ẑ, Lẑ)"),)


def regimes(cfg: Config):
    lo, hi = cfg.sigma_lo, cfg.sigma_hi
    mid = math.sqrt(lo * hi)
    rows = [("σ_E > σ_R", lo, hi), ("σ_E = σ_R", mid, mid), ("σ_E < σ_R", hi, lo)]
    if cfg.sigma_r > 0 and cfg.sigma_e > 0:
        rows.append(("extra (--sigma-r/--sigma-e)", cfg.sigma_r, cfg.sigma_e))
    return rows


def _task(args):
    return run_seed(*args)


def run_many(cfg: Config, settings, log=None):
    """settings: list of (sigma_r, sigma_e). Returns {setting: [per-seed dicts]} (deterministic per seed)."""
    tasks = [(cfg, sr, se, s) for sr, se in settings for s in range(cfg.seeds)]
    if cfg.workers > 1 and len(tasks) > 1:
        import multiprocessing as mp

        with mp.get_context("fork").Pool(min(cfg.workers, len(tasks))) as pool:
            results = pool.map(_task, tasks, chunksize=max(1, len(tasks) // (4 * cfg.workers)))
    else:
        results = [_task(t) for t in tasks]
    out = {st: [] for st in settings}
    for t, r in zip(tasks, results):
        out[(t[1], t[2])].append(r)
    return out


def mean_ci(x):
    """Mean and half-width of the 95% t-interval across seeds."""
    from scipy import stats

    x = np.asarray(x, float)
    half = stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x))
    return float(x.mean()), float(half)


def summarise(rows):
    s = {}
    for key, _ in MODELS + CONTROL:
        if f"dist_{key}" in rows[0]:
            s[key] = mean_ci([r[f"dist_{key}"] for r in rows])
    s["gap"] = mean_ci([r["dist_z"] - r["dist_z+zR"] for r in rows])
    for k in ("agent_r2_z", "agent_r2_z+zR", "reward_r2_z", "reward_r2_z+zR"):
        s[k] = mean_ci([r[k] for r in rows])
    return s


def markdown_table(cfg: Config, res) -> str:
    lines = [
        f"| regime | σ_R | σ_E | {MODELS[0][1]} | {MODELS[1][1]} | gap (paired) | agent R² from ẑ "
        "| reward-model R², V(ẑ) / V(ẑ, ẑ_R) |" + (f" {CONTROL[0][1]} |" if cfg.control else ""),
        "|---|---|---|---|---|---|---|---|" + ("---|" if cfg.control else ""),
    ]
    for name, sr, se in regimes(cfg):
        s = summarise(res[(sr, se)])
        cell = lambda m: f"{s[m][0]:.2f} ± {s[m][1]:.2f}"  # noqa: E731
        lines.append(f"| {name} | {sr:.3g} | {se:.3g} | {cell('z')} | {cell('z+zR')} | {cell('gap')} "
                     f"| {cell('agent_r2_z')} | {s['reward_r2_z'][0]:.2f} / {s['reward_r2_z+zR'][0]:.2f} |"
                     + (f" {cell('z+Lz')} |" if cfg.control else ""))
    return "\n".join(lines)


def _new_file(out_dir: Path, stem: str, suffix: str) -> Path:
    """A path that did not exist before (timestamped, with a counter on collision); created exclusively."""
    for i in range(1000):
        p = out_dir / f"{stem}{'' if i == 0 else f'-{i}'}{suffix}"
        try:
            with open(p, "x"):
                return p
        except FileExistsError:
            continue
    raise OSError(f"could not find a free file name for {stem}{suffix} in {out_dir}")


def write_csv(path: Path, rows):
    cols = ["regime", "sigma_r", "sigma_e", "log_ratio", "seed", "dist_z", "dist_z+zR", "gap",
            "agent_r2_z", "agent_r2_z+zR", "reward_r2_z", "reward_r2_z+zR", "dist_z+Lz_control"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for regime, r in rows:
            w.writerow([regime, f"{r['sigma_r']:.6g}", f"{r['sigma_e']:.6g}",
                        f"{math.log(r['sigma_e'] / r['sigma_r']):.6g}", r["seed"],
                        f"{r['dist_z']:.6g}", f"{r['dist_z+zR']:.6g}", f"{r['dist_z'] - r['dist_z+zR']:.6g}",
                        f"{r['agent_r2_z']:.6g}", f"{r['agent_r2_z+zR']:.6g}",
                        f"{r['reward_r2_z']:.6g}", f"{r['reward_r2_z+zR']:.6g}",
                        f"{r.get('dist_z+Lz', float('nan')):.6g}"])


def sweep_settings(cfg: Config):
    L = math.log(cfg.sigma_hi / cfg.sigma_lo)
    mid = math.sqrt(cfg.sigma_lo * cfg.sigma_hi)
    out = []
    for x in np.linspace(-L, L, cfg.sweep_points):
        sr, se = mid * math.exp(-x / 2), mid * math.exp(x / 2)
        # snap to the exact table values so the end/middle points reuse the same seeds
        for _, tr, te in regimes(cfg)[:3]:
            if abs(sr - tr) < 1e-9 and abs(se - te) < 1e-9:
                sr, se = tr, te
        out.append((sr, se))
    return out


def plot_sweep(cfg: Config, res, settings, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.array([math.log(se / sr) for sr, se in settings])
    S = [summarise(res[st]) for st in settings]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for key, label in MODELS:
        m = np.array([s[key][0] for s in S])
        h = np.array([s[key][1] for s in S])
        ax[0].errorbar(x, m, yerr=h, marker="o", capsize=3, label=label)
    ax[0].set_xlabel("log(σ_E / σ_R)   (σ_R·σ_E fixed)")
    ax[0].set_ylabel("final distance to goal (lower is better)")
    ax[0].legend()
    ax[0].set_title("MPC with each reward model")
    m = np.array([s["gap"][0] for s in S])
    h = np.array([s["gap"][1] for s in S])
    ax[1].errorbar(x, m, yerr=h, marker="o", capsize=3, color="k", label="gap: V(ẑ) − V(ẑ, ẑ_R)")
    ax[1].axhline(0, color="gray", lw=0.8)
    ax[1].set_xlabel("log(σ_E / σ_R)")
    ax[1].set_ylabel("distance gap (>0: ẑ_R helps)")
    ax2 = ax[1].twinx()
    ax2.plot(x, [s["agent_r2_z"][0] for s in S], "s--", color="tab:red", alpha=0.7, label="agent-position R² from ẑ")
    ax2.plot(x, [s["agent_r2_z+zR"][0] for s in S], ":", color="tab:red", alpha=0.7,
             label="… from [ẑ, ẑ_R] (noise ceiling)")
    ax2.set_ylim(-0.05, 1.05)
    ax2.set_ylabel("R² of a linear fit of the agent position", color="tab:red")
    h1, l1 = ax[1].get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax[1].legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    ax[1].set_title(f"gap, mean ± 95% CI over {cfg.seeds} seeds")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------------------- CLI
class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one clear line, no usage dump
        self.exit(2, f"{self.prog}: error: {message}\n")


def parse_args(argv=None) -> Config:
    p = _Parser(prog="toy_pointmass.py",
                description="SEAR toy point-mass experiment (see module docstring).",
                formatter_class=argparse.ArgumentDefaultsHelpFormatter, allow_abbrev=False)
    defaults = Config()
    for f in dataclasses.fields(Config):
        flag = "--" + f.name.replace("_", "-")
        kw = dict(dest=f.name, default=argparse.SUPPRESS,
                  help=f"{f.metadata['help']} (default: {getattr(defaults, f.name)})")
        if f.type in (bool, "bool"):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, **kw)
        else:
            typ = {"int": int, "float": float, "str": str}.get(f.type, f.type)
            p.add_argument(flag, type=typ, metavar=f.name.upper(), **kw)
    given = vars(p.parse_args(argv))
    values = dict(QUICK) if given.get("quick") else {}
    values.update(given)
    cfg = Config(**values)
    problem = validate(cfg)
    if problem:
        p.error(problem)
    return cfg


def validate(cfg: Config):
    if cfg.seeds < 2:
        return f"--seeds must be >= 2 (a 95% CI needs at least two seeds), got {cfg.seeds}"
    for name in ("train_episodes", "train_steps", "eval_episodes", "horizon", "rff", "candidates",
                 "plan_horizon", "workers", "obs_dim"):  # rff may be 0 (quadratic model only)
        if getattr(cfg, name) < 1:
            return f"--{name.replace('_', '-')} must be >= 1, got {getattr(cfg, name)}"
    if not 1 <= cfg.latent_dim < Z_DIM:
        return f"--latent-dim must be in [1, {Z_DIM - 1}] (a bottleneck narrower than z), got {cfg.latent_dim}"
    if cfg.obs_dim < Z_DIM:
        return f"--obs-dim must be >= {Z_DIM}, got {cfg.obs_dim}"
    for name in ("sigma_lo", "sigma_hi", "arena", "step", "goal_scale", "rff_bandwidth", "rho_min"):
        v = getattr(cfg, name)
        if not (v > 0 and math.isfinite(v)):
            return f"--{name.replace('_', '-')} must be a positive finite number, got {v}"
    if (cfg.sigma_r > 0) != (cfg.sigma_e > 0) or cfg.sigma_r < 0 or cfg.sigma_e < 0 \
            or not (math.isfinite(cfg.sigma_r) and math.isfinite(cfg.sigma_e)):
        return f"--sigma-r and --sigma-e must be given together as positive numbers, got {cfg.sigma_r}, {cfg.sigma_e}"
    if not cfg.sigma_lo < cfg.sigma_hi:
        return f"--sigma-lo ({cfg.sigma_lo}) must be smaller than --sigma-hi ({cfg.sigma_hi})"
    if not cfg.rho_min <= cfg.rho_max:
        return f"--rho-min ({cfg.rho_min}) must be <= --rho-max ({cfg.rho_max})"
    if not (cfg.ridge >= 0 and cfg.obstacle_weight >= 0):
        return "--ridge and --obstacle-weight must be >= 0"
    if cfg.sweep and cfg.sweep_points < 2:
        return f"--sweep-points must be >= 2, got {cfg.sweep_points}"
    return None


def main(argv=None) -> int:
    cfg = parse_args(argv)
    t0 = time.time()
    out_dir = Path(cfg.out)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"toy_pointmass.py: error: cannot create output directory {out_dir}: {e.strerror}", file=sys.stderr)
        return 1
    settings = list(dict.fromkeys((sr, se) for _, sr, se in regimes(cfg)))
    if cfg.sweep:
        settings += [st for st in sweep_settings(cfg) if st not in settings]
    res = run_many(cfg, settings)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    table = markdown_table(cfg, res)
    print(f"SEAR toy point-mass: final distance to goal, mean ± 95% CI over {cfg.seeds} seeds "
          f"({cfg.eval_episodes} eval episode{'s' * (cfg.eval_episodes != 1)} each){' [--quick: not meaningful]' if cfg.quick else ''}\n")
    print(table)
    rows = [(name, r) for name, sr, se in regimes(cfg) for r in res[(sr, se)]]
    try:
        path = _new_file(out_dir, f"toy_table_{stamp}", ".csv")
        write_csv(path, rows)
        print(f"\nwrote {path}")
        if cfg.sweep:
            sw = sweep_settings(cfg)
            path = _new_file(out_dir, f"toy_sweep_{stamp}", ".csv")
            write_csv(path, [("sweep", r) for st in sw for r in res[st]])
            print(f"wrote {path}")
            path = _new_file(out_dir, f"toy_sweep_{stamp}", ".png")
            plot_sweep(cfg, res, sw, path)
            print(f"wrote {path}")
            print("\nsweep (log σ_E/σ_R: gap V(ẑ) − V(ẑ, ẑ_R), mean ± 95% CI):")
            for st in sw:
                g = summarise(res[st])["gap"]
                print(f"  {math.log(st[1] / st[0]):+.2f}: {g[0]:+.2f} ± {g[1]:.2f}")
    except OSError as e:
        print(f"toy_pointmass.py: error: cannot write results to {out_dir}: {e}", file=sys.stderr)
        return 1
    print(f"wall time {time.time() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BrokenPipeError:  # e.g. `python toy_pointmass.py | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)
