"""Multi-task and transfer: Meta-World task sets, kitchen-multitask, the Kitchen camera, per-task
evaluation, the multi-task defaults and --init-from. Fast render, tiny networks and budgets."""
import csv
import json
import os
import subprocess
import sys
import types
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest
import torch
from scipy import ndimage

from harness import cli
import envs
from harness import experiment, runenvs
import sear
import train
from tests.test_envs import raw_robot, rand_vecs, is_one_of

ROOT = Path(__file__).resolve().parents[1]
# tests/test_cli.py's TINY, with shorter episodes: a task set switches renderers at every new task.
TINY = ["--frames", "8", "--seed-frames", "4", "--batch-size", "4", "--eval-every", "100",
        "--eval-episodes", "1", "--max-episode-steps", "4", "--replay-size", "400",
        "--latent-dim", "64", "--hidden-dim", "32", "--render-quality", "fast"]
KITCHEN_SOLVED = {  # FrankaKitchen's goals (OBS_ELEMENT_INDICES -> OBS_ELEMENT_GOALS)
    "microwave": (slice(22, 23), (-0.75,)), "light switch": (slice(17, 19), (-0.69, -0.05)),
    "bottom burner": (slice(11, 13), (-0.88, -0.01)),
    "kettle": (slice(23, 30), (-0.23, 0.75, 1.62, 0.99, 0.0, 0.0, -0.06))}


