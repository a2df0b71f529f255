"""SEAR: Structured Environment-Agent Representations for visual RL (ICML 2023).

DrQ-v2 (DDPG from pixels: random-shift augmentation, n-step returns, clipped double-Q, linearly
decaying exploration noise) whose image encoder is also trained by two decoders on a latent split in
two halves: one half predicts the robot's binary segmentation mask (Eq. 4), the other reconstructs
the image (Eq. 5); the total loss is Eq. 6, L = L_critic + c1 * L_recon + c2 * L_mask (c1 = 0.01,
c2 = 0.0025). The paper's baselines are the same agent with another auxiliary loss (one seam,
`AuxLoss`): drq (none), ae, mae, curl, rgbm (mask as an input channel), sear-nosplit; beyond it,
dear. --drm adds DrM to any of them (drm.py).

In reading order: 1. Config, 2. Networks, 3. Augmentation, 4. Auxiliary losses and METHODS, 5. Agent,
6. Replay buffer, 7. Evaluation, 8. Training loop. Around it: experiment.py (envs, the run directory,
logs, snapshots, progress, evaluation metrics) and cli.py (flags, recipes, checks, device, threads).

Usage:  python sear.py --env walker-walk-distracting [--method sear] [--seed 1]
        python sear.py --resume runs/<run dir>     |     python sear.py --evaluate runs/<run dir>
"""
from __future__ import annotations

import copy
import random
import sys
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

import cli
import drm
import experiment
from cli import arg


# ================================================================================================
# 1. Config
# ================================================================================================
@dataclass
class Config(experiment.EnvConfig, drm.DrMConfig):
    """The experiment: env, method and every hyper-parameter, one --flag each (the doc is its help). The
    envs' settings (masks, distractors, rendering) come from experiment.EnvConfig, DrM's (--drm) from
    drm.DrMConfig. How a process runs it (device, files, snapshots) is cli.RunConfig."""
    env: str = arg("walker-walk", "task name; see envs.py (e.g. walker-walk-distracting, metaworld-door-open)")
    method: str = arg("sear", "sear | drq | ae | mae | curl | rgbm | sear-nosplit | dear")
    seed: int = arg(1, "seeds python, numpy, torch and the environments")
    frames: int = arg(1_000_000, "environment frames to train for (frames = agent steps x action repeat)")
    precision: str = arg("fp32", "fp32 | bf16: the convolutional encoder and decoders under bf16 autocast; "
                                 "actor, critic and losses stay fp32", ("fp32", "bf16"))
    # --- environment (paper hyper-parameter table) ---
    action_repeat: int = arg(0, "0 = the suite's default (2 dm_control and Meta-World, 1 Kitchen and Adroit)")
    frame_stack: int = arg(3, "frames stacked into one observation")
    max_episode_steps: int = arg(0, "0 = the suite's time limit; N > 0 truncates episodes after N agent steps")
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
    eval_every: int = arg(10_000, "frames between evaluations (snapshots follow --snapshot-minutes)")
    eval_episodes: int = arg(10, "episodes per evaluation, mean action (task sets: at least this many in all)")
    eval_episodes_per_task: int = arg(0, "task sets (metaworld-mt*): evaluation episodes of every task; "
                                         "0 = ceil(--eval-episodes / number of tasks)")
    # --- SEAR, Eq. 6 (paper: c1 = 0.01, c2 = 0.0025; authors' code: 1.0 and 0.25, same 4:1 ratio) ---
    recon_coef: float = arg(0.01, "c1: weight of the reconstruction loss (mae too; ae uses 2 x c1, as the authors)")
    mask_coef: float = arg(0.0025, "c2: weight of the mask loss")
    # --- baselines (each default from its source) ---
    ae_latent_lambda: float = arg(0.0, "ae: L2 penalty on the latent (authors' DrQ-AE: none; SAC-AE: 1e-6)")
    mae_ratio: float = arg(0.75, "mae: fraction of patches hidden (MAE, He et al. 2022)")
    mae_patch: int = arg(12, "mae: patch side in pixels (84 = 7 x 12)")
    curl_tau: float = arg(0.05, "curl: EMA rate of the key encoder, every 2nd update (CURL, Laskin et al. 2020)")
    curl_lr: float = arg(1e-3, "curl: Adam learning rate of CURL's own step (curl_sac.py: encoder_lr)")
    dear_feature: str = arg("pull", "dear: pull (1 - cos, its released code) | push (max(0, cos))", ("pull", "push"))


