"""What one agent step of the loop costs the host, for N seeds together (train.py: act, the envs' step,
the frame stacks, the replay writes): copies of host data onto the agents' device and host reads of
device data, counted on the CPU as benchmarks/update_counts.py counts an update; the bytes each env
worker sends per step; and, with real envs, each worker's private memory.

    python benchmarks/step_counts.py --seeds 16                  # stand-in envs in 16 + 16 workers
    python benchmarks/step_counts.py --seeds 2 --env walker-walk # real envs: the workers' memory too

Counted per agent step over --steps steps after a warm-up:
  h2d        tensors made from host data for the agents (aten.lift_fresh: torch.as_tensor of an array,
             while train.act runs): what crosses PCIe to a GPU.
  ring copies  copies of host data into replay rings on a GPU per agent step, all seeds together: rings
             on torch's meta device stand in for the GPU (no data; every copy onto it is seen), written
             by ReplayBuffer.put (slot by slot: frame, packed mask, action) and through
             harness/speed.py's StagedWrites (one copy of every seed's rows), as train.py writes them.
  syncs      host reads of device data: .cpu() or a copy to the host, .item(); .numpy() of a tensor
             .cpu() already brought to the host is not counted again.
  answer     what a worker sends per step: its observation through shared memory (the newest frame and
             its bit-packed mask) plus its pickled reward, flags and info through the pipe.
  private    a worker's private memory (Private_Clean + Private_Dirty of /proc/PID/smaps_rollup).
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import os
import pickle
import sys

import gymnasium as gym
import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.join(HERE, ".."), HERE]
import update_counts  # noqa: E402
import train  # noqa: E402
from harness import cli, runenvs, speed  # noqa: E402

SIZE, ACTIONS, EPISODE = 84, 6, 50


class StandIn(gym.Env):
    """An env of a stack of one with the pixels and mask of a real one, random, and no simulator."""
    tasks = None

    def __init__(self, seed):
        self.rng, self.t = np.random.default_rng(seed), 0
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTIONS,), np.float32)
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Box(0, 255, (3, SIZE, SIZE), np.uint8),
            "mask": gym.spaces.Box(0, 1, (1, SIZE, SIZE), np.uint8)})

    def obs(self):
        return {"pixels": self.rng.integers(0, 256, (3, SIZE, SIZE), dtype=np.uint8),
                "mask": self.rng.integers(0, 2, (1, SIZE, SIZE), dtype=np.uint8)}

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return self.obs(), {}

    def step(self, action):
        self.t += 1
        return self.obs(), float(self.rng.random()), False, self.t >= EPISODE, {}


def stand_in(config: dict, split: str, render: bool, worker: bool):
    if worker:
        runenvs.as_worker()
    return runenvs.NewestFrame(StandIn(config["seed"] + (1 if split == "eval" else 0)))


def private_mb(pid: int) -> float:
    with open(f"/proc/{pid}/smaps_rollup") as f:
        fields = dict(line.split(":", 1) for line in f if ":" in line)
    return sum(int(fields[k].split()[0]) for k in ("Private_Clean", "Private_Dirty")) / 1024


def children(pid: int) -> list[int]:
    kids = []
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{entry}/stat") as f:
                if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                    kids.append(int(entry))
        except OSError:
            continue
    return kids


def setup(args):
    cfg = train.Config(env=args.env or "walker-walk", method=args.method, latent_dim=64, hidden_dim=32,
                       feature_dim=8, render_quality="fast", replay_size=1000)
    cfg.action_repeat = cfg.action_repeat or 2
    configs = [cli.config_dict(train.Config(**{**vars(cfg), "seed": k}), cli.RunConfig())
               for k in range(1, args.seeds + 1)]
    make = None if args.env else stand_in
    envs = runenvs.SeedEnvs(configs, train.METHODS[cfg.method].uses_mask, workers=True, make=make)
    agents, rings = [], {"put": [], "staged": []}
    for c in configs:
        torch.manual_seed(c["seed"])
        agents.append(train.make_agent(train.Config(**{**vars(cfg), "seed": c["seed"]}), envs.action_dim, "cpu"))
        for buffers in rings.values():
            buffers.append(train.make_replay(cfg, 1000, envs.frame_shape, envs.action_dim, cfg.frame_stack,
                                             cfg.nstep, cfg.discount, device="meta"))
    flushes = {"put": lambda: None, "staged": speed.stage_writes(rings["staged"])}
    return cfg, envs, agents, {name: (rings[name], flushes[name]) for name in rings}


def step_all(cfg, envs, agents, rings, stacks, step, counter=None):
    """One agent step of the loop for every seed: act, step, stack, write each set of rings."""
    where = counter.during if counter else lambda name: contextlib.nullcontext()
    with where("act"):
        actions = train.act(agents, stacks.obs, step, eval_mode=False)
    newest, rewards, terminated, truncated, _ = envs.step("train", actions)
    stacks.push(slice(None), newest)
    for name, (buffers, flush) in rings.items():
        with where(name):
            for i, b in enumerate(buffers):
                b.add(actions[i], rewards[i], terminated[i], stacks.seed(i))
            flush()
    return terminated | truncated


def measure(args) -> dict:
    cfg, envs, agents, rings = setup(args)
    try:
        n = len(agents)
        stacks = runenvs.Stacks(n, cfg.frame_stack, envs.frame_shape)
        stacks.reset(np.ones(n, bool), envs.reset("train", np.ones(n, bool), list(range(n)))[0])
        for buffers, flush in rings.values():
            for b, i in zip(buffers, range(n)):
                b.add_first(stacks.seed(i))
            flush()
        for step in range(3):  # warm-up
            step_all(cfg, envs, agents, rings, stacks, step)
        counter = StepCounter()
        with counter, update_counts.HostReads(counter.sync_names):
            for step in range(3, 3 + args.steps):
                step_all(cfg, envs, agents, rings, stacks, step, counter)
        scalar_reads = len(counter.scalar_reads)
        counter.sync_names.pop("Tensor.numpy", None)
        env = stand_in({"seed": 0}, "train", True, False) if not args.env else None
        answer = answer_bytes(env or runenvs.newest_frame_env(dict(envs_config(args)), "train", True, False))
        kids = children(os.getpid())
        private = [private_mb(k) for k in kids]
        return {"seeds": n, "h2d": counter.lifts["act"] / args.steps,
                "ring copies": {name: counter.copies[name] / args.steps for name in rings},
                "syncs": (sum(counter.sync_names.values()) + scalar_reads) / args.steps,
                "answer": answer, "workers": len(kids), "private": private}
    finally:
        envs.close()


def envs_config(args) -> dict:
    cfg = train.Config(env=args.env, method=args.method, render_quality="fast")
    return cli.config_dict(cfg, cli.RunConfig())


class StepCounter(update_counts.OpCounter):
    """update_counts' count, with the tensors made from host data or copied off the host counted."""

    def __init__(self):
        super().__init__("cpu")
        self.lifts, self.copies, self.part = collections.Counter(), collections.Counter(), None

    @contextlib.contextmanager
    def during(self, part: str):
        self.part = part
        try:
            yield
        finally:
            self.part = None

    def __torch_dispatch__(self, func, types_, args=(), kwargs=None):
        if func.overloadpacket in (torch.ops.aten.lift_fresh, torch.ops.aten.lift_fresh_copy):
            self.lifts[self.part] += 1
        if func.overloadpacket is torch.ops.aten.copy_ and args[1].device.type == "cpu" != args[0].device.type:
            self.copies[self.part] += 1
        return super().__torch_dispatch__(func, types_, args, kwargs)


