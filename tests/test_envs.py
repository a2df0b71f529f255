"""Tests for envs.py: the pixel + robot-mask contract that sear.py relies on.

Slow suites (Meta-World, Kitchen, Adroit) use render_quality="fast"; every env
is constructed once per module and shared between tests (see ``get_env``).
Run: MUJOCO_GL=egl pytest -q tests/test_envs.py
"""
import os
import pickle
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import envs  # noqa: E402
from envs import EnvError, make_env  # noqa: E402

DMC = ["walker-walk", "cup-catch", "walker-walk-distracting", "cup-catch-distracting"]
METAWORLD = ["metaworld-door-open", "metaworld-button-press-wall"]
KITCHEN = ["kitchen-kettle", "kitchen-light", "kitchen-slider"]
ADROIT = ["adroit-door", "adroit-hammer", "adroit-pen", "adroit-relocate"]
ALL = DMC + METAWORLD + KITCHEN + ADROIT
MANIPULATION = METAWORLD + KITCHEN + ADROIT

# Plausible robot-mask fractions of an 84x84 frame right after reset.
MASK_FRACTION = {"walker": (0.02, 0.25), "cup": (0.002, 0.05), "metaworld": (0.05, 0.5),
                 "kitchen": (0.02, 0.4), "adroit": (0.03, 0.5)}


def suite_of(name):
    return name.split("-")[0]


@pytest.fixture(scope="module")
def get_env():
    """Module-wide cache: constructing (and compiling) an env is the slow part."""
    cache = {}

    def get(name):
        if name not in cache:
            quality = "fast" if name in MANIPULATION else "paper"
            cache[name] = make_env(name, seed=0, render_quality=quality)
        return cache[name]

    yield get
    for env in cache.values():
        env.close()


def subtree_geoms(model, root_name):
    """Independent re-implementation of the robot rule: walk up body parents."""
    root = model.body(root_name).id
    robot = np.zeros(model.ngeom, bool)
    for g in range(model.ngeom):
        b = model.geom_bodyid[g]
        while b != 0 and b != root:
            b = model.body_parentid[b]
        robot[g] = b == root
    return robot


def raw_robot(env):
    """Robot pixels of the raw segmentation, oriented like the observation."""
    seg = env.segmentation()
    robot = subtree_geoms(env.model, env.robot_root)
    is_geom = seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
    mask = is_geom & robot[np.where(is_geom, seg[..., 0], 0)]
    if env.backend.flip:
        mask, seg = mask[::-1, ::-1], seg[::-1, ::-1]
    return mask, seg


