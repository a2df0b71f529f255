"""--method curl (CURLAux) as CURL's reference implementation (github.com/MishaLaskin/curl, curl_sac.py):
W on the critic's feature, the key an EMA copy every 2nd update, its own Adam step after each update
(outside Eq. 6), the state an exact resume needs; and the reference's own CURL, update_cpc and key EMA
on the same weights and batch, which needs SEAR_CURL_REFERENCE to name a checkout or a git mirror of it."""
import copy
import io

import pytest
import torch

from harness import experiment
import sear
from tests import reference
from tests.test_baselines import agent_of, numpy_batch
from tests.test_sear import grads

RELEASED_COMMIT = "8416d6e"  # the commit docs/baselines.md describes


def curl_agent(device, **kw):
    return agent_of("curl", device, **kw)


def stepped(opt):
    """The parameters an optimiser steps, in its order."""
    return [p for group in opt.param_groups for p in group["params"]]


def obs_batch(device, n=8, seed=0):
    return torch.as_tensor(numpy_batch(n=n, seed=seed)[0], device=device).float()


def snapshot(module):
    return [p.detach().clone() for p in module.parameters()]


# ---------------------------------------------------------------- what CURL reads and owns
def test_w_reads_the_critics_feature_and_the_key_is_a_frozen_copy_of_it(device):
    agent = curl_agent(device)
    aux, cfg = agent.aux, agent.cfg
    query = aux.query[0]  # curl_sac.py's critic encoder (convs, fc, LayerNorm) = ours + the critic trunk's
    assert query[0] is agent.encoder and query[1] is agent.critic.trunk[0] and query[2] is agent.critic.trunk[1]
    assert aux.W.shape == (cfg.feature_dim, cfg.feature_dim)
    assert all(not p.requires_grad for p in aux.key.parameters())
    assert all(torch.equal(k, q) for k, q in zip(aux.key.parameters(), query.parameters(), strict=True))
    # the agent's networks are not the aux's: saved once, optimised by the joint step once
    assert {k.split(".")[0] for k in aux.state_dict()} == {"W", "key", "_extra_state"}
    joint = {id(p) for group in agent.model_opt.param_groups for p in group["params"]}
    assert len(joint) == sum(len(group["params"]) for group in agent.model_opt.param_groups)


def test_the_key_follows_by_ema_every_second_update_only(device):
    agent = curl_agent(device)
    aux, obs = agent.aux, obs_batch(device)
    with torch.no_grad():  # a key far from the online networks, so that an EMA shows
        for p in aux.key.parameters():
            p.add_(1.0)
    for update in range(5):
        online, key = snapshot(aux.query[0]), snapshot(aux.key)
        aux.after_update(obs, agent.rng)
        for o, k_before, k in zip(online, key, aux.key.parameters()):
            expected = k_before + agent.cfg.curl_tau * (o - k_before) if update % 2 == 0 else k_before
            torch.testing.assert_close(k, expected, msg=f"update {update}")
    assert aux.updates == 5


def test_curl_is_its_own_adam_step_after_the_update_not_a_term_of_eq6(device):
    agent = curl_agent(device, curl_lr=1e-3)
    aux, batch = agent.aux, numpy_batch()
    torch_batch = sear.Batch._make(torch.as_tensor(x, device=device).float() for x in batch)
    W = aux.W.detach().clone()
    # the joint step (Eq. 6): no CURL term
    _, metrics = agent.update_critic(torch_batch, 10**5, agent.draw(8))
    assert "curl_loss" not in metrics and torch.equal(aux.W, W)
    online = snapshot(aux.query[0])
    metrics = aux.after_update(torch_batch.obs, agent.rng)
    assert metrics["curl_loss"] > 0
    # Adam's first step moves each parameter by its learning rate (m / sqrt(v) = sign of the gradient):
    # W by --curl-lr, the encoder and feature by twice that (curl_sac.py's encoder_ and cpc_optimizer)
    torch.testing.assert_close((aux.W - W).abs(), torch.full_like(W, 1e-3), rtol=1e-3, atol=0)
    for before, p, grad in zip(online, aux.query[0].parameters(), grads(stepped(aux.opt))):
        moved = (p - before).abs()[grad.abs() > 1e-4]  # where eps = 1e-8 is negligible
        torch.testing.assert_close(moved, torch.full_like(moved, 2e-3), rtol=1e-3, atol=0)
    # and in the agent's update it comes last, after the actor's step (curl_sac.py's order)
    order = []
    update_actor = agent.update_actor
    agent.update_actor = lambda *a: (order.append("actor"), update_actor(*a))[1]
    after = aux.after_update
    aux.after_update = lambda obs, rng: (order.append("curl"), after(obs, rng))[1]
    assert "curl_loss" in agent.update(batch, step=10**5) and order == ["actor", "curl"]


