"""The speed layer: what makes a run faster without changing what it computes, each device switched by
one flag (docs/speed.md). sear.py's update, as written, is the plain path: the reference every device
here equals (tests/test_speed.py), exactly where it can, else within rounding.

  --precision bf16 the convolutional networks (encoder, decoders) under bf16 autocast
  --compile        Agent.learn through torch.compile (inductor's fused kernels)
  --cuda-graph     Agent.learn captured once as a CUDA graph and replayed: one launch per update
  --replay-device  the replay ring on the run's GPU: batches are built there, nothing crosses PCIe
  --prefetch       the next batch sampled (and copied to the GPU) in a thread while the update runs
  --seeds on CUDA  N seeds' updates as one batched update (torch.func.vmap over stacked weights)

On the CPU each is off unless asked for. On CUDA each is on by default (`auto`); none needs a private
switch of torch. Every random number of an update is drawn before it from the agent's generator
(sear.Agent.draw), so a compiled, captured or batched update draws what the plain one draws; a method
that draws inside its update (MAE's patches, CURL's shifts: DRAWS_INSIDE) is neither captured nor
batched.
"""
from __future__ import annotations

import queue
import threading

import numpy as np
import torch
import torch.nn as nn

import sear
from harness import cli

# Methods whose update draws random numbers of its own from the agent's generator (tests/test_speed.py
# finds them): a CUDA graph would replay its first draws, vmap cannot draw from a generator.
DRAWS_INSIDE = ("mae", "curl")


def on(setting, device: torch.device) -> bool:
    """An auto | on | off flag: auto is on with CUDA (a bool: a config.json from before it had three)."""
    return setting in ("on", True) or (setting == "auto" and device.type == "cuda")


def bf16(agent) -> None:
    """--precision bf16: the convolutional networks (encoder, decoders: >90% of an update's FLOPs)
    under bf16 autocast, their outputs back in fp32; actor, critic and losses stay fp32 (a TD target
    in bf16 would be off by up to 0.5 at Q = 100). Set on the agent's modules after it is built."""
    def autocast(fn):
        def run(*args, **kwargs):
            with torch.autocast(agent.device.type, dtype=torch.bfloat16):
                out = fn(*args, **kwargs)
            return out.float() if torch.is_tensor(out) else out
        return run
    agent.encoder.forward = autocast(agent.encoder.forward)
    if agent.aux is not None:
        agent.aux.forward, agent.aux.decode = autocast(agent.aux.forward), autocast(agent.aux.decode)


def speed_up(agent, run: cli.RunConfig, device: torch.device) -> list[str]:
    """One agent's update through the devices this run asks for (--compile, --cuda-graph), set on
    `agent`; a line for each that was asked for and cannot run for its method."""
    said = []
    if on(run.compile, device):
        agent.learn = torch.compile(agent.learn)
    if on(run.cuda_graph, device):
        if device.type != "cuda":
            raise cli.ConfigError("--cuda-graph on needs a CUDA device")
        if agent.cfg.method in DRAWS_INSIDE:
            said.append(f"--cuda-graph: --method {agent.cfg.method} draws random numbers inside its "
                        "update; it runs without a graph")
        else:
            agent.learn = GraphedUpdate(agent)
    return said


class Learner:
    """Every seed's update at an agent step: one after another, each through the devices of
    speed_up (the plain path), or with --batch-seeds (on with CUDA) as one batched update
    (SeedBatch), for a method whose update batches (not DRAWS_INSIDE, not --drm, not EF's
    BatchNorm)."""

    def __init__(self, agents: list, run: cli.RunConfig, device: torch.device):
        self.agents, self.batch = agents, None
        cfg = agents[0].cfg
        if cfg.precision == "bf16":
            for agent in agents:
                bf16(agent)
        why = ("--drm" if cfg.drm else f"--method {cfg.method}"
               if cfg.method in (*DRAWS_INSIDE, "ef") else None)
        if len(agents) > 1 and on(run.batch_seeds, device) and why is None:
            self.batch = SeedBatch(agents)
            return
        if len(agents) > 1 and run.batch_seeds == "on":
            print(f"--batch-seeds: {why} updates seed by seed")
        said = [line for agent in agents for line in speed_up(agent, run, device)]
        for line in dict.fromkeys(said):
            print(line)

    def update(self, batches: list, step: int) -> list[dict]:
        if self.batch is not None:
            return self.batch.update(batches, step)
        return [agent.update(batch, step) for agent, batch in zip(self.agents, batches)]