def answer_bytes(env) -> tuple[int, int]:
    """(shared-memory bytes, pipe bytes) of one step's answer of a worker holding `env`."""
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    env.close()
    return sum(np.asarray(v).nbytes for v in obs.values()), len(pickle.dumps(((None, reward, terminated,
                                                                                truncated, info), True)))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=16)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--method", default="sear")
    p.add_argument("--env", default="", help="a real env (default: stand-in envs, no simulator)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    m = measure(args)
    shared, pipe = m["answer"]
    print(f"## One agent step of {m['seeds']} seeds ({args.method}, {'stand-in envs' if not args.env else args.env}, "
          f"{m['workers']} env workers)\n")
    print("| host->device copies (act) | host syncs | copies into GPU rings: put / staged "
          "| worker answer: shared memory + pipe | worker private memory |")
    print("|---|---|---|---|---|")
    mem = (f"{np.mean(m['private']):.0f} MB mean, {max(m['private']):.0f} MB largest" if m["private"] else "n/a")
    copies = m["ring copies"]
    print(f"| {m['h2d']:.1f} | {m['syncs']:.1f} | {copies['put']:.1f} / {copies['staged']:.1f} | {shared} + {pipe} = "
          f"{(shared + pipe) / 1000:.1f} KB | {mem} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
