"""The paper's baselines (and DEAR, beyond it) on sear.py's seam: each is an auxiliary loss (an
`AuxLoss` subclass) or an input change, and one row of this module's METHODS, which train.py puts
beside sear.METHODS. docs/baselines.md says where each follows its source.

    ae            DrQ-AE: one decoder on the whole latent (the authors' drqv2AE.py)
    mae           DrQ-MAE: reconstruct hidden patches (He et al. 2022)
    curl          CURL: contrastive, momentum key (curl_sac.py)
    rgbm          DrQ-RGBM: the mask appended to the input
    sear-nosplit  SEAR without latent separation (the paper's appendix)
    dear          DEAR: SEAR's mask half and a cosine term in place of reconstruction (docs/dear.md)
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

import sear
from sear import AuxLoss, Decoder, Method, SearAux, arg, random_shift, reconstruction_loss, summed_bce


@dataclass
class BaselineConfig:
    """The baselines' own settings (train.Config adds them to the run's flags); each default is its source's."""
    ae_latent_lambda: float = arg(0.0, "ae: L2 penalty on the latent (authors' DrQ-AE: none; "
                                       "SAC-AE: 1e-6)", low=0, acts=("ae",))
    mae_ratio: float = arg(0.75, "mae: fraction of patches hidden (MAE, He et al. 2022)", low=0,
                           high=1, acts=("mae",))
    mae_patch: int = arg(12, "mae: patch side in pixels (84 = 7 x 12)", above=0, acts=("mae",))
    curl_tau: float = arg(0.05, "curl: EMA rate of the key encoder, every 2nd update (CURL, Laskin "
                                "et al. 2020)", low=0, high=1, acts=("curl",))
    curl_lr: float = arg(1e-3, "curl: Adam learning rate of CURL's own step (curl_sac.py: "
                               "encoder_lr)", low=0, acts=("curl",), group="the method")
    dear_feature: str = arg("pull", "dear: pull (1 - cos, its released code) | push (max(0, cos))",
                            ("pull", "push"), acts=("dear",), group="the method")


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
        return self.c1 * feature + self.c2 * mask_loss, {"feature_loss": feature.detach(), "mask_loss": mask_loss.detach()}

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

    def __init__(self, cfg, encoder: nn.Module, critic: nn.Module | None = None):
        super().__init__()
        self.c1, self.latent_lambda = 2 * cfg.recon_coef, cfg.ae_latent_lambda
        self.recon_decoder = Decoder(encoder.repr_dim, 3 * cfg.frame_stack, in_channels=32)

    def forward(self, latent, obs_aug, mask_aug, **extra):
        recon_loss = reconstruction_loss(self.recon_decoder(latent), obs_aug)
        penalty = 0.5 * latent.pow(2).sum(1).mean()
        loss = self.c1 * recon_loss + self.latent_lambda * penalty
        return loss, {"recon_loss": recon_loss.detach()}


def patch_mask(n, size, patch, ratio, device, generator=None):
    """MAE's masking: per sample, hide round(ratio * patches) of the (size/patch)^2 patches, chosen
    uniformly (with `generator`: the agent's). Returns a (n, 1, size, size) float map, 1 where hidden."""
    side = size // patch
    num, hide = side * side, int(round(ratio * side * side))
    order = torch.rand(n, num, device=device, generator=generator).argsort(dim=1)
    hidden = torch.zeros(n, num, device=device)
    hidden.scatter_(1, order[:, :hide], 1.0)
    hidden = hidden.view(n, 1, side, side)
    return hidden.repeat_interleave(patch, dim=2).repeat_interleave(patch, dim=3)


class MAEAux(ReconstructionAux):
    """DrQ-MAE: hide random patches (the same patches in every stacked frame), encode the masked
    image, reconstruct the whole stack, and score only the hidden pixels."""

    def __init__(self, cfg, encoder: nn.Module, critic: nn.Module | None = None):
        super().__init__()
        self.c1, self.ratio, self.patch = cfg.recon_coef, cfg.mae_ratio, cfg.mae_patch
        self.recon_decoder = Decoder(encoder.repr_dim, 3 * cfg.frame_stack)

    def forward(self, latent, obs_aug, mask_aug, encoder, rng=None, **extra):
        hidden = patch_mask(obs_aug.shape[0], obs_aug.shape[-1], self.patch, self.ratio, obs_aug.device, rng)
        masked = obs_aug * (1 - hidden) + 127.5 * hidden  # 127.5 -> 0 after normalisation
        pred = self.recon_decoder(encoder(masked))
        recon_loss = reconstruction_loss(pred, obs_aug, weight=hidden)
        return self.c1 * recon_loss, {"recon_loss": recon_loss.detach()}


