"""Many seeds of one configuration in one process (`--seeds 1-16`): their networks stacked and updated as
one batched update, so that a GPU that one seed's small update leaves idle serves all of them, and their
envs stepped side by side in worker processes.

SeedGroup takes N agents built as N single runs build them (each from its own seed) and stacks their
parameters and Adam states, seed first; each agent's own parameters and optimiser states become views
of the stacks, so that acting, snapshots and resumes of one seed are a single run's. The update is the
agents' own: sear.Agent.critic_objective and actor_loss, called through torch.func (functional_call on
the stacked parameters, vmap over the seeds, grad), each seed with its own batch and its own random
draws (shifts, exploration noise); one sear.Adam step and one Polyak step over the stacks are every
seed's steps, element for element.

The loop (train_group) is train.train's, seed by seed in lockstep: every seed is an ordinary run directory
(config.json, train.csv, eval.csv, snapshot.pt: plot.py, sweep.py and published_curve.py read them as any
run's), inside the group's folder with group.json; its console lines go to its console.log, while the
terminal shows one progress line for the group. `--resume GROUP_DIR` continues every seed; `--resume` of
one seed's run directory continues that seed as a single run.

Layering: imports sear, experiment and cli; train.py calls it (it never imports train.py, which runs as
__main__: train.py hands it what it needs).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import multiprocessing
import os
import sys
import time
import types

import numpy as np
import torch
import torch.nn as nn

import sear
from harness import cli, experiment

NETWORKS = ("encoder", "actor", "critic", "critic_target", "aux")


def refusal(cfg, run) -> str | None:
    """Why a configuration cannot run as a seed group (one line), or None."""
    if cfg.drm:
        return "--seeds does not take --drm: DrM re-initialises networks in place, seed by seed"
    aux = sear.METHODS[cfg.method].aux
    if aux is not None and aux.replay is not sear.AuxLoss.replay:
        return f"--seeds does not take --method {cfg.method} yet: its replay is its own"
    if aux is not None and aux.after_update is not sear.AuxLoss.after_update:
        return f"--seeds does not take --method {cfg.method}: its own optimiser step runs outside the batched update"
    if run.compile:
        return "--seeds does not take --compile yet: the batched update runs eagerly"
    if run.init_from:
        return "--seeds does not take --init-from: start the group's seeds afresh"
    return None


class Bound(nn.Module):
    """An agent's networks as one module, so that torch.func.functional_call runs the agent's own methods
    with other parameters: functional_call(bound, params, (method,)) calls method() while the networks
    hold `params`."""

    def __init__(self, agent):
        super().__init__()
        for name in NETWORKS:
            if getattr(agent, name) is not None:
                self.add_module(name, getattr(agent, name))

    def forward(self, method):
        return method()


class SeedGroup:
    """N agents (sear.Agent, one configuration, one device) updated as one."""

    def __init__(self, agents: list, randomness: str = "different"):
        self.agents, self.template, self.randomness = agents, agents[0], randomness
        self.cfg, self.device = agents[0].cfg, agents[0].device
        bounds = [Bound(a) for a in agents]
        self.bound = bounds[0]
        names = [name for name, _ in self.bound.named_parameters()]
        model_names, actor_names = self.names_of(bounds[0], agents[0].model_opt), self.names_of(bounds[0], agents[0].actor_opt)
        per_agent = [dict(b.named_parameters()) for b in bounds]
        # the stacks, seed first: the group's parameters; each agent's become views of them
        self.params = {n: nn.Parameter(torch.stack([p[n].detach() for p in per_agent]),
                                       requires_grad=per_agent[0][n].requires_grad) for n in names}
        self.model_names, self.actor_names = model_names, actor_names
        self.model_opt = sear.Adam([self.params[n] for n in model_names], lr=self.cfg.lr)
        self.actor_opt = sear.Adam([self.params[n] for n in actor_names], lr=self.cfg.lr)
        for i, (agent, bound) in enumerate(zip(agents, bounds)):
            for n in names:
                module_name, _, leaf = n.rpartition(".")
                view = nn.Parameter(self.params[n].detach()[i], requires_grad=self.params[n].requires_grad)
                bound.get_submodule(module_name)._parameters[leaf] = view
            params = dict(bound.named_parameters())  # each agent's optimisers on its views, their states too
            agent.model_opt = self.views(agent.model_opt, self.model_opt, [params[n] for n in model_names], i)
            agent.actor_opt = self.views(agent.actor_opt, self.actor_opt, [params[n] for n in actor_names], i)
        self.critic_pairs = [(self.params[n], self.params["critic" + n[len("critic_target"):]])
                             for n in names if n.startswith("critic_target.")]

    @staticmethod
    def names_of(bound, opt) -> list[str]:
        """The parameter names (in the bound networks) of what `opt` steps, in its order."""
        by_id = {id(p): n for n, p in bound.named_parameters()}
        return [by_id[id(p)] for p in opt.params]

    @staticmethod
    def views(own, group, params, i) -> sear.Adam:
        """An agent's optimiser over its parameter views, its state the group's state at seed i."""
        opt = sear.Adam(params, lr=own.param_groups[0]["lr"])
        for p, own_p, stacked in zip(params, own.params, group.params):
            mine, theirs = own.state[own_p], group.state[stacked]
            theirs["exp_avg"][i].copy_(mine["exp_avg"])
            theirs["exp_avg_sq"][i].copy_(mine["exp_avg_sq"])
            theirs["step"].copy_(mine["step"])  # every seed steps together
            opt.state[p] = {"step": theirs["step"], "exp_avg": theirs["exp_avg"][i], "exp_avg_sq": theirs["exp_avg_sq"][i]}
        return opt

    def objective(self, fn):
        """fn(params dict of one seed, *args) -> fn run through the template agent's networks holding them."""
        def call(params, *args):
            return torch.func.functional_call(self.bound, params, (lambda: fn(*args),))
        return call

    def update(self, batches: list, step: int) -> list[dict]:
        """One update of every seed, seed i on batches[i] (tensors on the device); returns each seed's
        metrics (0-d tensors, read at log lines)."""
        a = self.template
        batch = sear.Batch._make(torch.stack([torch.as_tensor(x, device=self.device) for x in xs])
                                 for xs in zip(*batches))
        if not a.method.uses_mask:
            batch = batch._replace(mask=None, next_mask=None)
        batch = sear.Batch._make(None if x is None else x.float() for x in batch)
        batch = batch._replace(obs=torch.vmap(a.encoder_input)(batch.obs, batch.mask),
                               next_obs=torch.vmap(a.encoder_input)(batch.next_obs, batch.next_mask)) \
            if a.method.mask_input else batch
        step = torch.full((), step, dtype=torch.float64, device=self.device)
        model = {n: self.params[n] for n in self.model_names}
        rest = {n: p.detach() for n, p in self.params.items() if n not in model}

        def critic(model, rest, batch):
            loss, metrics, latent = self.objective(a.critic_objective)({**model, **rest}, batch, step)
            return loss, (metrics, latent.detach())
        batch_dims = sear.Batch._make(None if x is None else 0 for x in batch)  # masks left out: None
        grads, (metrics, latent) = torch.func.vmap(torch.func.grad(critic, has_aux=True), in_dims=(0, 0, batch_dims),
                                                   randomness=self.randomness)(model, rest, batch)
        self.model_opt.step([grads[n] for n in self.model_names])

        actor = {n: self.params[n] for n in self.actor_names}
        rest = {n: p.detach() for n, p in self.params.items() if n not in actor}

        def actor_step(actor, rest, latent, std):
            loss, mu = self.objective(a.actor_loss)({**actor, **rest}, latent, std)
            return loss, sear.actor_metrics(loss, mu)
        grads, actor_metrics = torch.func.vmap(torch.func.grad(actor_step, has_aux=True),
                                               randomness=self.randomness)(actor, rest, latent, metrics["expl_std"])
        self.actor_opt.step([grads[n] for n in self.actor_names])
        with torch.no_grad():  # Polyak averaging of every seed's target critic at once
            torch._foreach_lerp_([t for t, _ in self.critic_pairs], [c for _, c in self.critic_pairs],
                                 self.cfg.critic_tau)
        metrics = {**metrics, **actor_metrics}
        return [{k: v[i] for k, v in metrics.items()} for i in range(len(self.agents))]