# ----------------------------------------------------------------------------
# Contract
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ALL)
def test_contract(get_env, name):
    env = get_env(name)
    stack, size = 3, 84
    assert env.observation_space["pixels"].shape == (3 * stack, size, size)
    assert env.observation_space["pixels"].dtype == np.uint8
    assert env.observation_space["mask"].shape == (stack, size, size)
    assert env.observation_space["mask"].dtype == np.uint8
    assert env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)

    obs, info = env.reset(seed=1)
    assert obs["pixels"].shape == (3 * stack, size, size) and obs["pixels"].dtype == np.uint8
    assert obs["mask"].shape == (stack, size, size) and obs["mask"].dtype == np.uint8
    assert set(np.unique(obs["mask"])) <= {0, 1}
    # At reset the first frame fills the stack.
    assert np.array_equal(obs["pixels"][:3], obs["pixels"][6:])
    assert np.array_equal(obs["mask"][0], obs["mask"][2])
    assert obs["pixels"].std() > 5  # not a blank image

    rng = np.random.default_rng(0)
    first = obs["pixels"][6:].copy()
    for i in range(3):
        obs, reward, terminated, truncated, info = env.step(
            rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        assert obs["pixels"].shape == (3 * stack, size, size)
        assert isinstance(reward, float)
        assert isinstance(terminated, bool) and isinstance(truncated, bool)
        assert not terminated and not truncated
        if i == 0:
            # Oldest frame first: two copies of the reset frame, then the new one.
            assert np.array_equal(obs["pixels"][:3], first)
            assert np.array_equal(obs["pixels"][3:6], first)
    assert ("success" in info) == (name in MANIPULATION)
    # Something moved in the image over three random actions.
    assert not np.array_equal(obs["pixels"][6:], first)


def test_env_names_and_action_repeat():
    names = envs.env_names()
    for n in ALL:
        assert n in names
    assert len([n for n in names if n.startswith("metaworld-")]) == 50 + 3   # MT1 tasks, task sets
    assert {"metaworld-mt3", "metaworld-mt10", "metaworld-mt50", "kitchen-multitask"} <= set(names)
    assert "metaworld-hammer" in names and "metaworld-door-open-v3" not in names
    dmc = [n for n in names if envs._parse_name(n)[0] == "dmc"]  # `envs.py --list` is complete: every
    assert [n for n in names if n.endswith("-distracting")] == [f"{n}-distracting" for n in dmc]  # one distracting too
    assert envs.default_action_repeat("walker-walk") == 2
    assert envs.default_action_repeat("walker-walk-distracting") == 2
    assert envs.default_action_repeat("cheetah-run-distracting") == 2
    assert envs.default_action_repeat("metaworld-hammer") == 2
    assert envs.default_action_repeat("kitchen-kettle") == 1
    assert envs.default_action_repeat("adroit-pen") == 1


def test_every_listed_dm_control_name_builds_and_steps():
    """`envs.py --list` is a promise: each dm_control name it prints builds, resets and steps (the
    quadruped tasks once died in dm_control on numpy 2.4, quadruped-fetch after quadruped-escape on
    a GL context freed late). Cheapest settings: fast render, one frame, 32 px; one env at a time."""
    names = [n for n in envs.env_names() if envs._parse_name(n)[0] in ("dmc", "distracting")]
    assert {"quadruped-walk", "dog-run", "walker-walk-distracting"} <= set(names)
    failures, env = {}, None
    for name in names:
        try:
            # As in any `env = make_env(...)` loop, the previous (closed) env is garbage only once
            # the next one exists: the order that broke quadruped-fetch after quadruped-escape.
            env = make_env(name, seed=0, frame_stack=1, size=32, render_quality="fast")
            env.reset(seed=0)
            obs, reward, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
            assert obs["pixels"].shape == (3, 32, 32) and np.isfinite(reward)
        except Exception as e:  # collect them all: one run names every broken task
            failures[name] = f"{type(e).__name__}: {e}"
        finally:
            if env is not None:
                env.close()
    assert not failures, failures


def test_new_terrain_per_episode_is_what_the_pixels_show():
    """quadruped-escape writes a new height field into the model at every reset; the renderer's
    copy must follow (the first episode used to show the XML's flat floor)."""
    env = make_env("quadruped-escape", seed=0, frame_stack=1, size=32, render_quality="fast")
    try:
        for seed in (1, 2):
            obs, _ = env.reset(seed=seed)
            env._upload(hfields=range(env.model.nhfield))  # what a fresh renderer would see
            assert np.array_equal(env._render()[0], obs["pixels"])
    finally:
        env.close()


@pytest.mark.parametrize("name", ["walker-walk", "walker-walk-distracting",
                                  "metaworld-door-open", "kitchen-kettle", "adroit-door"])
def test_reset_seed_reproducible(get_env, name):
    env = get_env(name)
    a, _ = env.reset(seed=7)
    b, _ = env.reset(seed=7)
    for k in ("pixels", "mask"):
        assert np.array_equal(a[k], b[k])


def rand_vecs(tasks):
    """The placements (rand_vec) of a list of metaworld.Task."""
    return np.array([pickle.loads(t.data)["rand_vec"] for t in tasks])


def is_one_of(vec, vecs):
    return any(np.array_equal(vec, v) for v in vecs)


def test_metaworld_variation_sampled_per_reset_seed(get_env):
    import metaworld
    env = get_env("metaworld-door-open")   # seed 0, so variation seed 0
    mt1 = rand_vecs(metaworld.MT1("door-open-v3", seed=0).train_tasks)
    assert len(mt1) == 50
    seen, pixels = {}, {}
    for s in range(6):
        obs, _ = env.reset(seed=s)
        rand_vec = env.backend.env._last_rand_vec
        # The placement is one of the 50 MT1 train tasks, and the door really
        # stands there (set_task + reset moved the object, not only the goal).
        assert is_one_of(rand_vec, mt1)
        assert np.allclose(env.data.body("door").xpos, rand_vec[:3])
        seen[s] = np.concatenate([env.data.body("door").xpos, env.backend.env._target_pos])
        pixels[s] = obs["pixels"]
    assert len({tuple(np.round(p, 6)) for p in seen.values()}) >= 4, seen
    s, t = next((s, t) for s in seen for t in seen if not np.allclose(seen[s], seen[t]))
    assert not np.array_equal(pixels[s], pixels[t])
    # The same reset seed gives the same placement and image.
    obs, _ = env.reset(seed=3)
    assert np.array_equal(env.data.body("door").xpos, seen[3][:3])
    assert np.array_equal(obs["pixels"], pixels[3])


def test_metaworld_train_and_eval_share_variations(get_env):
    train = get_env("metaworld-door-open")   # seed 0
    evalenv = make_env("metaworld-door-open", seed=100_000, split="eval", variation_seed=0,
                       frame_stack=1, render_quality="fast")
    default = make_env("metaworld-door-open", seed=100_000, frame_stack=1, render_quality="fast")
    try:
        # The same 50 placements whatever the construction seed...
        shared = rand_vecs(train.backend.variations)
        assert np.array_equal(rand_vecs(evalenv.backend.variations), shared)
        # ...and every eval reset draws one of them.
        for s in range(5):
            evalenv.reset(seed=s)
            assert is_one_of(evalenv.backend.env._last_rand_vec, shared)
        # Without variation_seed, the variation seed is the env seed: other placements.
        default.reset(seed=0)
        assert not any(np.allclose(default.backend.env._last_rand_vec, v) for v in shared)
    finally:
        evalenv.close(), default.close()


# walker: 1000 env steps at action repeat 2; adroit-pen: D4RL's pen-human-v1, 100 steps (the pen
# stays in the hand under zero actions; gymnasium-robotics registers 200).
@pytest.mark.parametrize("name, steps", [("walker-walk", 500), ("adroit-pen", 100)])
def test_time_limit_is_truncation(get_env, name, steps):
    env = get_env(name)
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, np.float32)
    for t in range(1, steps + 1):
        _, _, terminated, truncated, _ = env.step(action)
        assert not terminated
        if truncated:
            break
    assert truncated and t == steps
    with pytest.raises(RuntimeError):
        env.step(action)


