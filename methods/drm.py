"""DrM (Xu et al., "DrM: Mastering Visual Reinforcement Learning through Dormant Ratio Minimization",
ICLR 2024) on top of any method of sear.py: `python sear.py --method drq --drm` is DrM, `--method sear
--drm` is SEAR + DrM. docs/drm.md says what each piece is and where it follows the released code
(github.com/XuGW-Kevin/DrM, agents/drm.py and utils.py, commit 317116a).

DrM watches the actor's dormant ratio (the share of its neurons whose activation is near zero over a
batch) and lets it drive three things:
  * awaken exploration: while the actor is dormant the exploration std is a sigmoid of the ratio; once
    the ratio first falls below its target, the larger of that and DrQ-v2's schedule restarted there;
  * exploitation: the critic's target blends in an expectile value V(s') with a weight that is high
    when the ratio is low;
  * every --drm-perturb-every agent steps, shrink-and-perturb: every Linear layer becomes a mix of
    itself and a fresh initialisation, by a factor that falls as the ratio rises; Adam's state resets.

The seam: `DrMAgent` is sear.Agent with four of its methods overridden: `std` (the exploration std),
`joint_loss` (before Eq. 6, the ratio and V's step on the batch's latent), `next_value` (the critic's
target) and `update` (shrink-and-perturb at an update's start); its `state_dict` adds DrM's state.
train.py builds it for --drm.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch
import torch.nn as nn

import sear
from sear import arg

# What an update adds to train.csv: the actor's dormant ratio and the target's lambda of the update, V's
# expectile loss, and the factor of a perturbation (empty in episodes without); every agent logs expl_std.
METRICS = ("dormant_ratio", "drm_lambda", "value_loss", "perturb_factor")


@dataclass
class DrMConfig:
    """DrM's flags (train.Config adds them to the run's). Defaults: the released code's cfgs/agent/drm.yaml, and
    for what it leaves to the task cfgs, the value of its dm_control tasks (cfgs/task/*.yaml)."""
    drm: bool = arg(False, "DrM on top of --method (docs/drm.md): dormant-ratio-driven exploration "
                           "std, expectile value blended into the critic's target, periodic "
                           "shrink-and-perturb", group="what to run")
    drm_dormant_threshold: float = arg(0.025, "DrM: a neuron is dormant when its mean |activation| "
                                              "over the batch is below this fraction of its "
                                              "layer's mean (dormant_threshold)", low=0, high=1,
                                       when="drm")
    drm_target_ratio: float = arg(0.2, "DrM: target dormant ratio: the actor is awake once below "
                                       "it, and the std's and lambda's sigmoids are centred on it "
                                       "(target_dormant_ratio)", low=0, high=1, when="drm")
    drm_dormant_temp: float = arg(10.0, "DrM: slope of the dormant std, sigmoid(temp x (ratio - "
                                        "target)) (dormant_temp)", low=0, when="drm")
    drm_lambda: float = arg(0.6, "DrM: largest weight of the expectile value V(s') in the critic's "
                                 "target (target_lambda; every dm_control task cfg: 0.6)", low=0,
                            high=1, when="drm")
    drm_lambda_temp: float = arg(50.0, "DrM: slope of lambda = drm_lambda / (1 + exp(temp x "
                                       "(ratio - target))) (lambda_temp)", low=0, when="drm")
    drm_perturb_every: int = arg(100_000, "DrM: AGENT STEPS between shrink-and-perturbs "
                                          "(dormant_perturb_interval); an update step that is a "
                                          "multiple of it perturbs", above=0, when="drm")
    drm_min_perturb: float = arg(0.2, "DrM: smallest shrink factor (min_perturb_factor)", low=0,
                                 high=1, when="drm")
    drm_max_perturb: float = arg(1.0, "DrM: largest shrink factor (max_perturb_factor: 1.0 in the "
                                      "task cfgs of medium tasks, 0.9 or 0.6 for some hard ones: "
                                      "cli.DRM_MAX_PERTURB)", low=0, high=1, when="drm")
    drm_perturb_rate: float = arg(2.0, "DrM: shrink factor = clip(1 - rate x ratio, min, max) "
                                       "(perturb_rate)", low=0, when="drm")
    drm_expectile: float = arg(0.9, "DrM: expectile of V's asymmetric squared loss on min(Q1, Q2) "
                                    "(expectile)", low=0, high=1, when="drm")


def dormant_ratio(actor: nn.Module, latent: torch.Tensor, threshold: float) -> torch.Tensor:
    """DrM's dormant ratio (utils.cal_dormant_ratio) of the actor on a batch of latents: for every Linear
    layer the mean |output| of each neuron over the batch; a neuron is dormant when that is below
    `threshold` x the layer's mean. Returns dormant neurons / all neurons of the Linear layers, as a
    float64 0-d tensor on the device (no host sync).

    The actor is a chain of layers (trunk, then policy: sear.Actor), walked here in order, as DrM's
    forward hooks see its pass: a Linear layer followed by an in-place ReLU (the hidden layers) is scored
    on its ReLU activation, as the paper defines a neuron's score; the trunk's layer (before its
    LayerNorm) and the output layer (before tanh) on what they compute."""
    outputs, x = [], latent
    with torch.no_grad():
        for layer in (m for m in actor.modules() if not list(m.children())):
            x = layer(x)
            if isinstance(layer, nn.Linear):
                outputs.append(x)
    dormant = []
    for out in outputs:
        score = out.abs().mean(0)
        dormant.append((score < score.mean() * threshold).sum())
    total = sum(out.shape[-1] for out in outputs)
    return torch.stack(dormant).sum().double() / total


def shrink_and_perturb(net: nn.Module, factor: float, init) -> None:
    """DrM's perturb (utils.perturb): every Linear layer's weight and bias become factor x themselves
    + (1 - factor) x a fresh initialisation; other layers (convolutions, LayerNorm) keep theirs. The
    fresh weights come from a re-initialised copy of the whole network, as DrM draws them, so the same
    RNG state gives the same noise (convolutions' draws included, though unused)."""
    fresh = copy.deepcopy(net).to(memory_format=torch.contiguous_format)  # orthogonal_ needs a 2-D view
    fresh.apply(init)
    with torch.no_grad():
        for mine, new in zip(net.modules(), fresh.modules()):
            if isinstance(mine, nn.Linear):
                for p, q in zip(mine.parameters(), new.parameters()):
                    p.copy_(p * factor + q * (1 - factor))


def expectile_loss(diff: torch.Tensor, expectile: float) -> torch.Tensor:
    """IQL's asymmetric squared loss on diff = V - Q: weight `expectile` where V <= Q, 1 - expectile
    where V > Q, so V settles at an upper expectile of Q over the batch's actions."""
    weight = torch.where(diff > 0, 1 - expectile, expectile)
    return (weight * diff ** 2).mean()


def forget(opt: torch.optim.Adam, params) -> None:
    """Adam's moments and step counts of `params` back to their start (zeroed in place: a fresh
    optimiser's first step, at the same addresses)."""
    for p in params:
        for t in opt.state[p].values():
            t.zero_()


class DrMAgent(sear.Agent):
    """sear.Agent with DrM: the value network V and its optimiser, the actor's latest dormant ratio and
    the step at which the actor first woke up (float64 0-d tensors on the device: the update reads and
    writes them without a host sync; NaN: not yet awake)."""

    def __init__(self, cfg, action_dim: int, device: torch.device, method=None):
        super().__init__(cfg, action_dim, device, method)
        # V's initial weights come from a fork of the torch RNG: the run's own stream is left as the
        # same seed without --drm has it (same initial networks, same first actions).
        with torch.random.fork_rng(devices=[]):
            self.value = nn.Sequential(sear.trunk(self.encoder.repr_dim, cfg.feature_dim),
                                       sear.mlp(cfg.feature_dim, cfg.hidden_dim, 1)).apply(sear.weight_init)
        self.value.to(device)
        self.value_opt = torch.optim.Adam(self.value.parameters(), lr=cfg.lr, fused=True)
        # The actor's dormant ratio and the step it woke up at (NaN: not yet), updated in place by the
        # update (a compiled one reads and writes them at fixed addresses). DrM's start: std ~1, lambda ~0.
        self.state = torch.tensor([1.0, math.nan], dtype=torch.float64, device=device)
        self.metric_names += METRICS

    ratio = property(lambda self: self.state[0], lambda self, value: self.state[0].copy_(self.scalar(value)))
    awaken_step = property(lambda self: self.state[1], lambda self, value: self.state[1].copy_(self.scalar(value)))

    @property
    def awake_at(self) -> int | None:
        """The agent step at which the actor woke up, None before (a host sync: for logs and tests)."""
        step = float(self.awaken_step)
        return None if math.isnan(step) else int(step)

    def scalar(self, value) -> torch.Tensor:
        """A float64 0-d tensor on the device (a step or a ratio given as a number, None as NaN)."""
        return torch.as_tensor(math.nan if value is None else value, dtype=torch.float64, device=self.device)

    def std(self, step):
        """Awaken exploration (DrM's stddev_type "awake"): sigmoid(temp x (ratio - target)) while the
        actor is dormant; once awake, the larger of that and DrQ-v2's schedule counted from the
        awakening."""
        cfg, awaken = self.cfg, self.awaken_step
        dormant = 1 / (1 + torch.exp(-cfg.drm_dormant_temp * (self.ratio - cfg.drm_target_ratio)))
        return torch.where(awaken.isnan(), dormant, torch.maximum(dormant, sear.linear_std(cfg, step - awaken)))

    @property
    def lam(self) -> torch.Tensor:
        """The exploitation weight: drm_lambda / (1 + exp(temp x (ratio - target)))."""
        cfg = self.cfg
        return cfg.drm_lambda / (1 + torch.exp(cfg.drm_lambda_temp * (self.ratio - cfg.drm_target_ratio)))

    def joint_loss(self, latent, obs_aug, mask_aug, batch, step, noise):
        """Before the critic's loss (DrM's update_predictor comes before its update_critic), on the
        batch's detached latent: the actor's dormant ratio, which sets this update's std and lambda,
        and V's step; then Eq. 6."""
        metrics = self.observe(latent.detach(), batch.action, step)
        loss, terms = super().joint_loss(latent, obs_aug, mask_aug, batch, step, noise)
        return loss, {**terms, **metrics}

    def observe(self, latent: torch.Tensor, action: torch.Tensor, step) -> dict:
        """The actor's dormant ratio; the awakening (the first update after the uniform steps with the
        ratio below its target); one expectile step of V towards the critic's min(Q1, Q2) of the
        batch's actions. Returns the update's DrM metrics."""
        cfg = self.cfg
        self.ratio = dormant_ratio(self.actor, latent, threshold=cfg.drm_dormant_threshold)
        step = self.scalar(step)
        wakes = self.awaken_step.isnan() & (step > cfg.exploration_steps) & (self.ratio < cfg.drm_target_ratio)
        self.awaken_step = torch.where(wakes, step, self.awaken_step)
        with torch.no_grad():
            q = torch.min(*self.critic(latent, action))
        value_loss = expectile_loss(self.value(latent) - q, cfg.drm_expectile)
        self.value_opt.zero_grad(set_to_none=True)
        value_loss.backward()
        self.value_opt.step()
        return {"dormant_ratio": self.ratio.clone(), "drm_lambda": self.lam,
                "value_loss": value_loss.detach()}

    def next_value(self, next_latent, std, noise):
        """The critic's bootstrap value: lambda x V(s') + (1 - lambda) x min(Q1', Q2')."""
        lam = self.lam
        return lam * self.value(next_latent) + (1 - lam) * super().next_value(next_latent, std, noise)

    def perturb_factor(self) -> torch.Tensor:
        """How much of each Linear layer a perturbation keeps: clip(1 - rate x ratio, min, max)."""
        cfg = self.cfg
        return (1 - cfg.drm_perturb_rate * self.ratio).clamp(cfg.drm_min_perturb, cfg.drm_max_perturb)

    def perturb_if_due(self, step: int) -> torch.Tensor | None:
        """At the start of an update whose step is a multiple of --drm-perturb-every: shrink-and-perturb
        actor, critic, target critic, encoder and V by perturb_factor() (in DrM's order: the noise is drawn
        from the agent's generator in that order), and forget those parameters' Adam moments. An auxiliary
        loss's decoders are not DrM's: they keep their weights and their moments. Returns the factor, if it
        did."""
        if step % self.cfg.drm_perturb_every:
            return None
        factor = self.perturb_factor()
        for net in (self.actor, self.critic, self.critic_target, self.encoder, self.value):
            shrink_and_perturb(net, factor, lambda m: sear.weight_init(m, self.rng))
        for opt, nets in ((self.model_opt, (self.encoder, self.critic)), (self.actor_opt, (self.actor,)),
                          (self.value_opt, (self.value,))):
            forget(opt, [p for net in nets for p in net.parameters()])
        return factor

    def update(self, batch, step):
        factor = self.perturb_if_due(step)  # outside learn(): it re-initialises networks, rarely
        metrics = super().update(batch, step)
        return metrics if factor is None else {**metrics, "perturb_factor": factor}

    # --- snapshots: DrM's state beside the agent's ---
    def state_dict(self) -> dict:
        return {**super().state_dict(), "drm": {"value": self.value.state_dict(), "value_opt": self.value_opt.state_dict(),
                                                "ratio": float(self.ratio), "awaken_step": self.awake_at}}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        drm = state["drm"]
        self.value.load_state_dict(drm["value"])
        self.value_opt.load_state_dict(drm["value_opt"])
        self.ratio, self.awaken_step = drm["ratio"], drm["awaken_step"]