# ================================================================================================
# The envs: one worker process per seed (each with its own renderers), or this process
# ================================================================================================
def serve(conn, config: dict, uses_mask: bool):
    """A worker: the seed's train and eval env (experiment.make_envs), stepped on request."""
    cfg = types.SimpleNamespace(**config)
    envs = dict(zip(("train", "eval"), experiment.make_envs(cfg, uses_mask)))
    conn.send({name: (env.action_space, env.observation_space, getattr(env.unwrapped, "tasks", None))
               for name, env in envs.items()})
    while True:
        which, method, args = conn.recv()
        if method == "close":
            for env in envs.values():
                env.close()
            return
        try:
            conn.send(getattr(envs[which], method)(*args[0], **args[1]))
        except Exception as e:  # the loop raises it: never hang
            conn.send(e)


class RemoteEnv:
    """One seed's train or eval env in its worker, as an env (reset, step, spaces, unwrapped.tasks);
    send_step() asks for a step without waiting, the next step() takes its answer."""

    def __init__(self, conn, which, spaces):
        self.conn, self.which, self.pending = conn, which, False
        self.action_space, self.observation_space, tasks = spaces
        self.unwrapped = types.SimpleNamespace(tasks=tasks)

    def call(self, method, *args, **kwargs):
        self.conn.send((self.which, method, (args, kwargs)))
        return self.answer()

    def answer(self):
        out = self.conn.recv()
        if isinstance(out, Exception):
            raise out
        return out

    def reset(self, **kwargs):
        return self.call("reset", **kwargs)

    def send_step(self, action):
        self.conn.send((self.which, "step", ((action,), {})))
        self.pending = True

    def step(self, action):
        if not self.pending:
            self.send_step(action)
        self.pending = False
        return self.answer()

    def close(self):
        pass


