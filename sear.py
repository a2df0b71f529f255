"""SEAR: Structured Environment-Agent Representations for visual RL (ICML 2023). DrQ-v2 (DDPG from
pixels: random shifts, n-step returns, clipped double-Q, a linearly decaying exploration std) whose
encoder two decoders also train, on a latent split in two halves: one predicts the robot's mask
(Eq. 4), the other reconstructs the image (Eq. 5); L = L_critic + c1 L_recon + c2 L_mask (Eq. 6).
Sections: 1. Config, 2. Networks, 3. Augmentation, 4. Auxiliary losses and METHODS, 5. Agent,
6. Replay buffer. torch, numpy and the standard library only; `python sear.py` runs train.py."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


# ================================================================================================
# 1. Config
def arg(default, doc, choices=None, **keys):
    """A config field: its doc (--help), its values if a fixed set, and the keys cli.py reads."""
    return field(default=default, metadata={"doc": doc, "choices": choices, **keys})


@dataclass
class Config:
    """The algorithm's hyper-parameters (the paper's table); train.Config adds the experiment's."""
    method: str = arg("sear", "a row of METHODS (sear, drq, ...)", group="what to run")
    precision: str = arg("fp32", "fp32 | bf16: encoder and decoders under bf16 autocast (actor, "
                                 "critic, losses: fp32)", ("fp32", "bf16"), group="the method")
    frame_stack: int = arg(3, "frames stacked into one observation", above=0)
    # --- DrQ-v2 (paper hyper-parameter table) ---
    replay_size: int = arg(250_000, "replay capacity in transitions", above=0, group="budgets")
    seed_frames: int = arg(4000, "frames before the first update (DrQ-v2's num_seed_frames)", low=0)
    exploration_steps: int = arg(2000, "first agent steps: uniform actions (num_expl_steps)", low=0)
    nstep: int = arg(3, "n of the n-step return", above=0)
    batch_size: int = arg(256, "mini-batch size", above=0, group="budgets")
    discount: float = arg(0.99, "discount factor gamma", low=0, high=1)
    lr: float = arg(1e-4, "Adam learning rate of actor, critic, encoder and decoders", above=0)
    update_every: int = arg(2, "agent steps between updates", above=0)
    critic_tau: float = arg(0.01, "Polyak rate of the target critic", low=0, high=1)
    feature_dim: int = arg(50, "actor/critic trunk width (Linear + LayerNorm + tanh)", above=0)
    latent_dim: int = arg(4096, "latent size, split in two halves", above=0, acts="pooled")
    hidden_dim: int = arg(1024, "actor and critic MLP width", above=0)
    std_start: float = arg(1.0, "exploration std at the start of the linear schedule")
    std_end: float = arg(0.1, "exploration std at the end of the linear schedule", low=0)
    std_steps: int = arg(500_000, "AGENT STEPS over which the std decays, as DrQ-v2 (frames = "
                                  "steps x action repeat)", above=0, group="the method")
    std_clip: float = arg(0.3, "clip of the exploration noise in the actor update (DrQ-v2)", low=0)
    # --- SEAR, Eq. 6 (paper: c1 = 0.01, c2 = 0.0025; authors' code: 1.0 and 0.25, same ratio) ---
    recon_coef: float = arg(0.01, "c1: reconstruction loss weight", low=0, group="the method",
                            acts=("sear", "sear-nosplit", "ae (2 x c1)", "mae", "dear (cosine)"))
    mask_coef: float = arg(0.0025, "c2: weight of the mask loss", low=0, group="the method",
                           acts=("sear", "sear-nosplit", "dear"))


# ================================================================================================
# 2. Networks
def weight_init(m, generator=None):
    """DrQ-v2's init: orthogonal weights, zero biases (ReLU gain for convolutions)."""
    if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
        gain = 1.0 if isinstance(m, nn.Linear) else nn.init.calculate_gain("relu")
        nn.init.orthogonal_(m.weight.data, gain, generator=generator)
        if m.bias is not None:
            m.bias.data.fill_(0.0)