def test_metaworld_time_limit_stops_action_repeat(get_env):
    env = get_env("metaworld-door-open")
    env.reset(seed=0)
    mw = env.backend.env
    assert mw.max_path_length == 500
    # One env step before the limit: the first of the two repeats ends the
    # episode and the second must not run (Meta-World raises if stepped past).
    mw.curr_path_length = mw.max_path_length - 1
    _, _, terminated, truncated, info = env.step(np.zeros(4, np.float32))
    assert truncated and not terminated and "success" in info
    assert mw.curr_path_length == mw.max_path_length


def test_kitchen_time_limit_is_280_steps(get_env):
    env = get_env("kitchen-kettle")
    env.reset(seed=0)
    limit = env.backend.env  # gymnasium TimeLimit wrapper
    assert limit.spec.max_episode_steps == 280
    limit._elapsed_steps = 279
    _, _, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, np.float32))
    assert truncated and not terminated


def test_kitchen_solved_task_is_truncation(get_env):
    env = get_env("kitchen-light")
    zero = np.zeros(env.action_space.shape, np.float32)

    def switch_light_on():
        # FrankaKitchen's light-switch goal: qpos[17:19] near (-0.69, -0.05).
        env.reset(seed=0)
        env.data.qpos[17:19] = (-0.69, -0.05)
        env.data.qvel[:] = 0
        mujoco.mj_forward(env.model, env.data)

    switch_light_on()
    _, _, raw_terminated, raw_truncated, _ = env.backend.env.step(zero)
    assert raw_terminated and not raw_truncated   # gymnasium-robotics: a termination
    switch_light_on()
    _, reward, terminated, truncated, info = env.step(zero)
    assert reward == 1.0 and info["success"]
    assert truncated and not terminated             # ours: the agent bootstraps


def d4rl_dense_reward(task, model, data):
    """D4RL's reward (d4rl/hand_manipulation_suite/<task>_v0.py), written out with D4RL's own
    lookups: site_xpos, body_xpos, qpos[jnt_dofadr]. The hand-to-object term is negative."""
    site = lambda n: data.site_xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, n)]
    body = lambda n: data.xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n)]
    norm = np.linalg.norm
    palm = site("S_grasp")
    if task == "door":
        door = data.qpos[model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "door_hinge")]]
        r = -0.1 * norm(palm - site("S_handle")) - 0.1 * (door - 1.57) ** 2 - 1e-5 * np.sum(data.qvel ** 2)
        return r + (2 if door > 0.2 else 0) + (8 if door > 1.0 else 0) + (10 if door > 1.35 else 0)
    if task == "hammer":
        obj, tool, target, goal = body("Object"), site("tool"), site("S_target"), site("nail_goal")
        r = (-0.1 * norm(palm - obj) - norm(tool - target) - 10 * norm(target - goal)
             - 1e-2 * norm(data.qvel))
        r += 2 if obj[2] > 0.04 and tool[2] > 0.04 else 0
        return r + (25 if norm(target - goal) < 0.02 else 0) + (75 if norm(target - goal) < 0.01 else 0)
    obj, target = body("Object"), site("target")   # relocate
    r = -0.1 * norm(palm - obj)
    if obj[2] > 0.04:
        r += 1.0 - 0.5 * norm(palm - target) - 0.5 * norm(obj - target)
    return r + (10 if norm(obj - target) < 0.1 else 0) + (20 if norm(obj - target) < 0.05 else 0)


HAND_TO_OBJECT = {"door": ("site", "S_handle"), "hammer": ("body", "Object"), "relocate": ("body", "Object")}


@pytest.mark.parametrize("task", ["door", "hammer", "relocate"])
def test_adroit_pays_d4rl_reward_hand_toward_object(get_env, task):
    """gymnasium-robotics 1.4.2's AdroitHand*-v1 pays +0.1 x hand-to-object distance; D4RL (the
    authors' envs) pays -0.1 x. On recorded states the env pays D4RL's reward, whatever the
    installed env's own reward is, and moving the palm toward the object raises it."""
    env = get_env(f"adroit-{task}")
    model, data = env.model, env.data
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(25):
        _, reward, *_ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        assert reward == pytest.approx(d4rl_dense_reward(task, model, data), abs=1e-9)
    # Move the palm 1 cm toward the object along its site Jacobian (hand joints only: no object or
    # door joint moves the palm), velocities zero; nothing else in the state changes.
    kind, name = HAND_TO_OBJECT[task]
    data.qvel[:] = 0
    mujoco.mj_forward(model, data)
    obj = (data.site(name) if kind == "site" else data.body(name)).xpos.copy()
    before_dist, before = np.linalg.norm(obj - data.site("S_grasp").xpos), envs.d4rl_reward(task, data)
    jac = np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, data, jac, None, model.site("S_grasp").id)
    dq = jac.T @ (obj - data.site("S_grasp").xpos)
    mujoco.mj_integratePos(model, data.qpos, dq * 0.01 / np.linalg.norm(jac @ dq), 1.0)
    mujoco.mj_forward(model, data)
    after_dist, after = np.linalg.norm(obj - data.site("S_grasp").xpos), envs.d4rl_reward(task, data)
    assert np.allclose((data.site(name) if kind == "site" else data.body(name)).xpos, obj)
    assert after_dist < before_dist - 0.005
    assert after == pytest.approx(before + 0.1 * (before_dist - after_dist), abs=1e-6)
    assert after == pytest.approx(d4rl_dense_reward(task, model, data), abs=1e-9)