class EnvPool:
    """Every seed's train and eval env: in spawned worker processes (a process that rendered with EGL
    must not fork one that renders), or, where workers do not start, in this process, one seed after
    another. `kind` says which runs."""

    START_SECONDS = 300  # a worker that has not made its envs by then (EGL can hang at start) falls back

    def __init__(self, configs: list[dict], uses_mask: bool, workers: str):
        self.procs, self.envs = [], None
        if workers == "spawn":
            try:
                self.envs = self.spawn(configs, uses_mask)
                self.kind = f"{len(configs)} worker processes, one per seed, each with its own renderers"
                return
            except Exception as e:  # noqa: BLE001  (any failure to start: the fallback runs, and says why)
                self.close()
                print(f"envs: the worker processes did not start ({cli.first_sentence(e)}); stepping them here")
        made = [experiment.make_envs(types.SimpleNamespace(**c), uses_mask) for c in configs]
        self.envs = [dict(zip(("train", "eval"), pair)) for pair in made]
        self.kind = "this process, one seed after another"

    def spawn(self, configs, uses_mask):
        context, envs = multiprocessing.get_context("spawn"), []
        for config in configs:
            parent, child = context.Pipe()
            proc = context.Process(target=serve, args=(child, config, uses_mask), daemon=True)
            proc.start()
            self.procs.append((proc, parent))
        for proc, conn in self.procs:
            if not conn.poll(self.START_SECONDS):
                raise TimeoutError(f"a worker made no envs in {self.START_SECONDS} s")
            spaces = conn.recv()
            if isinstance(spaces, Exception):
                raise spaces
            envs.append({name: RemoteEnv(conn, name, spaces[name]) for name in ("train", "eval")})
        return envs

    def step_all(self, which: str, actions: dict) -> dict:
        """{seed index: step result} of env.step(actions[i]) for each i, the workers stepping at once."""
        for i, action in actions.items():
            if isinstance(self.envs[i][which], RemoteEnv):
                self.envs[i][which].send_step(action)
        return {i: self.envs[i][which].step(action) for i, action in actions.items()}

    def close(self):
        for proc, conn in self.procs:
            with contextlib.suppress(Exception):
                conn.send((None, "close", ((), {})))
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()
        self.procs = []
        for envs in (self.envs or []) if not self.procs else ():
            for env in envs.values():
                env.close()


