"""docs/robots.md's steps, followed: a dm_control task whose robot root the page names
(manipulator-bring_ball), checked with `envs.py --robot` and the gallery, and the page's gymnasium
backend (Hopper-v5) through SEAREnv. The mask must hold the whole body subtree of the root and
nothing else: not the floor, the ball, its target or the arm's fixed base on the world body."""
import os
import re
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import envs  # noqa: E402

PAGE = ROOT / "docs" / "robots.md"
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}


def subtree_bodies(model, root_name):
    """The bodies under root_name, found by walking each body's parents (not envs.body_subtree)."""
    root, names = model.body(root_name).id, set()
    for b in range(model.nbody):
        a = b
        while a not in (0, root):
            a = model.body_parentid[a]
        if a == root:
            names.add(model.body(b).name)
    return names


def geom_pixels(env, names):
    """Pixels of the named geoms in the segmentation of the current frame."""
    seg = env.segmentation()
    is_geom = seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
    ids = [env.model.geom(n).id for n in names]
    return is_geom & np.isin(seg[..., 0], ids)


def test_a_dm_control_task_named_in_the_roots_table_masks_the_arm_and_nothing_else():
    assert "manipulator-bring_ball" in envs.env_names()           # an --env name
    assert envs._DMC_ROBOT_ROOTS["manipulator"] == "upper_arm"     # its root, named
    env = envs.make_env("manipulator-bring_ball", seed=0, frame_stack=1, render_quality="fast")
    try:
        report = envs.robot_report(env, frames=5)
        arm = subtree_bodies(env.model, "upper_arm")
        robot_geoms = [env.model.geom(g).name for g in range(env.model.ngeom)
                       if env.model.body(env.model.geom_bodyid[g]).name in arm]
        outside = ["ball", "target_ball", "arm_root", "floor", "background"]
        obs, _ = env.reset(seed=1)
        rng = np.random.default_rng(1)
        for _ in range(3):
            obs, *_ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            mask = obs["mask"][-1].astype(bool)
            assert np.array_equal(mask, geom_pixels(env, robot_geoms))   # the whole subtree
            assert not (mask & geom_pixels(env, outside)).any()          # nothing else
        assert geom_pixels(env, ["ball", "target_ball"]).any()           # both in view
        labels = {f"{g} ({env.model.body(env.model.geom(g).bodyid[0]).name})" for g in robot_geoms}
    finally:
        env.close()
    assert report["root"] == "upper_arm" and report["named"]
    assert set(report["bodies"]) == arm and {"hand", "fingertip", "thumbtip"} <= arm
    assert report["mask_fraction"] > 0.005 and report["iou"] == 1.0
    assert set(report["robot_px"]) == labels
    for other in ("ball (ball)", "target_ball (target_ball)", "arm_root (world)"):
        assert report["other_px"][other] > 0


def test_envs_py_robot_names_the_root_and_its_source_and_the_gallery_draws_it(tmp_path):
    def cli(*args):
        r = subprocess.run([sys.executable, str(ROOT / "envs.py"), *args], capture_output=True,
                           text=True, timeout=600, env=ENV, cwd=tmp_path)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stdout

    out = cli("--robot", "manipulator-bring_ball", "--frames", "2")
    assert "robot root body 'upper_arm', named in envs._DMC_ROBOT_ROOTS" in out
    assert re.search(r"IoU with the segmentation's robot geoms 1\.000", out)
    others = next(line for line in out.splitlines() if line.startswith("other geoms in view"))
    assert "ball (ball)" in others and "arm_root (world)" in others
    assert "GUESSED" in cli("--robot", "lqr-lqr_2_1", "--frames", "1")   # a domain not named
    assert "wrote" in cli("--gallery", "arm.png", "--envs", "manipulator-bring_ball")
    assert (tmp_path / "arm.png").stat().st_size > 0


def test_the_pages_gymnasium_backend_masks_the_hopper_and_not_the_floor():
    page = PAGE.read_text()
    block = re.search(r"## A gymnasium MuJoCo env.*?```python\n(.*?)```", page, re.S).group(1)
    namespace = {}
    exec(compile(block, str(PAGE), "exec"), namespace)
    report = namespace["report"]
    assert report["root"] == "torso" and report["named"]
    assert set(report["bodies"]) == {"torso", "thigh", "leg", "foot"}
    assert report["mask_fraction"] > 0.005 and report["iou"] == 1.0
    assert all(px > 0 for px in report["robot_px"].values())
    assert report["other_px"]["floor (world)"] > 0
