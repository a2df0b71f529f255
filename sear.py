"""SEAR: Structured Environment-Agent Representations for visual RL (ICML 2023).

DrQ-v2 (DDPG from pixels: random-shift augmentation, n-step returns, clipped double-Q, linearly
decaying exploration noise) whose image encoder is also trained by two decoders on a latent split in
two halves: one half predicts the robot's binary segmentation mask (Eq. 4), the other reconstructs
the image (Eq. 5); the total loss is Eq. 6, L = L_critic + c1 * L_recon + c2 * L_mask (c1 = 0.01,
c2 = 0.0025). Other representation losses plug into the same seam (`AuxLoss`, a row of `METHODS`):
baselines.py adds the paper's baselines, foresight.py Ego-Foresight, drm.py DrM (`DrMAgent`). In reading
order: 1. Config, 2. Networks, 3. Augmentation, 4. Auxiliary losses and METHODS, 5. Agent, 6. Replay buffer.
It needs torch, numpy and the standard library only; the loop, the envs and the command line stand on it
in train.py: `python sear.py --env walker-walk-distracting` runs train.py.
"""
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
# ================================================================================================
def arg(default, doc, choices=None):  # a config field, its one-line doc (--help), its values if a fixed set
    return field(default=default, metadata={"doc": doc, "choices": choices})


@dataclass
class Config:
    """The algorithm's hyper-parameters (the paper's table). The experiment around them (env, budget,
    evaluation, the baselines' and DrM's settings) is train.Config, which adds its fields to these."""
    method: str = arg("sear", "a row of METHODS: sear, drq (baselines.py adds ae, mae, curl, rgbm, sear-nosplit, dear)")
    precision: str = arg("fp32", "fp32 | bf16: the convolutional encoder and decoders under bf16 autocast; "
                                 "actor, critic and losses stay fp32", ("fp32", "bf16"))
    frame_stack: int = arg(3, "frames stacked into one observation")
    # --- DrQ-v2 (paper hyper-parameter table) ---
    replay_size: int = arg(250_000, "replay buffer capacity in transitions")
    seed_frames: int = arg(4000, "frames collected before the first update (DrQ-v2's num_seed_frames)")
    exploration_steps: int = arg(2000, "first agent steps of uniformly random actions (DrQ-v2's num_expl_steps); "
                                       "then the actor plus noise acts, updated or not yet")
    nstep: int = arg(3, "n of the n-step return")
    batch_size: int = arg(256, "mini-batch size")
    discount: float = arg(0.99, "discount factor gamma")
    lr: float = arg(1e-4, "Adam learning rate of actor, critic, encoder and decoders")
    update_every: int = arg(2, "agent steps between updates")
    critic_tau: float = arg(0.01, "Polyak rate of the target critic")
    feature_dim: int = arg(50, "actor/critic trunk width (Linear + LayerNorm + tanh)")
    latent_dim: int = arg(4096, "encoder latent size (SEAR's pooled encoder), split in two halves")
    hidden_dim: int = arg(1024, "actor and critic MLP width")
    std_start: float = arg(1.0, "exploration std at the start of the linear schedule")
    std_end: float = arg(0.1, "exploration std at the end of the linear schedule")
    std_steps: int = arg(500_000, "AGENT STEPS over which the std decays, as DrQ-v2 (frames = steps x action "
                                  "repeat)")
    std_clip: float = arg(0.3, "clip of the exploration noise in the actor update (DrQ-v2)")
    # --- SEAR, Eq. 6 (paper: c1 = 0.01, c2 = 0.0025; authors' code: 1.0 and 0.25, same 4:1 ratio) ---
    recon_coef: float = arg(0.01, "c1: weight of the reconstruction loss (mae too; ae uses 2 x c1, as the authors)")
    mask_coef: float = arg(0.0025, "c2: weight of the mask loss")


# ================================================================================================
# 2. Networks
# ================================================================================================
def weight_init(m):
    """DrQ-v2's init: orthogonal weights, zero biases (ReLU gain for convolutions)."""
    if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
        nn.init.orthogonal_(m.weight.data, 1.0 if isinstance(m, nn.Linear) else nn.init.calculate_gain("relu"))
        if m.bias is not None:
            m.bias.data.fill_(0.0)


