"""Unit tests of sear.py's pieces: networks, losses (Eq. 4-6), augmentation, replay buffer."""
import io
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from harness import cli
from harness import experiment, speed
import sear
import train


def small_cfg(**kw):
    base = dict(latent_dim=64, hidden_dim=32, feature_dim=8, batch_size=4, frame_stack=3,
                action_repeat=2)
    base.update(kw)
    return train.Config(**base)


def fake_batch(n=4, stack=3, action_dim=2, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randint(0, 256, (n, 3 * stack, 84, 84), generator=g).float()
    mask = (torch.rand(n, stack, 84, 84, generator=g) > 0.7).float()
    action = torch.rand(n, action_dim, generator=g) * 2 - 1
    reward = torch.rand(n, 1, generator=g)
    discount = torch.full((n, 1), 0.99)
    next_obs = torch.randint(0, 256, (n, 3 * stack, 84, 84), generator=g).float()
    next_mask = (torch.rand(n, stack, 84, 84, generator=g) > 0.7).float()
    return sear.Batch(*(x.to(device) for x in (obs, mask, action, reward, discount, next_obs, next_mask)))


# ---------------------------------------------------------------- networks
def test_encoder_shapes():
    x = torch.rand(2, 9, 84, 84) * 255
    enc = sear.PooledEncoder(9, 4096)
    assert enc.convs(x).shape == (2, 32, 35, 35)
    assert enc.pool(enc.convs(x)).shape == (2, 32, 8, 8)
    assert enc(x).shape == (2, 4096)
    assert sear.DrQEncoder(9)(x).shape == (2, 32 * 35 * 35)


@pytest.mark.parametrize("out_channels", [9, 3])
def test_decoders_return_exactly_84x84(out_channels):
    dec = sear.Decoder(2048, out_channels)
    assert dec(torch.randn(2, 2048)).shape == (2, out_channels, 84, 84)


# ---------------------------------------------------------------- losses
def test_mask_loss_equals_hand_computed_bce():
    logits = torch.tensor([[[[2.0, -1.0], [0.5, 0.0]]], [[[-3.0, 1.0], [0.0, 4.0]]]])
    target = torch.tensor([[[[1.0, 0.0], [0.0, 1.0]]], [[[0.0, 1.0], [1.0, 1.0]]]])
    per_sample = []
    for lg, tg in zip(logits.flatten(1).tolist(), target.flatten(1).tolist()):
        s = 0.0
        for x, t in zip(lg, tg):
            p = 1 / (1 + math.exp(-x))
            s += -(t * math.log(p) + (1 - t) * math.log(1 - p))
        per_sample.append(s)
    expected = sum(per_sample) / len(per_sample)  # summed over pixels, averaged over the batch
    assert sear.summed_bce(logits, target).item() == pytest.approx(expected, rel=1e-6)


def test_recon_loss_zero_for_perfect_reconstruction():
    cfg = small_cfg()
    aux = sear.SearAux(cfg.latent_dim, cfg.frame_stack, cfg.recon_coef, cfg.mask_coef)
    obs, mask = fake_batch()[:2]

    class Perfect(torch.nn.Module):
        def forward(self, z):
            return obs / 255.0 - 0.5

    aux.recon_decoder = Perfect()
    _, metrics = aux(torch.randn(4, cfg.latent_dim), obs, mask)
    assert metrics["recon_loss"] == 0.0
    assert sear.summed_mse(obs, obs + 1.0).item() == pytest.approx(9 * 84 * 84)  # summed, not averaged


def test_total_loss_is_critic_plus_c1_recon_plus_c2_mask(device):
    cfg = small_cfg(recon_coef=0.5, mask_coef=0.25)
    agent = sear.Agent(cfg, action_dim=2, device=device)
    batch = fake_batch(device=device)
    noise = agent.draw(len(batch.obs))
    obs_aug, mask_aug = sear.shift_together(batch.obs, batch.mask, noise.shift)
    loss, m = agent.joint_loss(agent.encoder(obs_aug), obs_aug, mask_aug, batch, 0, noise)
    expected = (m["critic_loss"] + 0.5 * m["recon_loss"] + 0.25 * m["mask_loss"]).item()  # the terms: 0-d tensors
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    assert m["recon_loss"] > 0 and m["mask_loss"] > 0


def test_paper_defaults():
    cfg = train.Config()
    assert (cfg.recon_coef, cfg.mask_coef) == (0.01, 0.0025)
    assert (cfg.batch_size, cfg.nstep, cfg.latent_dim, cfg.feature_dim, cfg.hidden_dim) == (256, 3, 4096, 50, 1024)
    assert (cfg.replay_size, cfg.seed_frames, cfg.critic_tau, cfg.lr) == (250_000, 4000, 0.01, 1e-4)


def grads(params) -> list:
    """The gradients an optimiser's step took: torch's Adam leaves them on .grad until the next
    zero_grad (which each update step calls before its backward)."""
    return [p.grad.detach().clone() for p in params]


def test_actor_loss_does_not_reach_encoder(device):
    cfg = small_cfg()
    agent = sear.Agent(cfg, action_dim=2, device=device)
    noise = agent.draw(4)
    latent, _ = agent.update_critic(fake_batch(device=device), 0, noise)
    encoder = [p.detach().clone() for p in agent.encoder.parameters()]
    encoder_grads = grads(agent.encoder.parameters())
    agent.update_actor(latent, agent.std(0), noise.actor)
    assert latent.grad_fn is None and all(torch.equal(a, b) for a, b in zip(encoder, agent.encoder.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(encoder_grads, grads(agent.encoder.parameters())))
    assert any(g.any() for g in grads(agent.actor.parameters()))


def test_actor_metrics_show_a_saturated_state_independent_actor(device):
    """actor_saturated counts action dims where float32 tanh is exactly +-1 (zero gradient);
    action_spread is the std of the mean action over the batch (0: the same action in every state)."""
    cfg = small_cfg()
    agent = sear.Agent(cfg, action_dim=2, device=device)
    latent = torch.randn(8, agent.encoder.repr_dim, device=device)
    fresh = agent.update_actor(latent, agent.std(0), agent.draw(8).actor)
    assert fresh["actor_saturated"] == 0.0 and fresh["action_spread"] > 0.0
    with torch.no_grad():  # a last layer pushed past tanh's float32 range, as in EXPERIMENTS rung 2
        agent.actor.policy[-1].weight.zero_()
        agent.actor.policy[-1].bias.copy_(torch.tensor([12.0, -12.0]))
    stuck = agent.update_actor(latent, agent.std(0), agent.draw(8).actor)
    assert stuck["actor_saturated"] == 1.0 and stuck["action_spread"] == 0.0
    names = [name for name, _ in agent.actor.named_parameters()]
    step = grads(agent.actor.parameters())
    policy = [g for name, g in zip(names, step) if name.startswith("policy.")]
    assert policy and all(not g.any() for g in policy)


def test_actor_update_computes_no_critic_gradient_and_takes_drqv2s_step(device):
    """The actor's step asks autograd for the actor's gradient alone: none is computed for the critic
    (DrQ-v2 computes it, then the next critic step drops it), and the actor's gradient is DrQ-v2's
    (its noise drawn from torch's stream: the same numbers handed to ours)."""
    cfg = small_cfg()
    agent = sear.Agent(cfg, action_dim=2, device=device)
    latent = torch.randn(8, agent.encoder.repr_dim, device=device)
    torch.manual_seed(1)
    dist = agent.actor(latent, 0.5)
    (-torch.min(*agent.critic(latent, dist.sample(clip=cfg.std_clip))).mean()).backward()
    expected = [p.grad.clone() for p in agent.actor.parameters()]
    assert all(p.grad is not None for p in agent.critic.parameters())  # what DrQ-v2 computes, then drops
    agent.critic.zero_grad(set_to_none=True)
    torch.manual_seed(1)
    noise = torch.randn(8, 2, device=device)  # what sample() drew above
    agent.cfg.std_start = 0.5  # linear_std at step 0: the std used above
    agent.update_actor(latent, agent.std(0), noise)
    for e, g in zip(expected, grads(agent.actor.parameters()), strict=True):  # the step's gradient
        torch.testing.assert_close(g, e)
    assert all(p.grad is None and p.requires_grad for p in agent.critic.parameters())


def test_critic_and_aux_losses_reach_encoder(device):
    cfg = small_cfg()
    agent = sear.Agent(cfg, action_dim=2, device=device)
    before = [p.detach().clone() for p in agent.encoder.parameters()]
    agent.update_critic(fake_batch(device=device), 0, agent.draw(4))
    assert any(not torch.equal(b, p) for b, p in zip(before, agent.encoder.parameters()))


def test_exploration_std_schedule():
    cfg = train.Config()
    assert sear.linear_std(cfg, 0) == pytest.approx(1.0)
    assert sear.linear_std(cfg, 250_000) == pytest.approx(0.55)
    assert sear.linear_std(cfg, 10**7) == pytest.approx(0.1)


# ---------------------------------------------------------------- augmentation
def test_random_shift_is_an_integer_translation_of_the_padded_image():
    x = torch.rand(2, 3, 84, 84)
    shift = torch.tensor([[[[3, 7]]], [[[0, 8]]]])  # (dx, dy) per sample
    out = sear.random_shift(x, pad=4, shift=shift)
    padded = torch.nn.functional.pad(x, (4,) * 4, mode="replicate")
    for i, (dx, dy) in enumerate([(3, 7), (0, 8)]):  # DrQ-v2's float32 grid: on the pixel centres to ~1e-5
        torch.testing.assert_close(out[i], padded[i, :, dy:dy + 84, dx:dx + 84], atol=1e-4, rtol=0)


def test_same_shift_moves_image_and_mask_identically():
    torch.manual_seed(0)
    obs = torch.randint(0, 256, (8, 9, 84, 84)).float()
    mask = (obs[:, [0, 3, 6]] > 127).float()  # a mask that is a function of the image
    obs_aug, mask_aug = sear.shift_together(obs, mask)
    assert not torch.equal(obs_aug, obs)
    assert torch.equal(mask_aug.round(), (obs_aug[:, [0, 3, 6]].round() > 127).float())
    assert torch.allclose(mask_aug, mask_aug.round(), atol=1e-4)  # still binary


# ---------------------------------------------------------------- replay buffer
def numpy(batch: sear.Batch) -> sear.Batch:
    """A sampled batch (tensors on the ring's device) as numpy arrays."""
    return sear.Batch._make(x.cpu().numpy() for x in batch)


def make_obs(time_id, episode, stack=3, terminal=False):
    """A fake observation whose newest frame encodes (time, episode) in its pixels."""
    frame = np.zeros((3, 84, 84), dtype=np.uint8)
    frame[0] = time_id % 256
    frame[1] = episode % 256
    mask = np.zeros((stack, 84, 84), dtype=np.uint8)
    mask[-1, : (time_id % 80) + 1, 0] = 1  # mask content also identifies the time
    return {"pixels": np.concatenate([np.zeros((3 * (stack - 1), 84, 84), np.uint8), frame]), "mask": mask}


def fill(buffer, episodes, action_dim=2):
    """episodes: list of (rewards, terminated). Returns per-time records [(episode, reward, first, term)]."""
    log, t = [], 0
    for e, (rewards, terminated) in enumerate(episodes):
        buffer.add_first(make_obs(t, e))
        log.append((e, 0.0, True, False))
        t += 1
        for k, r in enumerate(rewards):
            term = terminated and k == len(rewards) - 1
            buffer.add(np.full(action_dim, t / 1000, np.float32), r, term, make_obs(t, e))
            log.append((e, r, False, term))
            t += 1
    return log


def reference_episodes(log):
    """The log as DrQ-v2's ReplayBufferStorage stores it (replay_buffer.py add): one record per episode,
    its reset first (dummy reward 0, discount 1), then a step's reward and discount (0 at a termination);
    with the time of each observation in our ring."""
    episodes = []
    for time, (e, r, first, term) in enumerate(log):
        if first:
            episodes.append({"time": [], "reward": [], "discount": []})
        episodes[-1]["time"].append(time)
        episodes[-1]["reward"].append(np.float32(r))
        episodes[-1]["discount"].append(np.float32(0.0 if term else 1.0))
    return episodes


def reference_sample(episode, idx, n, gamma):
    """DrQ-v2's ReplayBuffer._sample at a given idx (1 <= idx <= len - n): the obs, next obs and action
    times in our ring, the n-step return and the bootstrap discount."""
    reward, discount = np.float32(0.0), np.float32(1.0)
    for i in range(n):
        reward += discount * episode["reward"][idx + i]
        discount *= episode["discount"][idx + i] * gamma
    return episode["time"][idx - 1], episode["time"][idx + n - 1], episode["time"][idx], reward, discount


def reference_distribution(log, n, finished):
    """{start time: probability} of DrQ-v2's draw over the first `finished` episodes of the log:
    random.choice of an episode, then idx = randint(0, len - n + 1) + 1 (the start is obs idx - 1).
    Episodes shorter than n, on which the official loader fails, are left out."""
    episodes = [ep for ep in reference_episodes(log)[:finished] if len(ep["time"]) - 1 >= n]
    return {ep["time"][idx - 1]: 1 / len(episodes) / (len(ep["time"]) - n)
            for ep in episodes for idx in range(1, len(ep["time"]) - n + 1)}


def test_nstep_returns_match_drqv2_and_termination_vs_truncation():
    """Every start DrQ-v2 can draw gives its sample: obs, action, n-step return, discount, next obs."""
    rng = np.random.default_rng(0)
    episodes = [(list(rng.normal(size=L)), term)
                for L, term in [(7, False), (3, True), (5, True), (1, False), (9, False)]]
    buf = sear.ReplayBuffer(1000, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.9)
    log = fill(buf, episodes)
    buf.add_first(make_obs(len(log), len(episodes)))
    starts = sorted(reference_distribution(log, 3, len(episodes)))
    obs, mask, action, ret, disc, next_obs, next_mask = numpy(buf.transitions(np.array(starts)))
    by_start = {reference_sample(ep, idx, 3, 0.9)[0]: reference_sample(ep, idx, 3, 0.9)
                for ep in reference_episodes(log) for idx in range(1, len(ep["time"]) - 2)}
    for i, l in enumerate(starts):
        _, next_time, action_time, r, g = by_start[l]
        assert ret[i, 0] == r and disc[i, 0] == g  # the same float32 arithmetic
        assert obs[i, -3].flat[0] == l % 256 and next_obs[i, -3].flat[0] == next_time % 256
        assert action[i, 0] == pytest.approx(action_time / 1000)
    # A terminated episode's last window does not bootstrap, a truncated one's does. Episode 0: reset at
    # t=0, 7 steps, truncated; 1: reset at 8, 3 steps, terminated; 2: reset at 12, 5 steps, terminated.
    assert disc[starts.index(4), 0] == pytest.approx(0.9 ** 3) and disc[starts.index(8), 0] == 0.0
    assert disc[starts.index(13), 0] == pytest.approx(0.9 ** 3) and disc[starts.index(14), 0] == 0.0
    assert 5 not in starts and 15 not in starts and 18 not in starts  # last n-1 steps; the 1-step episode


def numpy_transitions(buf, times):
    """The transitions of a ring as the host ring built them with numpy (np.unpackbits, float32 sums):
    the reference the ring's tensor code (on any device) is held to."""
    times, cap = np.asarray(times, np.int64), buf.capacity
    first, rewards, terminal = (getattr(buf, a).cpu().numpy() for a in ("first", "rewards", "terminal"))
    frames, masks, actions = (getattr(buf, a).cpu().numpy() for a in ("frames", "masks", "actions"))

    def stacked(t):
        idx = [t]
        for _ in range(buf.stack - 1):
            idx.append(np.where(first[idx[-1] % cap], idx[-1], idx[-1] - 1))
        idx = np.stack(idx[::-1], axis=1) % cap
        bits = np.unpackbits(masks[idx], axis=-1)[..., :84 * 84]
        return frames[idx].reshape(len(t), -1, 84, 84), bits.reshape(len(t), buf.stack, 84, 84)
    ret, gamma = np.zeros(len(times), np.float32), np.float32(1.0)
    for k in range(1, buf.nstep + 1):
        ret += gamma * rewards[(times + k) % cap]
        gamma *= np.float32(buf.gamma)
    discount = np.where(terminal[(times + buf.nstep) % cap], 0.0, gamma).astype(np.float32)
    return sear.Batch(*stacked(times), actions[(times + 1) % cap], ret[:, None], discount[:, None],
                      *stacked(times + buf.nstep))


def test_the_rings_batches_equal_a_numpy_ring_for_the_same_draws(device):
    """The ring keeps its slots as tensors on the run's device (the GPU's when it fits) and builds stacks,
    n-step returns and unpacked masks there: for the same draws its batches equal, value for value, what
    the host ring computed with numpy (wrapped ring, terminations, random masks and rewards)."""
    rng = np.random.default_rng(3)
    buf = sear.ReplayBuffer(57, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.97, device=device)
    obs = lambda: {"pixels": rng.integers(0, 256, (9, 84, 84), dtype=np.uint8),  # noqa: E731
                   "mask": rng.integers(0, 2, (3, 84, 84), dtype=np.uint8)}
    for episode in range(9):
        buf.add_first(obs())
        for k in range(int(rng.integers(4, 12))):
            buf.add(rng.uniform(-1, 1, 2).astype(np.float32), rng.normal(), bool(rng.random() < 0.1), obs())
    assert buf.t > buf.capacity and buf.frames.device.type == device.type
    times = buf.draw_starts(64, np.random.default_rng(0), max(0, buf.t - buf.capacity))
    for name, got, want in zip(sear.Batch._fields, buf.transitions(times), numpy_transitions(buf, times)):
        assert np.array_equal(got.cpu().numpy(), want), name


def test_stacks_never_cross_episodes_and_repeat_first_frame():
    episodes = [([1.0] * 4, False), ([1.0] * 1, True), ([1.0] * 6, False)]
    buf = sear.ReplayBuffer(100, (3, 84, 84), 2, frame_stack=3, nstep=1, discount=0.99)
    log = fill(buf, episodes)
    l = np.arange(len(log))
    pixels, masks = (x.numpy() for x in buf.stacked(torch.as_tensor(l)))
    for i in l:
        times = pixels[i, 0::3, 0, 0].astype(int)  # red channel = time of each stacked frame
        eps = pixels[i, 1::3, 0, 0].astype(int)
        assert (eps == log[i][0]).all(), f"stack at t={i} crosses an episode"
        start = max(j for j in range(i + 1) if log[j][2])
        expected = [max(i - 2, start), max(i - 1, start), i]
        assert list(times) == expected
        assert [int(m[:, 0].sum()) for m in masks[i]] == [(t % 80) + 1 for t in expected]  # masks unpack right


def test_sampling_only_valid_and_ring_never_serves_overwritten_frames():
    episodes = [([0.5] * 9, False)] * 6
    buf = sear.ReplayBuffer(25, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    log = fill(buf, episodes)
    oldest = len(log) - 25
    rng = np.random.default_rng(1)
    for _ in range(20):
        obs, *_ = numpy(buf.sample(16, rng))
        times = obs[:, 0::3, 0, 0].astype(int)
        assert (times >= oldest % 256).all()


def drawn(buf, n, seed=0):
    return buf.draw_starts(n, np.random.default_rng(seed), max(0, buf.t - buf.capacity))


def test_episodes_then_starts_are_drawn_with_drqv2s_frequencies():
    """Chi-square of 300k draws against DrQ-v2's distribution, enumerated from its rule
    (replay_buffer.py _sample): an episode uniformly, then a start whose n-step window lies in it. Here
    the 3-step episode is drawn as often as the 100-step one, 33 times more per start."""
    from scipy import stats
    lengths = [3, 40, 7, 100, 2, 33, 12]  # the 2-step episode has no whole 3-step window
    buf = sear.ReplayBuffer(400, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    log = fill(buf, [([1.0] * length, False) for length in [*lengths, 50]])  # then a running episode
    expected = reference_distribution(log, 3, len(lengths))
    starts = drawn(buf, 300_000)
    support = sorted(expected)
    assert set(starts.tolist()) == set(support)  # no start outside DrQ-v2's (running episode, last steps)
    counts = np.array([np.sum(starts == l) for l in support])
    p = np.array([expected[l] for l in support])
    assert stats.chisquare(counts, p * len(starts)).pvalue > 1e-3
    firsts = np.flatnonzero([r[2] for r in log])
    episode = np.searchsorted(firsts, starts, side="right") - 1
    per_episode = np.bincount(episode, minlength=len(lengths))[[0, 1, 2, 3, 5, 6]]
    assert stats.chisquare(per_episode).pvalue > 1e-3  # each episode with a window, equally often


def test_the_running_episode_is_never_drawn():
    buf = sear.ReplayBuffer(400, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    fill(buf, [([1.0] * 50, False)])
    assert not buf.can_sample()  # no episode has ended: DrQ-v2's loader has no file yet
    fill(buf, [([1.0] * 5, False), ([1.0] * 200, False)])  # 50 steps of the running episode were added first
    starts = drawn(buf, 20_000)
    assert buf.can_sample() and starts.min() == 0 and starts.max() == 51 + 5 - 3


def test_an_episodes_last_n_minus_1_steps_never_start_a_sample():
    buf = sear.ReplayBuffer(400, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    fill(buf, [([1.0] * 5, False), ([1.0] * 4, True), ([1.0] * 3, False), ([1.0] * 1, False)])
    # resets at 0, 6, 11, 15; the episode at 15 runs
    assert set(drawn(buf, 5000).tolist()) == {0, 1, 2, 6, 7, 11}


def test_a_wrapped_ring_draws_only_episodes_it_holds_whole():
    """Step by step through several wraps of a small ring: every sample's stacks and next obs lie in
    one episode whose reset is still in the ring (DrQ-v2 evicts whole episodes, oldest first)."""
    buf = sear.ReplayBuffer(60, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    rng, t, episode, resets = np.random.default_rng(0), 0, 0, {}
    for length in rng.integers(1, 25, size=30):
        resets[episode] = t
        buf.add_first(make_obs(t, episode))
        for _ in range(length):
            t += 1
            buf.add(np.zeros(2, np.float32), 1.0, False, make_obs(t, episode))
            if buf.can_sample():
                b = numpy(buf.sample(32, rng))
                ep = b.obs[:, 1, 0, 0].astype(int)
                for x in (b.obs, b.next_obs):
                    assert (x[:, 1::3, 0, 0] == ep[:, None]).all()  # one episode
                assert all(resets[e] >= buf.t - buf.capacity for e in ep.tolist())  # its reset not overwritten
        t += 1
        episode += 1
    assert buf.t > 5 * buf.capacity


@pytest.mark.parametrize("mid_episode", [False, True])
def test_a_saved_ring_loads_to_the_same_draws(tmp_path, mid_episode):
    """buffer.npz holds no episode index: it is rebuilt from the reset flags, to the same draws now and
    after the run goes on (exact resume), wrapped or not."""
    rng = np.random.default_rng(0)
    a = sear.ReplayBuffer(100, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    episodes = [([1.0] * int(n), False) for n in rng.integers(1, 30, size=12)]
    for ring_full in (False, True):
        fill(a, episodes[:4] if not ring_full else episodes)
        if mid_episode:
            a.add_first(make_obs(a.t, 99)), a.add(np.zeros(2, np.float32), 1.0, False, make_obs(a.t, 99))
        experiment.save_buffer(a, str(tmp_path / "buffer.npz"))
        b = sear.ReplayBuffer(100, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
        experiment.load_buffer(b, str(tmp_path / "buffer.npz"))
        assert (a.t > a.capacity) == ring_full
        for _ in range(2):  # now, and after an episode more
            assert a.can_sample() == b.can_sample()
            x, y = a.sample(64, np.random.default_rng(1)), b.sample(64, np.random.default_rng(1))
            assert all(torch.equal(u, v) for u, v in zip(x, y))
            for buf in (a, b):
                fill(buf, [([1.0] * 7, True)])
                buf.add_first(make_obs(buf.t, 98))


DRQV2 = os.environ.get("SEAR_DRQV2", "")  # a checkout of facebookresearch/drqv2, not part of this project


@pytest.mark.skipif(not os.path.isfile(os.path.join(DRQV2, "replay_buffer.py")),
                    reason="SEAR_DRQV2=<a checkout of facebookresearch/drqv2> not given")
def test_samples_and_their_frequencies_equal_the_official_drqv2_replay(tmp_path):
    """The official ReplayBuffer._sample (replay_buffer.py, one worker, every episode fetched) over episode
    files whose observations name (episode, step), and this ring over the same episodes: each official
    sample's action, n-step return and discount equal ours at its start, bit for bit, and the two
    draws' frequencies of (episode, start) agree (chi-square of the two samples)."""
    import importlib.util
    import random

    from scipy import stats
    spec = importlib.util.spec_from_file_location("drqv2_replay_buffer", os.path.join(DRQV2, "replay_buffer.py"))
    official = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(official)
    rng = np.random.default_rng(0)
    lengths, terminated = [3, 40, 7, 100, 5, 33, 12], [False, True, False, False, True, False, True]
    ours = sear.ReplayBuffer(400, (3, 1, 1), 1, frame_stack=3, nstep=3, discount=0.99)

    def step_obs(k):  # 1x1 frames that name the step in the episode
        return {"pixels": np.full((9, 1, 1), k, np.uint8), "mask": np.zeros((3, 1, 1), bool)}
    for e, (length, term) in enumerate(zip(lengths, terminated)):
        reward = np.concatenate([[0], rng.normal(size=length)]).astype(np.float32)[:, None]
        action = np.concatenate([[0], rng.uniform(-1, 1, size=length)]).astype(np.float32)[:, None]
        discount = np.ones((length + 1, 1), np.float32)
        discount[-1] = 0.0 if term else 1.0
        obs = np.stack([np.full(length + 1, e), np.arange(length + 1)], 1).astype(np.uint8)[:, :, None, None]
        np.savez(tmp_path / f"20260101T000000_{e}_{length}.npz", observation=obs, action=action, reward=reward,
                 discount=discount)
        ours.add_first(step_obs(0))
        for k in range(1, length + 1):
            ours.add(action[k], reward[k, 0], term and k == length, step_obs(k))
    ours.add_first(step_obs(0))  # the running episode: the official loader sees files only
    buffer = official.ReplayBuffer(tmp_path, 10 ** 6, 1, 3, 0.99, fetch_every=10 ** 9, save_snapshot=True)
    random.seed(0), np.random.seed(0)
    samples = [buffer._sample() for _ in range(40_000)]
    firsts = np.flatnonzero(ours.first[:ours.t].numpy())
    keys = [(int(o[0, 0, 0]), int(o[1, 0, 0])) for o, *_ in samples]  # (episode, start) of each official sample
    starts = np.array([firsts[e] + k for e, k in keys])
    batch = numpy(ours.transitions(starts))
    assert np.array_equal(batch.reward[:, 0], np.array([s[2][0] for s in samples]))
    assert np.array_equal(batch.discount[:, 0], np.array([s[3][0] for s in samples]))
    assert np.array_equal(batch.action, np.array([s[1] for s in samples]))
    assert [(int(o[0, 0, 0]), int(o[1, 0, 0])) for *_, o in samples] == [(e, k + 3) for e, k in keys]
    assert batch.obs[:, -3, 0, 0].tolist() == [k for _, k in keys]
    assert batch.next_obs[:, -3, 0, 0].tolist() == [k + 3 for _, k in keys]
    mine = drawn(ours, 40_000)
    support = sorted(set(starts.tolist()))
    assert set(mine.tolist()) == set(support)
    table = [[np.sum(x == l) for l in support] for x in (starts, mine)]
    assert stats.chi2_contingency(table).pvalue > 1e-3


def test_bytes_per_transition_within_target():
    buf = sear.ReplayBuffer(10, (3, 84, 84), 6, frame_stack=3, nstep=3, discount=0.99)  # walker: 6 actions
    assert buf.bytes_per_transition <= 22_100
    assert buf.masks.shape[1] == 882  # 84 * 84 bits


# ---------------------------------------------------------------- acting
def test_act_returns_bounded_action_and_rgbm_needs_mask(device):
    cfg = small_cfg()
    agent = sear.Agent(cfg, action_dim=3, device=device)
    pixels = np.random.randint(0, 256, (9, 84, 84), dtype=np.uint8)
    mask = np.zeros((3, 84, 84), dtype=np.uint8)
    a = agent.act(pixels, mask, step=10**6, eval_mode=False)
    # on the agent's device: the loop reads every seed's at once
    assert a.device.type == device.type
    a = a.cpu().numpy()
    assert a.shape == (3,) and a.dtype == np.float32 and np.all(np.abs(a) <= 1)
    rgbm = train.make_agent(small_cfg(method="rgbm"), action_dim=3, device=device)
    assert rgbm.encoder.convs[0].in_channels == 12
    with pytest.raises(ValueError, match="mask"):
        rgbm.act(pixels, None, step=0, eval_mode=True)


# ---------------------------------------------------------------- protocol
@pytest.mark.parametrize("action_repeat", [1, 2])
def test_exploration_std_counts_agent_steps_not_frames(action_repeat):
    """DrQ-v2's linear(1.0, 0.1, 500000) is evaluated at the agent step: 0.55 after 250k steps
    whatever the action repeat (250k frames at repeat 1, 500k frames at repeat 2)."""
    cfg = train.Config(action_repeat=action_repeat)
    assert cfg.std_steps == 500_000
    for step, std in [(0, 1.0), (100_000, 0.82), (250_000, 0.55), (500_000, 0.1), (10**7, 0.1)]:
        assert sear.linear_std(cfg, step) == pytest.approx(std)


def parse(argv):
    return cli.parse_args(argv, train.Config, train.METHODS)[0]


@pytest.mark.parametrize("env, steps", [
    ("walker-walk", 100_000), ("cup-catch", 100_000), ("cartpole-balance_sparse", 100_000),   # easy.yaml
    ("cheetah-run", 500_000), ("walker-run", 500_000), ("reacher-hard", 500_000),           # medium.yaml
    ("humanoid-run", 2_000_000),                                                            # hard.yaml
    ("fish-swim", 500_000),               # not in DrQ-v2's table: medium, as its default task
    ("walker-walk-distracting", 500_000), ("cup-catch-distracting", 500_000),   # the authors' distracting.yaml
    ("metaworld-door-open", 500_000), ("kitchen-kettle", 500_000), ("adroit-pen", 500_000),
    ("metaworld-mt10", 2_000_000)])
def test_exploration_schedule_per_task_as_drqv2(env, steps):
    """DrQ-v2's and the authors' cfgs/task/{easy,medium,hard}.yaml decay the std over 100k / 500k / 2M
    agent steps by task; the paper's Distracting Control tasks and the manipulation suites keep 500k,
    task sets 2M. Under both recipes; an explicit --std-steps wins."""
    for recipe in ("paper", "authors"):
        assert parse(["--env", env, "--recipe", recipe]).std_steps == steps
    assert parse(["--env", env, "--std-steps", "7"]).std_steps == 7


def test_recipe_paper_is_the_defaults_and_authors_follows_their_code(capsys):
    paper = parse(["--env", "walker-walk-distracting"])
    assert paper == train.Config(env="walker-walk-distracting")
    assert (paper.recon_coef, paper.mask_coef, paper.nstep, paper.batch_size) == (0.01, 0.0025, 3, 256)
    authors = parse(["--env", "walker-walk-distracting", "--recipe", "authors"])
    assert (authors.recon_coef, authors.mask_coef, authors.nstep, authors.batch_size) == (1.0, 0.25, 1, 512)
    assert authors.discount == 0.99 and authors.difficulty == "medium"
    assert "recon_coef=1.0" in capsys.readouterr().out  # the run says what the recipe changed
    other = parse(["--env", "cup-catch-distracting", "--recipe", "authors"])
    assert (other.nstep, other.batch_size) == (3, 256)  # walker-only values stay off elsewhere
    mw = parse(["--env", "metaworld-door-open", "--recipe", "authors"])
    assert mw.discount == pytest.approx(0.99 ** 3) and mw.mask_downsample == "stride"
    kitchen = parse(["--env", "kitchen-kettle", "--recipe", "authors"])
    assert kitchen.discount == pytest.approx(0.99 ** 2)
    humanoid = parse(["--env", "humanoid-walk", "--recipe", "authors"])
    assert (humanoid.lr, humanoid.feature_dim, humanoid.replay_size) == (8e-5, 100, 250_000)  # DrQ-v2's hard cfgs
    quadruped = parse(["--env", "quadruped-run", "--recipe", "authors"])
    assert (quadruped.lr, quadruped.feature_dim, quadruped.replay_size) == (1e-4, 50, 100_000)
    assert parse(["--env", "humanoid-walk"]).lr == 1e-4   # the paper's table
    explicit = parse(["--env", "walker-walk", "--recipe", "authors", "--nstep", "3", "--recon-coef", "0.5"])
    assert (explicit.nstep, explicit.recon_coef, explicit.batch_size) == (3, 0.5, 512)  # flags win
    with pytest.raises(cli.ConfigError, match="--recipe"):
        parse(["--recipe", "mine"])


def test_prefetcher_delivers_the_batches_direct_sampling_would(device):
    """The background sampler draws from the same RNG in the same order (on CUDA: through pinned memory
    and its own stream)."""
    buf = sear.ReplayBuffer(100, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    rng = np.random.default_rng(0)
    for ep in range(3):
        buf.add_first({"pixels": rng.integers(0, 256, (9, 84, 84), dtype=np.uint8),
                       "mask": rng.integers(0, 2, (3, 84, 84), dtype=np.uint8)})
        for _ in range(20):
            buf.add(rng.uniform(-1, 1, 2), rng.normal(), False,
                    {"pixels": rng.integers(0, 256, (9, 84, 84), dtype=np.uint8),
                     "mask": rng.integers(0, 2, (3, 84, 84), dtype=np.uint8)})
    direct = [buf.sample(8, r) for r in [np.random.default_rng(5)] for _ in range(3)]
    pre = speed.Prefetcher(buf, 8, np.random.default_rng(5), device, margin=4)
    fetched = [pre.next() for _ in range(3)]
    pre.close()
    assert not pre.thread.is_alive()
    for d, f in zip(direct, fetched):
        assert all(y.device.type == device.type for y in f)  # cuda:0 where the fixture says cuda
        assert all(torch.equal(x.to(y.device), y) for x, y in zip(d, f))


def test_prefetcher_keeps_clear_of_the_oldest_slots_of_a_full_ring():
    """While the background sampler reads, the loop overwrites the oldest slots of a full ring: the
    prefetched batches come from episodes that start `margin` slots after the oldest, where direct
    sampling takes any episode still whole in the ring."""
    buf = sear.ReplayBuffer(30, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    fill(buf, [([0.5] * 9, False)] * 8)  # 80 slots into 30: episodes at 0, 10, ..., 70 (running)
    direct = buf.sample(256, np.random.default_rng(0)).obs[:, -3, 0, 0].numpy().astype(int)  # 50 and 60 are whole
    pre = speed.Prefetcher(buf, 64, np.random.default_rng(0), torch.device("cpu"), margin=7)
    fetched = [pre.next() for _ in range(5)]
    pre.close()
    start_times = np.concatenate([b.obs[:, -3, 0, 0].numpy() for b in fetched]).astype(int)  # newest frame: start
    assert isinstance(fetched[0], sear.Batch) and set(start_times) == set(range(60, 67))  # 50 < 50 + 7
    assert set(direct) == set(range(50, 57)) | set(range(60, 67))


def test_prefetcher_waits_while_the_margin_leaves_no_episode_and_the_loop_waits_too():
    """A ring of about two episodes: the only finished episode starts in the margin. The thread draws
    nothing (no error, no batch), and the loop's can_sample() says no as well, so the learner never
    waits for a batch that cannot come."""
    buf = sear.ReplayBuffer(19, (3, 84, 84), 2, frame_stack=3, nstep=3, discount=0.99)
    fill(buf, [([0.5] * 9, False)] * 3)  # episodes at 0, 10, 20
    buf.add_first(make_obs(30, 3))  # episode 20-29 ends
    for time in range(31, 40):
        if time == 34:  # the oldest slot holds time 15: episode 20 is whole, but starts in the margin
            assert buf.can_sample()
            pre = speed.Prefetcher(buf, 8, np.random.default_rng(0), torch.device("cpu"), margin=7)
            assert pre.sample() is None and not pre.can_sample()  # 20 < 15 + 7
        buf.add(np.zeros(2, np.float32), 0.5, False, make_obs(time, 3))
    buf.add_first(make_obs(40, 4))  # episode 30-39 ends: 30 >= 41 - 19 + 7
    assert pre.can_sample() and set(pre.next().obs[:, -3, 0, 0].numpy().astype(int)) <= set(range(30, 37))
    pre.close()


@pytest.mark.parametrize("name, code, says", [("cpu", 0, "1 passed"), ("nonsense", 2, "is not a torch device")]
                         + ([] if torch.cuda.is_available() else [("cuda", 2, "torch sees no CUDA device")]))
def test_sear_test_device_sets_the_device_fixture(name, code, says):
    """benchmarks/gpu_check.sh runs the suite with SEAR_TEST_DEVICE=cuda: the `device` fixture (tests/conftest.py)
    hands it to every test that takes a device, and a device torch cannot use stops the run at once."""
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0",  # no workers
                        f"{__file__}::test_prefetcher_delivers_the_batches_direct_sampling_would"],
                       env={**os.environ, "SEAR_TEST_DEVICE": name}, capture_output=True, text=True,
                       cwd=os.path.dirname(os.path.dirname(__file__)), timeout=300)
    assert r.returncode == code and says in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]


def test_eval_due_is_the_schedule_the_run_dir_kept_before():
    """The loop's predicate (drqv2's Every, in frames) evaluates at exactly the frames where the former
    counter (next_eval, moved on by --eval-every past each evaluation) did, for any action repeat."""
    for every, repeat in ((10_000, 2), (1001, 2), (16, 2), (7, 3), (5, 1)):
        old, next_eval, new, last = [], 0, [], -1
        for frame in range(0, 20 * every, repeat):
            if frame >= next_eval:
                old.append(frame)
                while next_eval <= frame:
                    next_eval += every
            if train.eval_due(frame, last, every):
                new.append(frame)
                last = frame
        assert new == old and new[0] == 0, (every, repeat)


def test_the_agents_generator_is_seeded_by_torch_and_saved_with_it(device):
    """Every random number of an agent comes from its own generator, started where building the
    networks left torch's stream: torch.manual_seed(k) before building seeds it (the same k, the
    same draws; another k, others), and nothing else drawn from torch's stream after moves it. It
    is saved in state_dict(): a restored agent draws and updates as the original, to the bit."""
    cfg = small_cfg()
    pixels = np.random.default_rng(0).integers(0, 256, (9, 84, 84), dtype=np.uint8)
    agents = []
    for seed in (3, 3, 4):
        torch.manual_seed(seed)
        agents.append(sear.Agent(cfg, action_dim=2, device=device))
        torch.rand(100, device=device)  # the global stream moves on: the agent's does not
    a, b, other = agents
    assert torch.equal(a.draw(4).target, b.draw(4).target)
    assert not torch.equal(a.draw(4).target, other.draw(4).target)
    for step in (5000, 5002):
        a.update(fake_batch(seed=step, device=device), step)
    state = io.BytesIO()
    torch.save(a.state_dict(), state)
    torch.manual_seed(9)
    restored = sear.Agent(cfg, action_dim=2, device=device)
    restored.load_state_dict(torch.load(io.BytesIO(state.getvalue()), weights_only=False))
    for agent in (a, restored):
        agent.metrics = agent.update(fake_batch(seed=1, device=device), 5004)
        agent.action = agent.act(pixels, None, step=5004, eval_mode=False)
    assert all(torch.equal(a.metrics[k], restored.metrics[k]) for k in a.metrics)
    assert torch.equal(a.action, restored.action)
    for name in ("encoder", "actor", "critic", "critic_target", "aux"):
        assert all(torch.equal(p, q) for p, q in zip(getattr(a, name).parameters(),
                                                     getattr(restored, name).parameters())), name