class CURLAux(AuxLoss):
    """CURL as curl_sac.py (docs/baselines.md): W between the critic's feature (encoder, then its trunk's Linear +
    LayerNorm) of one shift and an EMA copy's of another; not in Eq. 6 but its own Adam step after each update."""
    metric_names = ("curl_loss",)

    def __init__(self, cfg, encoder: nn.Module, critic: nn.Module):
        super().__init__()
        self.tau, lr, device = cfg.curl_tau, cfg.curl_lr, next(encoder.parameters()).device
        self.register_buffer("updates", torch.zeros((), dtype=torch.int64, device=device), persistent=False)
        query = nn.Sequential(encoder, *critic.trunk[:2])  # curl_sac.py's encoder output: the critic's feature
        self.query, self.key = (query,), copy.deepcopy(query).requires_grad_(False)  # a tuple: the agent's own
        self.W = nn.Parameter(torch.rand(cfg.feature_dim, cfg.feature_dim).to(device))
        self.opt = torch.optim.Adam([{"params": query.parameters(), "lr": 2 * lr}, {"params": [self.W]}],
                                    lr=lr, fused=True)

    def after_update(self, obs, rng):  # curl_sac.py: the key's EMA every 2nd update, then update_cpc
        with torch.no_grad():
            # key += w (query - key), w = tau on even updates, 0 (the key unchanged) on odd ones: a
            # tensor weight, no host read
            weight = self.tau * (self.updates % 2 == 0).float()
            for k, q in zip(self.key.parameters(), self.query[0].parameters()):
                k.lerp_(q, weight)
            self.updates += 1
        # the anchor's shift, then the positive's: DrQ's shifts of up to 4 pixels
        shifts = [torch.randint(0, 9, (len(obs), 1, 1, 2), device=obs.device, dtype=obs.dtype,
                                generator=rng) for _ in range(2)]
        logits = self.query[0](random_shift(obs, shifts[0])) @ (self.W @ self.key(random_shift(obs, shifts[1])).T)
        loss = F.cross_entropy(logits - logits.max(1, keepdim=True).values, torch.arange(len(obs), device=obs.device))
        self.opt.zero_grad(set_to_none=True)
        loss.backward(inputs=[p for group in self.opt.param_groups for p in group["params"]])
        self.opt.step()
        return {"curl_loss": loss.detach()}

    def get_extra_state(self):  # for an exact resume: the EMA's phase and CURL's own Adam
        return int(self.updates), self.opt.state_dict()

    def set_extra_state(self, state):
        self.updates.fill_(state[0])
        self.opt.load_state_dict(state[1])


def with_masks(pixels, mask):
    """DrQ-RGBM's input: each stacked frame's RGB followed by its robot mask (0/1 x 255)."""
    n, c, h, w = pixels.shape
    rgb = pixels.view(n, c // 3, 3, h, w)
    m = (mask.to(pixels.dtype) * 255.0).view(n, c // 3, 1, h, w)
    return torch.cat([rgb, m], dim=2).view(n, -1, h, w)


class RGBMAgent(sear.Agent):
    """DrQ-RGBM: the encoder reads every frame's RGB and its robot mask, 4 channels a frame, when
    acting and in the update (the mask shifted with its image)."""
    frame_channels = 4

    def act(self, obs, mask, step: int, eval_mode: bool):
        if mask is None:
            raise ValueError("method rgbm needs the robot mask when acting: pass mask=obs['mask']")
        obs, mask = (torch.as_tensor(x, device=self.device).float()[None] for x in (obs, mask))
        return super().act(with_masks(obs, mask)[0], None, step, eval_mode)

    def critic_objective(self, batch, step, noise):
        batch = batch._replace(obs=with_masks(batch.obs, batch.mask),
                               next_obs=with_masks(batch.next_obs, batch.next_mask))
        return super().critic_objective(batch, step, noise)


# The baselines' rows of the methods table (train.py puts them beside sear.METHODS).
METHODS = {
    "ae": Method("DrQ-AE: one decoder on the whole latent", aux=AEAux),
    "mae": Method("DrQ-MAE: reconstruct hidden patches", aux=MAEAux),
    "curl": Method("CURL: contrastive, momentum key", aux=CURLAux),
    "rgbm": Method("DrQ-RGBM: mask appended to the input", encoder="drq", uses_mask=True),
    "sear-nosplit": Method("SEAR without latent split", aux=SearNoSplitAux, uses_mask=True),
    "dear": Method("DEAR: mask half + cosine term, no reconstruction", aux=DEARAux, uses_mask=True),
}