# ================================================================================================
# The loop: train.train for every seed at once
# ================================================================================================
@dataclasses.dataclass
class Member:
    """One seed of the group: its config, run directory, agent, replay, sampling RNG, counters and
    episode under way; its console lines go to its run directory's console.log."""
    cfg: object
    run: cli.RunConfig
    rundir: experiment.RunDir
    snapshot: dict | None = None
    agent: object = None
    buffer: object = None
    rng: np.random.Generator = None
    counters: experiment.Counters = None
    console: object = None
    obs: dict = None
    ep: list = dataclasses.field(default_factory=lambda: [0.0, 0, False])  # return, length, success

    def quiet(self):
        """What the member's run dir prints goes to its console.log (the terminal shows the group's)."""
        return contextlib.redirect_stdout(self.console) if self.console else contextlib.nullcontext()


def parse_seeds(spec: str) -> list[int]:
    """'1-16' -> [1, ..., 16]; '1,3,5' and '1-4,9' too. A bad spec is a ConfigError."""
    seeds = []
    try:
        for part in spec.split(","):
            lo, _, hi = part.partition("-")
            seeds += list(range(int(lo), int(hi or lo) + 1))
    except ValueError:
        raise cli.ConfigError(f"--seeds takes seeds like 1-16 or 1,3,5, got '{spec}'") from None
    if len(seeds) < 2 or len(set(seeds)) != len(seeds):
        raise cli.ConfigError(f"--seeds takes two or more different seeds, got '{spec}'")
    return seeds


GROUP_FILE = "group.json"
WORKERS = "SEAR_ENV_WORKERS"  # spawn (the default: one worker process per seed) | serial (this process)


def split_argv(argv: list[str]) -> tuple[list[int] | None, str | None, list[str]]:
    """(seeds, group folder to resume, argv for one member) of a command line: --seeds SPEC (removed, the
    member's --seed is set per seed), or --resume GROUP_DIR (its first member's run dir in its place)."""
    argv, seeds, group_dir = list(argv), None, None
    for flag in ("--seeds", "--resume"):
        for i, token in enumerate(argv):
            name, eq, value = token.partition("=")
            if name != flag or (not eq and i + 1 >= len(argv)):
                continue
            value = value if eq else argv[i + 1]
            if flag == "--seeds":
                seeds, argv = parse_seeds(value), argv[:i] + argv[i + 1 + (not eq):]
            elif os.path.isfile(os.path.join(value, GROUP_FILE)):
                group_dir = value
                with open(os.path.join(value, GROUP_FILE)) as f:
                    saved = json.load(f)
                seeds = saved["seeds"]
                argv[i:i + 1 + (not eq)] = ["--resume", os.path.join(value, saved["runs"][str(seeds[0])])]
            break
    return seeds, group_dir, argv


def wanted(argv) -> bool:
    """Whether the command line asks for a group: --seeds, or --resume of a group's folder."""
    try:
        return split_argv(argv)[0] is not None
    except cli.ConfigError:  # a bad --seeds: group.main says so in one line
        return True


def main(argv, Config, methods, parts) -> int:
    """`--seeds SPEC` or `--resume GROUP_DIR`: cli.main with the group's loop in place of train.train.
    parts: train.py's make_agent, Episode and eval_due (this module does not import train.py)."""
    try:
        seeds, group_dir, member_argv = split_argv(argv)
    except cli.ConfigError as e:
        print(f"sear.py: error: {e}", file=sys.stderr)
        return 2

    def run_group(cfg, run, snapshot):
        if run.evaluate:
            raise cli.ConfigError("--evaluate scores one run directory; give one seed's, not --seeds")
        check(cfg, run)
        return train_group(cfg, run, snapshot, seeds, group_dir, parts)
    return cli.main(member_argv, Config, methods, run_group, run_group)


