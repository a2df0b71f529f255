"""drm.py (--drm): DrM's dormant ratio, awaken exploration, expectile value and blended target, and
shrink-and-perturb. Each piece is checked twice: against hand-computed values (runs everywhere), and
against the released code (github.com/XuGW-Kevin/DrM, agents/drm.py and utils.py) on the same
weights and batch, which needs SEAR_DRM_REFERENCE to name a checkout or a git mirror of it (its files
are read at test time; this project ships none of them)."""
import copy
import importlib.util
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from harness import cli
from methods import drm
import sear
import train
from tests.test_cli import rows, run, straight_and_resumed, tiny

REFERENCE = os.environ.get("SEAR_DRM_REFERENCE", "")
RELEASED_COMMIT = "317116a"  # the commit docs/drm.md describes


def drm_cfg(method="drq", **kw):
    base = dict(method=method, drm=True, latent_dim=64, hidden_dim=64, feature_dim=16, batch_size=8,
                action_repeat=2, std_steps=100_000)
    return train.Config(**{**base, **kw})


def replay_batch(n=8, action_dim=2, seed=0):
    """(obs, mask, action, reward, discount, next_obs, next_mask) as the replay buffer samples them."""
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8), rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8),
            rng.uniform(-1, 1, (n, action_dim)).astype(np.float32), rng.normal(size=(n, 1)).astype(np.float32),
            np.full((n, 1), 0.97, np.float32), rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8),
            rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8))


def never_stepped(state) -> bool:
    """An Adam state as a parameter that has never been stepped has it: count 0, moments 0."""
    return not state["step"] and not state["exp_avg"].any() and not state["exp_avg_sq"].any()


# ---------------------------------------------------------------- hand-computed
def test_dormant_ratio_scores_the_relu_activation_of_hidden_layers():
    """A 2-3-3-1 actor by hand. Trunk outputs (before LayerNorm) have batch means |.| = [1, 0.01]: the
    second is below 0.025 x their mean 0.505, dormant. Hidden layer 1: unit 0 follows h0, unit 2 h1
    (each positive in one of the two samples), unit 1 has bias -100: its ReLU is 0, dormant; scored
    before the ReLU it would be the largest (100) and units 0 and 2 (0.76 < 0.025 x 33.8) the dormant
    ones. Hidden layer 2 copies layer 1 (unit 1 dormant); the one output neuron is never dormant.
    3 of 2 + 3 + 3 + 1 = 9."""
    actor = sear.Actor(repr_dim=2, action_dim=1, feature_dim=2, hidden_dim=3)
    with torch.no_grad():
        for m in actor.modules():
            if isinstance(m, torch.nn.Linear):
                m.bias.zero_()
        actor.trunk[0].weight.copy_(torch.eye(2))
        actor.policy[0].weight.copy_(torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]))
        actor.policy[0].bias.copy_(torch.tensor([0.0, -100.0, 0.0]))
        actor.policy[2].weight.copy_(torch.eye(3))
        actor.policy[4].weight.copy_(torch.ones(1, 3))
    latent = torch.tensor([[1.0, 0.01], [-1.0, 0.01]])
    assert drm.dormant_ratio(actor, latent, threshold=0.025) == 3 / 9
    assert drm.dormant_ratio(actor, latent, threshold=0.0) == 0.0  # nothing is below 0


def test_awaken_std_lambda_and_perturb_factor_by_hand():
    agent = train.make_agent(drm_cfg(), action_dim=2, device=torch.device("cpu"))
    d = agent
    assert d.ratio == 1.0 and d.awake_at is None  # DrM's start: std ~1, lambda ~0, factor at its floor
    assert d.std(0) == pytest.approx(1 / (1 + math.exp(-8)), abs=1e-15)
    assert d.lam == pytest.approx(0.6 / (1 + math.exp(40)), rel=1e-12)
    assert d.perturb_factor() == 0.2
    d.ratio = 0.2  # at the target both sigmoids are at their middle
    assert d.std(10**6) == 0.5 and d.lam == pytest.approx(0.3) and d.perturb_factor() == pytest.approx(0.6)
    d.ratio, d.awaken_step = 0.0, 1000  # awake: the larger of the dormant std and DrQ-v2's schedule from 1000
    assert d.std(1000) == 1.0 and d.std(51_000) == pytest.approx(0.55)
    assert d.std(10**7) == pytest.approx(1 / (1 + math.exp(2)))  # the schedule's 0.1 is below sigmoid(-2)
    assert d.lam == pytest.approx(0.6 / (1 + math.exp(-10))) and d.perturb_factor() == 1.0
    agent.cfg.drm_max_perturb = 0.9
    assert d.perturb_factor() == 0.9