def state_tensors(agent) -> list[torch.Tensor]:
    """Every tensor an update writes in place: parameters, buffers, optimiser states, a variant's own."""
    nets = [v for v in vars(agent).values() if isinstance(v, torch.nn.Module)]
    if agent.aux is not None:
        nets += [v for v in vars(agent.aux).values() if isinstance(v, torch.nn.Module)]
    tensors = [t for net in nets for t in (*net.parameters(), *net.buffers())]
    opts = [v for v in (*vars(agent).values(), *vars(agent.aux or torch.nn.Module()).values())
            if isinstance(v, torch.optim.Optimizer)]
    tensors += [t for opt in opts for state in opt.state.values() for t in state.values() if torch.is_tensor(t)]
    tensors += [v for v in vars(agent).values() if torch.is_tensor(v)]  # DrM's state
    return list({id(t): t for t in tensors}.values())


class GraphedUpdate:
    """agent.learn captured as one CUDA graph at its first call and replayed at every call after: the
    inputs are copied into the graph's own tensors, the metrics cloned out of it (a replay overwrites
    them). Before the capture, warm-up updates on a side stream let cuDNN choose its kernels and the
    optimisers make their states; the agent's state is then set back, so the first update is the
    graph's first replay."""

    WARMUP = 3

    def __init__(self, agent):
        self.agent, self.learn, self.graph = agent, agent.learn, None
        self.inputs = self.outputs = None
        for opt in (v for v in vars(agent).values() if isinstance(v, torch.optim.Optimizer)):
            for group in opt.param_groups:
                group["capturable"] = True  # the step counts stay on the GPU, read by the kernels

    def __call__(self, batch, step, noise):
        if self.graph is None:
            self.capture(batch, step, noise)
        for mine, given in zip(self.inputs, leaves(batch, step, noise)):
            mine.copy_(given)
        self.graph.replay()
        return {name: value.clone() for name, value in self.outputs.items()}

    def capture(self, batch, step, noise):
        args = (type(batch)._make(None if x is None else x.clone() for x in batch), step.clone(),
                type(noise)._make(x.clone() for x in noise))
        self.inputs = leaves(*args)
        before = {id(t): (t, t.clone()) for t in state_tensors(self.agent)}
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(self.WARMUP):
                self.learn(*args)
        torch.cuda.current_stream().wait_stream(side)
        with torch.no_grad():  # back to the state before the warm-up; states it made start afresh
            for t in state_tensors(self.agent):
                if id(t) in before:
                    t.copy_(before[id(t)][1])
                else:
                    t.zero_()
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = self.learn(*args)


def leaves(batch, step, noise) -> list[torch.Tensor]:
    return [x for x in (*batch, step, *noise) if x is not None]


# ================================================================================================
# Seeds batched: N agents' updates as one
# ================================================================================================
NETWORKS = ("encoder", "actor", "critic", "critic_target", "aux")


class Bound(nn.Module):
    """An agent's networks as one module, so that torch.func.functional_call runs the agent's own
    methods with other parameters: functional_call(bound, params, (method,)) calls method() while
    the networks hold `params`."""

    def __init__(self, agent):
        super().__init__()
        for name in NETWORKS:
            if getattr(agent, name) is not None:
                self.add_module(name, getattr(agent, name))

    def forward(self, method):
        return method()


