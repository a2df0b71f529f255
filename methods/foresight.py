"""Ego-Foresight (EF; Nunes, Dehban, Demiris, Santos-Victor, "Ego-Foresight: Self-supervised Learning of
Agent-Aware Representations for Improved RL", arXiv 2407.01570) on sear.py's seam: `--method ef`. Where SEAR
tells the encoder where the robot is with a mask, EF learns it without one, from motion: the first
--ef-agent-dim entries of the latent (the agent part) are rolled forward by an MLP, once per action, to a frame
`ahead` agent steps later, and a decoder draws that frame from the rolled agent part and the context's
scene part (the rest of the latent). Only what the actions move is predictable from the actions, so the agent
part learns the agent. docs/foresight.md says where each piece follows the released code
(github.com/ego-foresight/efrl at 7c316bf: agents/drqv2ef.py, cfgs/agent/drqv2ef.yaml).

The pieces, each a subclass of sear.py's:
  * ForesightAux: the MLP, the decoder and the loss, an AuxLoss: its term joins Eq. 6's joint step, so the
    critic and EF train the encoder together, as the release's one backward does;
  * WindowReplay (--ef-horizon), a sear.ReplayBuffer, samples Window batches: each start's next actions and the
    frame `ahead` steps after it, `ahead` drawn once per batch in 1..horizon from the run's sample RNG;
  * ForesightAgent, a sear.Agent, shifts that frame with its context (one shift per sample, as the release's
    repeat_last) and babbles: for the first --ef-babbling-steps agent steps of training, uniform actions in
    +-4 clipped to +-1.
`--method ef --drm` is EF on DrM's agent: train.make_agent puts drm.DrMAgent before ForesightAgent.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

import sear
from sear import AuxLoss, Method, arg, random_shift, summed_mse


class Window(NamedTuple):
    """A sear.Batch, and what EF predicts from it (WindowReplay)."""
    obs: torch.Tensor
    mask: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_obs: torch.Tensor
    next_mask: torch.Tensor
    actions_ahead: torch.Tensor  # (B, horizon, A) the actions of the steps after obs
    frame_ahead: torch.Tensor    # (B, 3, H, W) the newest frame `ahead` steps after obs
    ahead: torch.Tensor          # (B, 1) how many steps ahead (fewer where the episode ends sooner)


class WindowReplay(sear.ReplayBuffer):
    """sear.ReplayBuffer whose batches are Windows: the same draws, and after them one horizon per batch."""

    def __init__(self, *args, window: int, **kwargs):
        super().__init__(*args, **kwargs)
        self.window = window

    def batch(self, times, rng: np.random.Generator) -> Window:
        ahead = int(rng.integers(1, self.window + 1))  # EF's horizon, one per batch, in agent steps
        return Window(*self.transitions(times), *self.windows(times, self.window, ahead))

    def windows(self, times, length, ahead):
        """The actions of the `length` steps after each of `times` (B, length, A), the frame `ahead` steps after it
        (B, 3, H, W) and ahead (B, 1); never across an episode start (past an episode's end: its last step)."""
        times = torch.as_tensor(np.asarray(times, dtype=np.int64)).to(self.device, non_blocking=True)[:, None]
        idx = times + torch.arange(1, length + 1, device=self.device)
        left = (self.first[idx % self.capacity].cumsum(1) == 0).sum(1, keepdim=True)  # steps before a next start
        idx, ahead = torch.minimum(idx, times + left) % self.capacity, left.clamp(max=ahead)
        return self.actions[idx], self.frames[idx.gather(1, (ahead - 1).clamp(min=0))[:, 0]], ahead



@dataclass
class ForesightConfig:
    """EF's flags (train.Config adds them to the run's). Defaults: the released cfgs/agent/drqv2ef.yaml; its
    hs_dim 2048 is --latent-dim (docs/foresight.md)."""
    ef_agent_dim: int = arg(32, "ef: the latent's first N entries are the agent part the MLP rolls "
                                "forward; the rest is the scene part (ha_dim)", above=0,
                            acts=("ef",))
    ef_horizon: int = arg(10, "ef: the most AGENT STEPS ahead EF predicts: each batch draws its "
                              "own in 1..N (horizon)", above=0, acts=("ef",))
    ef_coef: float = arg(1.0, "ef: weight of the foresight loss (summed over pixels) in the joint "
                              "loss (rec_loss_weight)", low=0, acts=("ef",))
    ef_babbling_steps: int = arg(12_500, "ef: first AGENT STEPS of training that babble: uniform "
                                         "actions in +-4, clipped to +-1 (num_babbling_steps)",
                                 low=0, acts=("ef",))


MLP_WIDTH = 512     # the release's mlp(ha_dim + A, [512, 512], ha_dim)
DECODER_WIDTH = 64  # the release's decoder_no_skips: nf = 64
BABBLE = 4.0        # the release's act: uniform_(-4, 4), then clamp to [-1, 1]


def forward_model(agent_dim: int, action_dim: int) -> nn.Sequential:
    """The release's MLP (a TD-MPC2 layers copy, models/mlp.py): Linear, LayerNorm, Mish twice, then a plain
    Linear back to the agent part. PyTorch's default initialisation, as there (DrQ-v2's orthogonal one is not
    applied to it). Not residual: the agent part is replaced at every step."""
    return nn.Sequential(nn.Linear(agent_dim + action_dim, MLP_WIDTH), nn.LayerNorm(MLP_WIDTH), nn.Mish(),
                         nn.Linear(MLP_WIDTH, MLP_WIDTH), nn.LayerNorm(MLP_WIDTH), nn.Mish(),
                         nn.Linear(MLP_WIDTH, agent_dim))


def frame_decoder(latent_dim: int) -> nn.Sequential:
    """The release's decoder_no_skips (models/dcgan_unet_64.py), a DCGAN decoder from the latent as a 1x1 map:
    1 -> 5 (k5 s1) -> 10 (k4 s2 p1) -> 21 (k5 s2 p1) -> 42 -> 84 (k4 s2 p1), 64 channels, transposed
    convolutions without bias, each but the last followed by BatchNorm (train mode: the batch's statistics;
    running statistics kept, momentum 0.1) and LeakyReLU(0.2); a sigmoid at the end: an RGB frame in [0, 1].
    DCGAN's initialisation: weights N(0, 0.02), BatchNorm scales N(1, 0.02)."""
    def up(cin, kernel, stride, padding):
        return [nn.ConvTranspose2d(cin, DECODER_WIDTH, kernel, stride, padding, bias=False),
                nn.BatchNorm2d(DECODER_WIDTH), nn.LeakyReLU(0.2, inplace=True)]
    net = nn.Sequential(*up(latent_dim, 5, 1, 0), *up(DECODER_WIDTH, 4, 2, 1), *up(DECODER_WIDTH, 5, 2, 1),
                        *up(DECODER_WIDTH, 4, 2, 1), nn.ConvTranspose2d(DECODER_WIDTH, 3, 4, 2, 1, bias=False),
                        nn.Sigmoid())
    for m in net.modules():
        if isinstance(m, nn.ConvTranspose2d):
            nn.init.normal_(m.weight, 0.0, 0.02)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.normal_(m.weight, 1.0, 0.02)
            nn.init.zeros_(m.bias)
    return net


class ForesightAux(AuxLoss):
    """EF's term of the joint loss. The context is the augmented observation's stack (the critic's): its latent
    is cut into the agent part (the first ef_agent_dim entries) and the scene part (the rest). The MLP rolls
    the agent part once per action of the batch's window, `ahead` times; the decoder draws the frame from the
    rolled agent part and the scene part, unchanged. Loss: squared error against the frame `ahead` steps after
    the context (shifted with it, in [0, 1]), summed over pixels, averaged over the batch, weighted --ef-coef.
    Its gradient reaches the encoder through both parts, the MLP and the decoder; the actor's never does.

    The rollout runs all --ef-horizon steps and keeps a step only where it is one of the sample's `ahead`: the
    same values and gradients as a loop of `ahead` steps, in one graph whatever `ahead` is (torch.compile).
    A plain Batch (a replay without a window) is the 0-step case: the context's newest frame itself."""
    metric_names = ("ef_loss", "ef_ahead")

    def __init__(self, cfg, encoder: nn.Module, critic: nn.Module):
        super().__init__()
        self.agent_dim, self.coef, self.window = cfg.ef_agent_dim, cfg.ef_coef, cfg.ef_horizon
        if not 0 < self.agent_dim < encoder.repr_dim or self.window < 1:
            raise ValueError(f"--method ef needs 0 < --ef-agent-dim < --latent-dim ({self.agent_dim}, "
                             f"{encoder.repr_dim}) and --ef-horizon >= 1 ({self.window})")
        action_dim = critic.q1[0].in_features - critic.trunk[0].out_features  # Q's input: feature, then action
        self.mlp = forward_model(self.agent_dim, action_dim)
        self.decoder = frame_decoder(encoder.repr_dim)

    def forward(self, latent, obs_aug, mask_aug, batch=None, **extra):
        agent, scene = latent[:, :self.agent_dim], latent[:, self.agent_dim:]
        if isinstance(batch, Window):
            target, ahead = batch.frame_ahead, batch.ahead
            for i in range(self.window):
                rolled = self.mlp(torch.cat([agent, batch.actions_ahead[:, i]], dim=1))
                agent = torch.where(ahead > i, rolled, agent)
        else:
            target, ahead = obs_aug[:, -3:], latent.new_zeros(len(latent), 1)
        frame = self.decoder(torch.cat([agent, scene], dim=1)[:, :, None, None])
        ef_loss = summed_mse(frame.float().clamp(0.0, 1.0), target / 255.0)
        return self.coef * ef_loss, {"ef_loss": ef_loss.detach(), "ef_ahead": ahead.float().mean()}

class ForesightAgent(sear.Agent):
    """sear.Agent for EF: its batches' frame ahead is shifted with the context, and it babbles."""

    def act(self, obs, mask, step: int, eval_mode: bool):
        """Motor babbling: while training and step < --ef-babbling-steps (agent steps), every action entry is
        uniform in +-4 clipped to +-1 (3/8 at each bound, uniform in between with probability 1/4)."""
        action = super().act(obs, mask, step, eval_mode)
        if eval_mode or step >= self.cfg.ef_babbling_steps:
            return action
        return action.uniform_(-BABBLE, BABBLE, generator=self.rng).clamp_(-1.0, 1.0)

    def critic_objective(self, batch, step, noise):
        """The frame ahead shifted as its context (the same shift per sample), then sear.Agent's."""
        if isinstance(batch, Window):
            batch = batch._replace(frame_ahead=random_shift(batch.frame_ahead, noise.shift))
        return super().critic_objective(batch, step, noise)


def make_replay(cfg, *args, **kwargs) -> WindowReplay:
    """EF's replay: its batches are Windows of --ef-horizon steps."""
    return WindowReplay(*args, window=cfg.ef_horizon, **kwargs)


METHODS = {"ef": Method("Ego-Foresight: the latent's agent part rolled forward by the actions, "
                        "a future frame decoded", aux=ForesightAux)}