def test_the_actor_wakes_once_after_the_uniform_steps_below_the_target(monkeypatch):
    """DrM: awaken_step is the first update after num_expl_steps whose ratio is below the target; it
    never goes back to sleep, and the std then follows the schedule counted from that step."""
    agent = train.make_agent(drm_cfg(exploration_steps=2000), action_dim=2, device=torch.device("cpu"))
    ratios = iter([0.1, 0.3, 0.1, 0.5])
    monkeypatch.setattr(drm, "dormant_ratio", lambda *a, **k: next(ratios))
    latent, action = torch.randn(4, agent.encoder.repr_dim), torch.zeros(4, 2)
    for step, awake in ((2000, None), (2002, None), (2004, 2004), (2006, 2004)):
        m = agent.observe(latent, action, step)
        assert agent.awake_at == awake
    assert m["dormant_ratio"] == 0.5
    assert agent.std(2006) == pytest.approx(max(1 / (1 + math.exp(-3)), sear.linear_std(agent.cfg, 2)), rel=1e-12)
    assert "perturb_factor" not in m


def test_expectile_loss_and_blended_target_by_hand(device):
    diff = torch.tensor([[-1.0], [2.0]], device=device)  # V - Q: one below (weight 0.9), one above (weight 0.1)
    assert drm.expectile_loss(diff, 0.9).item() == pytest.approx((0.9 * 1 + 0.1 * 4) / 2)
    agent = train.make_agent(drm_cfg(), action_dim=2, device=device)
    agent.ratio = 0.2  # lambda = 0.3
    next_latent = torch.randn(5, agent.encoder.repr_dim, device=device)
    noise = torch.randn(5, 2, device=device)
    with torch.no_grad():
        # min(Q1', Q2') of the same noisy action
        target_q = sear.Agent.next_value(agent, next_latent, agent.std(5000), noise)
        expected = 0.3 * agent.value(next_latent) + 0.7 * target_q
        torch.testing.assert_close(agent.next_value(next_latent, agent.std(5000), noise), expected)


def test_value_steps_bring_v_to_the_expectile_of_q_over_the_actions():
    """observe() takes one Adam step of V on the expectile loss against min(Q1, Q2) of the batch's
    actions. One state with 64 actions: V(s) goes to the 0.9-expectile of their Q (the m with
    sum_i w_i (q_i - m) = 0, w_i = 0.9 above m and 0.1 below), above their mean; the critic is untouched."""
    torch.manual_seed(0)
    agent = train.make_agent(drm_cfg(lr=1e-3), action_dim=2, device=torch.device("cpu"))
    latent, action = torch.randn(1, agent.encoder.repr_dim).repeat(64, 1), torch.rand(64, 2) * 2 - 1
    critic = copy.deepcopy(agent.critic.state_dict())
    for _ in range(150):
        agent.observe(latent, action, 5000)
    assert all(torch.equal(v, agent.critic.state_dict()[k]) for k, v in critic.items())
    with torch.no_grad():
        q = torch.min(*agent.critic(latent, action)).squeeze(1).double().numpy()
        v = agent.value(latent)[0].item()
    m = q.mean()
    for _ in range(200):  # the expectile's fixed point
        w = np.where(q > m, 0.9, 0.1)
        m = (w * q).sum() / w.sum()
    assert v == pytest.approx(m, abs=0.01 * q.std()) and v > q.mean() + 0.5 * q.std()