class SeedBatch:
    """N agents (one configuration, one device) updated as one. Their parameters are stacked, seed
    first, and each agent's own become views of the stacks, as do its Adam states: acting, snapshots
    and a resume of one seed are a single run's. The update is the agents' own critic_objective and
    actor_loss through torch.func (functional_call on the stacked parameters, vmap over the seeds,
    grad), each seed on its own batch and its own draws (Agent.draw, from its generator); Adam is
    element-wise, so one fused step over the stacks is every seed's step."""

    def __init__(self, agents: list):
        self.agents, self.template, self.device = agents, agents[0], agents[0].device
        bounds = [Bound(a) for a in agents]
        self.bound, per_agent = bounds[0], [dict(b.named_parameters()) for b in bounds]
        self.params = {n: nn.Parameter(torch.stack([p[n].detach() for p in per_agent]),
                                       requires_grad=q.requires_grad) for n, q in per_agent[0].items()}
        self.names = {opt: self.names_of(bounds[0], getattr(agents[0], opt)) for opt in ("model_opt", "actor_opt")}
        self.opts = {opt: self.stacked_adam(opt, names) for opt, names in self.names.items()}
        for i, (agent, bound) in enumerate(zip(agents, bounds)):
            for n, stacked in self.params.items():
                module, _, leaf = n.rpartition(".")
                bound.get_submodule(module)._parameters[leaf] = nn.Parameter(stacked.detach()[i],
                                                                             requires_grad=stacked.requires_grad)
            views = dict(bound.named_parameters())
            for opt, names in self.names.items():
                setattr(agent, opt, self.view_adam(self.opts[opt], [views[n] for n in names], names, i))
        self.pairs = [(self.params[n], self.params["critic" + n[len("critic_target"):]])
                      for n in self.params if n.startswith("critic_target.")]

    @staticmethod
    def names_of(bound, opt) -> list[str]:
        """The parameter names (in the bound networks) of what `opt` steps, in its order."""
        by_id = {id(p): n for n, p in bound.named_parameters()}
        return [by_id[id(p)] for group in opt.param_groups for p in group["params"]]

    def stacked_adam(self, opt: str, names) -> torch.optim.Adam:
        """Adam over the stacks, its state the agents' stacked (zeros where none has stepped yet)."""
        own = [getattr(a, opt) for a in self.agents]
        adam = torch.optim.Adam([self.params[n] for n in names], **own[0].defaults)
        mine = [[o.state[p] for group in o.param_groups for p in group["params"]] for o in own]
        for k, stacked in enumerate(self.params[n] for n in names):
            states = [m[k] for m in mine]
            adam.state[stacked] = {
                "step": states[0]["step"].clone() if states[0] else torch.zeros((), device=self.device),
                **{key: torch.stack([s[key] for s in states]) if states[0] else torch.zeros_like(stacked)
                   for key in ("exp_avg", "exp_avg_sq")}}
        return adam

    @staticmethod
    def view_adam(stacked: torch.optim.Adam, params, names, i) -> torch.optim.Adam:
        """An agent's Adam over its parameter views, its state seed i's views of the stacked state."""
        adam = torch.optim.Adam(params, **stacked.defaults)
        for p, q in zip(params, (p for group in stacked.param_groups for p in group["params"])):
            state = stacked.state[q]
            adam.state[p] = {"step": state["step"], "exp_avg": state["exp_avg"][i],
                             "exp_avg_sq": state["exp_avg_sq"][i]}
        return adam

    def objective(self, fn):
        """fn(*args) run through the template agent's networks holding one seed's params."""
        def call(params, *args):
            return torch.func.functional_call(self.bound, params, (lambda: fn(*args),))
        return call

    def update(self, batches: list, step: int) -> list[dict]:
        """One update of every seed, seed i on batches[i]; each seed's metrics (0-d tensors)."""
        a = self.template
        batch = sear.Batch._make(torch.stack([torch.as_tensor(x, device=self.device) for x in xs])
                                 for xs in zip(*batches))
        if not a.method.uses_mask:
            batch = batch._replace(mask=None, next_mask=None)
        batch = sear.Batch._make(None if x is None else x.float() for x in batch)
        noise = sear.Noise._make(torch.stack(xs) for xs in zip(*(x.draw(len(b.obs)) for x, b in
                                                                 zip(self.agents, batches))))
        step = torch.full((), step, dtype=torch.float64, device=self.device)
        batch_dims = type(batch)._make(None if x is None else 0 for x in batch)
        latent, metrics = self.step("model_opt", self.critic, (batch_dims, 0, None), batch, noise, step)
        _, actor_metrics = self.step("actor_opt", self.actor, (0, 0, 0), latent, metrics["expl_std"],
                                     noise.actor)
        with torch.no_grad():  # Polyak averaging of every seed's target critic at once
            for target, critic in self.pairs:
                target.lerp_(critic, a.cfg.critic_tau)
        metrics = {**metrics, **actor_metrics}
        return [{k: v[i] for k, v in metrics.items()} for i in range(len(self.agents))]

    def critic(self, params, batch, noise, step):
        loss, metrics, latent = self.objective(self.template.critic_objective)(params, batch, step, noise)
        return loss, (latent.detach(), metrics)

    def actor(self, params, latent, std, noise):
        loss, mu = self.objective(self.template.actor_loss)(params, latent, std, noise)
        return loss, (loss.detach(), sear.actor_metrics(loss, mu))

    def step(self, opt: str, fn, in_dims: tuple, *args):
        """One Adam step of `opt`'s stacks on fn's gradient, vmapped over the seeds (`in_dims`: of
        args); returns fn's (aux, metrics), seed first."""
        names = self.names[opt]
        trained = {n: self.params[n] for n in names}
        rest = {n: p.detach() for n, p in self.params.items() if n not in trained}

        def objective(trained, rest, *args):
            return fn({**trained, **rest}, *args)
        grads, (aux, metrics) = torch.func.vmap(torch.func.grad(objective, has_aux=True),
                                                in_dims=(0, 0, *in_dims))(trained, rest, *args)
        for n in names:
            self.params[n].grad = grads[n]
        self.opts[opt].step()
        return aux, metrics