def normalise(pixels):
    """Pixels in [0, 255] to [-0.5, 0.5]: what the encoder reads and Eq. 5 reconstructs (DrQ-v2's scale)."""
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
    """The decoder body shared by the mask and the reconstruction heads (appendix "Architecture").
    8x8 -> 35 (k4 s4, output_padding 3) -> 37 -> 39 -> 41 (k3 s1) -> 84 (k3 s2, output_padding 1)."""

    def __init__(self, in_dim: int, out_channels: int, in_channels: int = 16):
        super().__init__()
        self.in_channels = in_channels  # 16 for SEAR's heads; DrQ-AE's decoder starts from 32 (authors' code)
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

    def sample(self, clip=None):
        noise = torch.randn_like(self.loc) * self.scale
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
        mu = torch.tanh(self.policy(self.trunk(latent)))
        # std: a float (acting), or the update's 0-d float64 tensor, rounded to float32 as a float would be
        return TruncatedNormal(mu, torch.full_like(mu, std) if isinstance(std, float) else std.float().expand_as(mu))


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
# ================================================================================================
def random_shift(x: torch.Tensor, pad: int = 4, shift: torch.Tensor | None = None):
    """DrQ's random shift: replicate-pad by `pad`, then crop back with a per-sample integer shift,
    done as a bilinear grid sample (DrQ-v2's RandomShiftsAug, its arithmetic). Integer shifts land on
    pixel centres (to float32 rounding), so a 0/1 mask stays 0/1. SEAR shifts image and mask stack together by
    concatenating them along channels: the same shift for both is what makes the mask a label of the
    image the encoder sees."""
    n, c, h, w = x.shape
    assert h == w
    padded = F.pad(x, (pad,) * 4, mode="replicate")
    eps = 1.0 / (h + 2 * pad)
    arange = torch.linspace(-1.0 + eps, 1.0 - eps, h + 2 * pad, device=x.device, dtype=x.dtype)[:h]
    arange = arange.unsqueeze(0).expand(h, h).unsqueeze(2)
    base_grid = torch.cat([arange, arange.transpose(1, 0)], dim=2).unsqueeze(0)  # broadcast over the batch
    if shift is None:
        shift = torch.randint(0, 2 * pad + 1, size=(n, 1, 1, 2), device=x.device, dtype=x.dtype)
    grid = base_grid + shift.to(x.dtype) * (2.0 / (h + 2 * pad))
    return F.grid_sample(padded, grid, padding_mode="zeros", align_corners=False)


def shift_together(obs: torch.Tensor, *labels: torch.Tensor):
    """One random shift per sample, applied identically to the image stack and each label stack (masks, EF's frame)."""
    both = random_shift(torch.cat([obs, *labels], dim=1) if labels else obs)
    return both.split([obs.shape[1], *(x.shape[1] for x in labels)], dim=1)


# ================================================================================================
# 4. Auxiliary losses: one seam for SEAR and every baseline
# ================================================================================================
def summed_mse(pred, target, weight=None):
    """Squared error summed over channels and pixels, averaged over the batch (Eq. 5). c1 is
    relative to this sum, not to a per-pixel mean."""
    err = (pred.float() - target) ** 2  # fp32 even when the decoder ran in bf16
    if weight is not None:
        err = err * weight
    return err.flatten(1).sum(1).mean()


def reconstruction_loss(pred, obs, weight=None):
    """Eq. 5 on the [-0.5, 0.5]-normalised image, the prediction clamped to that range first (the authors'
    sear/agents/sear.py, drqv2AE.py): no gradient pushes a pixel already past black or white further."""
    return summed_mse(pred.float().clamp(-0.5, 0.5), normalise(obs), weight)


def summed_bce(logits, target):
    """Binary cross-entropy on mask logits, summed over pixels, averaged over the batch (Eq. 4)."""
    bce = F.binary_cross_entropy_with_logits(logits.float(), target, reduction="none")
    return bce.flatten(1).sum(1).mean()