@pytest.mark.parametrize("method", ["drq", "sear"])
def test_perturb_mixes_every_linear_layer_with_a_fresh_init_and_resets_adam(method, device):
    """factor 0.4 (ratio 0.3): each Linear bias becomes 0.4 x itself (fresh biases are 0) and each
    weight 0.4 W + 0.6 O with O orthogonal (DrQ-v2's init); LayerNorm, convolutions and SEAR's
    decoders keep theirs. Adam forgets the moments of the perturbed networks, not the decoders'."""
    torch.manual_seed(0)
    agent = train.make_agent(drm_cfg(method, drm_perturb_every=10), action_dim=2, device=device)
    agent.update(replay_batch(), step=4)  # Adam moments everywhere
    before = {name: copy.deepcopy(getattr(agent, name).state_dict()) for name in ("actor", "critic", "encoder", "aux")
              if getattr(agent, name) is not None}
    before["value"] = copy.deepcopy(agent.value.state_dict())
    agent.ratio = 0.3
    agent.perturb_if_due(15)
    assert torch.equal(agent.actor.trunk[0].weight, before["actor"]["trunk.0.weight"])  # not due
    agent.perturb_if_due(20)
    nets = {"actor": agent.actor, "critic": agent.critic, "encoder": agent.encoder, "value": agent.value}
    linear = 0
    for name, net in nets.items():
        for mod_name, m in net.named_modules():
            prefix = f"{mod_name}." if mod_name else ""
            if isinstance(m, torch.nn.Linear):
                linear += 1
                torch.testing.assert_close(m.bias, 0.4 * before[name][prefix + "bias"])
                fresh = (m.weight - 0.4 * before[name][prefix + "weight"]) / 0.6
                small = min(fresh.shape)
                gram = fresh @ fresh.T if fresh.shape[0] == small else fresh.T @ fresh
                torch.testing.assert_close(gram, torch.eye(small, device=device), atol=1e-4, rtol=0)
            elif not list(m.children()):
                for p_name, p in m.named_parameters():
                    assert torch.equal(p, before[name][prefix + p_name]), (name, prefix + p_name)
    assert linear == 4 + 7 + (1 if method == "sear" else 0) + 4  # SEAR's encoder has one Linear (its fc)
    perturbed = [*agent.actor.parameters(), *agent.critic.parameters(), *agent.encoder.parameters(),
                 *agent.value.parameters()]
    states = {**agent.model_opt.state, **agent.actor_opt.state, **agent.value_opt.state}
    assert all(never_stepped(states[p]) for p in perturbed)
    if method == "sear":
        assert all(torch.equal(v, before["aux"][k]) for k, v in agent.aux.state_dict().items())
        assert not any(never_stepped(agent.model_opt.state[p]) for p in agent.aux.parameters())
    agent.ratio = 0.3
    m = agent.update(replay_batch(), step=30)  # an update that perturbs reports it, the next one does not
    assert m["perturb_factor"] == pytest.approx(0.4) and "perturb_factor" not in agent.update(replay_batch(), 32)
    assert set(m) == set(agent.metric_names)


def test_drm_leaves_the_runs_initial_networks_and_random_stream_as_without_it():
    """V is drawn from a fork of the torch RNG: a DrQ run and a DrM run of one seed start from the same
    networks, their agents' generators from the same state (the same first actions), and torch's
    stream is left where it was."""
    states = []
    for flag in (False, True):
        torch.manual_seed(3)
        agent = train.make_agent(drm_cfg(drm=flag), action_dim=2, device=torch.device("cpu"))
        actor = {k: v.clone() for k, v in agent.actor.state_dict().items()}
        states.append((actor, agent.rng.get_state(), torch.get_rng_state()))
    assert all(torch.equal(v, states[1][0][k]) for k, v in states[0][0].items())
    assert torch.equal(states[0][1], states[1][1]) and torch.equal(states[0][2], states[1][2])


def test_without_drm_nothing_of_it_is_built_logged_or_saved(device):
    agent = train.make_agent(drm_cfg(drm=False), action_dim=2, device=device)
    assert not isinstance(agent, drm.DrMAgent) and not set(drm.METRICS) & set(agent.metric_names)
    assert "drm" not in agent.state_dict()
    assert not set(drm.METRICS) & set(agent.update(replay_batch(), step=4))


def test_a_snapshot_holds_all_of_drms_state(device):
    a = train.make_agent(drm_cfg(drm_perturb_every=6), action_dim=2, device=device)
    for step in (4, 6):
        a.update(replay_batch(), step)
    a.awaken_step = 4
    b = train.make_agent(drm_cfg(drm_perturb_every=6), action_dim=2, device=device)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    assert (b.ratio, b.awake_at) == (a.ratio, 4)
    ma = a.update(replay_batch(seed=1), 8)  # b's generator: a's, from the snapshot
    mb = b.update(replay_batch(seed=1), 8)
    assert ma.keys() == mb.keys() and all(torch.equal(ma[k], mb[k]) for k in ma)
    assert all(torch.equal(v, b.value.state_dict()[k]) for k, v in a.value.state_dict().items())


