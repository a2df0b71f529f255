"""Does the actor saturate? Runs sear.py's training loop with a hook on the actor that prints, every
50 actor updates, the mean |pre-tanh| output and its std over the batch's states (~0: one action
for every state), and the share of outputs past 9 (float32 tanh is exactly +-1 there, gradient 0).
The numbers of EXPERIMENTS.md rung 2 ("What the actor does"). Any sear.py flags, e.g.

    MUJOCO_GL=egl python benchmarks/actor_probe.py --env walker-stand --method drq --seed 1 \
        --action-repeat 4 --frames 10000 --seed-frames 4000 --exploration-steps 1000 --std-steps 100000 \
        --update-every 2 --batch-size 64 --lr 2e-4 --precision bf16 --render-quality fast \
        --eval-every 100000 --eval-episodes 1 --threads 1 --run-root /tmp/probe

train.csv's actor_saturated and action_spread give the same picture after the tanh in any run.
"""
import os
import sys

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402

seen = []


def forward(self, latent, std):
    pre = self.policy(self.trunk(latent))
    if torch.is_grad_enabled() and latent.shape[0] > 1:  # the actor's update (not act, not the TD target)
        p = pre.detach()
        seen.append(1)
        if len(seen) % 50 == 0:
            print(f"PROBE update {len(seen)}: |pre-tanh| {p.abs().mean():.2f}, std over states {p.std(0).mean():.2f}, "
                  f"share > 9 {(p.abs() > 9.0).float().mean():.2f}", flush=True)
    return sear.TruncatedNormal(torch.tanh(pre), torch.full_like(pre, std))


if __name__ == "__main__":
    sear.Actor.forward = forward
    cfg, run, _ = cli.parse_args(sys.argv[1:], train.Config, sear.METHODS)
    train.train(cfg, run)