def normalise(pixels):
    """Pixels in [0, 255] to [-0.5, 0.5]: what the encoder reads and Eq. 5 reconstructs."""
    return pixels / 255.0 - 0.5


def conv_trunk(in_channels: int) -> nn.Sequential:
    """DrQ-v2's four 3x3 convolutions, 32 channels, first with stride 2: 84x84 -> 32x35x35."""
    return nn.Sequential(
        nn.Conv2d(in_channels, 32, 3, stride=2), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU(),
        nn.Conv2d(32, 32, 3, stride=1), nn.ReLU())


class DrQEncoder(nn.Module):
    """DrQ-v2 as published: the 32x35x35 feature map, flattened (39200), goes into the trunks."""

    def __init__(self, in_channels: int):
        super().__init__()
        self.convs = conv_trunk(in_channels)
        self.repr_dim = 32 * 35 * 35
        self.apply(weight_init)

    def forward(self, obs):
        return self.convs(normalise(obs)).flatten(1)


class PooledEncoder(nn.Module):
    """SEAR's encoder (appendix "Architecture"): the same convolutions, then AvgPool(4) to 32x8x8,
    flatten (2048) and a linear map to the latent (4096) that the decoders read."""

    def __init__(self, in_channels: int, latent_dim: int):
        super().__init__()
        self.convs = conv_trunk(in_channels)
        self.pool = nn.AvgPool2d(4, 4)
        self.fc = nn.Linear(32 * 8 * 8, latent_dim)
        self.repr_dim = latent_dim
        self.apply(weight_init)

    def forward(self, obs):
        h = self.pool(self.convs(normalise(obs)))
        return self.fc(h.flatten(1))