# ---------------------------------------------------------------- flags
def parse(argv):
    return cli.parse_args(argv, train.Config, train.METHODS)[0]


def test_drm_flags_defaults_and_task_cfgs():
    cfg = parse(["--env", "humanoid-run", "--drm"])
    assert (cfg.drm_max_perturb, cfg.drm_lambda, cfg.drm_expectile, cfg.drm_perturb_every) == (0.6, 0.6, 0.9, 100_000)
    assert parse(["--env", "humanoid-walk", "--drm"]).drm_max_perturb == 0.9
    assert parse(["--env", "humanoid-run"]).drm_max_perturb == 1.0  # no --drm: DrM's table does not apply
    assert parse(["--env", "humanoid-run", "--drm", "--drm-max-perturb", "0.8"]).drm_max_perturb == 0.8
    assert parse(["--env", "cartpole-balance_sparse", "--drm"]).drm_max_perturb == 1.0
    assert cli.method_label(cfg) == "sear+drm" and cli.method_label({"method": "drq"}) == "drq"


@pytest.mark.parametrize("argv, message", [
    (["--drm-expectile", "1.5"], "--drm-expectile must be in [0, 1], got 1.5"),
    (["--drm-perturb-every", "0"], "--drm-perturb-every must be > 0, got 0"),
    (["--drm-min-perturb", "0.9", "--drm-max-perturb", "0.5"], "--drm-min-perturb (0.9) must not exceed"),
    (["--drm-perturb-every", "1001"], "--drm-perturb-every (1001) must be a multiple of --update-every (2)"),
])
def test_bad_drm_flags_are_one_line(tmp_path, argv, message):
    r = run(["--env", "cartpole-balance_sparse", "--drm", *argv], tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and message in r.stderr, r.stderr


# ---------------------------------------------------------------- sear.py end to end
DRM_TINY = [*tiny("drq"), "--method", "drq", "--drm", "--drm-perturb-every", "8", "--exploration-steps", "4",
            "--drm-target-ratio", "0.5", "--feature-dim", "8", "--threads", "1"]


def test_a_drm_run_logs_its_columns_and_resumes_exactly(tmp_path):
    """48 frames + --resume to 80 equal 80 in one go, perturbations (every 8 steps) and awakening
    included: DrM's state is in the snapshot and its randomness in the agent's generator, saved
    there."""
    straight_dir, split_dir, r = straight_and_resumed(
        ["--env", "cartpole-balance_sparse", "--seed", "2", "--save-buffer", *DRM_TINY], tmp_path)
    assert "__drq+drm__2__" in straight_dir.name and "method drq+drm on" in r.stdout
    cols = ["frame", "return", "critic_loss", "actor_loss", *drm.METRICS]
    table = [[row[c] for c in cols] for row in rows(straight_dir / "train.csv")]
    assert table == [[row[c] for c in cols] for row in rows(split_dir / "train.csv")]
    assert sum(row[-1] != "" for row in table) >= 3  # perturbations before and after the split
    a = torch.load(straight_dir / "snapshot.pt", weights_only=False)["agent"]
    b = torch.load(split_dir / "snapshot.pt", weights_only=False)["agent"]
    assert a["drm"]["awaken_step"] is not None and a["drm"]["awaken_step"] == b["drm"]["awaken_step"]
    for part in ("encoder", "actor", "critic"):
        assert all(torch.equal(v, b[part][k]) for k, v in a[part].items())
    assert all(torch.equal(v, b["drm"]["value"][k]) for k, v in a["drm"]["value"].items())


# ---------------------------------------------------------------- against the released code
@pytest.fixture(scope="module")
def released(tmp_path_factory):
    """DrM's agents/drm.py and utils.py, read from SEAR_DRM_REFERENCE (a checkout, or a git mirror at
    RELEASED_COMMIT) and imported under a name of their own."""
    if not REFERENCE:
        pytest.skip("set SEAR_DRM_REFERENCE to a checkout (or git mirror) of github.com/XuGW-Kevin/DrM to "
                    "compare with the released code")
    src = tmp_path_factory.mktemp("drm_released")
    for path in ("agents/drm.py", "utils.py"):
        if (Path(REFERENCE) / path).is_file():
            text = (Path(REFERENCE) / path).read_text()
        else:
            r = subprocess.run(["git", "--git-dir", REFERENCE, "show", f"{RELEASED_COMMIT}:{path}"],
                               capture_output=True, text=True)
            if r.returncode:
                pytest.fail(f"SEAR_DRM_REFERENCE={REFERENCE}: no {path} at {RELEASED_COMMIT} ({r.stderr.strip()})")
            text = r.stdout
        (src / Path(path).name).write_text(text)
    path, utils = list(sys.path), sys.modules.pop("utils", None)
    sys.path.insert(0, str(src))  # their drm.py imports their utils.py as `utils`
    try:
        spec = importlib.util.spec_from_file_location("drm_released", src / "drm.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path[:] = path
        sys.modules.pop("utils", None)
        if utils is not None:
            sys.modules["utils"] = utils
    return module


def released_agent(released, cfg, action_dim=2):
    return released.DrMAgent(
        obs_shape=(9, 84, 84), action_shape=(action_dim,), device=torch.device("cpu"), lr=cfg.lr,
        feature_dim=cfg.feature_dim, hidden_dim=cfg.hidden_dim, critic_target_tau=cfg.critic_tau,
        dormant_threshold=cfg.drm_dormant_threshold, target_dormant_ratio=cfg.drm_target_ratio,
        dormant_temp=cfg.drm_dormant_temp, target_lambda=cfg.drm_lambda, lambda_temp=cfg.drm_lambda_temp,
        dormant_perturb_interval=cfg.drm_perturb_every, min_perturb_factor=cfg.drm_min_perturb,
        max_perturb_factor=cfg.drm_max_perturb, perturb_rate=cfg.drm_perturb_rate,
        num_expl_steps=cfg.exploration_steps, stddev_type="awake",
        stddev_schedule=f"linear({cfg.std_start},{cfg.std_end},{cfg.std_steps})", stddev_clip=cfg.std_clip,
        expectile=cfg.drm_expectile, use_tb=True)


def pairs(theirs, ours):
    return ((theirs.encoder, ours.encoder), (theirs.actor, ours.actor), (theirs.critic, ours.critic),
            (theirs.critic_target, ours.critic_target), (theirs.value_predictor, ours.value))


def same_weights(released, cfg):
    """Our agent and the released one, the released one given our weights (tensor by tensor, in order)."""
    ours = train.make_agent(cfg, action_dim=2, device=torch.device("cpu"))
    theirs = released_agent(released, cfg)
    with torch.no_grad():
        for t, o in pairs(theirs, ours):
            for (kt, vt), (ko, vo) in zip(t.state_dict().items(), o.state_dict().items(), strict=True):
                assert vt.shape == vo.shape, (kt, ko)
                vt.copy_(vo)
    return theirs, ours


def assert_same_weights(theirs, ours, atol=0.0):
    for t, o in pairs(theirs, ours):
        for (kt, vt), (ko, vo) in zip(t.state_dict().items(), o.state_dict().items(), strict=True):
            torch.testing.assert_close(vt, vo.contiguous(), rtol=0, atol=atol, msg=f"{kt} / {ko}")


def dormant_actor(actor, seed=0):
    """The actor with some neurons silenced (dead ReLUs, tiny trunk rows), so that ratios are not 0."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        actor.policy[0].bias[torch.randperm(actor.policy[0].out_features, generator=g)[:20]] = -50.0
        actor.trunk[0].weight[:3] *= 1e-3


def test_dormant_ratio_equals_the_released_cal_dormant_ratio(released):
    theirs, ours = same_weights(released, drm_cfg())
    dormant_actor(ours.actor)
    theirs.actor.load_state_dict(ours.actor.state_dict())
    obs = torch.as_tensor(replay_batch(n=16)[0]).float()
    latent = ours.encoder(sear.random_shift(obs)).detach()
    for threshold in (0.025, 0.1, 0.5):
        want = released.utils.cal_dormant_ratio(theirs.actor, latent, 0, percentage=threshold)
        assert drm.dormant_ratio(ours.actor, latent, threshold=threshold) == want
    assert want > 0.05


def test_std_lambda_and_perturb_factor_equal_the_released(released):
    for max_perturb in (1.0, 0.9, 0.6):
        theirs, ours = same_weights(released, drm_cfg(drm_max_perturb=max_perturb))
        for ratio in (0.0, 0.05, 0.2, 0.37, 0.9, 1.0):
            for awaken in (None, 3000):
                theirs.dormant_ratio = ours.ratio = ratio
                theirs.awaken_step = ours.awaken_step = awaken
                for step in (3000, 5000, 60_000, 10**6):  # float64 on the device: torch's exp, not libm's
                    assert ours.std(step) == pytest.approx(theirs.stddev(step), rel=1e-12), (ratio, awaken, step)
                assert ours.lam == pytest.approx(theirs.lambda_, rel=1e-12, abs=1e-300)
                assert ours.perturb_factor() == pytest.approx(theirs.perturb_factor(0), rel=1e-15)


def test_shrink_and_perturb_equals_the_released_on_the_same_rng(released):
    """Same weights, same torch RNG state: the same perturbed weights, bit for bit, and the same RNG
    state after (the fresh initialisations draw the same numbers in the same order)."""
    theirs, ours = same_weights(released, drm_cfg())
    ours.update(replay_batch(), step=4)  # Adam moments to forget; then the released agent gets these weights
    with torch.no_grad():
        for t, o in pairs(theirs, ours):
            for vt, vo in zip(t.state_dict().values(), o.state_dict().values()):
                vt.copy_(vo)
    theirs.dormant_ratio = ours.ratio = 0.3
    torch.manual_seed(11)
    theirs.perturb(100_000)
    rng_theirs = torch.get_rng_state()
    ours.rng.manual_seed(11)  # ours draws from its own generator what theirs draws from torch's
    ours.perturb_if_due(100_000)
    assert torch.equal(ours.rng.get_state(), rng_theirs)
    assert_same_weights(theirs, ours)
    assert all(never_stepped(s) for opt in (ours.model_opt, ours.actor_opt, ours.value_opt) for s in opt.state.values())
    assert all(not opt.state for opt in (theirs.encoder_opt, theirs.critic_opt, theirs.actor_opt, theirs.predictor_opt))


def test_value_step_equals_the_released_update_predictor(released):
    theirs, ours = same_weights(released, drm_cfg())
    obs = torch.as_tensor(replay_batch(n=16)[0]).float()
    latent = ours.encoder(sear.random_shift(obs)).detach()
    action = torch.rand(16, 2) * 2 - 1
    for _ in range(3):
        want = theirs.update_predictor(latent, action)["predictor_loss"]
        got = ours.observe(latent, action, 5000)["value_loss"]
        assert got == pytest.approx(want, rel=1e-6)
    for vt, vo in zip(theirs.value_predictor.parameters(), ours.value.parameters()):
        torch.testing.assert_close(vt, vo, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("awake", [False, True])
def test_whole_updates_equal_the_released_on_the_same_weights_and_batch(released, awake):
    """Three updates from step 100,000 (the first one perturbs): the blended target, the std of the
    next action and of the actor's step, V's step and the perturbation all as the released update, on
    the same weights, batches and torch RNG state. The losses agree to float rounding (our convolutions
    run channels_last); the weights to 2 x lr per update: Adam's first steps are +-lr whatever the
    gradient's size, so a gradient that rounding moves across 0 moves its weight by 2 lr."""
    theirs, ours = same_weights(released, drm_cfg(drm_target_ratio=0.6))  # lambda ~0.6 here: the blend counts
    if awake:
        theirs.awaken_step = ours.awaken_step = 90_000
    for i, step in enumerate((100_000, 100_002, 100_004)):
        batch = replay_batch(n=16, seed=i)
        obs, mask, action, reward, discount, next_obs, _ = batch
        torch.manual_seed(100 + i)
        want = theirs.update(iter([(obs, action, reward, discount, next_obs)]), step)
        ours.rng.manual_seed(100 + i)
        got = ours.update(batch, step)
        assert got["dormant_ratio"] == want["actor_dormant_ratio"] and ours.awake_at == theirs.awaken_step
        for ours_name, their_name in (("critic_loss", "critic_loss"), ("actor_loss", "actor_loss"),
                                      ("value_loss", "predictor_loss")):
            assert got[ours_name] == pytest.approx(want[their_name], rel=1e-4, abs=1e-6), ours_name
        assert_same_weights(theirs, ours, atol=2 * ours.cfg.lr * (i + 1))
        assert got["drm_lambda"] > 0.1