def test_adroit_episode_lengths_are_d4rl(get_env):
    for task, steps in [("door", 200), ("hammer", 200), ("pen", 100), ("relocate", 200)]:
        assert get_env(f"adroit-{task}").backend.env.spec.max_episode_steps == steps


def test_adroit_dropped_pen_ends_the_episode_as_truncation(get_env):
    """D4RL's pen is done when the pen falls below 0.075 m (reward -5); the authors' Adroit wrapper
    returns every done as dm_env.truncation, so the agent bootstraps there."""
    env = get_env("adroit-pen")
    zero = np.zeros(env.action_space.shape, np.float32)
    data = env.data
    env.reset(seed=0)
    _, _, terminated, truncated, _ = env.step(zero)
    assert not (terminated or truncated)
    drop = np.array([0.0, 0.0, 0.03 - data.body("Object").xpos[2]])   # the pen 3 cm above z = 0
    for axis in ("OBJTx", "OBJTy", "OBJTz"):   # the pen's slide joints, orthogonal in the world
        data.joint(axis).qpos[0] += data.xaxis[env.model.joint(axis).id] @ drop
    data.qvel[:] = 0
    mujoco.mj_forward(env.model, data)
    _, reward, terminated, truncated, _ = env.step(zero)
    assert data.body("Object").xpos[2] < 0.075
    assert truncated and not terminated
    unit = lambda v: v / np.linalg.norm(v)
    orientation = np.dot(unit(data.site("object_top").xpos - data.site("object_bottom").xpos),
                         unit(data.site("target_top").xpos - data.site("target_bottom").xpos))
    distance = np.linalg.norm(data.body("Object").xpos - data.site("eps_ball").xpos)
    assert distance > 0.075   # far from the goal: no bonus, only the drop penalty
    assert reward == pytest.approx(-distance + orientation - 5, abs=1e-9)
    with pytest.raises(RuntimeError):
        env.step(zero)


@pytest.mark.parametrize("name", ["quadruped-walk", "walker-walk"])
def test_dm_control_receives_drqv2s_float32_action(name):
    """DrQ-v2's dmc.py wraps a suite task in ActionDTypeWrapper(float32), then dm_control's own
    action_scale.Wrapper(-1, 1): the scaled action is a float32 value, handed to dm_control as
    float64. Quadruped's bounds (-1 .. 1.1) make that rounding visible; walker's (-1 .. 1) do not."""
    from dm_control.suite.wrappers import action_scale
    from dm_env import specs

    env = make_env(name, seed=0, frame_stack=1, render_quality="fast", render_mask=False)
    received = []
    dmc_step = env.backend.env.step
    env.backend.env.step = lambda a: (received.append(np.array(a, copy=True)), dmc_step(a))[1]

    class Float32Spec:   # ActionDTypeWrapper(env, np.float32) over the same task
        def __init__(self, spec):
            self.spec = specs.BoundedArray(spec.shape, np.float32, spec.minimum, spec.maximum, "action")
            self.received = []

        def action_spec(self):
            return self.spec

        def step(self, action):
            self.received.append(action.astype(env.backend.env.action_spec().dtype))

    inner = Float32Spec(env.backend.env.action_spec())
    drqv2 = action_scale.Wrapper(inner, minimum=-1.0, maximum=+1.0)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, env.action_space.shape).astype(np.float32) for _ in range(20)]
    actions += [np.full(env.action_space.shape, v, np.float32) for v in (-1.0, 1.0, 1e-9, -0.3)]
    env.reset(seed=0)
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        drqv2.step(action)
        assert not (terminated or truncated)
    env.close()
    ours = received[::env.action_repeat]   # the same action at every repeat
    assert len(ours) == len(inner.received) == len(actions)
    for a, b in zip(ours, inner.received):
        assert a.dtype == b.dtype == np.float64
        assert np.array_equal(a, b)                          # bit for bit
        assert np.array_equal(a, a.astype(np.float32))       # a float32 value