def run_sear(args, cwd, timeout=300):
    env = {**os.environ, "MUJOCO_GL": "egl"}
    return subprocess.run([sys.executable, str(ROOT / "sear.py"), *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=env)


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------- Meta-World task sets
@pytest.fixture(scope="module")
def mt10():
    env = envs.make_env("metaworld-mt10", seed=0, render_quality="fast")
    yield env
    env.close()


def test_task_sampling_covers_every_task_uniformly_and_reproducibly(mt10):
    from metaworld import env_dict   # what metaworld.MT10 takes as its train_classes
    assert mt10.tasks == tuple(n[:-len("-v3")] for n in env_dict.MT10_V3) and len(mt10.tasks) == 10
    assert len(envs.metaworld_set_tasks("mt50")) == 50
    backend = mt10.backend
    drawn = [backend.draw(seed) for seed in range(1000)]   # task and variation from the reset seed
    counts = {t: sum(task == t for task, _ in drawn) for t in mt10.tasks}
    assert all(70 <= c <= 130 for c in counts.values()), counts   # 100 +- 3 sd per task
    assert all(0 <= v < 50 for _, v in drawn) and len({v for _, v in drawn}) == 50
    assert [backend.draw(seed) for seed in range(1000)] == drawn
    assert backend.draw(3, task="door-open") == backend.draw(3, task="door-open")
    # Through the env: info names the task at reset and at every step; same seed, same episode.
    a, info = mt10.reset(seed=5)
    _, _, _, _, step_info = mt10.step(np.zeros(4, np.float32))
    task, variation = backend.draw(int(np.random.default_rng(5).integers(2**31 - 1)))  # SEAREnv's seed
    assert info["task"] == step_info["task"] == task and backend.variation == variation
    assert is_one_of(backend.env._last_rand_vec, rand_vecs(backend.variations))   # set_task took it
    b, info_b = mt10.reset(seed=5)   # after a step: the same episode start again
    assert info_b == info and np.array_equal(a["pixels"], b["pixels"]) and np.array_equal(a["mask"], b["mask"])
    with pytest.raises(envs.EnvError, match="has no task 'reach-v3'"):
        mt10.reset(options={"task": "reach-v3"})


def test_mask_is_exactly_the_robot_on_every_mt10_task(mt10):
    for task in mt10.tasks:
        obs, info = mt10.reset(seed=1, options={"task": task})
        assert info["task"] == task
        mask = obs["mask"][-1].astype(bool)
        robot, seg = raw_robot(mt10)  # an independent walk of the body tree, oriented like obs
        # The paper's pipeline on the robot-geom pixels: binary opening, then 3x3 majority.
        votes = ndimage.binary_opening(robot).reshape(84, 3, 84, 3).sum(axis=(1, 3))
        assert np.array_equal(mask, votes > 4), task
        # The task's objects are in view and none of their pixels is robot.
        is_geom = seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
        objects = is_geom & ~mt10.geom_is_robot[np.where(is_geom, seg[..., 0], 0)]
        object_bodies = {mt10.model.body(mt10.model.geom_bodyid[g]).name for g in np.unique(seg[..., 0][objects])}
        assert object_bodies - {"tablelink", "world"}, task  # more than table and floor
        assert not (robot & objects).any() and 0.03 < mask.mean() < 0.5, task


# ---------------------------------------------------------------- Kitchen
@pytest.fixture(scope="module")
def kitchen():
    env = envs.make_env("kitchen-multitask", seed=0, render_quality="fast", kitchen_camera="random")
    yield env
    env.close()


def solve(env, *subtasks):
    for name in subtasks:
        index, goal = KITCHEN_SOLVED[name]
        env.data.qpos[index] = goal
    env.data.qvel[:] = 0
    mujoco.mj_forward(env.model, env.data)


def test_kitchen_multitask_reward_sums_solved_subtasks(kitchen):
    zero = np.zeros(kitchen.action_space.shape, np.float32)
    kitchen.reset(seed=0)
    solve(kitchen, "microwave", "light switch")
    _, reward, terminated, truncated, info = kitchen.step(zero)
    assert reward == 2.0 and not info["success"] and not (terminated or truncated)
    solve(kitchen, "microwave", "light switch")   # still solved: each sub-task counts once
    assert kitchen.step(zero)[1] == 0.0
    solve(kitchen, "microwave", "light switch", "bottom burner", "kettle")
    _, reward, terminated, truncated, info = kitchen.step(zero)
    assert reward == 2.0 and info["success"] and truncated and not terminated  # all four: solved


def test_random_kitchen_camera_moves_image_and_mask(kitchen):
    views = {}
    for seed in range(12):
        obs, _ = kitchen.reset(seed=seed)
        cam = kitchen.backend.camera
        views.setdefault((cam.azimuth, cam.elevation), obs)
        robot, _ = raw_robot(kitchen)  # the segmentation render uses the same camera
        votes = ndimage.binary_opening(robot).reshape(84, 3, 84, 3).sum(axis=(1, 3))
        assert np.array_equal(obs["mask"][-1].astype(bool), votes > 4)
    assert set(views) == set(envs._KITCHEN_CAMERAS)   # the authors' six views
    a, b = views[70.0, -60.0], views[110.0, -30.0]
    assert np.abs(a["pixels"].astype(int) - b["pixels"]).mean() > 10
    assert (a["mask"][-1] != b["mask"][-1]).mean() > 0.02
    with pytest.raises(envs.EnvError, match="only applies to kitchen"):
        envs.make_env("walker-walk", kitchen_camera="random")


# ---------------------------------------------------------------- sear.py: defaults, evaluation plan
def test_multitask_defaults_apply_to_task_sets_unless_given():
    cfg, _, _ = cli.parse_args(["--env", "metaworld-mt10"], train.Config, train.METHODS)
    assert (cfg.latent_dim, cfg.std_steps) == (512, 2_000_000)
    cfg, _, _ = cli.parse_args(["--env", "metaworld-mt10", "--recipe", "authors"], train.Config,
                               train.METHODS)
    assert (cfg.latent_dim, cfg.std_steps) == (4096, 2_000_000)   # the authors' code keeps 4096
    cfg, _, _ = cli.parse_args(["--env", "metaworld-mt50", "--latent-dim", "256", "--std-steps", "7"], train.Config,
                               train.METHODS)
    assert (cfg.latent_dim, cfg.std_steps) == (256, 7)
    cfg, _, _ = cli.parse_args(["--env", "metaworld-door-open"], train.Config, train.METHODS)
    assert (cfg.latent_dim, cfg.std_steps) == (4096, 500_000)


def test_evaluation_runs_every_task():
    cfg = train.Config(eval_episodes=10)
    three = ("a", "b", "c")
    assert runenvs.eval_tasks(three, cfg) == ["a"] * 4 + ["b"] * 4 + ["c"] * 4   # ceil(10 / 3)
    cfg.eval_episodes_per_task = 2
    assert runenvs.eval_tasks(three, cfg) == ["a", "a", "b", "b", "c", "c"]
    one = None
    assert runenvs.eval_tasks(one, cfg) == [None] * 10
    episodes = [train.Episode(1.0, False, "a"), train.Episode(3.0, True, "a")]
    assert experiment.eval_columns(episodes) == {"success": 0.5, "return/a": 2.0, "success/a": 0.5}


# ---------------------------------------------------------------- transfer
@pytest.mark.parametrize("parts", ["encoder", "encoder+decoders", "all"])
def test_copy_parts_copies_exactly_the_named_parts(parts, device):
    cfg = train.Config(latent_dim=64, hidden_dim=32, feature_dim=8)
    torch.manual_seed(0)
    source = sear.Agent(cfg, 4, device)
    with torch.no_grad():  # stands for training: every weight moves
        for net in (source.encoder, source.aux, source.actor, source.critic, source.critic_target):
            for p in net.parameters():
                p.add_(1.0)
    torch.manual_seed(1)
    agent = sear.Agent(cfg, 4, device)
    fresh = {k: {n: v.clone() for n, v in sd.items()} for k, sd in agent.state_dict().items()
             if k in ("encoder", "aux", "actor", "critic", "critic_target")}
    experiment.copy_parts(agent, source.state_dict(), parts)
    copied = {"encoder": ["encoder"], "encoder+decoders": ["encoder", "aux"],
              "all": ["encoder", "aux", "actor", "critic"]}[parts]
    saved, now = source.state_dict(), agent.state_dict()
    for name in fresh:
        like = "critic" if name == "critic_target" and "critic" in copied else name
        expected = saved[like] if like in copied else fresh[name]
        assert all(torch.equal(now[name][k], expected[k]) for k in expected), name
        if like not in copied:
            assert not any(torch.equal(now[name][k], saved[name][k]) for k in expected if k.endswith("weight")), name
    assert all(not s["step"] and not s["exp_avg"].any() for opt in (agent.model_opt, agent.actor_opt)
               for s in opt.state.values())  # optimisers fresh


@pytest.fixture(scope="module")
def mt3_run(tmp_path_factory):
    """A CLI smoke run of metaworld-mt3: the source of the transfer tests."""
    root = tmp_path_factory.mktemp("mt3")
    r = run_sear(["--run-root", str(root / "runs"), "--env", "metaworld-mt3", "--log-every", "0", *TINY], root)
    assert r.returncode == 0, r.stderr[-2000:]
    (run_dir,) = (root / "runs").iterdir()
    return run_dir, r.stdout


def test_mt3_smoke_run_evaluates_every_task(mt3_run):
    run_dir, stdout = mt3_run
    tasks = envs.metaworld_set_tasks("mt3")
    assert "evaluating at frame 0 (3 episodes)" in stdout   # ceil(1 / 3) = 1 per task
    evals = rows(run_dir / "eval.csv")
    assert [int(r["frame"]) for r in evals] == [0, 8]
    for r in evals:
        per_task = [float(r[f"success/{t}"]) for t in tasks]
        assert float(r["success"]) == pytest.approx(np.mean(per_task))
        assert float(r["return"]) == pytest.approx(np.mean([float(r[f"return/{t}"]) for t in tasks]))
        # sear's decoder metrics sit next to the per-task columns, over the frames of every task
        assert 0.0 <= float(r["mask_iou"]) <= 1.0 and float(r["mask_bce"]) > 0 and float(r["recon_psnr"]) > 0
    assert {r["task"] for r in rows(run_dir / "train.csv")} <= set(tasks)
    config = json.loads((run_dir / "config.json").read_text())
    assert config["std_steps"] == 2_000_000 and config["latent_dim"] == 64   # explicit flags win


def test_plot_per_task_draws_one_panel_per_task(mt3_run, tmp_path, capsys):
    import plot
    run_dir, _ = mt3_run
    assert plot.main([str(run_dir), "--per-task", "--metric", "success", "--out", str(tmp_path / "t.png")]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| metaworld-mt3")]
    assert [line.split(" | ")[0] for line in table] == [f"| metaworld-mt3: {t}" for t in envs.metaworld_set_tasks("mt3")] \
        + ["| metaworld-mt3: mean over 3 tasks"]
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"
    assert plot.main([str(run_dir), "--per-task", "--csv", "train", "--out", str(tmp_path / "u.png")]) == 2


def test_finetune_starts_from_the_whole_source_agent_by_default(mt3_run, tmp_path):
    """The authors' default (cfgs/agent/common.yaml pretrain.just_encoder_decoders: false): encoder,
    decoders, actor and critic; fresh optimisers."""
    source_dir, _ = mt3_run
    args = ["--run-root", str(tmp_path / "runs"), "--env", "metaworld-peg-insert-side", "--init-from",
            str(source_dir), *TINY, "--frames", "8", "--seed-frames", "100"]
    assert train.main(args) == 0  # the CLI in this process; no update: the seed frames outlast the budget
    (run_dir,) = (tmp_path / "runs").iterdir()
    config = json.loads((run_dir / "config.json").read_text())
    assert config["init_from"] == str(source_dir) and config["init_parts"] == "all"
    assert config["latent_dim"] == 64 and config["hidden_dim"] == 32   # the source's sizes
    source = torch.load(source_dir / "snapshot.pt", weights_only=False)["agent"]
    agent = torch.load(run_dir / "snapshot.pt", weights_only=False)["agent"]
    for part, like in (("encoder", "encoder"), ("aux", "aux"), ("actor", "actor"), ("critic", "critic"),
                       ("critic_target", "critic")):
        assert all(torch.equal(agent[part][k], source[like][k]) for k in source[like]), part
    assert all(not s["step"] and not s["exp_avg"].any() for s in agent["model_opt"]["state"].values())  # never stepped


@pytest.mark.parametrize("extra, message", [
    (["--env", "metaworld-hammer", "--latent-dim", "128"],
     "--init-from: the source run has --latent-dim 64 but this run 128;"),
    (["--env", "metaworld-hammer", "--method", "drq"], "--init-from: the source run has --method sear but this run drq;"),
    (["--env", "walker-walk"], "--init-parts all: the source run's actor has 4 actions, walker-walk has 6;"),
])
def test_init_from_refuses_mismatches_and_creates_nothing(mt3_run, tmp_path, capsys, extra, message):
    source_dir, _ = mt3_run
    code = train.main(["--run-root", str(tmp_path / "runs"), "--init-from", str(source_dir), *TINY, *extra])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("holds, says", [("config.json", "has no snapshot.pt"), (None, "is not a run directory")])
def test_init_from_a_run_without_snapshot(tmp_path, capsys, holds, says):
    """A run that stopped before its first snapshot (config.json only), and a folder that is no run."""
    (tmp_path / "source").mkdir()
    if holds:
        (tmp_path / "source" / holds).write_text("{}")
    code = train.main(["--run-root", str(tmp_path / "runs"), "--init-from", str(tmp_path / "source")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("sear.py: error: --init-from:") and says in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "runs").exists()


@pytest.mark.parametrize("args, message", [
    (["--kitchen-camera", "sideways"], "argument --kitchen-camera: invalid choice: 'sideways'"),
    (["--eval-episodes-per-task", "-1"], "--eval-episodes-per-task must be >= 0, got -1"),
    (["--init-parts", "all"], "--init-parts all does nothing in this run (sear on walker-walk): it is for runs with "
                               "--init-from"),
    (["--init-from", "x", "--init-parts", "decoders"], "argument --init-parts: invalid choice: 'decoders'"),
    (["--env", "walker-walk", "--kitchen-camera", "random"], "--kitchen-camera random does nothing in this run (sear on "
                                                          "walker-walk): it is for Kitchen (kitchen-* envs)"),
])
def test_bad_multitask_flags_are_one_line(tmp_path, capsys, args, message):
    code = train.main(["--run-root", str(tmp_path / "runs"), *TINY, *args])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "runs").exists()
