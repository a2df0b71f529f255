"""How far --precision bf16 moves an update from fp32, measured in one run.

    python benchmarks/bench_precision.py                       # sear, batch 64, 300 updates
    python benchmarks/bench_precision.py --method drq --updates 200 --batch-size 32

Two agents start from the same weights and see the same batches with the same augmentation and
exploration noise (the torch RNG is re-seeded before each update). Reported:
  * gradient error: at a few points of the fp32 run, the bf16 agent is loaded with the fp32 agent's
    weights and both compute Eq. 6's gradient on the same batch; relative L2 of the encoder's and of
    all of the joint loss's gradients;
  * drift: both agents train on their own, side by side; the losses of each and the relative L2
    distance of the encoder weights after N updates.
The batches are a fixed set of real frames when --env is given (rendered once), else random pixels.
"""
import argparse
import copy
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402
from harness import experiment  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402


def batches_from_env(env_name, n_batches, batch_size, seed=0):
    """Real frames: random-action episodes of `env_name` in a replay buffer, then fixed samples."""
    cfg = train.Config(env=env_name, render_quality="fast", replay_size=4_000)
    train_env, eval_env = runenvs.make_envs(cfg, sear.METHODS[cfg.method].uses_mask)
    eval_env.close()
    adim = train_env.action_space.shape[0]
    buf = sear.ReplayBuffer(cfg.replay_size, (3, 84, 84), adim, cfg.frame_stack, cfg.nstep, cfg.discount)
    rng = np.random.default_rng(seed)
    obs, _ = train_env.reset(seed=seed)
    buf.add_first(obs)
    for i in range(1_500):
        a = rng.uniform(-1, 1, adim).astype(np.float32)
        obs, r, term, trunc, _ = train_env.step(a)
        buf.add(a, r, term, obs)
        if term or trunc:
            obs, _ = train_env.reset(seed=seed + i + 1)
            buf.add_first(obs)
    train_env.close()
    return [buf.sample(batch_size, rng) for _ in range(n_batches)], adim


def random_batches(n_batches, batch_size, adim=6, seed=0):
    rng = np.random.default_rng(seed)
    n = batch_size
    return [(rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8), rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8),
             rng.uniform(-1, 1, (n, adim)).astype(np.float32), rng.normal(size=(n, 1)).astype(np.float32),
             np.full((n, 1), 0.99 ** 3, np.float32), rng.integers(0, 256, (n, 9, 84, 84), dtype=np.uint8),
             rng.integers(0, 2, (n, 3, 84, 84), dtype=np.uint8)) for _ in range(n_batches)], adim


def joint_grads(agent, batch, seed):
    """Eq. 6's gradient on (encoder, critic, decoders) for one batch, with a fixed RNG."""
    batch = sear.Batch._make(torch.as_tensor(x).float() for x in batch)
    torch.manual_seed(seed)
    loss, _, _ = agent.joint_loss(batch, step=5_000)
    agent.model_opt.zero_grad(set_to_none=True)
    loss.backward()
    enc = torch.cat([p.grad.flatten() for p in agent.encoder.parameters()])
    every = torch.cat([p.grad.flatten() for g in agent.model_opt.param_groups for p in g["params"] if p.grad is not None])
    return enc, every


def rel(a, b):
    return ((a - b).norm() / b.norm()).item()


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--method", default="sear", choices=list(sear.METHODS))
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--updates", type=int, default=300)
    p.add_argument("--env", default="cup-catch", help="real frames from this env ('' = random pixels)")
    p.add_argument("--threads", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(args.threads or cli.default_threads())
    batches, adim = (batches_from_env(args.env, 16, args.batch_size) if args.env
                     else random_batches(16, args.batch_size))
    torch.manual_seed(0)
    fp32 = sear.Agent(train.Config(method=args.method, batch_size=args.batch_size, precision="fp32"), adim,
                      torch.device("cpu"))
    bf16 = sear.Agent(train.Config(method=args.method, batch_size=args.batch_size, precision="bf16"), adim,
                      torch.device("cpu"))
    bf16.load_state_dict(copy.deepcopy(fp32.state_dict()))
    probe = sear.Agent(train.Config(method=args.method, batch_size=args.batch_size, precision="bf16"), adim,
                       torch.device("cpu"))

    print(f"## bf16 vs fp32: {args.method}, batch {args.batch_size}, {args.updates} updates, "
          f"{'frames of ' + args.env if args.env else 'random pixels'}\n")
    print("| update | rel. L2 of encoder grad | rel. L2 of joint grad | fp32 critic loss | bf16 critic loss | "
          "fp32 aux losses | bf16 aux losses | encoder weights rel. distance |")
    print("|---|---|---|---|---|---|---|---|")
    checkpoints = {0, 10, 50, 100, 200, args.updates - 1}
    for k in range(args.updates):
        batch = batches[k % len(batches)]
        if k in checkpoints:
            probe.load_state_dict(copy.deepcopy(fp32.state_dict()))
            g32, a32 = joint_grads(copy.deepcopy(fp32), batch, seed=k)
            g16, a16 = joint_grads(probe, batch, seed=k)
        torch.manual_seed(10_000 + k)
        m32 = fp32.update(batch, step=5_000)
        torch.manual_seed(10_000 + k)
        m16 = bf16.update(batch, step=5_000)
        if k in checkpoints:
            w32 = torch.cat([p.flatten() for p in fp32.encoder.parameters()])
            w16 = torch.cat([p.flatten() for p in bf16.encoder.parameters()])
            aux = [n for n in m32 if n.endswith("_loss") and n not in ("critic_loss", "actor_loss")]
            fmt = lambda m: " / ".join(f"{m[n]:.1f}" for n in aux) or "-"  # noqa: E731
            print(f"| {k} | {rel(g16, g32):.4f} | {rel(a16, a32):.4f} | {m32['critic_loss']:.4f} | "
                  f"{m16['critic_loss']:.4f} | {fmt(m32)} | {fmt(m16)} | {rel(w16, w32):.4f} |", flush=True)


if __name__ == "__main__":
    cli.configure_allocator()  # glibc's malloc as sear.py sets it
    main()
