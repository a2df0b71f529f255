"""The baselines and ablations behind the auxiliary-loss seam: drq, ae, mae, curl, rgbm, sear-nosplit, dear
(CURL's own checks: test_curl.py; DEAR's: test_dear.py)."""
import csv

import numpy as np
import pytest
import torch

import sear
from methods import baselines, foresight
import train
from tests.test_cli import only_run_dir, run, tiny

def tiny_cfg(method, **kw):
    return train.Config(method=method, latent_dim=64, hidden_dim=32, feature_dim=8, batch_size=8,
                       action_repeat=2, **kw)


def numpy_batch(n=8, action_dim=2, seed=0):
    """A replay-style batch: (obs, mask, action, reward, discount, next_obs, next_mask)."""
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8)
    # a structured image (a bright square where the "robot" is) so that decoders have something to learn
    masks = np.zeros((n, 3, 84, 84), dtype=np.uint8)
    for i in range(n):
        y, x = rng.integers(10, 60, 2)
        masks[i, :, y:y + 20, x:x + 20] = 1
        frames[i] = (frames[i] // 4) + masks[i].repeat(3, axis=0) * 180
    return (frames, masks, rng.uniform(-1, 1, (n, action_dim)).astype(np.float32),
            rng.normal(size=(n, 1)).astype(np.float32), np.full((n, 1), 0.97, np.float32), frames, masks)


def agent_of(method, device, **kw):
    """A tiny agent of any --method, as train.py builds it (EF's agent for ef)."""
    return train.make_agent(tiny_cfg(method, **kw), action_dim=2, device=device)


@pytest.mark.parametrize("method", list(train.METHODS))
def test_every_method_builds_acts_and_updates(method, device):
    agent = agent_of(method, device)
    batch = numpy_batch()
    a = agent.act(batch[0][0], batch[1][0], step=10**6, eval_mode=True)
    assert a.shape == (2,) and a.device.type == device.type and bool((a.abs() <= 1).all())
    metrics = agent.update(batch, step=10**5)
    assert set(agent.metric_names) == set(metrics)
    assert all(bool(torch.isfinite(torch.as_tensor(v))) for v in metrics.values())


def test_the_methods_table_is_sears_and_the_modules_rows():
    """train.METHODS puts every module's own rows side by side; sear.py's holds its two alone."""
    assert list(sear.METHODS) == ["sear", "drq"]
    assert train.METHODS == {**sear.METHODS, **baselines.METHODS, **foresight.METHODS}
    assert set(train.METHODS) == {"sear", "drq", "ae", "mae", "curl", "rgbm", "sear-nosplit",
                                  "dear", "ef"}


@pytest.mark.parametrize("method, terms", [("sear", ["recon_loss", "mask_loss"]), ("sear-nosplit", ["recon_loss", "mask_loss"]),
                                           ("ae", ["recon_loss"]), ("mae", ["recon_loss"]), ("curl", ["curl_loss"]),
                                           ("dear", ["mask_loss"])])
def test_auxiliary_loss_decreases_on_a_fixed_batch(method, terms, device):
    torch.manual_seed(0)
    agent = agent_of(method, device, lr=1e-3)
    batch = numpy_batch(n=4, seed=1)
    history = {t: [] for t in terms}
    for _ in range(40):
        m = agent.update(batch, step=10**5)
        for t in terms:
            history[t].append(m[t])
    for t in terms:
        values = [float(v) for v in history[t]]
        first, last = np.mean(values[:5]), np.mean(values[-5:])
        assert last < 0.8 * first, f"{method} {t}: {first:.3f} -> {last:.3f}"


def test_mae_hides_the_requested_fraction_and_scores_only_hidden_pixels(device):
    torch.manual_seed(0)
    hidden = baselines.patch_mask(6, 84, 12, 0.75, device).cpu()
    assert hidden.shape == (6, 1, 84, 84)
    assert torch.allclose(hidden.mean(dim=(1, 2, 3)), torch.full((6,), 37 / 49))  # round(0.75 * 49) patches
    # every patch is wholly hidden or wholly visible
    patches = hidden.view(6, 7, 12, 7, 12)
    assert torch.all(patches.amax(dim=(2, 4)) == patches.amin(dim=(2, 4)))

    cfg = tiny_cfg("mae")
    encoder = sear.PooledEncoder(9, cfg.latent_dim)
    aux = baselines.MAEAux(cfg, encoder)
    obs = torch.full((4, 9, 84, 84), 255.0)  # target +0.5 everywhere

    class Grey(torch.nn.Module):  # predicts 0 everywhere: squared error 0.25 on every pixel
        def forward(self, z):
            return torch.zeros_like(obs)

    aux.recon_decoder = Grey()
    _, m = aux(None, obs, None, encoder=encoder)
    assert m["recon_loss"] == pytest.approx(0.25 * 9 * 37 * 144)  # hidden pixels only, 9 channels


def test_rgbm_sees_twelve_channels_with_the_mask_after_each_frame(device):
    agent = agent_of("rgbm", device)
    assert isinstance(agent, baselines.RGBMAgent) and agent.encoder.convs[0].in_channels == 12
    pixels = torch.rand(2, 9, 84, 84, device=device) * 255
    mask = (torch.rand(2, 3, 84, 84, device=device) > 0.5).float()
    x = baselines.with_masks(pixels, mask)
    assert x.shape == (2, 12, 84, 84)
    for f in range(3):
        assert torch.equal(x[:, 4 * f:4 * f + 3], pixels[:, 3 * f:3 * f + 3])
        assert torch.equal(x[:, 4 * f + 3], mask[:, f] * 255)
    seen = []  # what the encoder reads: when acting, and in the update (shifted with its mask)
    agent.encoder.register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    agent.act(pixels[0], mask[0], step=0, eval_mode=True)
    assert torch.equal(seen[-1], x[:1])
    zeros = torch.zeros(2, 1, device=device)
    batch = sear.Batch(pixels, mask, zeros.repeat(1, 2), zeros, zeros + 1, pixels, mask)
    noise = agent.draw(2)
    agent.critic_objective(batch, torch.zeros((), dtype=torch.float64, device=device), noise)
    torch.testing.assert_close(seen[-2], sear.random_shift(x, noise.shift))  # obs; next_obs last
    with pytest.raises(ValueError, match="needs the robot mask"):
        agent.act(pixels[0].cpu().numpy(), None, step=0, eval_mode=True)


@pytest.mark.parametrize("method, split", [("sear", True), ("sear-nosplit", False)])
def test_decoder_inputs_split_or_not(method, split, device):
    cfg = tiny_cfg(method)
    agent = agent_of(method, device)
    seen = {}
    agent.aux.recon_decoder.fc.register_forward_hook(lambda m, i, o: seen.__setitem__("recon", i[0]))
    agent.aux.mask_decoder.fc.register_forward_hook(lambda m, i, o: seen.__setitem__("mask", i[0]))
    latent = torch.randn(4, cfg.latent_dim, device=device)
    obs = torch.rand(4, 9, 84, 84, device=device) * 255
    agent.aux(latent, obs, torch.zeros(4, 3, 84, 84, device=device))
    half = cfg.latent_dim // 2
    if split:  # the authors' order: first half -> reconstruction (z), second half -> mask (z_R)
        assert torch.equal(seen["recon"], latent[:, :half]) and torch.equal(seen["mask"], latent[:, half:])
    else:
        assert torch.equal(seen["recon"], latent) and torch.equal(seen["mask"], latent)


@pytest.mark.parametrize("method", [m for m in train.METHODS if m != "sear"])  # sear: test_cli.py
def test_cli_smoke_run_per_method(method, tmp_path):
    extra = ["--mask-noise", "0.2"] if method in ("rgbm", "sear-nosplit") else []  # noise combines with mask users
    r = run(["--env", "walker-walk", "--method", method, *tiny(method), "--frames", "32", "--eval-every", "100", *extra],
            tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert run_dir.name.startswith(f"walker-walk__{method}__")
    with open(run_dir / "train.csv", newline="") as f:
        train = list(csv.DictReader(f))
    assert train and train[-1]["critic_loss"] != ""
    assert (run_dir / "eval.csv").exists() and (run_dir / "snapshot.pt").exists()
