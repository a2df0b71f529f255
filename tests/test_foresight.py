"""--method ef (foresight.py): the replay's windows, babbling, the rollout, compile, runs on every suite, with
--drm, a resume, the `masks` grid; and the released agent (github.com/ego-foresight/efrl, agents/drqv2ef.py) on
the same weights and batches: losses, gradients and parameters after a few updates, which needs
SEAR_EF_REFERENCE to name a checkout or a git mirror of it (its replay_buffer.py: the same windows)."""
import copy

import numpy as np
import pytest
import torch

from harness import cli
from methods import foresight
import sear
import sweep
import train
from tests import reference
from tests.test_cli import ROOT, TINY, only_run_dir, rows, run, straight_and_resumed
from tests.test_sear import grads
from tests.test_speed import OPTIMISER_BREAKS, control

RELEASED_COMMIT = "7c316bf"  # the commit docs/foresight.md describes
FILES = ["agents/drqv2ef.py", "utils.py", *(f"models/{m}.py" for m in (
    "actor", "critic", "mlp", "encoder", "random_shifts_aug", "dcgan_unet_64", "time_distributed"))]
CONTEXT, HORIZON = 3, 10  # the release's context_steps and horizon: windows of 13 frames


def tiny_cfg(**kw):
    base = dict(method="ef", latent_dim=64, ef_agent_dim=8, hidden_dim=32, feature_dim=8, batch_size=6,
                frame_stack=3, action_repeat=2)
    return train.Config(**{**base, **kw})


