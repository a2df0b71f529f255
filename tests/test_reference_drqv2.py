"""--method drq against the official DrQ-v2 agent (github.com/facebookresearch/drqv2, drqv2.py's
DrQV2Agent at c0c650b), update for update. Both start from our initial weights (encoder
convolutions, actor, critic, target critic: ours copied into theirs) and take the same batches and
the same random draws: the shift of obs, the shift of next_obs, the target action's noise and the
actor action's noise, drawn in that order on both sides from a generator seeded alike before each
update. After each of 3 updates the critic loss, the actor loss and every parameter are compared.
Needs SEAR_DRQV2 to name a checkout or a git mirror of it; skipped without.

`exact`: the reference as released but for three implementation choices of ours, each equal to its
own in exact arithmetic (reference.take_our_implementation): its optimisers, one per module,
rebuilt with our optimisers' settings (torch's Adam still: per parameter that is our one Adam over
encoder and critic, Adam being per-parameter; today the settings are its own, and sear.Adam equals
torch's arithmetic to the bit); our memory layout (channels_last convolutions); our Polyak
arithmetic (a lerp, where it writes tau p + (1 - tau) p'). Every loss and parameter is then equal
to the bit, and asserted so. `released`: the reference as released; the differences are rounding,
bounded as `rounding_only` says. The two controls run the released case with a wrong learning rate
(x 1.01) and a wrong sign: its bounds must catch both.
"""
import math
import types

import pytest
import torch

import sear
import train
from tests import reference
from tests.test_baselines import numpy_batch

RELEASED_COMMIT = "c0c650b"  # the commit docs/recipes.md names
ACTION_DIM = 2
STEP = 250_000  # an update step (update_every 2) where the exploration std is 0.55
LOSSES = {"critic_loss": "critic_loss", "actor_loss": "actor_loss"}  # ours: the reference's
CASES = ["exact", "released", "control: lr x 1.01", "control: wrong sign"]
LOSS_RTOL = 2e-4  # the released case's bounds: `rounding_only` says how they were chosen
DRIFT = 5e-3


class Ours:
    """Everything these tests know of our agent's API, in one place: adapt here when it changes.
    How its networks are read, how an update's random draws are seeded and one update is called,
    and for the exact case its optimisers' settings and how it averages the target critic."""

    def __init__(self, cfg):
        self.agent = sear.Agent(cfg, action_dim=ACTION_DIM, device=torch.device("cpu"))

    def networks(self) -> dict:  # by the reference's names, parameters in the reference's order
        a = self.agent
        return {"encoder": a.encoder, "actor": a.actor, "critic": a.critic,
                "critic_target": a.critic_target}

    def update(self, batch, step, seed) -> dict:
        """One update on `batch` (numpy: obs, mask, action, reward, discount, next_obs, next_mask)
        at agent step `step`, its random draws from a generator seeded with `seed`; its losses."""
        self.agent.rng.manual_seed(seed)  # the agent draws an update's numbers from its own generator
        metrics = self.agent.update(sear.Batch(*batch), step)
        return {k: float(metrics[k]) for k in LOSSES}

    def optimiser(self, params):
        """torch's Adam over `params` with our optimisers' settings (lr, and all torch.optim.Adam
        takes: its `defaults`: fused)."""
        return torch.optim.Adam(params, **self.agent.model_opt.defaults)

    @staticmethod
    @torch.no_grad()
    def polyak(net, target, tau):  # as the reference's soft_update_params, in our arithmetic
        sear.polyak(net, target, tau)


def batches(action_dim, updates=3, n=8):
    """Replay batches (numpy), each with next observations and masks of its own and two terminal
    rows (discount 0)."""
    for u in range(updates):
        obs, mask, action, reward, discount, _, _ = numpy_batch(n, action_dim, seed=2 * u)
        next_obs, next_mask = numpy_batch(n, action_dim, seed=2 * u + 1)[:2]
        discount[::4] = 0.0
        yield obs, mask, action, reward, discount, next_obs, next_mask


