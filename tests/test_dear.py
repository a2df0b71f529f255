"""--method dear (DEARAux): the cosine term's value and sign, which half each term trains, the actor kept
off the encoder, DEAR's coefficients and flag; and the released agent (github.com/Ameyapores/DEAR,
dear/agents/dear_mask_decoder.py) on the same weights and batch: losses, gradients and parameters after a
few updates, which needs SEAR_DEAR_REFERENCE to name a checkout or a git mirror of it."""
import copy
import types

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from methods import baselines
from harness import cli
import sear
import sweep
import train
from tests import reference
from tests.test_baselines import agent_of, numpy_batch, tiny_cfg
from tests.test_sear import grads

RELEASED_COMMIT = "a2885d9"  # the commit docs/dear.md describes
FILES = ["dear/agents/dear_mask_decoder.py", "dear/utils.py", *(f"dear/models/{m}.py" for m in (
    "actor", "critic", "decoder", "encoder", "random_shifts_aug"))]


def dear_aux(feature="pull", c1=1.0, c2=0.25, latent_dim=8):
    cfg = train.Config(method="dear", latent_dim=latent_dim, dear_feature=feature, recon_coef=c1, mask_coef=c2)
    return baselines.DEARAux.build(cfg, sear.PooledEncoder(9, latent_dim), None)


def halves(z, z_r):
    """A latent whose first half is z and second half is z_R (the authors' order)."""
    return torch.cat([torch.as_tensor(z, dtype=torch.float32), torch.as_tensor(z_r, dtype=torch.float32)], 1)


# ---------------------------------------------------------------- the cosine term, by hand
@pytest.mark.parametrize("feature, expected", [
    # rows: z_R equal to z (cos 1), orthogonal (cos 0), opposite (cos -1), at 60 degrees (cos 0.5)
    ("pull", [0.0, 1.0, 2.0, 0.5]),   # 1 - cos: the halves pulled together
    ("push", [1.0, 0.0, 0.0, 0.5]),   # max(0, cos): apart until orthogonal or beyond
])
def test_cosine_term_value_and_sign_on_hand_built_halves(feature, expected):
    z = [[1, 0, 0, 0]] * 4
    z_r = [[2, 0, 0, 0], [0, 3, 0, 0], [-1, 0, 0, 0], [0.5, 0.5 * 3 ** 0.5, 0, 0]]
    aux = dear_aux(feature)
    _, m = aux(halves(z, z_r), torch.zeros(4, 9, 84, 84), torch.zeros(4, 3, 84, 84))
    assert m["feature_loss"] == pytest.approx(np.mean(expected), abs=1e-6)
    for row, value in enumerate(expected):  # row by row: the batch's mean is CosineEmbeddingLoss's reduction
        _, m = aux(halves(z[row:row + 1], z_r[row:row + 1]), torch.zeros(1, 9, 84, 84), torch.zeros(1, 3, 84, 84))
        assert m["feature_loss"] == pytest.approx(value, abs=1e-6)


def test_total_is_c1_times_the_cosine_term_plus_c2_times_the_mask_bce():
    torch.manual_seed(0)
    aux = dear_aux(c1=0.7, c2=0.3)
    latent, mask = torch.randn(3, 8), (torch.rand(3, 3, 84, 84) > 0.5).float()
    loss, m = aux(latent, torch.zeros(3, 9, 84, 84), mask)
    bce = sear.summed_bce(aux.mask_decoder(latent[:, 4:]), mask)
    cos = F.cosine_similarity(latent[:, :4], latent[:, 4:]).mean()
    assert m["mask_loss"] == pytest.approx(bce.item(), rel=1e-6) and m["feature_loss"] == pytest.approx(1 - cos.item())
    assert loss.item() == pytest.approx(0.7 * (1 - cos.item()) + 0.3 * bce.item(), rel=1e-5)


@pytest.mark.parametrize("feature", ["pull", "push"])
def test_the_cosine_term_trains_z_r_alone_and_the_mask_trains_z_r(feature):
    """z is detached in the cosine term (f1.detach() in the released code): only z_R moves, towards z
    (pull) or away from it (push); the mask decoder reads z_R only. The critic alone trains z."""
    torch.manual_seed(0)
    z = torch.randn(5, 4)
    z_r = z + 0.3 * torch.randn(5, 4)  # cos > 0 everywhere, so that push has a gradient
    for c1, c2 in ((1.0, 0.0), (0.0, 1.0)):
        latent = halves(z, z_r).requires_grad_(True)
        loss, _ = dear_aux(feature, c1, c2)(latent, torch.zeros(5, 9, 84, 84), torch.ones(5, 3, 84, 84))
        loss.backward()
        assert torch.count_nonzero(latent.grad[:, :4]) == 0
        assert torch.count_nonzero(latent.grad[:, 4:]) > 0
    latent = halves(z, z_r).requires_grad_(True)
    loss, _ = dear_aux(feature, 1.0, 0.0)(latent, None, torch.zeros(5, 3, 84, 84))
    loss.backward()
    stepped = latent.detach()[:, 4:] - 0.1 * latent.grad[:, 4:]
    closer = F.cosine_similarity(z, stepped) > F.cosine_similarity(z, z_r)
    assert bool(closer.all()) == (feature == "pull") and bool((~closer).all()) == (feature == "push")