# ================================================================================================
# 2. Networks
# ================================================================================================
def weight_init(m):
    """DrQ-v2's init: orthogonal weights, zero biases (ReLU gain for convolutions)."""
    if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
        nn.init.orthogonal_(m.weight.data, 1.0 if isinstance(m, nn.Linear) else nn.init.calculate_gain("relu"))
        if m.bias is not None:
            m.bias.data.fill_(0.0)


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
        return self.convs(obs / 255.0 - 0.5).flatten(1)


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
        h = self.pool(self.convs(obs / 255.0 - 0.5))
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
        return x - x.detach() + clamped.detach()


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
        return TruncatedNormal(mu, torch.full_like(mu, std))


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
    done as a bilinear grid sample. Integer shifts land on pixel centres, so a 0/1 mask stays 0/1.
    SEAR shifts the image stack and its mask stack together by concatenating them along channels:
    the same shift for both is what makes the mask a label of the image the encoder sees."""
    n, c, h, w = x.shape
    assert h == w
    padded = F.pad(x, (pad,) * 4, mode="replicate")
    eps = 1.0 / (h + 2 * pad)
    arange = torch.linspace(-1.0 + eps, 1.0 - eps, h + 2 * pad, device=x.device, dtype=x.dtype)[:h]
    arange = arange.unsqueeze(0).repeat(h, 1).unsqueeze(2)
    base_grid = torch.cat([arange, arange.transpose(1, 0)], dim=2).unsqueeze(0).repeat(n, 1, 1, 1)
    if shift is None:
        shift = torch.randint(0, 2 * pad + 1, size=(n, 1, 1, 2), device=x.device)
    grid = base_grid + shift.to(x.dtype) * 2.0 / (h + 2 * pad)
    return F.grid_sample(padded, grid, padding_mode="zeros", align_corners=False)


def shift_together(obs: torch.Tensor, mask: torch.Tensor):
    """One random shift per sample, applied identically to the image stack and the mask stack."""
    both = random_shift(torch.cat([obs, mask], dim=1))
    return both[:, :obs.shape[1]], both[:, obs.shape[1]:]


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
    """Eq. 5 on the [-0.5, 0.5]-normalised image. The prediction is clamped to that range first, as
    in the authors' code (sear/agents/sear.py and drqv2AE.py): no gradient pushes a pixel that is
    already past black or white any further."""
    return summed_mse(pred.float().clamp(-0.5, 0.5), obs / 255.0 - 0.5, weight)


def summed_bce(logits, target):
    """Binary cross-entropy on mask logits, summed over pixels, averaged over the batch (Eq. 4)."""
    bce = F.binary_cross_entropy_with_logits(logits.float(), target, reduction="none")
    return bce.flatten(1).sum(1).mean()


class AuxLoss(nn.Module):
    """The seam. An auxiliary loss sees the latent of the augmented observation (which also feeds
    the critic) and the augmented image and mask (same shift); baselines that need more take it as
    keywords (`encoder`, the un-augmented `obs`). It returns its weighted contribution to Eq. 6 and
    its unweighted terms for the logs; its parameters join the encoder's and critic's optimiser (CURL
    steps its own, in after_update). METHODS builds it with build(cfg, encoder, critic)."""
    metric_names: tuple[str, ...] = ()
    decodes: tuple[str, ...] = ()  # what decode() returns: "mask" (logits), "recon" (normalised image)

    @classmethod
    def build(cls, cfg, encoder, critic):  # METHODS' constructor; SEAR's own takes plain arguments
        return cls(cfg, encoder, critic)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        return latent.new_zeros(()), {}  # nothing in Eq. 6 (CURL: its own step, after_update)

    def decode(self, latent) -> dict:
        """What the decoders make of a latent, for the evaluation's metrics and videos."""
        return {}

    def after_update(self, obs) -> dict:  # at the end of each update (CURL's own step): its terms for the logs
        return {}


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

    def decoder_inputs(self, latent):
        if not self.split:
            return latent, latent
        z, z_r = latent.chunk(2, dim=1)
        return z, z_r

    def forward(self, latent, obs_aug, mask_aug, **extra):
        z, z_r = self.decoder_inputs(latent)
        recon_loss = reconstruction_loss(self.recon_decoder(z), obs_aug)
        mask_loss = summed_bce(self.mask_decoder(z_r), mask_aug)
        loss = self.c1 * recon_loss + self.c2 * mask_loss
        return loss, {"recon_loss": recon_loss.detach(), "mask_loss": mask_loss.detach()}

    def decode(self, latent):
        z, z_r = self.decoder_inputs(latent)
        return {"mask": self.mask_decoder(z_r), "recon": self.recon_decoder(z)}


class SearNoSplitAux(SearAux):
    """The ablation without latent separation (appendix "Auxiliary Mask Loss Without Latent
    Separation"): both decoders read the whole latent."""
    split = False