def test_a_restored_agent_continues_exactly(device):
    """The key's EMA phase, CURL's own Adam and the generator its shifts come from are saved with
    the agent (a snapshot, --resume)."""
    torch.manual_seed(0)
    a = curl_agent(device)
    for i in range(3):
        a.update(numpy_batch(seed=i), step=10**5)
    buffer = io.BytesIO()
    torch.save(a.state_dict(), buffer)
    b = curl_agent(device)
    b.load_state_dict(torch.load(io.BytesIO(buffer.getvalue()), weights_only=False))
    assert b.aux.updates == 3 and len(b.aux.opt.state) == len(a.aux.opt.state) > 0
    for agent in (a, b):
        for i in range(3, 5):
            agent.update(numpy_batch(seed=i), step=10**5)
    for name in ("encoder", "critic", "actor", "aux"):
        sa, sb = getattr(a, name).state_dict(), getattr(b, name).state_dict()
        assert all(torch.equal(v, sb[k]) for k, v in sa.items() if k != "_extra_state"), name
    assert a.aux.updates == b.aux.updates == 5


@pytest.mark.parametrize("parts", ["encoder", "encoder+decoders", "all"])
def test_transfer_starts_the_key_from_what_was_loaded_and_curls_adam_afresh(device, parts):
    torch.manual_seed(0)
    source = curl_agent(device)
    for i in range(2):
        source.update(numpy_batch(seed=i), step=10**5)
    agent = curl_agent(device)
    experiment.copy_parts(agent, copy.deepcopy(source.state_dict()), parts)
    assert all(torch.equal(k, q) for k, q in zip(agent.aux.key.parameters(), agent.aux.query[0].parameters()))
    fresh = all(not s["step"] and not s["exp_avg"].any() for s in agent.aux.opt.state.values())
    assert agent.aux.updates == 0 and fresh  # CURL's own optimiser starts fresh
    assert torch.equal(agent.aux.W, source.aux.W) == (parts != "encoder")


# ---------------------------------------------------------------- against the reference
class Feature(torch.nn.Module):
    """Our critic's feature (encoder + trunk Linear + LayerNorm) behind curl_sac.py's encoder interface."""

    def __init__(self, net, feature_dim):
        super().__init__()
        self.net, self.feature_dim = net, feature_dim

    def forward(self, obs, detach=False):
        return self.net(obs)

    def copy_conv_weights_from(self, source):  # the actor's encoder: no part of CURL
        pass


@pytest.fixture(scope="module")
def curl_sac(tmp_path_factory):
    """The reference's curl_sac.py and encoder.py; of its utils.py (which imports gym and scikit-image)
    only soft_update_params, the key's EMA."""
    folder = reference.materialise("SEAR_CURL_REFERENCE", "MishaLaskin/curl", RELEASED_COMMIT,
                                   ["curl_sac.py", "encoder.py", "utils.py"], tmp_path_factory.mktemp("curl"))
    utils = reference.functions(folder / "utils.py", ["soft_update_params"], "utils")
    return reference.load(folder, "curl_sac.py", "curl_sac_released", stand_ins={"utils": utils})


class Replay:
    """curl_sac.py's replay buffer as CurlSacAgent.update reads it: one fixed batch, two given crops."""

    def __init__(self, anchor, positive):
        self.anchor, self.positive = anchor, positive

    def sample_cpc(self):
        n = len(self.anchor)
        return (self.anchor, torch.zeros(n, 2), torch.zeros(n, 1), self.anchor, torch.ones(n, 1),
                {"obs_anchor": self.anchor, "obs_pos": self.positive})


class Log:
    def __init__(self):
        self.curl = []

    def log(self, key, value, step):
        if key == "train/curl_loss":
            self.curl.append(value.item())