def test_dear_has_the_mask_decoder_and_no_reconstruction(device):
    agent = agent_of("dear", device)
    assert agent.aux.recon_decoder is None and agent.aux.decodes == ("mask",)
    assert {n.split(".")[0] for n, _ in agent.aux.named_parameters()} == {"mask_decoder"}
    assert agent.aux.mask_decoder.fc[0].in_features == 32  # half of --latent-dim 64
    decoded = agent.aux.decode(torch.randn(2, 64, device=device))
    assert set(decoded) == {"mask"} and decoded["mask"].shape == (2, 3, 84, 84)
    assert {"feature_loss", "mask_loss"} <= set(agent.metric_names)


def test_the_actor_loss_never_reaches_the_encoder(device):
    agent = agent_of("dear", device)
    batch = sear.Batch._make(torch.as_tensor(x, device=device).float() for x in numpy_batch())
    noise = agent.draw(len(batch.obs))
    latent, _ = agent.update_critic(batch, 10**5, noise)
    encoder = copy.deepcopy(agent.encoder.state_dict())
    agent.update_actor(latent, agent.std(10**5), noise.actor)
    assert latent.grad_fn is None and all(torch.equal(v, agent.encoder.state_dict()[k]) for k, v in encoder.items())
    assert any(g.any() for g in grads(agent.actor.parameters()))


# ---------------------------------------------------------------- flags, coefficients, sweeps
def parse(*argv):
    return cli.parse_args(["--env", "walker-walk", *argv], train.Config, train.METHODS)[0]


@pytest.mark.parametrize("recipe", ["paper", "authors"])
def test_dear_takes_its_released_coefficients_under_both_recipes(recipe):
    cfg = parse("--method", "dear", "--recipe", recipe)
    assert (cfg.recon_coef, cfg.mask_coef, cfg.dear_feature) == (1.0, 0.25, "pull")  # dear/cfgs/agent/dear.yaml
    cfg = parse("--method", "dear", "--recipe", recipe, "--mask-coef", "0.5", "--dear-feature", "push")
    assert (cfg.recon_coef, cfg.mask_coef, cfg.dear_feature) == (1.0, 0.5, "push")  # explicit flags win
    sear_cfg = parse("--method", "sear", "--recipe", recipe)  # SEAR's own are untouched
    assert (sear_cfg.recon_coef, sear_cfg.mask_coef) == ((0.01, 0.0025) if recipe == "paper" else (1.0, 0.25))


