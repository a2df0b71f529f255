"""--method sear against the authors' released SEAR agent (github.com/sear-rl/sear-rl,
sear/agents/sear.py's SEARAgent with sear/models at 1e5f36b), update for update. Both start from
our initial weights (encoder, reconstruction decoder, mask decoder, actor, critic, target critic:
ours copied into theirs) and take the same batches, masks and random draws: the shift of obs (the
masks' too), the shift of next_obs, the target action's noise and the actor action's noise, drawn
in that order on both sides from a generator seeded alike before each update. After each of 3
updates the critic, actor, reconstruction and mask losses and every parameter are compared. Needs
SEAR_AUTHORS to name a checkout or a git mirror of it; skipped without.

Set equal on both sides: the loss weights (their reconstruction_loss_coeff and mask_loss_coeff take
our c1 = 0.01 and c2 = 0.0025, the paper's; they release 1.0 and 0.25), the learning rates (their
decoder_lr and mask_lr are our one lr), the latent's split (split_latent: the first half
reconstructs, the second predicts the mask, as ours). Their replay's batch is ({"pixels",
"segmentation"}, action, reward, discount, next obs), the masks a (B, 3, 84, 84) stack of 0/1
bytes that `aug(masks, repeat_last=True)` shifts with the image's shift; ours shifts image and
masks concatenated, one draw for both.

`exact`: the reference as released but for four implementation choices of ours, each equal to
its own in exact arithmetic: the three of reference.take_our_implementation (its five
optimisers rebuilt with our optimisers' settings, where we have one over encoder, critic and
decoders: Adam is per-parameter; channels_last convolutions; our Polyak arithmetic), and the mask
loss on logits (BCE-with-logits, where it applies a sigmoid and BCELoss: the same wherever the
sigmoid does not round to 0 or 1 in float32, |logit| above about 17 or 88). Every loss and
parameter is then equal to the bit, and asserted so: no algorithmic difference is left.
`released`: the reference as released; the differences are rounding, bounded as `rounding_only`
says. The two controls run the released case with a wrong learning rate (x 1.01) and a wrong
sign: its bounds must catch both.
"""
import math

import pytest
import torch

import sear
import train
from tests import reference
from tests.test_reference_drqv2 import CASES, STEP, batches

RELEASED_COMMIT = "1e5f36b"  # the commit docs/recipes.md names
FILES = ["sear/agents/sear.py", "sear/utils.py", *(f"sear/models/{m}.py" for m in (
    "actor", "critic", "decoder", "encoder", "random_shifts_aug"))]
ACTION_DIM = 2
LOSSES = {"critic_loss": "critic_loss", "actor_loss": "actor_loss",
          "recon_loss": "reconstruction_loss", "mask_loss": "mask_loss"}  # ours: the reference's
LOSS_RTOL = 2e-4  # the released case's bounds: `rounding_only` says how they were chosen
DRIFT = 0.05