# ================================================================================================
# The replay ring's device, and the background sampler
# ================================================================================================
# GPU memory left to the updates beside a replay there (SEAR at batch 256 and more)
GPU_HEADROOM = 10 * 2**30


def replay_device(run, device: torch.device, replay_bytes: int) -> torch.device:
    """--replay-device: where the replay ring lives. auto: on the run's GPU when the whole ring fits
    in its free memory with GPU_HEADROOM to spare (batches are then built there), else on the host
    (one line says why, on a GPU); cpu, or the run's device, as given."""
    if run.replay_device != "auto":
        return torch.device(run.replay_device)
    if device.type != "cuda":
        return torch.device("cpu")
    free, _ = torch.cuda.mem_get_info(device)
    if replay_bytes + GPU_HEADROOM <= free:
        return device
    print(f"replay: {replay_bytes / 2**30:.1f} GiB does not fit on {device} ({free / 2**30:.1f} GiB free, "
          f"{GPU_HEADROOM / 2**30:.0f} GiB kept for the updates): on the host, each batch copied over "
          "(--replay-device cpu says so quietly)")
    return torch.device("cpu")


def stage_writes(buffers: list):
    """Where the rings live on a GPU, their writes go through one StagedWrites; returns the flush
    the loop calls once per agent step (nothing to do for rings on the host)."""
    if buffers[0].device.type == "cpu":
        return lambda: None
    return StagedWrites(buffers).flush