def test_action_repeat_sums_rewards():
    one = make_env("walker-walk", seed=3, action_repeat=1, render_quality="fast")
    two = make_env("walker-walk", seed=3, action_repeat=2, render_quality="fast")
    one.reset(seed=3), two.reset(seed=3)
    a = np.full(one.action_space.shape, 0.3, np.float32)
    r1 = one.step(a)[1] + one.step(a)[1]
    o1 = one._obs()
    o2, r2, *_ = two.step(a)
    one.close(), two.close()
    assert r2 == pytest.approx(r1)
    assert np.array_equal(o1["pixels"][-3:], o2["pixels"][-3:])


# ----------------------------------------------------------------------------
# Masks: only robot geoms, plausible, in the right place
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ALL)
def test_mask_fraction_plausible(get_env, name):
    env = get_env(name)
    obs, _ = env.reset(seed=0)
    lo, hi = MASK_FRACTION[suite_of(name)]
    frac = obs["mask"][-1].mean()
    assert lo < frac < hi, f"{name}: mask fraction {frac:.4f} outside ({lo}, {hi})"


@pytest.mark.parametrize("name", ALL)
def test_mask_contains_only_robot_geoms(get_env, name):
    env = get_env(name)
    obs, _ = env.reset(seed=2)
    mask = obs["mask"][-1].astype(bool)
    robot, seg = raw_robot(env)
    s = env.mask_scale
    if s == 1:
        # dm_control: masks are the segmentation itself.
        assert np.array_equal(mask, robot)
    else:
        # Manipulation: opening + 3x3 majority.  Every mask pixel needs a
        # majority of robot pixels in its block, and the mask keeps most of
        # the robot.
        counts = robot.reshape(84, s, 84, s).sum(axis=(1, 3))
        assert np.all(counts[mask] > (s * s) // 2)
        majority = counts > (s * s) // 2
        iou = (mask & majority).sum() / (mask | majority).sum()
        assert iou > 0.9, iou
        # Exactly the paper's pipeline: binary opening, then 3x3 majority.
        opened = ndimage.binary_opening(robot).reshape(84, s, 84, s).sum(axis=(1, 3))
        assert np.array_equal(mask, opened > (s * s) // 2)


def test_walker_mask_excludes_floor(get_env):
    env = get_env("walker-walk")
    obs, _ = env.reset(seed=0)
    mask = obs["mask"][-1].astype(bool)
    seg = env.segmentation()
    floor = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (seg[..., 0] == env.model.geom("floor").id)
    assert floor.sum() > 500           # the floor is in view...
    assert not (mask & floor).any()    # ...and never in the mask


def test_cup_mask_excludes_ball(get_env):
    env = get_env("cup-catch")
    obs, _ = env.reset(seed=0)
    mask = obs["mask"][-1].astype(bool)
    seg = env.segmentation()
    ball = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (seg[..., 0] == env.model.geom("ball").id)
    assert ball.sum() > 3
    assert not (mask & ball).any()
    assert env.robot_root == "cup"


def test_sawyer_subtree_is_arm_not_table(get_env):
    env = get_env("metaworld-door-open")
    m = env.model
    robot_bodies = {m.body(b).name for b in np.unique(m.geom_bodyid[env.geom_is_robot])}
    assert {"right_l0", "right_l6", "hand", "rightpad", "leftpad"} <= robot_bodies
    assert not robot_bodies & {"tablelink", "door", "door_link", "world"}


@pytest.mark.parametrize("name", METAWORLD)
def test_metaworld_upright(get_env, name):
    env = get_env(name)
    obs, _ = env.reset(seed=0)
    _, seg = raw_robot(env)  # oriented like the observation
    m = env.model
    table_geoms = np.flatnonzero(m.geom_bodyid == m.body("tablelink").id)
    table = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 0], table_geoms)
    rows = np.nonzero(table)[0] / env.mask_scale
    assert rows.size > 0 and rows.mean() > 84 / 2, "table should be in the lower half"
    # RGB and mask are flipped together: masked pixels are the red Sawyer.
    rgb = obs["pixels"][-3:].transpose(1, 2, 0).astype(float)
    mask = obs["mask"][-1].astype(bool)
    red, green = rgb[mask][:, 0].mean(), rgb[mask][:, 1].mean()
    assert red > 1.5 * green, (red, green)


def test_mask_noise_subset_and_fraction():
    clean_env = make_env("walker-walk", seed=4, render_quality="fast")
    noisy_env = make_env("walker-walk", seed=4, render_quality="fast", mask_noise=0.3)
    clean = clean_env.reset(seed=4)[0]["mask"].astype(bool)
    noisy = noisy_env.reset(seed=4)[0]["mask"].astype(bool)
    # The frame at reset is repeated; compare the newest one.
    clean, noisy = clean[-1], noisy[-1]
    assert np.all(noisy <= clean)      # noise only removes robot pixels
    ratio = noisy.sum() / clean.sum()
    assert 0.6 < ratio < 0.8, ratio   # about 1 - P
    # Reproducible from the seed, different for another seed.
    again = noisy_env.reset(seed=4)[0]["mask"][-1].astype(bool)
    other = noisy_env.reset(seed=5)[0]["mask"][-1].astype(bool)
    assert np.array_equal(noisy, again)
    assert not np.array_equal(noisy & clean, other & clean) or not np.array_equal(noisy, other)
    clean_env.close(), noisy_env.close()