def test_same_loss_gradients_and_weights_as_the_reference(curl_sac, monkeypatch):
    """The reference's CurlSacAgent built around our critic's feature (its make_encoder), run through its
    own update (its SAC critic and actor steps left out: DrQ-v2's are ours) for 4 updates: its key EMA
    (encoder_tau 0.05, critic_target_update_freq 2) and update_cpc (two Adams at encoder_lr 1e-3, CURL's
    W) against our after_update on the same two shifts."""
    device = torch.device("cpu")
    torch.manual_seed(0)
    ours = curl_agent(device)
    cfg, aux = ours.cfg, ours.aux
    monkeypatch.setattr(curl_sac, "make_encoder", lambda *a, **k: Feature(copy.deepcopy(aux.query[0]), cfg.feature_dim))
    theirs = curl_sac.CurlSacAgent((9, 84, 84), (2,), device, hidden_dim=32, encoder_feature_dim=cfg.feature_dim,
                                   encoder_lr=1e-3, encoder_tau=0.05, critic_target_update_freq=2, log_interval=1)
    assert (cfg.curl_lr, cfg.curl_tau) == (1e-3, 0.05)  # train.py's --encoder_lr and --encoder_tau
    theirs.update_critic = theirs.update_actor_and_alpha = lambda *a, **k: None
    with torch.no_grad():  # our weights (their Critic re-initialised its encoder, ours inside)
        theirs.CURL.W.copy_(aux.W)
        theirs.critic.encoder.net.load_state_dict(aux.query[0].state_dict())
        theirs.critic_target.encoder.net.load_state_dict(aux.key.state_dict())
    log = Log()
    for step in range(4):
        obs = obs_batch(device, seed=step)
        # ours draws the anchor's shift, then the positive's
        rng, size = torch.Generator().manual_seed(step), (len(obs), 1, 1, 2)
        shifts = [torch.randint(0, 9, size, generator=rng, dtype=obs.dtype) for _ in range(2)]
        anchor, positive = (sear.random_shift(obs, shift) for shift in shifts)
        mine = aux.after_update(obs, torch.Generator().manual_seed(step))
        theirs.update(Replay(anchor, positive), log, step)
        assert mine["curl_loss"] == pytest.approx(log.curl[-1], rel=1e-5)
        theirs_params = [*theirs.critic.encoder.net.parameters(), theirs.CURL.W]  # in our Adam's order
        for go, pt in zip(grads(stepped(aux.opt)), theirs_params, strict=True):
            torch.testing.assert_close(go, pt.grad, rtol=1e-4, atol=1e-6, msg=lambda m: f"gradient, update {step}: {m}")
    # Adam moves a weight by about its learning rate whatever the gradient's size, so a gradient that rounding
    # alone sets (near 0: one Adam at 2 x lr against two at lr, lerp against their soft update) can move a
    # weight differently by a part of 2e-3; 1e-4 still shows any wrong rate, period or EMA (1e-3 a step)
    for o, t in ((aux.query[0], theirs.critic.encoder.net), (aux.key, theirs.critic_target.encoder.net)):
        for po, pt in zip(o.parameters(), t.parameters(), strict=True):
            torch.testing.assert_close(po, pt, rtol=0, atol=1e-4, msg=lambda m: f"after 4 updates: {m}")
    torch.testing.assert_close(aux.W, theirs.CURL.W, rtol=0, atol=1e-4)


def test_a_snapshot_whose_networks_differ_is_one_line(tmp_path):
    """A curl run saved before CURL followed curl_sac.py (projection heads, no saved Adam) cannot continue:
    --resume and --evaluate say so in one line and leave the run as it was."""
    from tests.test_cli import TINY, only_run_dir, run
    from tests.test_firstweek import one_line, run as bare_run  # bare: --evaluate takes no --run-root
    assert run(["--env", "walker-walk", "--method", "curl", *TINY], tmp_path).returncode == 0
    run_dir = only_run_dir(tmp_path)
    state = torch.load(run_dir / "snapshot.pt", weights_only=False)
    aux = state["agent"]["aux"]
    del aux["_extra_state"], aux["W"]
    aux["query_head.0.weight"] = torch.zeros(128, 64)  # what the old CURLAux saved
    torch.save(state, run_dir / "snapshot.pt")
    before = (run_dir / "snapshot.pt").read_bytes()
    for args in (["--resume", run_dir, "--frames", "64"], ["--evaluate", run_dir]):
        r = bare_run(args, tmp_path)
        assert r.returncode == 2
        assert one_line(r).startswith(f"sear.py: error: {args[0]}: the snapshot's curl networks do not fit")
    assert (run_dir / "snapshot.pt").read_bytes() == before