class Decoder(nn.Module):
    """The mask and reconstruction heads' body (appendix "Architecture"), from 16 channels (DrQ-AE:
    32) at 8x8: -> 35 (k4 s4, output_padding 3) -> 37 -> 39 -> 41 (k3) -> 84 (k3 s2, padding 1)."""

    def __init__(self, in_dim: int, out_channels: int, in_channels: int = 16):
        super().__init__()
        self.in_channels = in_channels
        self.fc = nn.Sequential(nn.Linear(in_dim, in_channels * 8 * 8), nn.ReLU())
        self.deconvs = nn.Sequential(
            nn.ConvTranspose2d(in_channels, 16, 4, stride=4, output_padding=3), nn.ReLU(),
            nn.ConvTranspose2d(16, 32, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(32, 32, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(32, 32, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(32, out_channels, 3, stride=2, output_padding=1))
        self.apply(weight_init)

    def forward(self, z):
        return self.deconvs(self.fc(z).view(-1, self.in_channels, 8, 8))


class TruncatedNormal(torch.distributions.Normal):
    """Normal whose samples are clipped to (-1, 1) with a straight-through gradient (DrQ-v2)."""

    def __init__(self, loc, scale, eps=1e-6):
        super().__init__(loc, scale, validate_args=False)
        self.eps = eps

    def sample(self, clip=None, noise=None):
        """loc + scale x noise (standard normal; torch's RNG if None) in +-clip, then in (-1, 1)."""
        noise = (torch.randn_like(self.loc) if noise is None else noise) * self.scale
        if clip is not None:
            noise = noise.clamp(-clip, clip)
        x = self.loc + noise
        clamped = x.clamp(-1 + self.eps, 1 - self.eps)
        # Where no gradient flows, the straight-through terms add 0: the clamped sample, exactly.
        return x - x.detach() + clamped.detach() if torch.is_grad_enabled() else clamped


def trunk(repr_dim, feature_dim):
    return nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())


def mlp(in_dim, hidden_dim, out_dim):
    return nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(inplace=True),
                         nn.Linear(hidden_dim, hidden_dim), nn.ReLU(inplace=True),
                         nn.Linear(hidden_dim, out_dim))


class Actor(nn.Module):
    def __init__(self, repr_dim, action_dim, feature_dim, hidden_dim):
        super().__init__()
        self.trunk = trunk(repr_dim, feature_dim)
        self.policy = mlp(feature_dim, hidden_dim, action_dim)
        self.apply(weight_init)

    def forward(self, latent, std):
        """The policy at std: a float, or an update's float64 0-d tensor (rounded to float32 as a
        float would be)."""
        mu = torch.tanh(self.policy(self.trunk(latent)))
        std = torch.full_like(mu, std) if isinstance(std, float) else std.float().expand_as(mu)
        return TruncatedNormal(mu, std)


class Critic(nn.Module):
    """Two Q heads on one trunk; the target is the minimum of the two (clipped double-Q)."""

    def __init__(self, repr_dim, action_dim, feature_dim, hidden_dim):
        super().__init__()
        self.trunk = trunk(repr_dim, feature_dim)
        self.q1 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.apply(weight_init)

    def forward(self, latent, action):
        h = torch.cat([self.trunk(latent), action], dim=-1)
        return self.q1(h), self.q2(h)


# ================================================================================================
# 3. Augmentation
def random_shift(x: torch.Tensor, shift: torch.Tensor | None = None, pad: int = 4):
    """DrQ's random shift: replicate-pad by `pad`, then crop back with a per-sample integer shift
    (n, 1, 1, 2) in [0, 2 pad], done as a bilinear grid sample (DrQ-v2's RandomShiftsAug, its
    arithmetic). Integer shifts land on pixel centres (to float32 rounding): 0/1 masks stay 0/1."""
    n, c, h, w = x.shape
    assert h == w
    padded = F.pad(x, (pad,) * 4, mode="replicate")
    eps = 1.0 / (h + 2 * pad)
    arange = torch.linspace(-1.0 + eps, 1.0 - eps, h + 2 * pad, device=x.device, dtype=x.dtype)
    arange = arange[:h].unsqueeze(0).expand(h, h).unsqueeze(2)
    base_grid = torch.cat([arange, arange.transpose(1, 0)], dim=2).unsqueeze(0)
    if shift is None:
        shift = torch.randint(0, 2 * pad + 1, size=(n, 1, 1, 2), device=x.device, dtype=x.dtype)
    grid = base_grid + shift.to(x.dtype) * (2.0 / (h + 2 * pad))
    return F.grid_sample(padded, grid, padding_mode="zeros", align_corners=False)


def shift_together(obs: torch.Tensor, mask: torch.Tensor, shift: torch.Tensor | None = None):
    """The same shift per sample for the image stack and its mask stack, concatenated along
    channels: what makes the mask a label of the image the encoder sees."""
    both = random_shift(torch.cat([obs, mask], dim=1), shift)
    return both.split([obs.shape[1], mask.shape[1]], dim=1)


# ================================================================================================
# 4. Auxiliary losses: one seam for SEAR and every baseline
def summed_mse(pred, target, weight=None):
    """Squared error summed over channels and pixels, averaged over the batch (Eq. 5), in fp32 (a
    decoder may run in bf16). c1 is relative to this sum, not to a per-pixel mean."""
    err = (pred.float() - target) ** 2
    if weight is not None:
        err = err * weight
    return err.flatten(1).sum(1).mean()


def reconstruction_loss(pred, obs, weight=None):
    """Eq. 5 on the [-0.5, 0.5]-normalised image, the prediction clamped to that range first (the
    authors' code): no gradient pushes a pixel already past black or white further."""
    return summed_mse(pred.float().clamp(-0.5, 0.5), normalise(obs), weight)


def summed_bce(logits, target):
    """Binary cross-entropy on mask logits, summed over pixels, averaged over the batch (Eq. 4)."""
    bce = F.binary_cross_entropy_with_logits(logits.float(), target, reduction="none")
    return bce.flatten(1).sum(1).mean()


class AuxLoss(nn.Module):
    """The seam: forward() takes the latent of the augmented obs (the critic's), the augmented image
    and mask (same shift) and by keyword `encoder`, the raw `obs`, the `batch`, the agent's `rng`;
    returns its weighted term of Eq. 6 and its log terms. decode(): the decoders' output ("mask"
    logits, "recon" image) for evaluation; after_update(): a step of its own (CURL's)."""
    metric_names: tuple[str, ...] = ()
    decodes: tuple[str, ...] = ()

    @classmethod
    def build(cls, cfg, encoder, critic):
        return cls(cfg, encoder, critic)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        return 0.0, {}

    def decode(self, latent) -> dict:
        return {}

    def after_update(self, obs, rng) -> dict:
        return {}


class SearAux(AuxLoss):
    """SEAR: z_R -> robot mask (Eq. 4), z -> image (Eq. 5), weighted c1 and c2 (Eq. 6). As in the
    authors' code, the FIRST half of the latent is z (reconstruction), the SECOND z_R (mask);
    without the split (the ablation) both decoders read the whole latent."""
    metric_names = ("recon_loss", "mask_loss")
    decodes = ("mask", "recon")
    split = True

    def __init__(self, latent_dim: int, frame_stack: int, c1: float = 0.01, c2: float = 0.0025):
        super().__init__()
        self.c1, self.c2 = c1, c2
        dec_in = latent_dim // 2 if self.split else latent_dim
        self.recon_decoder = Decoder(dec_in, 3 * frame_stack)
        self.mask_decoder = Decoder(dec_in, frame_stack)

    @classmethod
    def build(cls, cfg, encoder, critic):
        return cls(encoder.repr_dim, cfg.frame_stack, cfg.recon_coef, cfg.mask_coef)

    def decoder_inputs(self, latent):
        return latent.chunk(2, dim=1) if self.split else (latent, latent)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        z, z_r = self.decoder_inputs(latent)
        recon_loss = reconstruction_loss(self.recon_decoder(z), obs_aug)
        mask_loss = summed_bce(self.mask_decoder(z_r), mask_aug)
        terms = {"recon_loss": recon_loss.detach(), "mask_loss": mask_loss.detach()}
        return self.c1 * recon_loss + self.c2 * mask_loss, terms

    def decode(self, latent):
        z, z_r = self.decoder_inputs(latent)
        return {"mask": self.mask_decoder(z_r), "recon": self.recon_decoder(z)}


@dataclass(frozen=True)
class Method:
    """A method: its auxiliary loss, its encoder (SEAR's "pooled", DrQ-v2's "drq"), masks read."""
    doc: str
    aux: type[AuxLoss] | None = None
    encoder: str = "pooled"
    uses_mask: bool = False


# The methods of this file; train.py adds the baselines' (methods/baselines.py) and Ego-Foresight's.
METHODS = {
    "sear": Method("SEAR: latent split, mask + recon", aux=SearAux, uses_mask=True),
    "drq": Method("DrQ-v2 as published", encoder="drq"),
}


# ================================================================================================
# 5. Agent
class Batch(NamedTuple):
    """n-step transitions: obs (B, 3 x stack, H, W) uint8, its masks (B, stack, H, W), the action,
    the n-step return, the bootstrap's gamma^m (0 after a termination), the obs m steps on."""
    obs: torch.Tensor
    mask: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_obs: torch.Tensor
    next_mask: torch.Tensor


class Noise(NamedTuple):
    """An update's random numbers in DrQ-v2's order: shifts, the target's and actor's noise."""
    shift: torch.Tensor
    next_shift: torch.Tensor
    target: torch.Tensor
    actor: torch.Tensor


def linear_std(cfg: Config, step):
    """DrQ-v2's `linear(std_start, std_end, std_steps)` at the AGENT step (an int, or an update's
    float64 tensor): at action repeat 2, std_end after 500k steps = 1M frames."""
    mix = step / cfg.std_steps
    mix = mix.clamp(0.0, 1.0) if torch.is_tensor(mix) else min(max(mix, 0.0), 1.0)
    return (1.0 - mix) * cfg.std_start + mix * cfg.std_end


def actor_metrics(actor_loss, mu) -> dict:
    """Short DDPG runs' failure, made visible: the share of mean actions at exactly +-1 (no gradient
    brings them back), and their std over the batch."""
    return {"actor_loss": actor_loss.detach(), "actor_saturated": (mu.abs() == 1.0).float().mean(),
            "action_spread": mu.std(0, correction=0).mean()}


@torch.no_grad()
def polyak(net: nn.Module, target: nn.Module, tau: float):
    """Polyak averaging of the target network: target <- target + tau (net - target)."""
    for p, t in zip(net.parameters(), target.parameters()):
        t.lerp_(p, tau)


class Agent:
    """DrQ-v2's agent whose encoder the method's auxiliary loss also trains (Eq. 6). A variant
    overrides act, std, next_value, joint_loss, critic_objective or update (methods/)."""
    frame_channels = 3

    def __init__(self, cfg: Config, action_dim: int, device, method: Method | None = None):
        self.cfg, self.device, self.action_dim = cfg, torch.device(device), action_dim
        self.method = method or METHODS[cfg.method]
        in_channels = self.frame_channels * cfg.frame_stack
        # The convolutions (>90% of the FLOPs) in NHWC, oneDNN's and cuDNN's fastest layout.
        nhwc = dict(device=self.device, memory_format=torch.channels_last)
        pooled = self.method.encoder == "pooled"
        encoder = PooledEncoder(in_channels, cfg.latent_dim) if pooled else DrQEncoder(in_channels)
        self.encoder = encoder.to(**nhwc)
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(self.device)
        self.critic = Critic(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(self.device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        aux = self.method.aux
        self.aux = aux.build(cfg, self.encoder, self.critic).to(**nhwc) if aux else None
        # Eq. 6 is one loss; Adam is per-parameter: one optimiser equals DrQ-v2's separate ones.
        # fused: one kernel, and no host sync.
        model_params = [*self.encoder.parameters(), *self.critic.parameters()]
        if self.aux is not None:
            model_params += [p for p in self.aux.parameters() if p.requires_grad]
        self.model_opt = torch.optim.Adam(model_params, lr=cfg.lr, fused=True)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr, fused=True)
        # Its random numbers continue torch's stream from where building the networks left it, in
        # a generator of its own: a seed draws the same numbers alone or beside other seeds.
        cuda = self.device.type == "cuda"
        state = torch.cuda.get_rng_state(self.device) if cuda else torch.get_rng_state()
        self.rng = torch.Generator(self.device).set_state(state)
        self.metric_names = ("critic_loss", "actor_loss", "q", "actor_saturated", "action_spread",
                             "expl_std") + (self.aux.metric_names if self.aux else ())

    def std(self, step):
        """The exploration std at this agent step."""
        return linear_std(self.cfg, step)

    @torch.no_grad()
    def act(self, obs, mask, step: int, eval_mode: bool) -> torch.Tensor:
        """The action at one observation (the RGB stack C x H x W, array or tensor; its masks, read
        by DrQ-RGBM alone), on the device: the actor's mean in evaluation; in training a sample with
        exploration noise, uniform for the first --exploration-steps agent steps."""
        obs = torch.as_tensor(obs, device=self.device).float()[None]
        dist = self.actor(self.encoder(obs), self.std(step))
        if eval_mode:
            return dist.mean[0]
        noise = torch.randn(dist.loc.shape, device=self.device, generator=self.rng)
        action = dist.sample(noise=noise)
        if step < self.cfg.exploration_steps:
            action.uniform_(-1.0, 1.0, generator=self.rng)
        return action[0]

    def draw(self, n: int) -> Noise:
        """An update's random numbers, first, from the agent's generator: the update is then the
        same as written, compiled, as a CUDA graph or batched with others (harness/speed.py)."""
        rng, device = self.rng, self.device
        shift = dict(size=(n, 1, 1, 2), device=device, dtype=torch.float32, generator=rng)
        noise = dict(size=(n, self.action_dim), device=device, generator=rng)
        return Noise(torch.randint(0, 9, **shift), torch.randint(0, 9, **shift),
                     torch.randn(**noise), torch.randn(**noise))

    def next_value(self, next_latent, std, noise):
        """The bootstrap value of s': min(Q1', Q2') of the target at the actor's noisy action."""
        next_action = self.actor(next_latent, std).sample(clip=self.cfg.std_clip, noise=noise)
        return torch.min(*self.critic_target(next_latent, next_action))

    def joint_loss(self, latent, obs_aug, mask_aug, batch: Batch, step, noise: Noise):
        """Eq. 6 on `latent`, the encoding of obs_aug (mask_aug: its masks): the loss, its terms."""
        std = self.std(step)
        with torch.no_grad():
            next_latent = self.encoder(random_shift(batch.next_obs, noise.next_shift))
            next_value = self.next_value(next_latent, std, noise.target)
            target_q = batch.reward + batch.discount * next_value
        q1, q2 = self.critic(latent, batch.action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        metrics = {"critic_loss": critic_loss.detach(), "q": q1.mean().detach(), "expl_std": std}
        if self.aux is None:
            return critic_loss, metrics
        aux_loss, terms = self.aux(latent, obs_aug, mask_aug, encoder=self.encoder, obs=batch.obs,
                                   batch=batch, rng=self.rng)
        # Eq. 6: L = L_critic + c1 L_recon + c2 L_mask (aux_loss: SearAux's c1 and c2 terms)
        return critic_loss + aux_loss, {**terms, **metrics}

    def critic_objective(self, batch: Batch, step, noise: Noise):
        """Eq. 6 on a batch: the loss, its terms for the logs, the latent of the augmented obs."""
        if batch.mask is None:
            obs_aug, mask_aug = random_shift(batch.obs, noise.shift), None
        else:
            obs_aug, mask_aug = shift_together(batch.obs, batch.mask, noise.shift)
        latent = self.encoder(obs_aug)
        return (*self.joint_loss(latent, obs_aug, mask_aug, batch, step, noise), latent)

    def update_critic(self, batch: Batch, step, noise: Noise):
        """One joint step on encoder, critic and decoders (Alg. 1)."""
        loss, metrics, latent = self.critic_objective(batch, step, noise)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.model_opt.step()
        return latent.detach(), metrics

    def actor_loss(self, latent, std, noise):
        """DDPG's loss, -min(Q1, Q2) of the actor's noisy action; the mean action, for the logs."""
        dist = self.actor(latent, std)
        action = dist.sample(clip=self.cfg.std_clip, noise=noise)
        return -torch.min(*self.critic(latent, action)).mean(), dist.mean.detach()

    def update_actor(self, latent, std, noise):
        """DDPG's step; `latent` is detached: no encoder learns from it, nor the critic."""
        actor_loss, mu = self.actor_loss(latent, std, noise)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward(inputs=list(self.actor.parameters()))
        self.actor_opt.step()
        return actor_metrics(actor_loss, mu)

    def update(self, batch: Batch, step: int) -> dict:
        """One update on a replay batch (arrays or tensors, on any device) at agent step `step`.
        Returns its metrics as 0-d tensors on the device: read them when a log line is written."""
        make = type(batch)._make if hasattr(batch, "_make") else Batch._make
        batch = make(None if x is None else torch.as_tensor(x, device=self.device) for x in batch)
        if not self.method.uses_mask:
            batch = batch._replace(mask=None, next_mask=None)
        step = torch.full((), step, dtype=torch.float64, device=self.device)
        return self.learn(batch, step, self.draw(len(batch.obs)))

    def learn(self, batch: Batch, step: torch.Tensor, noise: Noise) -> dict:
        """The update, tensors in and out: Eq. 6's step, the actor's (at the target's std), Polyak,
        a method's own step (CURL's, last as curl_sac.py's). `step`: a float64 0-d tensor."""
        batch = type(batch)._make(None if x is None else x.float() for x in batch)
        latent, metrics = self.update_critic(batch, step, noise)
        metrics = metrics | self.update_actor(latent, metrics["expl_std"], noise.actor)
        polyak(self.critic, self.critic_target, self.cfg.critic_tau)
        if self.aux is not None:
            metrics = metrics | self.aux.after_update(batch.obs, self.rng)
        return metrics

    PARTS = ("encoder", "actor", "critic", "critic_target", "model_opt", "actor_opt", "aux")

    def state_dict(self):
        parts = {name: getattr(self, name) for name in self.PARTS}
        return {**{k: None if v is None else v.state_dict() for k, v in parts.items()},
                "rng": self.rng.get_state()}

    def load_state_dict(self, state):
        for name in (name for name in self.PARTS if getattr(self, name) is not None):
            getattr(self, name).load_state_dict(state[name])
        if "rng" in state:
            self.rng.set_state(state["rng"])


# ================================================================================================
# 6. Replay buffer
class ReplayBuffer:
    """A ring of time steps on `device`: step t's newest frame, its mask bit-packed (882 bytes at
    84x84), the action and reward that led to it, whether it is terminal or starts an episode.
    Frame stacks (the first frame repeats at an episode start), masks and n-step returns are built
    at sampling; a time limit bootstraps, a termination does not. Draws follow DrQ-v2's loader:
    an episode uniformly among the finished ones, then a start inside it."""

    ARRAYS = ("frames", "masks", "actions", "rewards", "terminal", "first")

    def __init__(self, capacity, frame_shape, action_dim, frame_stack, nstep, discount,
                 device="cpu"):
        self.capacity, self.nstep, self.gamma, self.stack = capacity, nstep, discount, frame_stack
        self.frame_shape, self.device = tuple(frame_shape), torch.device(device)
        h, w = frame_shape[1:]
        ring = dict(device=self.device)
        self.frames = torch.empty((capacity, *frame_shape), dtype=torch.uint8, **ring)
        self.masks = torch.empty((capacity, (h * w + 7) // 8), dtype=torch.uint8, **ring)
        self.actions = torch.empty((capacity, action_dim), dtype=torch.float32, **ring)
        self.rewards = torch.empty((capacity,), dtype=torch.float32, **ring)
        self.terminal = torch.empty((capacity,), dtype=torch.bool, **ring)
        self.first = torch.empty((capacity,), dtype=torch.bool, **ring)
        # t: slots ever written (step t is in slot t % capacity); episodes: (first time, steps)
        # of the finished, drawable ones; running: the first time of the one under way.
        self.t, self.episodes, self.running = 0, np.zeros((0, 2), np.int64), -1
        self.bits = torch.arange(7, -1, -1, dtype=torch.uint8, device=self.device)

    @property
    def bytes_per_transition(self):
        return sum(getattr(self, a)[0].nbytes for a in self.ARRAYS)

    def __len__(self):
        return min(self.t, self.capacity)

    def _write(self, obs, action, reward, terminal, first):
        mask = np.packbits(np.asarray(obs["mask"][-1], dtype=bool).reshape(-1))
        self.put(self.t % self.capacity, obs["pixels"][-3:], mask, action, reward, terminal, first)
        self.t += 1

    def put(self, i, frame, mask, action, reward, terminal, first):
        """Slot i's contents, from host arrays and numbers."""
        self.frames[i], self.masks[i], self.actions[i] = map(torch.as_tensor, (frame, mask, action))
        self.rewards[i], self.terminal[i], self.first[i] = float(reward), bool(terminal), first

    def add_first(self, obs):
        """The observation returned by reset(): the episode before it is finished, drawn from now
        on if an n-step window fits in it (DrQ-v2's loader fails on a shorter one)."""
        if self.t - 1 - self.running >= self.nstep:
            kept = self.episodes[self.episodes[:, 0] >= self.t - self.capacity]
            self.episodes = np.append(kept, [[self.running, self.t - 1 - self.running]], axis=0)
        self.running = self.t
        self._write(obs, 0.0, 0.0, False, True)

    def add(self, action, reward, terminated, obs):
        """One env.step(): the action taken, the reward it earned, the observation it led to."""
        self._write(obs, action, reward, terminated, False)

    def drawable(self, lo):
        """(first time, steps) of the finished episodes that start at time lo or later."""
        return self.episodes[np.searchsorted(self.episodes[:, 0], lo):]

    def can_sample(self, margin=0):
        return len(self.drawable(max(0, self.t - self.capacity + margin))) > 0

    def sample(self, batch_size, rng: np.random.Generator, margin=0) -> Batch | None:
        """A batch drawn with `rng` (None while none can be), the `margin` oldest slots left out."""
        lo = max(0, self.t - self.capacity + margin)
        if not len(self.drawable(lo)):
            return None
        return self.batch(self.draw_starts(batch_size, rng, lo), rng)

    def batch(self, times, rng: np.random.Generator):
        """The batch of these start times (Ego-Foresight's replay adds its windows)."""
        return self.transitions(times)

    def draw_starts(self, n, rng: np.random.Generator, lo):
        """n starts: an episode among those from lo, then a start whose n steps lie inside it."""
        first, steps = self.drawable(lo).T
        e = rng.integers(len(first), size=n)
        return first[e] + rng.integers(0, steps[e] - self.nstep + 1)

    def stacked(self, times):
        """The frame and mask stacks at `times` (a device tensor): walk back from each time, never
        past an episode start (the frame there repeats instead), oldest frame first."""
        idx = [times]
        for _ in range(self.stack - 1):
            idx.append(torch.where(self.first[idx[-1] % self.capacity], idx[-1], idx[-1] - 1))
        idx = torch.stack(idx[::-1], dim=1) % self.capacity
        b, (h, w) = len(times), self.frame_shape[1:]
        pixels = self.frames[idx].view(b, -1, h, w)
        bits = (self.masks[idx].unsqueeze(-1) >> self.bits) & 1
        return pixels, bits.view(b, self.stack, -1)[..., :h * w].view(b, self.stack, h, w)

    def transitions(self, times) -> Batch:
        """The n-step transitions from `times`: R = sum_k gamma^(k-1) r_(t+k), and gamma^n (0 if the
        episode terminated at t+n, the window's only possible end), in float32 as numpy's."""
        times = torch.as_tensor(np.asarray(times, dtype=np.int64), device=self.device)
        ret, gamma_n = torch.zeros(len(times), device=self.device), np.float32(1.0)
        for k in range(1, self.nstep + 1):
            ret += float(gamma_n) * self.rewards[(times + k) % self.capacity]
            gamma_n *= np.float32(self.gamma)
        last = self.terminal[(times + self.nstep) % self.capacity]
        discount = torch.where(last, 0.0, float(gamma_n))
        obs, mask = self.stacked(times)
        next_obs, next_mask = self.stacked(times + self.nstep)
        action = self.actions[(times + 1) % self.capacity]
        return Batch(obs, mask, action, ret[:, None], discount[:, None], next_obs, next_mask)


if __name__ == "__main__":
    import os
    import runpy
    runpy.run_path(os.path.join(os.path.dirname(__file__), "train.py"), run_name="__main__")