class DEARAux(SearAux):
    """DEAR (Pore et al. 2024; docs/dear.md): SEAR's mask half and, in place of Eq. 5, c1 x a cosine term between
    the halves that trains z_R alone: pull = 1 - cos (its released code), push = max(0, cos)."""
    metric_names, decodes, target = ("feature_loss", "mask_loss"), ("mask",), 1.0

    @classmethod
    def build(cls, cfg, encoder, critic):
        aux = cls(encoder.repr_dim, cfg.frame_stack, cfg.recon_coef, cfg.mask_coef)
        aux.recon_decoder, aux.target = None, {"pull": 1.0, "push": -1.0}[cfg.dear_feature]  # no reconstruction
        return aux

    def forward(self, latent, obs_aug, mask_aug, **extra):
        z, z_r = self.decoder_inputs(latent)
        feature = F.cosine_embedding_loss(z.detach(), z_r, torch.full_like(z[:, 0], self.target))  # DEAR's loss
        mask_loss = summed_bce(self.mask_decoder(z_r), mask_aug)
        return self.c1 * feature + self.c2 * mask_loss, {"feature_loss": feature.item(), "mask_loss": mask_loss.item()}

    def decode(self, latent):
        return {"mask": self.mask_decoder(self.decoder_inputs(latent)[1])}


class ReconstructionAux(AuxLoss):
    """One reconstruction decoder on the whole latent: what DrQ-AE and DrQ-MAE share. At evaluation
    nothing is hidden: the decoder reconstructs from the whole image's latent."""
    metric_names = ("recon_loss",)
    decodes = ("recon",)

    def decode(self, latent):
        return {"recon": self.recon_decoder(latent)}


class AEAux(ReconstructionAux):
    """DrQ-AE, as in the authors' code (sear/agents/drqv2AE.py, cfgs/agent/drqv2AE.yaml): the decoder
    starts from 32 channels, the loss weight is twice SEAR's c1, and there is no latent penalty
    (SAC-AE's is --ae-latent-lambda)."""

    def __init__(self, cfg: Config, encoder: nn.Module, critic: nn.Module | None = None):
        super().__init__()
        self.c1, self.latent_lambda = 2 * cfg.recon_coef, cfg.ae_latent_lambda
        self.recon_decoder = Decoder(encoder.repr_dim, 3 * cfg.frame_stack, in_channels=32)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        recon_loss = reconstruction_loss(self.recon_decoder(latent), obs_aug)
        penalty = 0.5 * latent.pow(2).sum(1).mean()
        loss = self.c1 * recon_loss + self.latent_lambda * penalty
        return loss, {"recon_loss": recon_loss.detach()}


def patch_mask(n, size, patch, ratio, device):
    """MAE's masking: per sample, hide round(ratio * patches) of the (size/patch)^2 patches, chosen
    uniformly. Returns a (n, 1, size, size) float map, 1 where hidden."""
    side = size // patch
    num, hide = side * side, int(round(ratio * side * side))
    order = torch.rand(n, num, device=device).argsort(dim=1)
    hidden = torch.zeros(n, num, device=device)
    hidden.scatter_(1, order[:, :hide], 1.0)
    hidden = hidden.view(n, 1, side, side)
    return hidden.repeat_interleave(patch, dim=2).repeat_interleave(patch, dim=3)


class MAEAux(ReconstructionAux):
    """DrQ-MAE: hide random patches (the same patches in every stacked frame), encode the masked
    image, reconstruct the whole stack, and score only the hidden pixels."""

    def __init__(self, cfg: Config, encoder: nn.Module, critic: nn.Module | None = None):
        super().__init__()
        self.c1, self.ratio, self.patch = cfg.recon_coef, cfg.mae_ratio, cfg.mae_patch
        self.recon_decoder = Decoder(encoder.repr_dim, 3 * cfg.frame_stack)

    def forward(self, latent, obs_aug, mask_aug, encoder, **extra):
        hidden = patch_mask(obs_aug.shape[0], obs_aug.shape[-1], self.patch, self.ratio, obs_aug.device)
        masked = obs_aug * (1 - hidden) + 127.5 * hidden  # 127.5 -> 0 after normalisation
        pred = self.recon_decoder(encoder(masked))
        recon_loss = reconstruction_loss(pred, obs_aug, weight=hidden)
        return self.c1 * recon_loss, {"recon_loss": recon_loss.detach()}