@pytest.fixture(scope="module")
def drqv2(tmp_path_factory):
    """The released drqv2.py with its utils.py, imported under names of their own; hydra and
    omegaconf, which they import for configuration the agent does not use, are stand-ins."""
    folder = reference.materialise("SEAR_DRQV2", "facebookresearch/drqv2", RELEASED_COMMIT,
                                   ["drqv2.py", "utils.py"], tmp_path_factory.mktemp("drqv2"))
    omegaconf = types.ModuleType("omegaconf")
    omegaconf.OmegaConf = None
    stand_ins = {"hydra": types.ModuleType("hydra"), "omegaconf": omegaconf}
    utils = reference.load(folder, "utils.py", "drqv2_utils_released", stand_ins)
    return reference.load(folder, "drqv2.py", "drqv2_released", {**stand_ins, "utils": utils})


def official_agent(drqv2, cfg):
    return drqv2.DrQV2Agent(
        obs_shape=(9, 84, 84), action_shape=(ACTION_DIM,), device=torch.device("cpu"), lr=cfg.lr,
        feature_dim=cfg.feature_dim, hidden_dim=cfg.hidden_dim, critic_target_tau=cfg.critic_tau,
        num_expl_steps=cfg.exploration_steps, update_every_steps=cfg.update_every,
        stddev_schedule=f"linear({cfg.std_start},{cfg.std_end},{cfg.std_steps})",
        stddev_clip=cfg.std_clip, use_tb=True)


def rounding_only(mine, theirs, drifts):
    """The released case's bounds; the failures, as lines. Its update and ours differ by rounding
    alone: its convolutions in another memory layout (NCHW against our channels_last) sum in
    another order, and its Polyak step rounds otherwise. Adam divides a gradient by its own root
    mean square, so a gradient that rounding sets (large terms that cancel) becomes a step of up
    to lr either way: one weight may differ by up to 2 lr per update, so the largest |difference|
    is reported, not bounded: measured 2.2e-6 = 0.02 lr, the actor (3.1e-6 with one torch
    thread, as the suite's workers run; 2 threads otherwise). What rounding cannot do is move a
    loss or a whole network:
    (1) each loss within LOSS_RTOL = 2e-4 relative. Measured at most 4.9e-7; lr off by 1% moves
        the actor loss by 2.2e-3 at the first update, a wrong sign by 4.1.
    (2) each network within DRIFT = 5e-3 of how far our updates moved it, in the 2-norm over its
        parameters (reference.drift). Measured at most 9.2e-4: the target critic after the first
        update, whose Polyak step (tau times an Adam step) is only tens to thousands of ulps of
        its weights; lr off by 1% gives 1.0e-2 in every network, a wrong sign 2."""
    bad = [f"{k}: ours {mine[k]!r}, theirs {theirs[v]!r}" for k, v in LOSSES.items()
           if not math.isclose(mine[k], theirs[v], rel_tol=LOSS_RTOL)]
    return bad + [f"{k}: drift {d:.3g} > {DRIFT}" for k, d in drifts.items() if d > DRIFT]


@pytest.mark.parametrize("case", CASES)
def test_the_drq_update_equals_the_official_drqv2_update(drqv2, case, monkeypatch):
    cfg = train.Config(method="drq", feature_dim=8, hidden_dim=32, batch_size=8)
    torch.manual_seed(0)
    ours = Ours(cfg)
    theirs = official_agent(drqv2, cfg)
    networks = {k: getattr(theirs, k) for k in ours.networks()}
    reference.adopt(networks, ours.networks(), layout=case == "exact")
    if case == "exact":
        reference.take_our_implementation(theirs, theirs.encoder, ours, drqv2.utils, monkeypatch)
    reference.put_wrong(theirs, case)
    start, failures = reference.flat(ours.networks()), []
    for u, batch in enumerate(batches(ACTION_DIM)):
        obs, mask, action, reward, discount, next_obs, next_mask = batch
        step = STEP + 2 * u
        mine = ours.update(batch, step, seed=u)
        torch.manual_seed(u)
        their = theirs.update(iter([(obs, action, reward, discount, next_obs)]), step)
        diffs = reference.max_abs_diffs(networks, ours.networks())
        drifts = reference.drift(networks, ours.networks(), start)
        reference.report(case, u, mine, their, LOSSES, diffs, drifts)
        if case == "exact":
            assert [mine[k] for k in LOSSES] == [their[v] for v in LOSSES.values()], u + 1
            assert diffs == dict.fromkeys(diffs, 0.0), f"update {u + 1}"
        else:
            failures += [f"update {u + 1}: {line}" for line in rounding_only(mine, their, drifts)]
    if case == "released":
        assert not failures, "\n".join(failures)
    elif case.startswith("control"):
        assert failures, f"{case}: the released case's bounds do not see it"