def episode_frames(n_frames, action_dim, seed):
    """(B, n_frames, 3, 84, 84) uint8 frames with a bright square that moves (something to predict), and
    (B, n_frames, A) actions in [-1, 1]."""
    rng = np.random.default_rng(seed)
    b = tiny_cfg().batch_size
    frames = (rng.integers(0, 256, (b, n_frames, 3, 84, 84)) // 4).astype(np.uint8)
    for i in range(b):
        y, x = rng.integers(10, 50, 2)
        for t in range(n_frames):
            frames[i, t, :, y + t:y + t + 20, x:x + 20] = 200
    return frames, rng.uniform(-1, 1, (b, n_frames, action_dim)).astype(np.float32)


def window_batch(frames, actions, ahead, seed):
    """Our Window for a 13-frame window per sample: context frames 0-2 (the obs stack), the critic's action
    actions[3], next_obs frames 3-5 (n = 3), actions 3..12 and the frame `ahead` steps after frame 2."""
    rng = np.random.default_rng(seed + 1000)
    b = len(frames)
    stack = lambda f: f.reshape(b, -1, 84, 84)  # noqa: E731  (oldest RGB first, as the replay stacks them)
    masks = np.zeros((b, 3, 84, 84), np.uint8)  # EF renders no masks: the env's are zeros
    reward = rng.normal(size=(b, 1)).astype(np.float32)
    discount = np.full((b, 1), 0.99 ** 3, np.float32)
    return foresight.Window(stack(frames[:, :3]), masks, actions[:, 3], reward, discount, stack(frames[:, 3:6]), masks,
                       actions[:, 3:], frames[:, 2 + ahead], np.full((b, 1), ahead))


# ---------------------------------------------------------------- the replay's windows
def filled_buffer(lengths, window, capacity=200, shape=(3, 4, 4), action_dim=2):
    """A buffer holding episodes of `lengths` steps; each frame's pixels, action and reward hold its time t."""
    buffer = (foresight.WindowReplay(capacity, shape, action_dim, 3, 3, 0.99, window=window) if window else
              sear.ReplayBuffer(capacity, shape, action_dim, 3, 3, 0.99))
    t = 0
    for length in [*lengths, 0]:  # the last add_first closes the last episode
        buffer.add_first({"pixels": np.full((9, *shape[1:]), t % 256, np.uint8), "mask": np.zeros((3, *shape[1:]))})
        t += 1
        for _ in range(length):
            buffer.add(np.full(action_dim, t, np.float32), float(t), False,
                       {"pixels": np.full((9, *shape[1:]), t % 256, np.uint8), "mask": np.zeros((3, *shape[1:]))})
            t += 1
    return buffer


def test_windows_hold_the_next_actions_and_the_frame_ahead_and_never_cross_an_episode_start():
    buffer = filled_buffer([20, 6], window=10)  # episode 1: times 0..20, episode 2: 21..27
    actions, frame, ahead = buffer.windows(np.array([0, 5, 10, 21, 22]), 10, 4)
    # inside the episode: the actions that led to t+1 .. t+10, the frame at t+4
    assert actions[0, :, 0].tolist() == list(range(1, 11)) and frame[0].flatten()[0] == 4 and ahead[0] == 4
    assert actions[1, :, 0].tolist() == list(range(6, 16)) and frame[1].flatten()[0] == 9
    # episode 1 ends at 20: the steps past it repeat its last step, never episode 2's first (21)
    assert actions[2, :, 0].tolist() == [11, 12, 13, 14, 15, 16, 17, 18, 19, 20] and ahead[2] == 4
    assert actions[3, :, 0].tolist() == [22, 23, 24, 25, 26, 27, 27, 27, 27, 27] and ahead[3] == 4
    assert actions[4, :, 0].tolist() == [23, 24, 25, 26, 27, 27, 27, 27, 27, 27]
    assert frame[4].flatten()[0] == 26 and ahead[4] == 4
    actions, frame, ahead = buffer.windows(np.array([23, 24, 27]), 10, 9)  # an episode that ends sooner
    assert ahead[:, 0].tolist() == [4, 3, 0] and [int(f.flatten()[0]) for f in frame] == [27, 27, 27]


def test_a_windowed_replay_samples_the_same_starts_and_then_one_horizon_per_batch():
    """The starts are drawn as every method's (the common path), then `ahead` once for the batch with the same
    RNG: a buffer without a window draws the same starts; a resumed run continues the same draws."""
    plain, windowed = filled_buffer([30, 30], window=0), filled_buffer([30, 30], window=10)
    for seed in range(5):
        a, w = plain.sample(16, np.random.default_rng(seed)), windowed.sample(16, np.random.default_rng(seed))
        assert isinstance(w, foresight.Window) and not isinstance(a, foresight.Window)
        assert all(torch.equal(x, y) for x, y in zip(a, w[:len(sear.Batch._fields)]))
        rng = np.random.default_rng(seed)
        windowed.draw_starts(16, rng, 0)
        k = int(rng.integers(1, 11))
        times = w.obs[:, -3, 0, 0].long()  # the newest frame of each stack holds its time
        left = 30 - times % 31  # steps to the end of the episode (0..30, 31..61)
        assert torch.equal(w.ahead[:, 0], torch.minimum(torch.full_like(times, k), left)), seed  # one per batch
        assert torch.equal(w.frame_ahead[:, 0, 0, 0].long(), times + w.ahead[:, 0])
        assert w.actions_ahead.shape == (16, 10, 2)


@pytest.fixture(scope="module")
def released(tmp_path_factory):
    """The released drqv2ef.py with its models and utils (and replay_buffer.py), imported under names of their own."""
    folder = reference.materialise("SEAR_EF_REFERENCE", "ego-foresight/efrl", RELEASED_COMMIT,
                                   [*FILES, "replay_buffer.py"], tmp_path_factory.mktemp("ef_released"))
    agent = reference.load(folder, "agents/drqv2ef.py", "ef_released")
    replay = reference.load(folder, "replay_buffer.py", "ef_released_replay")
    return agent, replay


def test_the_released_replay_draws_the_same_windows(released):
    """Its _sample at every start it can draw (idx_ext) against ours at the same start: the context is our
    obs stack, its extended frames 3..12 and actions 3..12 are our window, its critic transition is ours."""
    _, replay = released
    length, shape = 40, (3, 4, 4)
    buffer = filled_buffer([length], window=HORIZON, shape=shape)
    stacks = [np.stack([np.full(shape, max(i - 2 + k, 0), np.uint8) for k in range(3)]) for i in range(length + 1)]
    episode = {"observation.pixels": np.stack(stacks), "reward": np.arange(length + 1, dtype=np.float32),
               "discount": np.ones(length + 1, np.float32),
               "action": np.stack([np.full(2, i, np.float32) for i in range(length + 1)])}
    theirs = replay.ReplayBuffer(None, 10**6, 1, 3, 0.99, 10**9, True, False, CONTEXT, HORIZON, True)
    theirs._episode_fns, theirs._episodes, theirs._samples_since_last_fetch = ["ep"], {"ep": episode}, 0
    for idx_ext in range(1, length - (CONTEXT + HORIZON) + 2):
        randint = np.random.randint
        np.random.randint = lambda lo, hi, idx_ext=idx_ext: idx_ext - 1
        try:
            extended, action, reward, discount, next_obs = theirs._sample()
        finally:
            np.random.randint = randint
        t = idx_ext + 1  # the critic's obs: the context's newest frame
        ours = buffer.transitions(np.array([t]))
        actions, frame, ahead = buffer.windows(np.array([t]), HORIZON, HORIZON)
        assert np.array_equal(extended["pixels"][:3].reshape(9, *shape[1:]), ours.obs[0].numpy())
        assert np.array_equal(extended["action"][CONTEXT:], actions[0].numpy())
        assert np.array_equal(extended["pixels"][-1], frame[0].numpy()) and ahead.item() == HORIZON
        assert np.array_equal(action, ours.action[0].numpy()) and reward.item() == pytest.approx(ours.reward.item())
        assert np.array_equal(next_obs["pixels"].reshape(9, *shape[1:]), ours.next_obs[0].numpy())
        for j in range(CONTEXT, CONTEXT + HORIZON):  # every horizon they draw: the same target frame
            assert np.array_equal(extended["pixels"][j], buffer.windows(np.array([t]), HORIZON, j - 2)[1][0].numpy())


# ---------------------------------------------------------------- babbling, the rollout
def test_babbling_for_the_first_agent_steps_of_training_only(device):
    """ForesightAgent.act: while training and step < --ef-babbling-steps, every action entry uniform
    in +-4 clipped to +-1, from the agent's generator; from then on sear.Agent's action, and in
    evaluation the policy's mean, babbling or not."""
    agent = train.make_agent(tiny_cfg(ef_babbling_steps=100, exploration_steps=0), 2, device)
    assert isinstance(agent, foresight.ForesightAgent)
    agent.rng.manual_seed(0)
    obs = np.zeros((9, 84, 84), np.uint8)

    def actions(n, step, eval_mode=False):
        return torch.stack([agent.act(obs, None, step, eval_mode) for _ in range(n)]).cpu().numpy()
    babbled = actions(1500, step=99)
    assert np.abs(babbled).max() == 1.0
    # +-4 clipped: 3/8 at each bound, uniform in between
    assert (np.abs(babbled) == 1.0).mean() == pytest.approx(0.75, abs=0.03)
    inside = babbled[np.abs(babbled) < 1]
    assert np.histogram(inside, bins=4, range=(-1, 1))[0].min() > 0.75 * len(inside) / 4
    # the last babbling step is over: sear.Agent's action, the same draws
    state = agent.rng.get_state()
    after = agent.act(obs, None, step=100, eval_mode=False)
    agent.rng.set_state(state)
    assert torch.equal(after, sear.Agent.act(agent, obs, None, 100, False))
    after = actions(20, step=100)
    assert (np.abs(after) < 1).all() and len(np.unique(after)) > 1  # the actor's noisy sample
    mean = actions(2, step=0, eval_mode=True)  # evaluation: the policy's mean
    assert np.array_equal(mean[0], mean[1]) and (np.abs(mean) < 1).all()


def test_the_rollout_is_the_release_loop_in_values_and_gradients(device):
    """`ahead` steps of the MLP on the agent part, the scene part untouched: the masked full-horizon rollout
    equals an explicit loop per sample, and the gradient reaches both parts of the latent."""
    torch.manual_seed(0)
    cfg = tiny_cfg()
    agent = train.make_agent(cfg, 2, device)
    aux, b = agent.aux, 4
    latent = torch.randn(b, cfg.latent_dim, device=device, requires_grad=True)
    ahead = torch.tensor([[1.0], [4.0], [10.0], [0.0]], device=device)
    actions = torch.rand(b, HORIZON, 2, device=device) * 2 - 1
    target = torch.rand(b, 3, 84, 84, device=device) * 255
    fields = dict(zip(sear.Batch._fields, [None] * 7))
    batch = foresight.Window(**fields, actions_ahead=actions, frame_ahead=target, ahead=ahead)
    loss, m = aux(latent, None, None, batch=batch)
    loss.backward()
    grad, latent2 = latent.grad.clone(), latent.detach().clone().requires_grad_(True)
    frames = []
    for i in range(b):
        h = latent2[i:i + 1, :cfg.ef_agent_dim]
        for k in range(int(ahead[i])):
            h = aux.mlp(torch.cat([h, actions[i:i + 1, k]], 1))
        frames.append(torch.cat([h, latent2[i:i + 1, cfg.ef_agent_dim:]], 1))
    frame = aux.decoder(torch.cat(frames)[:, :, None, None])  # one batch: BatchNorm's statistics as above
    loop = ((frame.clamp(0, 1) - target / 255) ** 2).flatten(1).sum(1).mean()
    loop.backward()
    assert m["ef_loss"].item() == pytest.approx(loop.item(), rel=1e-5) and m["ef_ahead"].item() == 3.75
    torch.testing.assert_close(grad, latent2.grad, rtol=1e-4, atol=1e-6)
    assert grad[:, :cfg.ef_agent_dim].abs().sum() > 0 and grad[:, cfg.ef_agent_dim:].abs().sum() > 0


# ---------------------------------------------------------------- against the released code
def released_agent(module, cfg):
    return module.DrQV2EfAgent(
        obs_shape=(3, 3, 84, 84), action_shape=(2,), device=torch.device("cpu"), lr=cfg.lr,
        feature_dim=cfg.feature_dim, hidden_dim=cfg.hidden_dim, critic_target_tau=cfg.critic_tau,
        num_expl_steps=cfg.exploration_steps, update_every_steps=cfg.update_every,
        stddev_schedule=f"linear({cfg.std_start},{cfg.std_end},{cfg.std_steps})", stddev_clip=cfg.std_clip,
        use_tb=True, context_steps=CONTEXT, hs_dim=cfg.latent_dim, ha_dim=cfg.ef_agent_dim,
        num_babbling_steps=cfg.ef_babbling_steps, rec_loss_weight=cfg.ef_coef, batch_size=cfg.batch_size,
        horizon=cfg.ef_horizon)


def pairs(theirs, ours):
    return (("encoder", theirs.encoder, ours.encoder), ("mlp", theirs.mlp, ours.aux.mlp),
            ("decoder", theirs.decoder, ours.aux.decoder), ("actor", theirs.actor, ours.actor),
            ("critic", theirs.critic, ours.critic), ("critic target", theirs.critic_target, ours.critic_target))


class Patched:
    """A module for the released code to use in place of `module`, with some of its names replaced."""

    def __init__(self, module, **names):
        self.module, self.names = module, names

    def __getattr__(self, name):
        return self.names[name] if name in self.names else getattr(self.module, name)


def test_same_losses_gradients_and_weights_as_the_released_agent(released):
    """Three updates at horizons 1, 5 and 10 (their j = 3, 7, 12) from the same weights: the losses, the gradients
    of encoder, MLP, decoder and actor at every update, and every weight and BatchNorm statistic after them, to
    float32 rounding (the first update to the bit). Our convolutions run in the contiguous layout here, as
    theirs: in the run's NHWC layout oneDNN sums the convolutions' weight gradients in another order, and
    with EF's pixel-summed loss (~2e3) those sums cancel to 1e-3 of their terms, so they agree to 1e-3 only.
    The largest differences are printed (gradients relative to each tensor's largest entry)."""
    module, _ = released
    cfg = tiny_cfg(std_steps=100_000)
    torch.manual_seed(0)
    ours = train.make_agent(cfg, 2, torch.device("cpu"))
    for net in (ours.encoder, ours.aux):
        net.to(memory_format=torch.contiguous_format)
    with contextlib_quiet():
        theirs = released_agent(module, cfg)
    with torch.no_grad():  # their networks get our weights, tensor by tensor in order (buffers too)
        for name, t, o in pairs(theirs, ours):
            for (kt, vt), (ko, vo) in zip(t.state_dict().items(), o.state_dict().items(), strict=True):
                assert vt.shape == vo.shape, (name, kt, ko)
                vt.copy_(vo)
    frames = torch.rand(6, 3, 3, 84, 84) * 255
    torch.manual_seed(0)
    their_shift = theirs.aug(frames)
    torch.manual_seed(0)
    assert (their_shift - SearGrid()(frames)).abs().max() < 0.002  # the only difference: the grid's rounding
    theirs.aug = SearGrid()
    worst = {}

    def note(key, value):
        worst[key] = max(worst.get(key, 0.0), value)
    for update, ahead in enumerate((1, 5, 10)):
        frames, actions = episode_frames(CONTEXT + HORIZON, 2, seed=update)
        batch = window_batch(frames, actions, ahead, seed=update)
        step = 10_000 + 2 * update  # an update step (update_every 2), after babbling
        ours.rng.manual_seed(update)  # the same shifts and action noise, drawn in the same order
        mine = ours.update(batch, step)
        stepped = [p for opt in (ours.model_opt, ours.actor_opt) for g in opt.param_groups
                   for p in g["params"]]
        # each step's gradient, left on .grad
        grad = dict(zip(stepped, grads(stepped), strict=True))
        torch.manual_seed(update)
        module.np = Patched(np, random=Patched(np.random, randint=lambda lo, hi: ahead + 2))  # their j
        replay = iter([({"pixels": torch.as_tensor(frames), "action": torch.as_tensor(actions)}, batch.action,
                        batch.reward, batch.discount, {"pixels": torch.as_tensor(frames[:, 3:6])})])
        their = theirs.update(replay, step)
        for mine_key, their_key in (("critic_loss", "critic_loss"), ("ef_loss", "reconstruction_loss"),
                                    ("actor_loss", "actor_loss")):
            assert mine[mine_key].item() == pytest.approx(their[their_key], rel=1e-6), (update, mine_key)
            note(f"{mine_key} (relative)", abs(mine[mine_key].item() / their[their_key] - 1))
        assert mine["ef_ahead"].item() == ahead
        for name, t, o in pairs(theirs, ours)[:4]:  # their critic's grads also hold the actor's (discarded)
            for pt, po in zip(t.parameters(), o.parameters(), strict=True):
                scale = pt.grad.abs().max().item()
                torch.testing.assert_close(pt.grad, grad[po], rtol=1e-5, atol=1e-5 * scale, msg=f"{name} grad {update}")
                note(f"{name} gradient", (pt.grad - grad[po]).abs().max().item() / scale)
                assert update or torch.equal(pt.grad, grad[po]), name  # the first update: to the bit
    for name, t, o in pairs(theirs, ours):
        for (k, vt), vo in zip(t.state_dict().items(), o.state_dict().values(), strict=True):
            torch.testing.assert_close(vt, vo, rtol=1e-5, atol=1e-6, msg=f"{name}.{k} after 3 updates")
            note(f"{name} weights", (vt.double() - vo.double()).abs().max().item())
    assert ours.aux.decoder[1].num_batches_tracked == 3  # BatchNorm in train mode, its statistics moved
    print("\nlargest differences against the released agent:", ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))