class CURLAux(AuxLoss):
    """CURL as curl_sac.py (docs/baselines.md): W between the critic's feature (encoder, then its trunk's Linear +
    LayerNorm) of one shift and an EMA copy's of another; not in Eq. 6 but its own Adam step after each update."""
    metric_names = ("curl_loss",)

    def __init__(self, cfg: Config, encoder: nn.Module, critic: nn.Module):
        super().__init__()
        self.tau, self.updates, lr = cfg.curl_tau, 0, cfg.curl_lr
        query = nn.Sequential(encoder, *critic.trunk[:2])  # curl_sac.py's encoder output: the critic's feature
        self.query, self.key = (query,), copy.deepcopy(query).requires_grad_(False)  # a tuple: the agent's own
        self.W = nn.Parameter(torch.rand(cfg.feature_dim, cfg.feature_dim))
        self.opt = torch.optim.Adam([{"params": query.parameters(), "lr": 2 * lr}, {"params": [self.W]}], lr=lr)

    def after_update(self, obs):  # curl_sac.py: the key's EMA every 2nd update, then update_cpc (anchor, positive)
        if self.updates % 2 == 0:
            for p, p_key in zip(self.query[0].parameters(), self.key.parameters()):
                p_key.lerp_(p.detach(), self.tau)
        self.updates += 1
        logits = self.query[0](random_shift(obs)) @ (self.W @ self.key(random_shift(obs)).T)
        loss = F.cross_entropy(logits - logits.max(1, keepdim=True).values, torch.arange(len(obs), device=obs.device))
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return {"curl_loss": loss.detach()}

    def get_extra_state(self):  # for an exact resume: the EMA's phase and CURL's own Adam
        return self.updates, self.opt.state_dict()

    def set_extra_state(self, state):
        self.updates, _ = state[0], self.opt.load_state_dict(state[1])


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
    "ae": Method("DrQ-AE: one decoder on the whole latent", aux=AEAux),
    "mae": Method("DrQ-MAE: reconstruct hidden patches", aux=MAEAux),
    "curl": Method("CURL: contrastive, momentum key", aux=CURLAux),
    "rgbm": Method("DrQ-RGBM: mask appended to the input", encoder="drq", mask_input=True, uses_mask=True),
    "sear-nosplit": Method("SEAR without latent split", aux=SearNoSplitAux, uses_mask=True),
    "dear": Method("DEAR: mask half + cosine term, no reconstruction", aux=DEARAux, uses_mask=True),
}


# ================================================================================================
# 5. Agent
# ================================================================================================
class Batch(NamedTuple):
    """n-step transitions, as the replay buffer samples them (numpy) and the update takes them."""
    obs: np.ndarray | torch.Tensor        # (B, 3 x stack, H, W) RGB frames, uint8
    mask: np.ndarray | torch.Tensor       # (B, stack, H, W) the robot's masks, 0/1
    action: np.ndarray | torch.Tensor     # (B, A) the action taken at obs
    reward: np.ndarray | torch.Tensor     # (B, 1) the n-step return R
    discount: np.ndarray | torch.Tensor   # (B, 1) gamma^m of the bootstrap, 0 after a termination
    next_obs: np.ndarray | torch.Tensor   # the observation m <= n steps later
    next_mask: np.ndarray | torch.Tensor


def linear_std(cfg: Config, step: int) -> float:
    """DrQ-v2's `linear(std_start, std_end, std_steps)`, evaluated at the global AGENT step (not the
    frame): at action repeat 2 the std reaches std_end after 500k steps = 1M frames."""
    mix = min(max(step / cfg.std_steps, 0.0), 1.0)
    return (1.0 - mix) * cfg.std_start + mix * cfg.std_end


def actor_metrics(actor_loss, mu) -> dict:
    """The failure of short DDPG runs, made visible: actor_saturated is the share of mean-action
    entries where float32's tanh is exactly +-1 (1 - tanh^2 = 0: no gradient brings them back),
    action_spread the std of the mean action over the batch (0: the same action in every state)."""
    return {"actor_loss": actor_loss.detach(), "actor_saturated": (mu.abs() == 1.0).float().mean(),
            "action_spread": mu.std(0, correction=0).mean()}