class AuxLoss(nn.Module):
    """The seam: sees the latent of the augmented observation (which the critic reads too) and the
    augmented image and mask (same shift; by keyword: `encoder`, the un-augmented `obs`, the `batch`); returns
    its weighted term of Eq. 6 and its unweighted terms for the logs. Its parameters join the encoder's and
    critic's optimiser (CURL steps its own, in after_update). METHODS builds it: build(cfg, encoder, critic)."""
    metric_names: tuple[str, ...] = ()
    decodes: tuple[str, ...] = ()  # what decode() returns: "mask" (logits), "recon" (normalised image)

    @classmethod
    def build(cls, cfg, encoder, critic):  # METHODS' constructor; SEAR's own takes plain arguments
        return cls(cfg, encoder, critic)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        return latent.new_zeros(()), {}  # nothing in Eq. 6 (CURL: its own step, after_update)

    def decode(self, latent) -> dict:  # what the decoders make of a latent: the evaluation's metrics and videos
        return {}

    def after_update(self, obs) -> dict:  # at the end of each update (CURL's own step): its terms for the logs
        return {}

    def act(self, action, step):  # the action a training step takes instead (EF's babbling)
        return action

    def replay(self, *args, **kwargs):  # the replay the method samples (EF's: windows)
        return ReplayBuffer(*args, **kwargs)


class SearAux(AuxLoss):
    """SEAR: z_R -> robot mask (Eq. 4), z -> image (Eq. 5), weighted c1 and c2 (Eq. 6). As in the
    authors' code, the FIRST half of the latent is z (reconstruction) and the SECOND half is z_R (mask)."""
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

    def decoder_inputs(self, latent):  # (z, z_R): the two halves, or the whole latent twice without the split
        return latent.chunk(2, dim=1) if self.split else (latent, latent)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        z, z_r = self.decoder_inputs(latent)
        recon_loss = reconstruction_loss(self.recon_decoder(z), obs_aug)
        mask_loss = summed_bce(self.mask_decoder(z_r), mask_aug)
        loss = self.c1 * recon_loss + self.c2 * mask_loss
        return loss, {"recon_loss": recon_loss.detach(), "mask_loss": mask_loss.detach()}

    def decode(self, latent):
        z, z_r = self.decoder_inputs(latent)
        return {"mask": self.mask_decoder(z_r), "recon": self.recon_decoder(z)}


@dataclass(frozen=True)
class Method:
    doc: str
    aux: type[AuxLoss] | None = None  # aux.build(cfg, encoder, critic); None: only the critic trains the encoder
    encoder: str = "pooled"           # "pooled" (SEAR's) or "drq" (DrQ-v2's, flattened)
    mask_input: bool = False          # DrQ-RGBM: the mask is a 4th channel of every stacked frame
    uses_mask: bool = False           # False: the env skips the segmentation render (it costs a second pass)


METHODS = {
    "sear": Method("SEAR: latent split, mask + recon", aux=SearAux, uses_mask=True),
    "drq": Method("DrQ-v2 as published", encoder="drq"),
}  # baselines.py adds the paper's baselines: ae, mae, curl, rgbm, sear-nosplit, dear


# ================================================================================================
# 5. Agent
# ================================================================================================
class Batch(NamedTuple):
    """n-step transitions, as the replay buffer samples them and the update takes them (tensors)."""
    obs: torch.Tensor        # (B, 3 x stack, H, W) RGB frames, uint8
    mask: torch.Tensor       # (B, stack, H, W) the robot's masks, 0/1
    action: torch.Tensor     # (B, A) the action taken at obs
    reward: torch.Tensor     # (B, 1) the n-step return R
    discount: torch.Tensor   # (B, 1) gamma^m of the bootstrap, 0 after a termination
    next_obs: torch.Tensor   # the observation m <= n steps later
    next_mask: torch.Tensor


def linear_std(cfg: Config, step):
    """DrQ-v2's `linear(std_start, std_end, std_steps)` at the AGENT step (an int, or the update's float64
    tensor: on the device, as a float would be): at action repeat 2, std_end after 500k steps = 1M frames."""
    mix = step / cfg.std_steps
    mix = mix.clamp(0.0, 1.0) if torch.is_tensor(mix) else min(max(mix, 0.0), 1.0)
    return (1.0 - mix) * cfg.std_start + mix * cfg.std_end