def test_mask_approx_is_the_authors_transform():
    """The authors' SlimMaskWrapper (skimage rescale 1/3 then 3, bilinear, no anti-aliasing; gaussian
    sigma 0.5; > 0.9). Expected shapes computed with their calls (scikit-image 0.26): the high
    threshold takes one pixel off every edge, and a one-pixel line survives only on a column the
    3x downsampling samples (3i + 1)."""
    def box(r0, r1, c0, c1):
        m = np.zeros((84, 84), bool)
        m[r0:r1, c0:c1] = True
        return m
    assert np.array_equal(envs.approximate_mask(box(30, 54, 30, 54)), box(31, 53, 31, 53))
    assert np.array_equal(envs.approximate_mask(box(0, 12, 0, 12)), box(0, 11, 0, 11))   # mirrored edge
    assert not envs.approximate_mask(box(20, 60, 39, 40)).any()
    assert np.array_equal(envs.approximate_mask(box(20, 60, 40, 41)), box(23, 58, 40, 41))
    assert np.array_equal(envs.approximate_mask(box(20, 60, 39, 41)), box(23, 58, 40, 41))


@pytest.mark.parametrize("name", ["walker-walk", "metaworld-door-open"])
def test_mask_approx_erodes_the_clean_mask(get_env, name):
    base = get_env(name)
    approx_env = make_env(name, seed=0, render_quality=base.render_quality, mask_approx=True)
    clean = base.reset(seed=0)[0]["mask"][-1].astype(bool)
    approx = approx_env.reset(seed=0)[0]["mask"][-1].astype(bool)
    approx_env.close()
    assert np.array_equal(approx, envs.approximate_mask(clean))
    kept, added = (approx & clean).sum() / clean.sum(), (approx & ~clean).sum() / clean.sum()
    assert 0.3 < kept < 0.9 and added < 0.02, (kept, added)


def test_mask_noise_comes_before_the_approximation():
    """The authors drop pixels first and approximate the noisy mask (NoisyMaskWrapper inside
    SlimMaskWrapper in every sear/environments/*_dm_env.py and distracting_dmc.py). The two envs
    draw the same noise: the approximation uses no random numbers."""
    noisy = make_env("walker-walk", seed=4, render_quality="fast", mask_noise=0.3)
    both = make_env("walker-walk", seed=4, render_quality="fast", mask_noise=0.3, mask_approx=True)
    for pair in ((noisy.reset(seed=4)[0], both.reset(seed=4)[0]),
                 (noisy.step(np.ones(6, np.float32))[0], both.step(np.ones(6, np.float32))[0])):
        dropped, approximated = (obs["mask"][-1].astype(bool) for obs in pair)
        assert dropped.any() and np.array_equal(approximated, envs.approximate_mask(dropped))
    noisy.close(), both.close()


def test_render_mask_false_gives_empty_masks():
    env = make_env("walker-walk", seed=0, render_quality="fast", render_mask=False)
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
    env.close()
    assert obs["mask"].shape == (3, 84, 84) and not obs["mask"].any()
    assert obs["pixels"].std() > 5


def test_majority_vs_stride_downsample():
    mask = np.zeros((9, 9), bool)
    mask[0:3, 0:3] = True
    mask[0, 0] = False           # a hole at a stride sample point
    assert not envs.downsample_mask(mask, 3, "stride")[0, 0]
    assert envs.downsample_mask(mask, 3, "majority")[0, 0]
    mask[3, 3] = True            # a lone pixel does not win a majority
    assert not envs.downsample_mask(mask, 3, "majority")[1, 1]


# ----------------------------------------------------------------------------
# Distracting Control: backgrounds
# ----------------------------------------------------------------------------

def sky(obs):
    """The top rows of the newest frame: background for walker and cup."""
    return obs["pixels"][-3:, :12].astype(float)


def test_backgrounds_differ_between_episodes_and_reproduce(get_env):
    env = get_env("walker-walk-distracting")
    first = sky(env.reset(seed=11)[0])
    second = sky(env.reset()[0])
    assert np.abs(first - second).mean() > 5
    again = sky(env.reset(seed=11)[0])
    assert np.array_equal(first, again)
    # A fresh instance with the same seeds sees the same episode.
    other = make_env("walker-walk-distracting", seed=0)
    assert np.array_equal(sky(other.reset(seed=11)[0]), first)
    other.close()


def test_backgrounds_never_enter_masks(get_env):
    plain, distracting = get_env("walker-walk"), get_env("walker-walk-distracting")
    plain.reset(seed=0)
    distracting.reset(seed=3)
    for _ in range(3):
        # Same physics state in both: masks must be identical, whatever the background.
        distracting.data.qpos[:] = plain.data.qpos
        distracting.data.qvel[:] = plain.data.qvel
        mujoco.mj_forward(distracting.model, distracting.data)
        assert np.array_equal(plain.clean_mask(), distracting.clean_mask())
        assert not np.array_equal(plain._render()[0], distracting._render()[0])
        distracting.reset()
        plain.step(np.ones(plain.action_space.shape, np.float32) * 0.5)