class Agent:
    def __init__(self, cfg: Config, action_dim: int, device: torch.device):
        self.cfg, self.device, self.action_dim = cfg, device, action_dim
        self.method = METHODS[cfg.method]
        in_channels = (4 if self.method.mask_input else 3) * cfg.frame_stack
        if self.method.encoder == "pooled":
            self.encoder = PooledEncoder(in_channels, cfg.latent_dim).to(device)
        else:
            self.encoder = DrQEncoder(in_channels).to(device)
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(device)
        self.critic = Critic(repr_dim, action_dim, cfg.feature_dim, cfg.hidden_dim).to(device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.aux = self.method.aux.build(cfg, self.encoder, self.critic).to(device) if self.method.aux else None
        # Eq. 6 is one loss over encoder, critic and decoders; Adam is per-parameter, so one
        # optimiser for all of them equals DrQ-v2's separate encoder/critic optimisers.
        model_params = [*self.encoder.parameters(), *self.critic.parameters()]
        if self.aux is not None:
            model_params += [p for p in self.aux.parameters() if p.requires_grad]
        self.model_opt = torch.optim.Adam(model_params, lr=cfg.lr)
        # The convolutions (encoder, decoders) hold >90% of an update's FLOPs. They use the NHWC
        # ("channels_last") layout, which oneDNN's and cuDNN's fastest kernels expect, and under
        # --precision bf16 only they run in bf16: a TD target rounded to bf16's 8-bit mantissa would
        # be off by up to 0.5 at Q = 100, so actor, critic and every loss stay in fp32.
        for net in (self.encoder, self.aux):
            if net is not None:
                net.to(memory_format=torch.channels_last)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr)
        self.metric_names = (("critic_loss", "actor_loss", "q", "actor_saturated", "action_spread")
                             + (self.aux.metric_names if self.aux else ()) + (drm.METRICS if cfg.drm else ()))
        self.drm = drm.DrM(cfg, self, linear_std, weight_init, trunk, mlp) if cfg.drm else None  # drm.py
        self.std = self.drm.std if self.drm else lambda step: linear_std(cfg, step)  # the exploration std

    def conv_precision(self):
        """bf16 autocast for the convolutional networks under --precision bf16; a no-op for fp32."""
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
        return action.squeeze(0).cpu().numpy().astype(np.float32)

    def joint_loss(self, batch: Batch, step):
        """Eq. 6: the critic's TD loss plus the auxiliary loss (c1 * recon + c2 * mask for SEAR), on a
        batch of float tensors whose obs and next_obs are the encoder's inputs. Returns the loss, the
        latent of the augmented observation, and the terms for the logs."""
        obs_aug, mask_aug = shift_together(batch.obs, batch.mask)
        latent = self.encode(obs_aug)
        drm_metrics = self.drm.observe(latent.detach(), batch.action, step) if self.drm else {}  # DrM's ratio, V
        with torch.no_grad():
            next_latent = self.encode(random_shift(batch.next_obs))
            dist = self.actor(next_latent, self.std(step))
            next_action = dist.sample(clip=self.cfg.std_clip)
            target_q = torch.min(*self.critic_target(next_latent, next_action))
            target_q = self.drm.blend(next_latent, target_q) if self.drm else target_q  # DrM: + lambda V(s')
            target_q = batch.reward + batch.discount * target_q
        q1, q2 = self.critic(latent, batch.action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        loss, metrics = critic_loss, {}
        if self.aux is not None:
            with self.conv_precision():  # decoders (and MAE's second encoder pass) in bf16; losses fp32
                aux_loss, metrics = self.aux(latent, obs_aug, mask_aug, encoder=self.encoder, obs=batch.obs)
            loss = loss + aux_loss
        metrics.update(drm_metrics, critic_loss=critic_loss.detach(), q=q1.mean().detach())
        return loss, latent, metrics

    def update_critic(self, batch: Batch, step):
        """One joint step on encoder, critic and decoders (Alg. 1)."""
        loss, latent, metrics = self.joint_loss(batch, step)
        self.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.model_opt.step()
        return latent.detach(), metrics

    def actor_loss(self, latent, step):
        """DDPG's loss, -min(Q1, Q2) of the actor's noisy action; and the mean action, for the logs."""
        dist = self.actor(latent, self.std(step))
        return -torch.min(*self.critic(latent, dist.sample(clip=self.cfg.std_clip))).mean(), dist.mean.detach()

    def update_actor(self, latent, step):
        """DDPG: move the actor towards actions of higher min(Q1, Q2). `latent` is detached: this
        loss does not train the encoder."""
        # Nor the critic: the gradient DrQ-v2 computes for it here is discarded by the next critic
        # step; frozen, the backward pass skips those GEMMs.
        self.critic.requires_grad_(False)
        actor_loss, mu = self.actor_loss(latent, step)
        self.critic.requires_grad_(True)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        return actor_metrics(actor_loss, mu)

    def update(self, batch: Batch, step):
        if self.drm is not None:  # DrM's shrink-and-perturb, when the step is due
            self.drm.perturb_if_due(step)
        batch = Batch._make(torch.as_tensor(x, device=self.device).float() for x in batch)
        batch = batch._replace(obs=self.encoder_input(batch.obs, batch.mask),
                               next_obs=self.encoder_input(batch.next_obs, batch.next_mask))
        latent, metrics = self.update_critic(batch, step)
        metrics.update(self.update_actor(latent, step))
        with torch.no_grad():  # Polyak averaging of the target critic
            for p, p_t in zip(self.critic.parameters(), self.critic_target.parameters()):
                p_t.lerp_(p, self.cfg.critic_tau)
        if self.aux is not None:  # CURL's own step, last as in curl_sac.py
            metrics.update(self.aux.after_update(batch.obs))
        tensors = {k: v.float() for k, v in metrics.items() if torch.is_tensor(v)}  # DrM's are numbers already
        return {**metrics, **dict(zip(tensors, torch.stack(list(tensors.values())).tolist()))}  # the logs' one sync

    def state_dict(self):
        return {"encoder": self.encoder.state_dict(), "actor": self.actor.state_dict(),
                "critic": self.critic.state_dict(), "critic_target": self.critic_target.state_dict(),
                "aux": self.aux.state_dict() if self.aux else None, "drm": self.drm.state_dict() if self.drm else None,
                "model_opt": self.model_opt.state_dict(), "actor_opt": self.actor_opt.state_dict()}

    def load_state_dict(self, state):
        for name in ("encoder", "actor", "critic", "critic_target", "model_opt", "actor_opt", "aux", "drm"):
            if getattr(self, name) is not None:  # aux: the method's networks, drm: DrM's (None without)
                getattr(self, name).load_state_dict(state[name])


# ================================================================================================
# 6. Replay buffer
# ================================================================================================
class ReplayBuffer:
    """A ring of time steps. Slot i holds the newest RGB frame of step i (uint8, stored once), its
    robot mask bit-packed (np.packbits: 882 bytes for 84x84), the action and reward that led to it,
    whether it is terminal, and whether it starts an episode. Frame stacks are rebuilt at sampling
    time, never across an episode start (the first frame repeats, as at reset), and n-step returns
    are summed at sampling. A time-limit end (truncation) bootstraps; a termination does not.
    Draws follow DrQ-v2's loader (replay_buffer.py _sample): an episode uniformly among the finished
    ones still whole in the ring, then a start whose whole n-step window lies in it."""

    def __init__(self, capacity, frame_shape, action_dim, frame_stack, nstep, discount):
        self.capacity, self.stack, self.nstep, self.discount = capacity, frame_stack, nstep, discount
        self.frame_shape = tuple(frame_shape)  # (3, H, W)
        h, w = frame_shape[1:]
        self.mask_bytes = (h * w + 7) // 8
        self.frames = np.empty((capacity, *frame_shape), dtype=np.uint8)
        self.masks = np.empty((capacity, self.mask_bytes), dtype=np.uint8)
        self.actions = np.empty((capacity, action_dim), dtype=np.float32)
        self.rewards = np.empty((capacity,), dtype=np.float32)
        self.terminal = np.empty((capacity,), dtype=bool)
        self.first = np.empty((capacity,), dtype=bool)
        self.t = 0  # slots ever written; slot of time step l is l % capacity
        self.episodes = np.zeros((0, 2), np.int64)  # (first time, steps) of the finished, drawable episodes
        self.running = -1  # first time of the running episode
        self.margin = 0  # oldest slots kept out of draws: a sampler thread reads while the loop overwrites them

    @property
    def bytes_per_transition(self):
        return sum(a.itemsize * int(np.prod(a.shape[1:])) for a in
                   (self.frames, self.masks, self.actions, self.rewards, self.terminal, self.first))

    def __len__(self):
        return min(self.t, self.capacity)

    def _write(self, obs, action, reward, terminal, first):
        i = self.t % self.capacity
        self.frames[i] = obs["pixels"][-3:]
        self.masks[i] = np.packbits(np.asarray(obs["mask"][-1], dtype=bool).reshape(-1))
        self.actions[i] = action
        self.rewards[i] = reward
        self.terminal[i] = terminal
        self.first[i] = first
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

    def index_episodes(self):
        """The episode index rebuilt from the `first` flags (after loading a saved ring)."""
        lo = max(0, self.t - self.capacity)
        firsts = lo + np.flatnonzero(self.first[np.arange(lo, self.t) % self.capacity])
        steps = np.diff(firsts) - 1
        self.episodes = np.stack([firsts[:-1], steps], axis=1)[steps >= self.nstep]
        self.running = firsts[-1] if len(firsts) else -1

    # --- sampling ---
    def _stack_indices(self, l):
        """Time indices of the frames stacked at time l: walk back, but never past an episode start
        (the frame there is repeated instead)."""
        idx = [l]
        for _ in range(self.stack - 1):
            idx.append(np.where(self.first[idx[-1] % self.capacity], idx[-1], idx[-1] - 1))
        return np.stack(idx[::-1], axis=1)  # oldest frame first

    def _obs(self, l):
        idx = self._stack_indices(l) % self.capacity  # (B, stack)
        b = len(l)
        pixels = self.frames[idx].reshape(b, -1, *self.frame_shape[1:])
        bits = np.unpackbits(self.masks[idx], axis=-1)[..., :int(np.prod(self.frame_shape[1:]))]
        masks = bits.reshape(b, self.stack, *self.frame_shape[1:])
        return pixels, masks

    def drawable(self, lo):
        """(first time, steps) of the finished episodes that start at time lo or later."""
        return self.episodes[np.searchsorted(self.episodes[:, 0], lo):]

    def can_sample(self):
        return len(self.drawable(max(0, self.t - self.capacity + self.margin))) > 0

    def sample(self, batch_size, rng: np.random.Generator) -> Batch:
        return self.transitions(self.draw_starts(batch_size, rng, lo=max(0, self.t - self.capacity + self.margin)))

    def draw_starts(self, n, rng: np.random.Generator, lo):
        """n start times: an episode uniformly among those drawable from lo, then a start from which
        all n steps lie inside it (DrQ-v2's idx range: an episode's last n-1 steps never start one)."""
        first, steps = self.drawable(lo).T
        e = rng.integers(len(first), size=n)
        return first[e] + rng.integers(0, steps[e] - self.nstep + 1)

    def transitions(self, l) -> Batch:
        """The n-step transitions starting at times l, each inside one episode (as drawn): R = sum_k
        gamma^(k-1) r_(l+k), and the bootstrap discount gamma^n, zero if the episode terminated at l+n."""
        l = np.asarray(l, dtype=np.int64)
        ret, gamma_n = np.zeros(len(l), dtype=np.float32), np.float32(1.0)
        for k in range(1, self.nstep + 1):
            ret += gamma_n * self.rewards[(l + k) % self.capacity]
            gamma_n *= np.float32(self.discount)
        # Only the window's last step can end the episode: no bootstrap after a termination there.
        discount = np.where(self.terminal[(l + self.nstep) % self.capacity], 0.0, gamma_n).astype(np.float32)
        obs, mask = self._obs(l)
        next_obs, next_mask = self._obs(l + self.nstep)
        action = self.actions[(l + 1) % self.capacity]
        return Batch(obs, mask, action, ret[:, None], discount[:, None], next_obs, next_mask)


# ================================================================================================
# 7. Evaluation
# ================================================================================================
class Episode(NamedTuple):
    """An evaluation episode."""
    ret: float
    success: bool | None  # None where the env reports no success
    task: str | None      # the task of a task set, else None


def evaluate(agent: Agent, env, cfg: Config, step: int, on_step=None) -> list[Episode]:
    """Episodes with the mean action on the eval env, from the same reset seeds at every evaluation
    (so that evaluations compare); a task set runs each of its tasks (experiment.eval_tasks).
    on_step(episode, t), if given, is called after every step (the progress line)."""
    episodes = []
    for i, task in enumerate(experiment.eval_tasks(env, cfg)):
        obs, info = env.reset(seed=experiment.episode_seed(cfg.seed + 100_000, i),
                              options=None if task is None else {"task": task})
        done, ret, success, t = False, 0.0, False, 0
        while not done:
            action = agent.act(obs["pixels"], obs["mask"], step, eval_mode=True)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            success = success or bool(info.get("success", False))
            done = terminated or truncated
            t += 1
            if on_step:
                on_step(i, t)
        episodes.append(Episode(ret, success if "success" in info else None, task))
    return episodes


# ================================================================================================
# 8. Training loop
# ================================================================================================
def seed_everything(seed):
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def eval_due(frame: int, last_eval_frame: int, every: int) -> bool:
    """drqv2's Every, in frames: a multiple of `every` lies in (last evaluation, frame]. Frame 0 is
    one (last_eval_frame starts at -1)."""
    return frame // every > last_eval_frame // every


def evaluate_and_log(agent: Agent, eval_env, cfg: Config, c, rundir) -> None:
    """An evaluation now: its episodes scored and filmed by the run dir, eval.csv's row, the counter."""
    env = rundir.start_eval(eval_env)  # the eval env, scored by the decoders, filmed with --save-video
    rundir.log_eval(evaluate(agent, env, cfg, c.step, on_step=rundir.show_eval))
    c.last_eval_frame = c.step * cfg.action_repeat


def train(cfg: Config, run: cli.RunConfig, snapshot: dict | None = None) -> str:
    """Train from scratch, or continue from `snapshot` (the last one of the run dir run.resume);
    returns the run directory. The loop decides when to evaluate, snapshot and stop; the
    experiment.RunDir writes config.json, the logs and the snapshots it is handed and turns a
    Ctrl-C, a SIGTERM or a storage error into one line."""
    with experiment.RunDir(cfg, run, snapshot) as rundir:
        device = cli.torch_setup(run)
        train_env, eval_env = experiment.make_envs(cfg, METHODS[cfg.method].uses_mask)  # sets action_repeat 0
        action_dim = train_env.action_space.shape[0]
        source = experiment.init_source(cfg, run, action_dim) if run.init_from and not snapshot else None
        rundir.create()  # a new run's directory and config.json, now that every input is checked

        seed_everything(cfg.seed)
        sample_rng = np.random.default_rng(cfg.seed)
        agent = Agent(cfg, action_dim, device)
        if source is not None:  # transfer: start from another run's networks
            experiment.copy_parts(agent, source, run.init_parts)
        experiment.compile_update(agent, run)  # --compile: the update through torch.compile, else eager
        frame_shape = (3, *train_env.observation_space["pixels"].shape[1:])
        buffer = ReplayBuffer(cfg.replay_size, frame_shape, action_dim, cfg.frame_stack, cfg.nstep, cfg.discount)
        prefetcher = experiment.prefetcher(buffer, cfg, run, sample_rng, device)  # None: sample here
        c = rundir.start(agent, buffer, sample_rng)  # step, episode, last evaluation: fresh, or the snapshot's
        snapshot_clock = time.monotonic()  # a snapshot every --snapshot-minutes, at the next episode end

        frame = c.step * cfg.action_repeat
        while frame < cfg.frames:  # drqv2's Until, in frames
            if not c.mid_episode:
                rundir.safe_point()  # a first SIGTERM stops the run here, between episodes (with a snapshot)
                c.mid_episode = True
                obs, info = train_env.reset(seed=experiment.episode_seed(cfg.seed, c.episode))
                buffer.add_first(obs)
                ep_return, ep_len, ep_success = 0.0, 0, False
            if eval_due(frame, c.last_eval_frame, cfg.eval_every):
                evaluate_and_log(agent, eval_env, cfg, c, rundir)

            # As DrQ-v2, the agent acts from the first step: uniformly for --exploration-steps agent steps
            # (Agent.act), then the actor plus noise, not yet updated while the seed frames are collected.
            action = agent.act(obs["pixels"], obs["mask"], c.step, eval_mode=False)
            # Learning starts once the buffer holds the seed frames' worth of steps: after the random
            # phase of a new run, and again after a resume that could not bring its buffer back.
            if (frame >= cfg.seed_frames and c.step % cfg.update_every == 0 and buffer.can_sample()
                    and len(buffer) >= cfg.seed_frames // cfg.action_repeat):
                batch = prefetcher.next() if prefetcher else buffer.sample(cfg.batch_size, sample_rng)
                rundir.log_update(agent.update(batch, c.step))

            obs, reward, terminated, truncated, info = train_env.step(action)
            buffer.add(action, reward, terminated, obs)
            c.step += 1
            frame = c.step * cfg.action_repeat
            ep_return += reward
            ep_len += 1
            ep_success = ep_success or bool(info.get("success", False))
            if terminated or truncated:
                rundir.log_episode(ep_return, ep_len, ep_success, info)  # train.csv and the progress line
                c.episode, c.mid_episode = c.episode + 1, False
                if frame < cfg.frames and time.monotonic() - snapshot_clock >= 60 * run.snapshot_minutes:
                    rundir.snapshot()  # between episodes: a resume continues exactly
                    snapshot_clock = time.monotonic()
            else:
                rundir.show_step(ep_len)

        if c.last_eval_frame != frame:  # the budget ends with an evaluation at its last frame
            evaluate_and_log(agent, eval_env, cfg, c, rundir)
        rundir.finish()  # the final snapshot
        for closing in (prefetcher, train_env, eval_env):
            if closing is not None:
                closing.close()
        return rundir.path


def evaluate_snapshot(cfg: Config, run: cli.RunConfig, snapshot: dict) -> None:
    """--evaluate RUN_DIR: the snapshot's agent on the run's eval env, scored and printed (no training)."""
    device = cli.torch_setup(run)
    _, eval_env = experiment.make_envs(cfg, METHODS[cfg.method].uses_mask, train=False)
    agent = Agent(cfg, eval_env.action_space.shape[0], device)
    experiment.score_snapshot(cfg, run, snapshot, agent, eval_env, evaluate)


def main(argv=None) -> int:
    """`python sear.py --flag value ...`: 0 when done; bad input (2), Ctrl-C (130) and SIGTERM (143) end
    in one line."""
    return cli.main(argv, Config, METHODS, train, evaluate_snapshot)


if __name__ == "__main__":
    sys.exit(main())