class SearGrid:
    """Their RandomShiftsAug's interface (5-D (B, T, 3, H, W), the same shift for every frame, `repeat_last`) and
    its draw, on sear.random_shift's grid arithmetic. Their grid adds shift * (2 / 92), ours (shift * 2) / 92:
    up to 0.002 grey levels apart at a pixel (checked in the test), which a summed pixel loss of ~2e3 turns
    into gradients 4e-4 apart and Adam into lr-sized steps on near-zero gradients; the rest compares to
    float32 rounding once the grids are the same."""

    def __call__(self, x, repeat_last=False):
        if not repeat_last:
            self.shift = torch.randint(0, 9, (len(x), 1, 1, 2), dtype=x.dtype)  # their draw, as they draw it
        return sear.random_shift(x.flatten(1, 2), shift=self.shift).view_as(x)


def contextlib_quiet():
    """The released constructor prints parameter counts: kept off the test's output."""
    import contextlib
    import io
    return contextlib.redirect_stdout(io.StringIO())


# ---------------------------------------------------------------- compile, runs, resume, grid
@pytest.mark.skipif(cli.cxx_compiler() is None, reason="inductor's CPU kernels need a C++ compiler")
def test_compiled_update_equals_the_plain_one_at_every_horizon(device):
    """--compile on EF (torch.compile(agent.learn)): the rollout over every horizon, BatchNorm's
    statistics and the Window batch are compiled at the first update and never again (the same
    graphs for every horizon), breaking the graph only where torch's optimisers and backward() do
    (tests/test_speed.py); on the CPU every update's metrics equal the plain update's within the
    bound below, which the plain update with lr x 1.01 (tests/test_speed.py's control) fails."""
    import torch._dynamo.utils
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    cfg = tiny_cfg(batch_size=4)
    torch.manual_seed(0)
    plain = train.make_agent(cfg, 2, device)
    compiled = copy.deepcopy(plain)
    compiled.learn = torch.compile(compiled.learn)  # what speed_up does for --compile
    agents = {"plain": plain, "compiled": compiled,
              "control": control(plain, "control: lr x 1.01")}
    metrics, graphs = {name: [] for name in agents}, []
    for i, ahead in enumerate((3, 10, 1)):
        frames, actions = episode_frames(CONTEXT + HORIZON, 2, seed=i)
        batch = window_batch(frames[:4], actions[:4], ahead, seed=i)
        for name, agent in agents.items():
            agent.rng.manual_seed(100 + i)
            metrics[name].append(agent.update(batch, step=5_000 + 2 * i))
        graphs.append(torch._dynamo.utils.counters["stats"]["unique_graphs"])
        assert all(torch.isfinite(v).all() for v in metrics["compiled"][-1].values())

    def apart(name):
        """The metrics that differ from the plain update's by more than the bound. EF's pixel-summed
        loss (~2e3) makes the compiled convolutions' rounding a part in 1e3 of their gradients,
        which Adam turns into lr-sized steps: a q near 0 then moves by ~2e-5 after two updates."""
        pairs = enumerate(zip(metrics[name], metrics["plain"]))
        return [(i, k) for i, (got, want) in pairs for k in want
                if float(got[k]) != pytest.approx(float(want[k]), rel=1e-4, abs=1e-4)]
    # on CUDA no bound has been measured: there the update runs, finite, in the same graphs
    if device.type == "cpu":
        assert not apart("compiled") and apart("control"), (apart("compiled"), apart("control"))
    assert graphs[0] > 0 and graphs[-1] == graphs[0], graphs  # every horizon: the same graphs
    breaks = list(torch._dynamo.utils.counters["graph_break"])
    assert all(any(where in reason for where in OPTIMISER_BREAKS) for reason in breaks), breaks