def members_of(cfg, run, snapshot, seeds, group_dir) -> tuple[str, list[Member]]:
    """The group's folder (made for a new group) and its members, each with its config and run settings."""
    if group_dir is None:
        label = f"{cfg.env}__{cli.method_label(cfg)}__seeds{seeds[0]}-{seeds[-1]}"
        group_dir = experiment.new_run_dir(run.run_root, label)
        members = [Member(dataclasses.replace(cfg, seed=k), dataclasses.replace(run, run_root=group_dir), None)
                   for k in seeds]
    else:
        with open(os.path.join(group_dir, GROUP_FILE)) as f:
            runs = json.load(f)["runs"]
        members = []
        for k in seeds:
            path = os.path.join(group_dir, runs[str(k)])
            state = snapshot if k == seeds[0] else cli.load_snapshot(path)
            if state["counters"]["step"] != snapshot["counters"]["step"]:
                raise cli.ConfigError(f"--resume: the group's seeds stopped at different steps ({path}): resume "
                                      f"each seed's run directory on its own")
            # one configuration: the first seed's, checked and with what a resume may change, per seed
            members.append(Member(dataclasses.replace(cfg, seed=k), dataclasses.replace(run, resume=path), None, state))
    for m in members:
        m.rundir = experiment.RunDir(m.cfg, m.run, m.snapshot)
        m.rundir.files.group = group_dir  # its lines name the group to resume
    return group_dir, members


def train_group(cfg, run, snapshot, seeds, group_dir, parts) -> str:
    """train.train for every seed of the group at once (see the module's doc); returns the group's folder."""
    device = cli.torch_setup(run)
    group_dir, members = members_of(cfg, run, snapshot, seeds, group_dir)
    uses_mask = sear.METHODS[cfg.method].uses_mask
    pool = None
    try:
        for m in members:
            m.rundir.__enter__()
        pool = EnvPool([cli.config_dict(m.cfg, m.run) for m in members], uses_mask, os.environ.get(WORKERS, "spawn"))
        import envs  # the suite's action repeat, as make_envs sets it in the workers
        for m in members:
            m.cfg.action_repeat = m.cfg.action_repeat or envs.default_action_repeat(m.cfg.env)
            with m.quiet():
                m.rundir.create()
            m.console = open(os.path.join(m.rundir.path, "console.log"), "a")
        write_group_file(group_dir, members)
        print(f"group: {len(members)} seeds ({seeds[0]}..{seeds[-1]}) of {cli.method_label(cfg)} on {cfg.env} in "
              f"{group_dir}; envs in {pool.kind}; device {device}", flush=True)
        env = pool.envs[0]["train"]
        action_dim, frame_shape = env.action_space.shape[0], (3, *env.observation_space["pixels"].shape[1:])
        ring = (frame_shape, action_dim, cfg.frame_stack, cfg.nstep, cfg.discount)
        ring_bytes = len(members) * cfg.replay_size * sear.ReplayBuffer(1, *ring).bytes_per_transition
        where = experiment.replay_device(run, device, ring_bytes)  # every seed's ring on the GPU, or all on the host
        for m in members:
            torch.manual_seed(m.cfg.seed)  # each seed's networks, as its single run draws them
            m.rng = np.random.default_rng(m.cfg.seed)
            m.agent = parts.make_agent(m.cfg, action_dim, device)
            m.buffer = sear.ReplayBuffer(m.cfg.replay_size, *ring, device=where)
            with m.quiet():
                m.counters = m.rundir.start(m.agent, m.buffer, m.rng)
        if snapshot is not None:  # the group's torch stream continues where it stood
            experiment.set_rng_state(snapshot["rng"])
        group = SeedGroup([m.agent for m in members])
        loop(members, group, pool, members[0].cfg, run, parts)  # its action repeat set
        for m in members:
            with m.quiet():
                m.rundir.finish()
        print(f"done: {len(members)} seeds in {group_dir}")
        return group_dir
    except BaseException as e:
        stop_members(members, e, group_dir)
        raise
    finally:
        for m in members:
            m.rundir.release()
            if m.console:
                m.console.close()
        if pool is not None:
            pool.close()


def write_group_file(group_dir, members):
    runs = {str(m.cfg.seed): os.path.basename(m.rundir.path) for m in members}
    cli.write_atomically(os.path.join(group_dir, GROUP_FILE),
                         lambda f: json.dump({"seeds": [m.cfg.seed for m in members], "runs": runs}, f, indent=2),
                         mode="w")