def actor_metrics(actor_loss, mu) -> dict:
    """Short DDPG runs' failure, made visible: actor_saturated, the share of mean actions at exactly +-1 in
    float32 (no gradient brings them back); action_spread, their std over the batch (0: one action always)."""
    return {"actor_loss": actor_loss.detach(), "actor_saturated": (mu.abs() == 1.0).mean(dtype=torch.float32),
            "action_spread": mu.std(0, correction=0).mean()}


class Adam(torch.optim.Adam):
    """torch.optim.Adam, stepped on given gradients: `opt.step(torch.autograd.grad(loss, opt.params))`.
    torch's CPU arithmetic to the bit, as one foreach operation per term over all parameters and each
    step count a float64 tensor on the device: no per-parameter loop, no host sync (torch's CPU step reads
    every count with .item()), one graph for torch.compile. Its state_dict is torch.optim.Adam's."""

    def __init__(self, params, lr):
        super().__init__(params, lr=lr)
        self.reset()

    @property
    def params(self):
        return [p for group in self.param_groups for p in group["params"]]

    def reset(self, params=None):  # fresh moments and counts (of `params`: DrM's perturbation forgets some)
        for p in self.params if params is None else params:
            self.state[p] = {"step": torch.zeros((), dtype=torch.float64, device=p.device),
                             "exp_avg": torch.zeros_like(p), "exp_avg_sq": torch.zeros_like(p)}

    def load_state_dict(self, state_dict):
        super().load_state_dict(state_dict)
        self.reset([p for p in self.params if p not in self.state])  # saved before its first step
        for p in self.params:  # torch.optim.Adam's counts are float32 on the CPU: ours on the parameter's device
            self.state[p]["step"] = self.state[p]["step"].to(p.device, torch.float64)

    @torch.no_grad()
    def step(self, grads):
        grads = iter(grads)
        for group in self.param_groups:
            params = group["params"]
            grad = [next(grads) for _ in params]
            m, v, t = ([self.state[p][k] for p in params] for k in ("exp_avg", "exp_avg_sq", "step"))
            (beta1, beta2), lr = group["betas"], group["lr"]
            torch._foreach_add_(t, 1)
            torch._foreach_lerp_(m, grad, 1 - beta1)
            torch._foreach_mul_(v, beta2)
            torch._foreach_addcmul_(v, grad, grad, 1 - beta2)
            # p += -lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps), the corrections in float64
            neg_step = torch._foreach_pow(beta1, t)
            torch._foreach_sub_(neg_step, 1)  # -(1 - beta1^t), exactly
            torch._foreach_reciprocal_(neg_step)
            torch._foreach_mul_(neg_step, lr)
            root = torch._foreach_pow(beta2, t)
            torch._foreach_neg_(root)
            torch._foreach_add_(root, 1)
            torch._foreach_sqrt_(root)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, root)
            torch._foreach_add_(denom, group["eps"])
            torch._foreach_addcdiv_(params, torch._foreach_mul(m, neg_step), denom)