class StagedWrites:
    """All seeds' replay writes of an agent step in one host->device copy. ReplayBuffer.put writes a
    slot at once: three copies from pageable host memory (frame, packed mask, action) and three fills
    per seed. Here each ring's put packs its slot into a row of one pinned host tensor (the ring's
    counters and episodes move on as before); flush() copies the rows without blocking and fills
    each ring's slots from the copy on the device. A slot still waiting is never drawn: a ring
    draws only from finished episodes, and the slot a write overwrites is already outside them."""

    # a slot's arrays in a row, in put's order; float32 first, so their offsets stay 4-aligned
    PARTS = ("actions", "rewards", "frames", "masks", "terminal", "first")

    def __init__(self, buffers: list):
        self.ring = buffers[0]
        row = -(-sum(getattr(self.ring, name)[0].nbytes for name in self.PARTS) // 4) * 4
        pin = self.ring.device.type == "cuda"
        # at most two writes a seed between flushes: an episode's first step and a step
        self.host = torch.zeros((2 * len(buffers), row), dtype=torch.uint8, pin_memory=pin)
        self.rows = torch.zeros_like(self.host, device=self.ring.device)
        self.copied = torch.cuda.Event() if pin else None
        self.pending = []  # (ring, slot) of each row filled since the last flush
        for ring in buffers:
            ring.put = self.putter(ring)

    def slot(self, row: torch.Tensor) -> list[torch.Tensor]:
        """A row of bytes, on the host or the device, as views of a slot's arrays (their dtypes and shapes)."""
        views, offset = [], 0
        for array in (getattr(self.ring, name) for name in self.PARTS):
            views.append(row[offset:offset + array[0].nbytes].view(array.dtype).view(array.shape[1:]))
            offset += array[0].nbytes
        return views

    def putter(self, ring):
        def put(i, frame, mask, action, reward, terminal, first):
            if len(self.pending) == len(self.host):
                self.flush()
            if not self.pending and self.copied is not None:
                # the last flush's copy has left these rows (long since: an act read the GPU after it)
                self.copied.synchronize()
            for view, value in zip(self.slot(self.host[len(self.pending)]),
                                   (action, reward, frame, mask, terminal, first)):
                view.copy_(torch.as_tensor(value))
            self.pending.append((ring, i))
        return put

    def flush(self) -> None:
        """The rows written since the last flush: one copy to the device, then each into its slot."""
        if not self.pending:
            return
        rows = self.rows[:len(self.pending)]
        rows.copy_(self.host[:len(self.pending)], non_blocking=True)
        if self.copied is not None:
            self.copied.record()
        for (ring, i), row in zip(self.pending, rows):
            for name, view in zip(self.PARTS, self.slot(row)):
                getattr(ring, name)[i] = view
        self.pending.clear()


def prefetcher(buffer, cfg, run, rng: np.random.Generator, device: torch.device):
    """The background sampler of --prefetch (on by default when a CUDA run keeps its replay on the
    host), or None: the loop samples."""
    if run.prefetch == "on" or (run.prefetch == "auto" and device.type == "cuda" and buffer.device.type == "cpu"):
        # While the thread reads a batch, the loop writes up to 2 x update_every steps and a reset
        # over the oldest slots of a full ring: episodes starting there are not drawn.
        return Prefetcher(buffer, cfg.batch_size, rng, device, margin=cfg.frame_stack + 2 * cfg.update_every)
    return None


class Prefetcher:
    """Replay sampling and the host->device copy of the next batch, in a background thread while the
    current update runs (--prefetch; on by default with CUDA and a replay on the host, where the
    update would otherwise wait for the host). Ahead of the loop: a batch is drawn two updates
    before it is used (an episode that ends reaches the batches 2 x update_every steps later than
    without it), and the sampling RNG runs ahead of the loop. On CUDA the copy goes from pinned
    memory on its own stream."""

    def __init__(self, buffer, batch_size: int, rng: np.random.Generator, device: torch.device, margin: int):
        self.buffer, self.batch_size, self.rng, self.device, self.margin = buffer, batch_size, rng, device, margin
        self.queue: queue.Queue = queue.Queue(maxsize=1)
        self.stop = threading.Event()
        self.thread = None
        self.stream = torch.cuda.Stream(device) if device.type == "cuda" else None

    def can_sample(self):
        """What the loop asks before an update: an episode this thread can draw (the `margin` oldest
        slots of the ring, which the loop may overwrite while this thread reads, left out)."""
        return self.buffer.can_sample(self.margin)

    def sample(self):
        """buffer.sample() without the `margin` oldest slots; None while no episode can be drawn (in
        a ring of about two episodes the loop may have overwritten the only one: the loop's next
        can_sample() waits)."""
        return self.buffer.sample(self.batch_size, self.rng, self.margin)

    def _produce(self):
        while not self.stop.is_set():
            try:
                batch = self.sample()
                if batch is None:
                    self.stop.wait(0.001)
                    continue
                event = None
                if self.stream is not None:
                    with torch.cuda.stream(self.stream):
                        batch = type(batch)._make(x.pin_memory().to(self.device, non_blocking=True) for x in batch)
                        event = torch.cuda.Event()
                        event.record(self.stream)
            except Exception as e:  # hand it to the learner, which raises it: never hang
                self.queue.put((e, None))
                return
            self.queue.put((batch, event))  # waits until the learner has taken the previous batch

    def next(self):
        if self.thread is None:  # started at the first update, once the buffer can be sampled
            self.thread = threading.Thread(target=self._produce, daemon=True)
            self.thread.start()
        batch, event = self.queue.get()
        if isinstance(batch, Exception):
            raise batch
        # the update's stream waits for the copy, and owns the tensors after it
        if event is not None:
            current = torch.cuda.current_stream(self.device)
            event.wait(current)
            for x in batch:
                x.record_stream(current)
        return batch

    def close(self):
        self.stop.set()
        while self.thread is not None and self.thread.is_alive():
            try:  # unblock a producer waiting on a full queue
                self.queue.get_nowait()
            except queue.Empty:
                pass
            self.thread.join(timeout=0.05)