def write_image(path, colour):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((32, 48, 3), colour, np.uint8)).save(path)


def dominant_channel(obs):
    return int(np.argmax(sky(obs).mean(axis=(1, 2))))


def test_davis_layout_train_and_eval_videos(tmp_path):
    frames = tmp_path / "DAVIS" / "JPEGImages" / "480p"
    write_image(frames / "bear" / "00000.jpg", (230, 10, 10))        # train: red
    write_image(frames / "bear" / "00001.jpg", (230, 10, 10))
    write_image(frames / "blackswan" / "00000.jpg", (10, 10, 230))   # val: blue
    train = make_env("walker-walk-distracting", backgrounds=str(tmp_path / "DAVIS"), split="train")
    evalenv = make_env("walker-walk-distracting", backgrounds=str(frames), split="eval")
    for seed in range(2):
        assert dominant_channel(train.reset(seed=seed)[0]) == 0
        assert dominant_channel(evalenv.reset(seed=seed)[0]) == 2
    train.close(), evalenv.close()


def test_image_folder_backgrounds(tmp_path):
    colours = [(230, 10, 10), (10, 230, 10)]
    for i, c in enumerate(colours):
        write_image(tmp_path / "imgs" / f"{i}.png", c)
    env = make_env("cup-catch-distracting", backgrounds=str(tmp_path / "imgs"), render_quality="fast")
    seen = {dominant_channel(env.reset(seed=s)[0]) for s in range(8)}
    env.close()
    assert seen == {0, 1}


def test_difficulty_controls_number_of_backgrounds(tmp_path):
    for i in range(10):
        write_image(tmp_path / f"video{i:02d}" / "00000.png", (i * 20, 0, 0))
    easy = envs.Backgrounds(str(tmp_path), "train", "easy")
    hard = envs.Backgrounds(str(tmp_path), "train", "hard")
    held_out = envs.Backgrounds(str(tmp_path), "eval", "hard")
    assert len(easy.groups) == 4 and len(hard.groups) == 8 and len(held_out.groups) == 2
    assert not {str(g[0]) for g in hard.groups} & {str(g[0]) for g in held_out.groups}
    assert len(envs.Backgrounds(None, "train", "hard").groups) == 60
    assert len(envs.Backgrounds(None, "eval", "hard").groups) == 30
    assert len(envs.Backgrounds(None, "train", "medium").groups) == 8


@pytest.mark.parametrize("name, alpha", [
    ("reacher-easy-distracting", 0.0), ("walker-walk-distracting", 1.0),
    ("cheetah-run-distracting", 1.0), ("cup-catch-distracting", 0.3),
    ("finger-spin-distracting", 0.3), ("hopper-hop-distracting", 0.3),
])
def test_ground_alpha_as_original_suite(name, alpha):
    env = make_env(name, seed=0, frame_stack=1, size=32, render_quality="fast", render_mask=False)
    grid_alpha = env.model.mat_rgba[env.model.material("grid").id, 3]
    env.close()
    assert grid_alpha == pytest.approx(alpha)


def test_non_image_background_fails_at_build(tmp_path):
    write_image(tmp_path / "flat" / "real.png", (230, 10, 10))
    (tmp_path / "flat" / "fake.jpg").write_text("not an image")
    with pytest.raises(EnvError, match="fake.jpg") as err:
        make_env("walker-walk-distracting", backgrounds=str(tmp_path / "flat"))
    assert "\n" not in str(err.value) and "real.png" not in str(err.value)
    # Only the split's files are checked: a bad file in the held-out 5th
    # group breaks the eval split, not the train split.
    for i in range(5):
        write_image(tmp_path / "videos" / f"v{i}" / "00000.png", (i * 40, 0, 0))
    (tmp_path / "videos" / "v4" / "00001.jpg").write_text("not an image")
    assert len(envs.Backgrounds(str(tmp_path / "videos"), "train", "hard").groups) == 4
    with pytest.raises(EnvError, match="00001.jpg"):
        envs.Backgrounds(str(tmp_path / "videos"), "eval", "hard")


def test_procedural_backgrounds_deterministic_and_varied():
    a, b = envs.procedural_background(3), envs.procedural_background(3)
    assert np.array_equal(a, b) and a.dtype == np.uint8 and a.shape == (256, 256, 3)
    imgs = [envs.procedural_background(s).astype(float) for s in range(6)]
    assert all(img.std() > 20 for img in imgs)
    assert min(np.abs(imgs[i] - imgs[j]).mean() for i in range(6) for j in range(i)) > 10


def test_camera_and_color_distraction_change_image_not_mask_rule():
    base = make_env("walker-walk-distracting", seed=0, render_quality="fast")
    moved = make_env("walker-walk-distracting", seed=0, render_quality="fast",
                     camera_distraction=0.3, color_distraction=0.3)
    a, b = base.reset(seed=1)[0], moved.reset(seed=1)[0]
    assert not np.array_equal(a["mask"], b["mask"])        # camera moved
    robot, _ = raw_robot(moved)
    assert np.array_equal(b["mask"][-1].astype(bool), robot)  # still exactly the robot
    base.close(), moved.close()


