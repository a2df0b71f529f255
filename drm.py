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

The seam: sear.Agent builds one DrM when cfg.drm is on and calls it from four places (`self.drm` in
sear.py): `std` (the exploration std), `observe` (before the critic's step: the ratio and V's step),
`blend` (the critic's target) and `perturb_if_due` (at the start of an update); its `state_dict` goes
into the agent's. Nothing here imports sear.py (it runs as __main__): the agent hands over the
building blocks DrM needs (its linear std schedule, weight init, trunk and MLP).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch
import torch.nn as nn

from cli import arg

# What an update adds to train.csv: the actor's dormant ratio, the exploration std and the target's
# lambda of the update, V's expectile loss, and the factor of a perturbation (empty in episodes without).
METRICS = ("dormant_ratio", "expl_std", "drm_lambda", "value_loss", "perturb_factor")


@dataclass
class DrMConfig:
    """DrM's flags (sear.Config inherits them). Defaults: the released code's cfgs/agent/drm.yaml, and
    for what it leaves to the task cfgs, the value of its dm_control tasks (cfgs/task/*.yaml)."""
    drm: bool = arg(False, "DrM on top of --method (docs/drm.md): dormant-ratio-driven exploration std, "
                           "expectile value blended into the critic's target, periodic shrink-and-perturb")
    drm_dormant_threshold: float = arg(0.025, "DrM: a neuron is dormant when its mean |activation| over the batch "
                                              "is below this fraction of its layer's mean (dormant_threshold)")
    drm_target_ratio: float = arg(0.2, "DrM: target dormant ratio: the actor is awake once below it, and the "
                                       "std's and lambda's sigmoids are centred on it (target_dormant_ratio)")
    drm_dormant_temp: float = arg(10.0, "DrM: slope of the dormant std, sigmoid(temp x (ratio - target)) "
                                        "(dormant_temp)")
    drm_lambda: float = arg(0.6, "DrM: largest weight of the expectile value V(s') in the critic's target "
                                 "(target_lambda; every dm_control task cfg: 0.6)")
    drm_lambda_temp: float = arg(50.0, "DrM: slope of lambda = drm_lambda / (1 + exp(temp x (ratio - target))) "
                                       "(lambda_temp)")
    drm_perturb_every: int = arg(100_000, "DrM: AGENT STEPS between shrink-and-perturbs (dormant_perturb_interval); "
                                          "an update step that is a multiple of it perturbs")
    drm_min_perturb: float = arg(0.2, "DrM: smallest shrink factor (min_perturb_factor)")
    drm_max_perturb: float = arg(1.0, "DrM: largest shrink factor (max_perturb_factor: 1.0 in the task cfgs of "
                                      "medium tasks, 0.9 or 0.6 for some hard ones: cli.DRM_MAX_PERTURB)")
    drm_perturb_rate: float = arg(2.0, "DrM: shrink factor = clip(1 - rate x ratio, min, max) (perturb_rate)")
    drm_expectile: float = arg(0.9, "DrM: expectile of V's asymmetric squared loss on min(Q1, Q2) (expectile)")


def sigmoid(x: float) -> float:
    """1 / (1 + exp(-x)), as DrM's code writes it, without overflowing for very negative x."""
    return 1 / (1 + math.exp(min(-x, 700.0)))


def dormant_ratio(net: nn.Module, *inputs, threshold: float) -> float:
    """DrM's dormant ratio (utils.cal_dormant_ratio): one forward pass of `net`, and for every Linear
    layer the mean |output| of each neuron over the batch; a neuron is dormant when that is below
    `threshold` x the layer's mean. Returns dormant neurons / all neurons of the Linear layers.

    The outputs are read after the whole pass, as DrM's forward hooks hold them: a Linear layer
    followed by an in-place ReLU (the actor's hidden layers) is scored on its ReLU activation, as the
    paper defines a neuron's score; the trunk's layer (before its LayerNorm) and the output layer
    (before tanh) on what they compute."""
    outputs = []
    hooks = [m.register_forward_hook(lambda m, inp, out: outputs.append(out))
             for m in net.modules() if isinstance(m, nn.Linear)]
    try:
        with torch.no_grad():
            net(*inputs)
    finally:
        for h in hooks:
            h.remove()
    dormant = []
    for out in outputs:
        score = out.abs().mean(0)
        dormant.append((score < score.mean() * threshold).sum())
    total = sum(out.shape[-1] for out in outputs)
    return int(torch.stack(dormant).sum()) / total  # one device sync


def shrink_and_perturb(net: nn.Module, factor: float, init) -> None:
    """DrM's perturb (utils.perturb): every Linear layer's weight and bias become factor x themselves
    + (1 - factor) x a fresh initialisation; other layers (convolutions, LayerNorm) keep theirs. The
    fresh weights come from a re-initialised copy of the whole network, as DrM draws them, so the same
    torch RNG state gives the same noise (convolutions' draws included, though unused)."""
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


class DrM:
    """DrM's state and machinery for one sear.Agent: the value network V and its optimiser, the
    actor's latest dormant ratio, the step at which the actor first woke up, and this update's perturbation."""

    def __init__(self, cfg, agent, schedule, init, trunk, mlp):
        """cfg: sear.Config; agent: the sear.Agent whose networks and optimisers DrM perturbs;
        schedule(cfg, step): DrQ-v2's linear std; init: the weight init; trunk, mlp: the layers V is
        made of (DrM's VNetwork: the actor's trunk and an MLP to one output)."""
        self.cfg, self.agent, self.schedule, self.init = cfg, agent, schedule, init
        # V's initial weights come from a fork of the torch RNG: the run's own stream is left as the
        # same seed without --drm has it (same initial networks, same first actions).
        with torch.random.fork_rng(devices=[]):
            self.value = nn.Sequential(trunk(agent.encoder.repr_dim, cfg.feature_dim),
                                       mlp(cfg.feature_dim, cfg.hidden_dim, 1)).apply(init)
        self.value.to(agent.device)
        self.value_opt = torch.optim.Adam(self.value.parameters(), lr=cfg.lr)
        self.ratio = 1.0          # DrM's initial dormant ratio: std ~1 and lambda ~0 until the first update
        self.awaken_step = None   # the first update after the uniform steps with ratio < target
        self.factor = None        # this update's perturbation, for its metrics

    # --- what the agent asks ---
    def std(self, step: int) -> float:
        """Awaken exploration (DrM's stddev_type "awake"): sigmoid(temp x (ratio - target)) while the
        actor is dormant; once awake, the larger of that and DrQ-v2's schedule counted from the
        awakening."""
        dormant = sigmoid(self.cfg.drm_dormant_temp * (self.ratio - self.cfg.drm_target_ratio))
        if self.awaken_step is None:
            return dormant
        return max(dormant, self.schedule(self.cfg, step - self.awaken_step))

    @property
    def lam(self) -> float:
        """The exploitation weight: drm_lambda / (1 + exp(temp x (ratio - target)))."""
        cfg = self.cfg
        return cfg.drm_lambda / (1 + math.exp(min(cfg.drm_lambda_temp * (self.ratio - cfg.drm_target_ratio), 700.0)))

    def observe(self, latent: torch.Tensor, action: torch.Tensor, step: int) -> dict:
        """Before the critic's step, on the batch's (detached) latent: the actor's dormant ratio, which
        sets this update's std and lambda; the awakening; one expectile step of V towards the critic's
        min(Q1, Q2) of the batch's actions (DrM's update_predictor, before update_critic). Returns the
        update's DrM metrics."""
        cfg = self.cfg
        self.ratio = dormant_ratio(self.agent.actor, latent, 0.0, threshold=cfg.drm_dormant_threshold)
        if self.awaken_step is None and step > cfg.exploration_steps and self.ratio < cfg.drm_target_ratio:
            self.awaken_step = step
        with torch.no_grad():
            q = torch.min(*self.agent.critic(latent, action))
        value_loss = expectile_loss(self.value(latent) - q, cfg.drm_expectile)
        self.value_opt.zero_grad(set_to_none=True)
        value_loss.backward()
        self.value_opt.step()
        metrics = {"dormant_ratio": self.ratio, "expl_std": self.std(step), "drm_lambda": self.lam,
                   "value_loss": value_loss.item()}
        if self.factor is not None:
            metrics["perturb_factor"], self.factor = self.factor, None
        return metrics

    def blend(self, next_latent: torch.Tensor, target_v: torch.Tensor) -> torch.Tensor:
        """The critic's bootstrap value: lambda x V(s') + (1 - lambda) x min(Q1', Q2')."""
        lam = self.lam
        return lam * self.value(next_latent) + (1 - lam) * target_v

    def perturb_factor(self) -> float:
        """How much of each Linear layer a perturbation keeps: clip(1 - rate x ratio, min, max)."""
        cfg = self.cfg
        return min(max(cfg.drm_min_perturb, 1 - cfg.drm_perturb_rate * self.ratio), cfg.drm_max_perturb)

    def perturb_if_due(self, step: int) -> None:
        """At the start of an update whose step is a multiple of --drm-perturb-every: shrink-and-perturb
        actor, critic, target critic, encoder and V by perturb_factor() (in DrM's order: the noise is drawn
        from the torch RNG in that order), and forget those parameters' Adam moments. An auxiliary loss's
        decoders are not DrM's: they keep their weights and their moments."""
        if step % self.cfg.drm_perturb_every:
            return
        a, self.factor = self.agent, self.perturb_factor()
        for net in (a.actor, a.critic, a.critic_target, a.encoder, self.value):
            shrink_and_perturb(net, self.factor, self.init)
        for opt, nets in ((a.model_opt, (a.encoder, a.critic)), (a.actor_opt, (a.actor,)),
                          (self.value_opt, (self.value,))):
            for net in nets:
                for p in net.parameters():
                    opt.state.pop(p, None)

    # --- snapshots ---
    def state_dict(self) -> dict:
        return {"value": self.value.state_dict(), "value_opt": self.value_opt.state_dict(), "ratio": self.ratio,
                "awaken_step": self.awaken_step}

    def load_state_dict(self, state: dict) -> None:
        self.value.load_state_dict(state["value"])
        self.value_opt.load_state_dict(state["value_opt"])
        self.ratio, self.awaken_step = state["ratio"], state["awaken_step"]