EF_TINY = [*TINY, "--ef-horizon", "3", "--ef-babbling-steps", "10"]  # 8-step episodes hold 3-step windows


@pytest.mark.parametrize("env_name", ["walker-walk", "walker-walk-distracting", "metaworld-door-open",
                                      "kitchen-kettle", "adroit-door"])
def test_smoke_run_on_every_suite(env_name, tmp_path):
    r = run(["--env", env_name, "--method", "ef", *EF_TINY, "--frames", "32", "--seed-frames", "8",
             "--eval-every", "100", "--max-episode-steps", "6"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert run_dir.name.startswith(f"{env_name}__ef__")
    train_rows = rows(run_dir / "train.csv")
    assert train_rows[-1]["ef_loss"] != "" and float(train_rows[-1]["ef_ahead"]) > 0
    assert (run_dir / "snapshot.pt").exists() and rows(run_dir / "eval.csv")


def test_with_drm_and_a_plot(tmp_path):
    r = run(["--env", "walker-walk", "--method", "ef", "--drm", *EF_TINY, "--frames", "32", "--eval-every", "16"],
            tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert run_dir.name.startswith("walker-walk__ef+drm__")
    last = rows(run_dir / "train.csv")[-1]
    assert last["ef_loss"] != "" and last["dormant_ratio"] != ""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, str(ROOT / "plot.py"), str(tmp_path / "runs"), "--out",
                        str(tmp_path / "c.png")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "c.png").exists()


def test_resume_replays_exactly_what_an_uninterrupted_run_does(tmp_path):
    """48 frames + --resume to 80 equal 80 frames in one go: the windows' horizons come from the
    saved sample RNG, babbling from the agent's generator (saved with it), BatchNorm's statistics
    from the snapshot."""
    common = ["--env", "walker-walk", "--method", "ef", "--seed", "5", "--save-buffer", *EF_TINY]
    straight_dir, split_dir, _ = straight_and_resumed(common, tmp_path)
    cols = ["frame", "return", "critic_loss", "actor_loss", "ef_loss", "ef_ahead"]
    table = lambda d, name, c: [[r[k] for k in c] for r in rows(d / name)]  # noqa: E731
    assert table(split_dir, "train.csv", cols) == table(straight_dir, "train.csv", cols)
    assert table(split_dir, "eval.csv", ["frame", "return"]) == table(straight_dir, "eval.csv", ["frame", "return"])
    assert rows(split_dir / "train.csv")[-1]["ef_loss"] != ""
    a = torch.load(straight_dir / "snapshot.pt", weights_only=False)["agent"]
    b = torch.load(split_dir / "snapshot.pt", weights_only=False)["agent"]
    for part in ("encoder", "aux"):
        assert all(torch.equal(v, b[part][k]) for k, v in a[part].items()), part
    assert a["aux"]["decoder.1.num_batches_tracked"] > 0  # BatchNorm's statistics moved, and came back


def test_flags_and_the_masks_grid():
    argv = ["--env", "metaworld-door-open", "--method", "ef"]
    cfg = cli.parse_args(argv, train.Config, train.METHODS)[0]
    assert (cfg.ef_agent_dim, cfg.ef_horizon, cfg.ef_coef, cfg.ef_babbling_steps) == (32, 10, 1.0, 12_500)
    assert not train.METHODS["ef"].uses_mask and train.METHODS["ef"].encoder == "pooled"
    args, unknown = sweep.build_parser().parse_known_args(["--grid", "masks", "--seeds", "1"])
    _, specs, grid = sweep.plan(args, unknown)
    assert {s.env for s in specs} == {"walker-walk-distracting", "metaworld-door-open"}
    assert list(dict.fromkeys(s.variant for s in specs)) == ["sear", "ef", "drq"]
    assert sorted(sweep.GRIDS["masks"].seeds) == [1, 2, 3, 4, 5] and {s.frames for s in specs} == {2_500_000}
    ef = next(s for s in specs if s.variant == "ef")
    assert ef.args[ef.args.index("--latent-dim") + 1] == "2048"  # the release's hs_dim
    ring = dict(capacity=10, frame_shape=(3, 84, 84), action_dim=2, frame_stack=3, nstep=3,
                discount=0.99)
    replay = train.make_replay(cfg, **ring)  # its replay samples windows of --ef-horizon steps
    assert isinstance(replay, foresight.WindowReplay) and replay.window == cfg.ef_horizon
    sear_cfg = train.Config(env="metaworld-door-open", latent_dim=64, hidden_dim=32)
    assert type(train.make_replay(sear_cfg, **ring)) is sear.ReplayBuffer
    assert type(train.make_agent(sear_cfg, 2, torch.device("cpu"))) is sear.Agent