def stop_members(members, error, group_dir):
    """Ctrl-C, SIGTERM, a storage error or a value that is not finite: every seed's run dir does what it
    does for a single run (a snapshot between episodes, one line of what stands); one line for all."""
    lines, said = [], {}
    for m in members:
        try:
            with m.quiet():
                m.rundir.stopped(type(error), error)
        except (cli.Interrupted, cli.StorageError, cli.NonFinite) as e:
            lines.append(str(e))
            said[m.rundir.path] = e
    if isinstance(error, (cli.StorageError, cli.NonFinite)) and said:  # the seed it happened to says what stands
        raise next((e for p, e in said.items() if p and p in str(error)), next(iter(said.values()))) from None
    if isinstance(error, KeyboardInterrupt) and lines:
        cause, code = cli.stop_cause(error)
        frames = sorted({m.rundir.files.snapshot_frame for m in members}, key=lambda f: -1 if f is None else f)
        stands = (f"every seed's snapshot holds frame {frames[0]}" if len(frames) == 1 and frames[0] is not None
                  else f"the seeds' last snapshots stand (frames {', '.join(map(str, frames))})")
        raise cli.Interrupted(f"{cause} at frame {members[0].rundir.frame}: {stands}; continue with: python sear.py "
                              f"--resume {group_dir}", code) from None


def loop(members, group, pool, cfg, run, parts):
    """The lockstep loop: train.train's, every seed at each step."""
    frame = members[0].counters.step * cfg.action_repeat
    clock, progress = time.monotonic(), Progress(members, cfg)
    while frame < cfg.frames:
        if all(not m.counters.mid_episode for m in members):
            members[0].rundir.safe_point()  # a first SIGTERM stops the group here, every seed between episodes
            if parts.eval_due(frame, members[0].counters.last_eval_frame, cfg.eval_every):
                evaluate_group(members, pool, cfg, parts.Episode, progress)
                members[0].rundir.safe_point()  # after an evaluation a SIGTERM cut short: redone on resume
        for i, m in enumerate(members):
            if not m.counters.mid_episode:
                m.counters.mid_episode = True
                m.obs, _ = pool.envs[i]["train"].reset(seed=experiment.episode_seed(m.cfg.seed, m.counters.episode))
                m.buffer.add_first(m.obs)
                m.ep = [0.0, 0, False]
        if parts.eval_due(frame, members[0].counters.last_eval_frame, cfg.eval_every):  # inside an episode
            evaluate_group(members, pool, cfg, parts.Episode, progress)
        actions = {i: m.agent.act(m.obs["pixels"], m.obs["mask"], m.counters.step, eval_mode=False)
                   for i, m in enumerate(members)}
        c = members[0].counters
        if (frame >= cfg.seed_frames and c.step % cfg.update_every == 0
                and all(m.buffer.can_sample() and len(m.buffer) >= cfg.seed_frames // cfg.action_repeat
                        for m in members)):
            metrics = group.update([m.buffer.sample(cfg.batch_size, m.rng) for m in members], c.step)
            for m, mine in zip(members, metrics):
                m.rundir.log_update(mine)
        results = pool.step_all("train", actions)
        for i, m in enumerate(members):
            obs, reward, terminated, truncated, info = results[i]
            m.buffer.add(actions[i], reward, terminated, obs)
            m.obs, m.counters.step = obs, m.counters.step + 1
            m.ep = [m.ep[0] + reward, m.ep[1] + 1, m.ep[2] or bool(info.get("success", False))]
            if terminated or truncated:
                with m.quiet():
                    m.rundir.log_episode(*m.ep, info)
                m.counters.episode, m.counters.mid_episode = m.counters.episode + 1, False
                progress.returns[i] = m.ep[0]
            else:
                with m.quiet():
                    m.rundir.show_step(m.ep[1])
        frame = members[0].counters.step * cfg.action_repeat
        progress.show(frame)
        if (frame < cfg.frames and all(not m.counters.mid_episode for m in members)
                and time.monotonic() - clock >= 60 * run.snapshot_minutes):
            for m in members:
                with m.quiet():
                    m.rundir.snapshot()
            clock = time.monotonic()
    if members[0].counters.last_eval_frame != frame:  # the budget ends with an evaluation at its last frame
        evaluate_group(members, pool, cfg, parts.Episode, progress)
        members[0].rundir.safe_point()  # cut short by a SIGTERM: the snapshot's resume evaluates again