class Agent:
    """DrQ-v2's agent whose encoder the method's auxiliary loss also trains (Eq. 6). A variant overrides
    `std` (exploration), `next_value` (the bootstrap), `joint_loss` (Eq. 6) or `update`: drm.DrMAgent."""

    def __init__(self, cfg: Config, action_dim: int, device: torch.device):
        self.cfg, self.device = cfg, device
        self.method = METHODS[cfg.method]
        in_channels = (4 if self.method.mask_input else 3) * cfg.frame_stack
        # The convolutions (encoder, decoders) hold >90% of an update's FLOPs: NHWC ("channels_last"), the
        # layout of oneDNN's and cuDNN's fastest kernels, and under --precision bf16 only they run in bf16:
        # a TD target in bf16 would be off by up to 0.5 at Q = 100, so actor, critic and losses stay fp32.
        nhwc = dict(device=device, memory_format=torch.channels_last)
        if self.method.encoder == "pooled":
            self.encoder = PooledEncoder(in_channels, cfg.latent_dim).to(**nhwc)
        else:
            self.encoder = DrQEncoder(in_channels).to(**nhwc)
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(device)
        self.critic = Critic(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.aux = self.method.aux.build(cfg, self.encoder, self.critic).to(**nhwc) if self.method.aux else None
        # Eq. 6 is one loss over encoder, critic and decoders; Adam is per-parameter, so one
        # optimiser for all of them equals DrQ-v2's separate encoder/critic optimisers.
        model_params = [*self.encoder.parameters(), *self.critic.parameters()]
        if self.aux is not None:
            model_params += [p for p in self.aux.parameters() if p.requires_grad]
        self.model_opt = Adam(model_params, lr=cfg.lr)
        self.actor_opt = Adam(self.actor.parameters(), lr=cfg.lr)
        self.metric_names = (("critic_loss", "actor_loss", "q", "actor_saturated", "action_spread", "expl_std")
                             + (self.aux.metric_names if self.aux else ()))

    def std(self, step):  # the exploration std at this agent step: DrQ-v2's linear schedule
        return linear_std(self.cfg, step)

    def conv_precision(self):  # bf16 autocast for the convolutional networks under --precision bf16
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.cfg.precision == "bf16")

    def encode(self, obs):
        with self.conv_precision():
            return self.encoder(obs).float()

    def encoder_input(self, pixels: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """The encoder's input: the RGB stack, or for RGBM each frame's RGB followed by its mask."""
        if not self.method.mask_input:
            return pixels
        if mask is None:
            raise ValueError("method rgbm needs the robot mask when acting: pass mask=obs['mask']")
        n, c, h, w = pixels.shape
        rgb = pixels.view(n, c // 3, 3, h, w)
        m = (mask.to(pixels.dtype) * 255.0).view(n, c // 3, 1, h, w)
        return torch.cat([rgb, m], dim=2).view(n, -1, h, w)

    @torch.no_grad()
    def act(self, pixels: np.ndarray, mask: np.ndarray | None, step: int, eval_mode: bool):
        obs = torch.as_tensor(pixels, device=self.device).float().unsqueeze(0)
        m = None if mask is None else torch.as_tensor(mask, device=self.device).float().unsqueeze(0)
        latent = self.encode(self.encoder_input(obs, m))
        dist = self.actor(latent, self.std(step))
        if eval_mode:
            action = dist.mean
        else:
            action = dist.sample(clip=None)
            if step < self.cfg.exploration_steps:
                action.uniform_(-1.0, 1.0)
            action = action if self.aux is None else self.aux.act(action, step)
        return action.squeeze(0).cpu().numpy().astype(np.float32)

    def next_value(self, next_latent, std):
        """The critic's bootstrap value of s': clipped double-Q, min(Q1', Q2') of the target critic at
        the actor's next action with exploration noise of this `std`."""
        next_action = self.actor(next_latent, std).sample(clip=self.cfg.std_clip)
        return torch.min(*self.critic_target(next_latent, next_action))

    def joint_loss(self, latent, obs_aug, mask_aug, batch: Batch, step):
        """Eq. 6, the critic's TD loss plus the auxiliary loss (SEAR: c1 recon + c2 mask), on `latent`, the
        encoding of obs_aug (mask_aug: its masks, same shift); the loss, and the logs' terms with expl_std."""
        std = self.std(step)
        with torch.no_grad():
            next_latent = self.encode(random_shift(batch.next_obs))
            target_q = batch.reward + batch.discount * self.next_value(next_latent, std)
        q1, q2 = self.critic(latent, batch.action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        loss, metrics = critic_loss, {}
        if self.aux is not None:
            with self.conv_precision():  # decoders (and MAE's second encoder pass) in bf16; losses fp32
                aux_loss, metrics = self.aux(latent, obs_aug, mask_aug, encoder=self.encoder, obs=batch.obs,
                                             batch=batch)
            loss = loss + aux_loss
        return loss, {**metrics, "critic_loss": critic_loss.detach(), "q": q1.mean().detach(), "expl_std": std}

    def critic_objective(self, batch: Batch, step):
        """Eq. 6 on a batch: the loss, its terms for the logs, the latent of the augmented observation."""
        labels = [x for x in (batch.mask, getattr(batch, "frame_ahead", None)) if x is not None]
        obs_aug, *labels = shift_together(batch.obs, *labels)  # one shift per sample: the same draws with or without
        mask_aug = labels.pop(0) if batch.mask is not None else None
        batch = batch._replace(frame_ahead=labels[0]) if labels else batch  # EF's frame ahead, shifted as its context
        latent = self.encode(obs_aug)
        return (*self.joint_loss(latent, obs_aug, mask_aug, batch, step), latent)

    def update_critic(self, batch: Batch, step):
        """One joint step on encoder, critic and decoders (Alg. 1)."""
        loss, metrics, latent = self.critic_objective(batch, step)
        # materialize_grads: a parameter Eq. 6 does not reach (CURL's W, which CURL steps itself) gets a
        # zero gradient, and Adam's step of a parameter that never had a gradient is exactly 0.
        self.model_opt.step(torch.autograd.grad(loss, self.model_opt.params, materialize_grads=True))
        return latent.detach(), metrics

    def actor_loss(self, latent, std):
        """DDPG's loss, -min(Q1, Q2) of the actor's noisy action; and the mean action, for the logs."""
        dist = self.actor(latent, std)
        return -torch.min(*self.critic(latent, dist.sample(clip=self.cfg.std_clip))).mean(), dist.mean.detach()

    def update_actor(self, latent, std):
        """DDPG: move the actor towards actions of higher min(Q1, Q2). `latent` is detached: this
        loss does not train the encoder; nor the critic, whose gradient is not computed at all."""
        actor_loss, mu = self.actor_loss(latent, std)
        self.actor_opt.step(torch.autograd.grad(actor_loss, self.actor_opt.params))
        return actor_metrics(actor_loss, mu)

    def update(self, batch: Batch, step: int) -> dict:
        """One update on a replay batch (arrays or tensors, on any device) at agent step `step`.
        Returns its metrics as 0-d tensors on the device: read them when a log line is written."""
        make = type(batch)._make if hasattr(batch, "_make") else Batch._make  # a Batch, or a method's (EF's Window)
        batch = make(torch.as_tensor(x, device=self.device) for x in batch)  # a ring's: there already
        if not self.method.uses_mask:  # neither shifted nor read
            batch = batch._replace(mask=None, next_mask=None)
        return self.learn(batch, torch.full((), step, dtype=torch.float64, device=self.device))

    def learn(self, batch: Batch, step: torch.Tensor) -> dict:
        """The update, tensors in and out (what --compile takes whole): the joint step of Eq. 6, the actor's,
        Polyak averaging, a method's own step (CURL's). `step`: the agent step, a float64 0-d tensor."""
        batch = type(batch)._make(None if x is None else x.float() for x in batch)
        batch = batch._replace(obs=self.encoder_input(batch.obs, batch.mask),
                               next_obs=self.encoder_input(batch.next_obs, batch.next_mask))
        latent, metrics = self.update_critic(batch, step)
        metrics.update(self.update_actor(latent, metrics["expl_std"]))  # the std the critic's target used
        with torch.no_grad():  # Polyak averaging of the target critic
            torch._foreach_lerp_(list(self.critic_target.parameters()), list(self.critic.parameters()),
                                 self.cfg.critic_tau)
        if self.aux is not None:  # CURL's own step, last as in curl_sac.py
            metrics.update(self.aux.after_update(batch.obs))
        return metrics

    def compile(self):
        """--compile: learn() as one torch.compile graph (a break is an error, on the CPU too), a CUDA graph on
        CUDA. Eager stays the reference: on the CPU it draws eager's numbers (fallback_random), equal to rounding."""
        import torch._dynamo
        import torch._inductor.config
        torch._dynamo.config.trace_autograd_ops = True  # torch.autograd.grad inside the graph
        torch._inductor.config.fallback_random = True
        held = [*vars(self).values(), *vars(self.aux or nn.Module()).values()]  # optimisers, DrM's state
        for t in [t for opt in held if isinstance(opt, Adam) for state in opt.state.values() for t in state.values()] \
                + [t for t in held if torch.is_tensor(t)]:
            torch._dynamo.mark_static_address(t)  # updated in place by the graph: its address must not move
        cuda_graph = "reduce-overhead" if self.device.type == "cuda" else None
        graph = torch.compile(self.learn, fullgraph=True, mode=cuda_graph)
        # A CUDA graph's outputs are overwritten by its next replay; the metrics wait for a log line.
        self.learn = lambda batch, step: {k: v.clone() for k, v in graph(batch, step).items()}

    PARTS = ("encoder", "actor", "critic", "critic_target", "model_opt", "actor_opt", "aux")  # aux: None for drq

    def state_dict(self):
        return {name: None if getattr(self, name) is None else getattr(self, name).state_dict() for name in self.PARTS}

    def load_state_dict(self, state):
        for name in (name for name in self.PARTS if getattr(self, name) is not None):
            getattr(self, name).load_state_dict(state[name])


# ================================================================================================
# 6. Replay buffer
# ================================================================================================
class ReplayBuffer:
    """A ring of time steps in tensors on `device` (the run's GPU when it fits there). Slot i holds the
    newest RGB frame of step i (uint8, stored once), its robot mask bit-packed (np.packbits: 882 bytes for
    84x84), the action and reward that led to it, whether it is terminal, whether it starts an episode.
    Frame stacks (never across an episode start: the first frame repeats, as at reset), unpacked masks
    and n-step returns are built at sampling, on the device. A time-limit end bootstraps; a termination
    does not. Draws follow DrQ-v2's loader (replay_buffer.py _sample): an episode uniformly among the
    finished ones whole in the ring, then a start whose n-step window lies in it; the index and the draws
    stay on the host (numpy): the start times are a batch's only host->device copy."""

    def __init__(self, capacity, frame_shape, action_dim, frame_stack, nstep, discount, device="cpu"):
        self.capacity, self.stack, self.nstep, self.discount = capacity, frame_stack, nstep, discount
        self.frame_shape, self.device = tuple(frame_shape), torch.device(device)  # (3, H, W)
        h, w = frame_shape[1:]
        self.mask_bytes = (h * w + 7) // 8
        ring = dict(device=self.device)
        self.frames = torch.empty((capacity, *frame_shape), dtype=torch.uint8, **ring)
        self.masks = torch.empty((capacity, self.mask_bytes), dtype=torch.uint8, **ring)
        self.actions = torch.empty((capacity, action_dim), dtype=torch.float32, **ring)
        self.rewards = torch.empty((capacity,), dtype=torch.float32, **ring)
        self.terminal = torch.empty((capacity,), dtype=torch.bool, **ring)
        self.first = torch.empty((capacity,), dtype=torch.bool, **ring)
        self.t = 0  # slots ever written; slot of time step t is t % capacity
        self.episodes = np.zeros((0, 2), np.int64)  # (first time, steps) of the finished, drawable episodes
        self.running = -1  # first time of the running episode
        self.bits = torch.arange(7, -1, -1, dtype=torch.uint8, device=self.device)  # np.packbits' order

    ARRAYS = ("frames", "masks", "actions", "rewards", "terminal", "first")

    @property
    def bytes_per_transition(self):
        return sum(getattr(self, a)[0].nbytes for a in self.ARRAYS)

    def __len__(self):
        return min(self.t, self.capacity)

    def _write(self, obs, action, reward, terminal, first):
        i = self.t % self.capacity
        self.frames[i] = torch.as_tensor(obs["pixels"][-3:])
        self.masks[i] = torch.from_numpy(np.packbits(np.asarray(obs["mask"][-1], dtype=bool).reshape(-1)))
        self.actions[i] = torch.as_tensor(action)
        self.rewards[i], self.terminal[i], self.first[i] = float(reward), bool(terminal), bool(first)
        self.t += 1

    def add_first(self, obs):
        """The observation returned by reset(): the episode before it is finished, drawn from now on
        if an n-step window fits in it (DrQ-v2's loader fails on a shorter one)."""
        if self.t - 1 - self.running >= self.nstep:
            kept = self.episodes[self.episodes[:, 0] >= self.t - self.capacity]  # still whole in the ring
            self.episodes = np.append(kept, [[self.running, self.t - 1 - self.running]], axis=0)
        self.running = self.t
        self._write(obs, 0.0, 0.0, False, True)

    def add(self, action, reward, terminated, obs):
        """One env.step(): the action taken, the reward it earned, and the observation it led to."""
        self._write(obs, action, reward, terminated, False)

    def load_arrays(self, arrays) -> None:
        """A saved ring back (a wrapped one in the same slots), the episode index rebuilt from its `first` flags."""
        n = len(arrays["rewards"])
        for a in self.ARRAYS:
            getattr(self, a)[:n] = torch.from_numpy(np.asarray(arrays[a]))
        self.t = int(arrays["t"])
        lo = max(0, self.t - self.capacity)
        firsts = lo + np.flatnonzero(self.first[:n].cpu().numpy()[np.arange(lo, self.t) % self.capacity])
        steps = np.diff(firsts) - 1
        self.episodes = np.stack([firsts[:-1], steps], axis=1)[steps >= self.nstep]
        self.running = firsts[-1] if len(firsts) else -1

    # --- sampling ---
    def drawable(self, lo):
        """(first time, steps) of the finished episodes that start at time lo or later."""
        return self.episodes[np.searchsorted(self.episodes[:, 0], lo):]

    def can_sample(self, margin=0):
        return len(self.drawable(max(0, self.t - self.capacity + margin))) > 0

    def sample(self, batch_size, rng: np.random.Generator, margin=0) -> Batch | None:
        """A batch of transitions drawn with `rng`, or None while no episode can be drawn. margin: the
        oldest slots kept out of the draws (a sampler thread reads while the loop overwrites them)."""
        lo = max(0, self.t - self.capacity + margin)
        return self.batch(self.draw_starts(batch_size, rng, lo), rng) if len(self.drawable(lo)) else None

    def batch(self, times, rng: np.random.Generator):  # a batch of these starts (EF's adds windows)
        return self.transitions(times)

    def draw_starts(self, n, rng: np.random.Generator, lo):
        """n start times: an episode uniformly among those drawable from lo, then a start from which
        all n steps lie inside it (DrQ-v2's idx range: an episode's last n-1 steps never start one)."""
        first, steps = self.drawable(lo).T
        e = rng.integers(len(first), size=n)
        return first[e] + rng.integers(0, steps[e] - self.nstep + 1)

    def stacked(self, times):
        """The frame stacks and mask stacks at `times` (a device tensor): walk back from each time, never
        past an episode start (the frame there is repeated instead), oldest frame first."""
        idx = [times]
        for _ in range(self.stack - 1):
            idx.append(torch.where(self.first[idx[-1] % self.capacity], idx[-1], idx[-1] - 1))
        idx = torch.stack(idx[::-1], dim=1) % self.capacity  # (B, stack)
        b, (h, w) = len(times), self.frame_shape[1:]
        pixels = self.frames[idx].view(b, -1, h, w)
        bits = (self.masks[idx].unsqueeze(-1) >> self.bits) & 1  # (B, stack, mask bytes, 8)
        return pixels, bits.view(b, self.stack, -1)[..., :h * w].view(b, self.stack, h, w)

    def transitions(self, times) -> Batch:
        """The n-step transitions from `times` (each inside one episode): R = sum_k gamma^(k-1) r_(t+k) and the
        bootstrap discount gamma^n, 0 if the episode terminated at t+n (float32, in numpy's order)."""
        times = torch.as_tensor(np.asarray(times, dtype=np.int64)).to(self.device, non_blocking=True)
        ret, gamma_n = torch.zeros(len(times), device=self.device), np.float32(1.0)
        for k in range(1, self.nstep + 1):
            ret += float(gamma_n) * self.rewards[(times + k) % self.capacity]
            gamma_n *= np.float32(self.discount)
        # Only the window's last step can end the episode: no bootstrap after a termination there.
        last = self.terminal[(times + self.nstep) % self.capacity]
        discount = torch.where(last, 0.0, float(gamma_n))
        obs, mask = self.stacked(times)
        next_obs, next_mask = self.stacked(times + self.nstep)
        action = self.actions[(times + 1) % self.capacity]
        return Batch(obs, mask, action, ret[:, None], discount[:, None], next_obs, next_mask)


if __name__ == "__main__":  # the training loop, the flags and the run harness stand on this file in train.py
    import os
    import runpy
    runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)), "train.py"), run_name="__main__")