class Ours:
    """Everything these tests know of our agent's API, in one place: adapt here when it changes.
    How its networks are read, how an update's random draws are seeded and one update is called,
    and for the exact case its optimisers' settings and how it averages the target critic."""

    def __init__(self, cfg):
        self.agent = sear.Agent(cfg, action_dim=ACTION_DIM, device=torch.device("cpu"))

    def networks(self) -> dict:  # by the reference's names, parameters in the reference's order
        a = self.agent
        return {"encoder": a.encoder, "decoder": a.aux.recon_decoder,
                "mask_decoder": a.aux.mask_decoder, "actor": a.actor, "critic": a.critic,
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


@pytest.fixture(scope="module")
def authors(tmp_path_factory):
    """The released sear/agents/sear.py with the models and utils it imports, under a name of its
    own; their package `sear`, whose name our sear.py holds, is a stand-in for that import."""
    folder = reference.materialise("SEAR_AUTHORS", "sear-rl/sear-rl", RELEASED_COMMIT, FILES,
                                   tmp_path_factory.mktemp("searrl"))
    return reference.load(folder, "sear/agents/sear.py", "sear_authors_released",
                          {"sear": reference.package(folder, "sear")})


def authors_agent(authors, cfg):
    return authors.SEARAgent(
        obs_shape=(9, 84, 84), action_shape=(ACTION_DIM,), device=torch.device("cpu"), lr=cfg.lr,
        latent_dim=cfg.latent_dim, feature_dim=cfg.feature_dim, hidden_dim=cfg.hidden_dim,
        critic_target_tau=cfg.critic_tau, num_expl_steps=cfg.exploration_steps,
        update_every_steps=cfg.update_every,
        stddev_schedule=f"linear({cfg.std_start},{cfg.std_end},{cfg.std_steps})",
        stddev_clip=cfg.std_clip, use_tb=True, reconstruction_loss_coeff=cfg.recon_coef,
        decoder_lr=cfg.lr, mask_lr=cfg.lr, mask_loss_coeff=cfg.mask_coef, detach_critic=False,
        detach_mask_decoder=False, detach_reconstruction_decoder=False, split_latent=True)


def rounding_only(mine, theirs, drifts):
    """The released case's bounds; the failures, as lines. Its update and ours differ by rounding
    alone: its convolutions in another memory layout (NCHW against our channels_last) sum in
    another order, its Polyak step rounds otherwise, its mask loss is BCELoss on a sigmoid. Adam
    divides a gradient by its own root mean square, so a gradient that rounding sets (large terms
    that cancel: the decoders' gradients sum the losses' over 8 x 84 x 84 pixels) becomes a step
    of up to lr either way: one weight may differ by up to 2 lr per update, so the largest
    |difference| is reported, not bounded. Measured (2 torch threads; 1, as the suite's workers):
    8.6e-6, the mask decoder (2.2e-4 = 2.2 lr, a few weights of the encoder and the reconstruction
    decoder turned around at the first update). What rounding cannot do is move a loss or a whole
    network:
    (1) each loss within LOSS_RTOL = 2e-4 relative. Measured at most 2.3e-7 (4.7e-5); lr off by
        1% moves the actor loss by 3.8e-4 at the first update and the critic loss by 2.2e-3 at
        the second, a wrong sign the actor loss by 8.2e-2 at the first.
    (2) each network within DRIFT = 0.05 of how far our updates moved it, in the 2-norm over its
        parameters (reference.drift). Measured at most 8.6e-3, the target critic after the first
        update, whose Polyak step (tau times an Adam step) is only tens of ulps of its weights
        (1.5e-2, the reconstruction decoder's turned weights); a wrong sign gives 2, lr off by 1%
        1e-2 to 5e-2 (which (1) catches)."""
    bad = [f"{k}: ours {mine[k]!r}, theirs {theirs[v]!r}" for k, v in LOSSES.items()
           if not math.isclose(mine[k], theirs[v], rel_tol=LOSS_RTOL)]
    return bad + [f"{k}: drift {d:.3g} > {DRIFT}" for k, d in drifts.items() if d > DRIFT]


@pytest.mark.parametrize("case", CASES)
def test_the_sear_update_equals_the_authors_released_sear_update(authors, case, monkeypatch):
    cfg = train.Config(method="sear", latent_dim=64, feature_dim=8, hidden_dim=32, batch_size=8)
    assert (cfg.recon_coef, cfg.mask_coef) == (0.01, 0.0025)  # the paper's c1, c2: both sides
    torch.manual_seed(0)
    ours = Ours(cfg)
    theirs = authors_agent(authors, cfg)
    networks = {k: getattr(theirs, k) for k in ours.networks()}
    reference.adopt(networks, ours.networks(), layout=case == "exact")
    if case == "exact":
        reference.take_our_implementation(theirs, theirs.encoder, ours, authors.utils, monkeypatch)
        theirs.mask_decoder.output_act = torch.nn.Identity()  # logits, and the loss on logits
        theirs.mask_loss_fn = torch.nn.BCEWithLogitsLoss(reduction="none")
    reference.put_wrong(theirs, case)
    start, failures = reference.flat(ours.networks()), []
    for u, batch in enumerate(batches(ACTION_DIM)):
        obs, mask, action, reward, discount, next_obs, next_mask = batch
        step = STEP + 2 * u
        mine = ours.update(batch, step, seed=u)
        torch.manual_seed(u)
        replay = iter([({"pixels": obs, "segmentation": mask}, action, reward, discount,
                        {"pixels": next_obs, "segmentation": next_mask})])
        their = theirs.update(replay, step)
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