def evaluate_group(members, pool, cfg, Episode, progress):
    """train.evaluate for every seed, their episodes side by side (the same reset seeds as a single run's)."""
    watches = []
    for i, m in enumerate(members):
        with m.quiet():
            watches.append(m.rundir.start_eval(pool.envs[i]["eval"]))
    tasks = experiment.eval_tasks(watches[0], members[0].cfg)
    episodes = [[] for _ in members]
    for e, task in enumerate(tasks):
        if members[0].rundir.stop_pending():  # a first SIGTERM: the evaluation stops at an episode end
            break
        obs = {}
        for i, (m, watch) in enumerate(zip(members, watches)):
            obs[i], _ = watch.reset(seed=experiment.episode_seed(m.cfg.seed + experiment.EVAL_SEED, e),
                                    options=None if task is None else {"task": task})
        running = {i: [0.0, False] for i in range(len(members))}  # return, success
        while running:
            actions = {i: members[i].agent.act(obs[i]["pixels"], obs[i]["mask"], members[i].counters.step,
                                               eval_mode=True) for i in running}
            for i, action in actions.items():
                env = watches[i].env
                if isinstance(env, RemoteEnv):
                    env.send_step(action)
            for i in list(running):
                obs[i], reward, terminated, truncated, info = watches[i].step(actions[i])
                running[i] = [running[i][0] + reward, running[i][1] or bool(info.get("success", False))]
                if terminated or truncated:
                    episodes[i].append(Episode(running[i][0], running[i][1] if "success" in info else None, task))
                    del running[i]
        progress.say(f"eval {e + 1}/{len(tasks)} done")
    for m, mine in zip(members, episodes):
        with m.quiet():
            done = m.rundir.end_eval(mine)  # False: a SIGTERM cut it short, redone on resume
        if done:
            m.counters.last_eval_frame = m.counters.step * cfg.action_repeat
    if all(len(mine) == len(tasks) for mine in episodes):
        progress.evaluated(episodes)


class Progress:
    """The group's one line: frame, frames/s of all seeds together, the seeds' last returns."""

    def __init__(self, members, cfg):
        self.members, self.cfg, self.returns = members, cfg, [float("nan")] * len(members)
        self.start, self.start_frame, self.last = time.monotonic(), members[0].counters.step * cfg.action_repeat, 0.0
        self.every = min(members[0].run.log_every, 1.0) if sys.stdout.isatty() else members[0].run.log_every

    def show(self, frame, force=False):
        now = time.monotonic()
        if not force and now - self.last < self.every:
            return
        self.last = now
        fps = len(self.members) * (frame - self.start_frame) / max(now - self.start, 1e-9)
        done = [r for r in self.returns if r == r]
        text = (f"frame {frame}/{self.cfg.frames} ({100 * frame / self.cfg.frames:.1f}%) | {fps:.1f} frames/s, "
                f"{len(self.members)} seeds" + (f" | last returns {min(done):.1f} to {max(done):.1f} "
                                                f"(mean {np.mean(done):.1f})" if done else ""))
        print(text, flush=True)

    def say(self, text):
        print(text, flush=True)

    def evaluated(self, episodes):
        means = [np.mean([e.ret for e in mine]) for mine in episodes]
        frame = self.members[0].counters.step * self.cfg.action_repeat
        print(f"eval @ frame {frame}: mean return over seeds {np.mean(means):.1f} (seeds: "
              + ", ".join(f"{m.cfg.seed}: {r:.1f}" for m, r in zip(self.members, means)) + ")", flush=True)


def check(cfg, run) -> None:
    """A configuration a seed group cannot run is one line (cli.ConfigError)."""
    why = refusal(cfg, run)
    if why:
        raise cli.ConfigError(why)