# ----------------------------------------------------------------------------
# Render quality
# ----------------------------------------------------------------------------

def test_fast_render_similar_to_paper(get_env):
    paper = get_env("walker-walk")
    fast = make_env("walker-walk", seed=0, render_quality="fast")
    a, b = paper.reset(seed=0)[0], fast.reset(seed=0)[0]
    fast.close()
    assert np.array_equal(a["mask"], b["mask"])
    diff = np.abs(a["pixels"].astype(float) - b["pixels"].astype(float))
    assert 0 < diff.mean() < 12, diff.mean()   # shadows / antialiasing only


# ----------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, match", [
    (dict(name="foo"), "unknown env 'foo'"),
    (dict(name="metaworld-flying"), "unknown env"),
    (dict(name="kitchen-microwave"), "unknown env"),
    (dict(name="walker-walk-distracting", backgrounds="/nonexistent/dir"), "does not exist"),
    (dict(name="walker-walk", render_quality="ultra"), "render_quality"),
    (dict(name="walker-walk-distracting", difficulty="insane"), "difficulty"),
])
def test_bad_input_raises_one_line_env_error(kwargs, match):
    with pytest.raises(EnvError, match=match) as err:
        make_env(**kwargs)
    assert "\n" not in str(err.value)
    assert isinstance(err.value, ValueError)


def test_unknown_env_lists_valid_names():
    with pytest.raises(EnvError) as err:
        make_env("foo")
    msg = str(err.value)
    for part in ("walker-walk", "cup-catch", "distracting", "metaworld-", "kitchen-", "adroit-"):
        assert part in msg
    assert "\n" not in msg and len(msg) < 400


def test_backgrounds_dir_without_images(tmp_path):
    (tmp_path / "notes.txt").write_text("no images here")
    with pytest.raises(EnvError, match="no images") as err:
        make_env("walker-walk-distracting", backgrounds=str(tmp_path))
    assert "\n" not in str(err.value)


def run_cli(*args):
    return subprocess.run([sys.executable, str(ROOT / "envs.py"), *args], capture_output=True,
                          text=True, timeout=120, env={**os.environ, "MUJOCO_GL": "egl"})


def test_cli_refuses_to_overwrite_a_picture_without_force(tmp_path):
    out = tmp_path / "suites.png"
    out.write_bytes(b"precious")
    for flag in ("--gallery", "--mask-figure"):
        proc = run_cli(flag, str(out), "--envs", "walker-walk")
        assert proc.returncode == 2 and out.read_bytes() == b"precious"
        assert proc.stderr == f"envs.py: error: {out} exists; refusing to overwrite it (use --force)\n"
    proc = run_cli("--gallery", str(out), "--envs", "walker-walk", "--render-quality", "fast", "--force")
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize("args", [
    ["--gallery", "out.png", "--envs", "foo"],
    ["--gallery", "out.png", "--backgrounds", "/nonexistent/dir"],
    ["--gallery", "out.png", "--backgrounds", "bgs"],   # holds a fake.jpg
])
def test_cli_bad_input_one_line_no_traceback(tmp_path, args):
    write_image(tmp_path / "bgs" / "real.png", (230, 10, 10))
    (tmp_path / "bgs" / "fake.jpg").write_text("not an image")
    args = [str(tmp_path / a) if a in ("out.png", "bgs") else a for a in args]
    proc = run_cli(*args)
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out.png").exists()


def test_pole_inertia_2021_gives_back_mujoco_2s_pole_and_only_on_cartpole():
    """MuJoCo 2.0 (under DrQ-v2's 2021 curves) weighed cartpole's capsule pole as a cylinder of length
    2h + r: body_inertia of pole_1 [0.00915083, 0.00915083, 0.00010125] then; MuJoCo 3.3.0 computes the
    exact capsule, 0.8% more about the hinge. The default keeps MuJoCo's own; both balance from one state."""
    qpos = {}
    for pole_inertia, inertia in (("exact", [0.00942459, 0.00942459, 0.000100104]),
                                  ("2021", [0.00915083, 0.00915083, 0.00010125])):
        env = make_env("cartpole-balance_sparse", seed=0, render_quality="fast",
                       **({} if pole_inertia == "exact" else {"pole_inertia": pole_inertia}))
        physics = env.backend.physics
        pole = physics.model.name2id("pole_1", "body")
        np.testing.assert_allclose(physics.model.body_inertia[pole], inertia, rtol=1e-5)
        hinge = physics.model.body_inertia[pole][0] + physics.model.body_mass[pole] * physics.model.body_ipos[pole][2] ** 2
        assert hinge == pytest.approx({"exact": 0.0344246, "2021": 0.0341508}[pole_inertia], rel=1e-5)
        env.reset(seed=3)
        for _ in range(50):
            env.step(np.array([0.7], np.float32))
        qpos[pole_inertia] = physics.data.qpos.copy()
        env.close()
    assert np.abs(qpos["exact"] - qpos["2021"]).max() > 1e-4  # the lighter pole moves otherwise
    with pytest.raises(EnvError, match="the 2021 pole inertia only applies to cartpole-"):
        make_env("walker-walk", pole_inertia="2021")