def test_bad_dear_feature_is_one_line(tmp_path):
    from tests.test_cli import run
    r = run(["--env", "walker-walk", "--method", "dear", "--dear-feature", "apart"], tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--dear-feature" in r.stderr
    assert "Traceback" not in r.stderr


def test_the_dear_grid_runs_both_signs_beside_sear_and_drq():
    args, unknown = sweep.build_parser().parse_known_args(["--grid", "dear", "--seeds", "1"])
    _, specs, grid = sweep.plan(args, unknown)
    assert grid.metric == "return" and {s.env for s in specs} == {"walker-walk-distracting", "cup-catch-distracting"}
    assert list(dict.fromkeys(s.variant for s in specs)) == ["dear", "dear-push", "sear", "drq"]
    push = next(s for s in specs if s.variant == "dear-push")
    assert ("--method", "dear") == push.args[2:4] and "push" == push.args[push.args.index("--dear-feature") + 1]
    keys = {s.variant: s.key for s in specs if s.env == "walker-walk-distracting"}
    assert keys["dear"] != keys["dear-push"] != keys["sear"]  # the sign and DEAR's coefficients are in the key
    args, unknown = sweep.build_parser().parse_known_args(["--grid", "dear-kitchen", "--seeds", "1"])
    _, specs, grid = sweep.plan(args, unknown)
    assert grid.metric == "success" and len(specs) == 3 * 4


# ---------------------------------------------------------------- against the released code
@pytest.fixture(scope="module")
def released(tmp_path_factory):
    """The released dear_mask_decoder.py with its models and utils, imported under a name of their own."""
    folder = reference.materialise("SEAR_DEAR_REFERENCE", "Ameyapores/DEAR", RELEASED_COMMIT, FILES,
                                   tmp_path_factory.mktemp("dear_released"))
    return reference.load(folder / "dear", "agents/dear_mask_decoder.py", "dear_released")


class Patched:
    """A module for the released code to use in place of `module`, with some of its names replaced."""

    def __init__(self, module, **names):
        self.module, self.names = module, names

    def __getattr__(self, name):
        return self.names[name] if name in self.names else getattr(self.module, name)


def released_agent(released, cfg, feature):
    # push: their CosineEmbeddingLoss target flipped to -1 (torch.ones gives -1), the only change
    released.torch = Patched(torch, ones=lambda *a, **k: -torch.ones(*a, **k)) if feature == "push" else torch
    return released.DEARAgent(
        obs_shape=(9, 84, 84), action_shape=(2,), device=torch.device("cpu"), lr=cfg.lr, latent_dim=cfg.latent_dim,
        feature_dim=cfg.feature_dim, hidden_dim=cfg.hidden_dim, critic_target_tau=cfg.critic_tau,
        num_expl_steps=cfg.exploration_steps, update_every_steps=cfg.update_every,
        stddev_schedule=f"linear({cfg.std_start},{cfg.std_end},{cfg.std_steps})", stddev_clip=cfg.std_clip,
        use_tb=True, reconstruction_loss_coeff=cfg.recon_coef, decoder_lr=cfg.lr, mask_lr=cfg.lr,
        mask_loss_coeff=cfg.mask_coef, detach_critic=False, detach_mask_decoder=False,
        detach_reconstruction_decoder=False, split_latent=True)


def pairs(theirs, ours):
    return (("encoder", theirs.encoder, ours.encoder), ("mask decoder", theirs.mask_decoder, ours.aux.mask_decoder),
            ("actor", theirs.actor, ours.actor), ("critic", theirs.critic, ours.critic),
            ("critic target", theirs.critic_target, ours.critic_target))


def tensors(module):
    return [*module.parameters()] or [*module.state_dict().values()]


@pytest.mark.parametrize("feature", ["pull", "push"])
def test_same_losses_gradients_and_weights_as_the_released_agent(released, feature):
    cfg = tiny_cfg("dear", std_steps=100_000, recon_coef=1.0, mask_coef=0.25, dear_feature=feature)
    torch.manual_seed(0)
    ours = train.make_agent(cfg, action_dim=2, device=torch.device("cpu"))
    theirs = released_agent(released, cfg, feature)
    with torch.no_grad():  # their networks get our weights, tensor by tensor in order
        for name, t, o in pairs(theirs, ours):
            for (kt, vt), (ko, vo) in zip(t.state_dict().items(), o.state_dict().items(), strict=True):
                assert vt.shape == vo.shape, (name, kt, ko)
                vt.copy_(vo)
    seen = []  # their cosine term, which they do not log

    class Recorded(torch.nn.CosineEmbeddingLoss):
        def forward(self, *args):
            out = super().forward(*args)
            seen.append(out.item())
            return out
    released.nn = Patched(torch.nn, CosineEmbeddingLoss=Recorded)

    for update in range(3):
        batch = numpy_batch(n=8, seed=update)
        obs, mask, action, reward, discount, next_obs, _ = batch
        step = 10_000 + 2 * update  # an update step (update_every 2); the std has decayed somewhat
        ours.rng.manual_seed(update)  # the same shifts and action noise, drawn in the same order
        mine = ours.update(batch, step)
        stepped = [p for opt in (ours.model_opt, ours.actor_opt) for g in opt.param_groups
                   for p in g["params"]]
        # each step's gradient, left on .grad
        grad = dict(zip(stepped, grads(stepped), strict=True))
        torch.manual_seed(update)
        replay = iter([({"pixels": obs, "segmentation": mask}, action, reward, discount, {"pixels": next_obs})])
        their = theirs.update(replay, step)
        assert mine["critic_loss"] == pytest.approx(their["critic_loss"], rel=1e-5)
        assert mine["mask_loss"] == pytest.approx(their["mask_loss"], rel=1e-5)
        assert mine["feature_loss"] == pytest.approx(seen[-1], rel=1e-5, abs=1e-6)
        assert mine["actor_loss"] == pytest.approx(their["actor_loss"], rel=1e-5)
        for name, t, o in pairs(theirs, ours)[:3]:  # their critic's grads also hold the actor's (discarded)
            for pt, po in zip(t.parameters(), o.parameters(), strict=True):
                torch.testing.assert_close(pt.grad, grad[po], rtol=1e-4, atol=1e-6, msg=f"{name} gradient")
    for name, t, o in pairs(theirs, ours):
        for vt, vo in zip(tensors(t), tensors(o), strict=True):
            torch.testing.assert_close(vt, vo.contiguous(), rtol=1e-4, atol=1e-5, msg=f"{name} after 3 updates")
