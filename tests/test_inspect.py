"""What SEAR learns: evaluation videos, decoder metrics in eval.csv, and `plot.py maps`."""
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from harness import experiment
import plot
import sear
import train
from tests.test_cli import ROOT, TINY, rows, run, tiny, tree_digest

# Two evaluations (frame 0 and the end of the budget), each 2 episodes of 8 agent steps.
RUN = [*TINY, "--env", "walker-walk", "--frames", "16", "--seed-frames", "8", "--eval-every", "100",
       "--eval-episodes", "2"]


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    """A sear run with --save-video and a drq run without, on the same env: {method: run dir}."""
    tmp = tmp_path_factory.mktemp("inspect")
    dirs = {}
    for method, extra in (("sear", ["--save-video"]), ("drq", [])):
        r = run([*tiny(method), *RUN[len(TINY):], "--method", method, *extra], tmp)
        assert r.returncode == 0, r.stderr[-2000:]
        (dirs[method],) = (tmp / "runs").glob(f"walker-walk__{method}__*")
    return dirs


# ---------------------------------------------------------------- metrics
def test_mask_iou_is_one_for_a_perfect_prediction_and_zero_for_an_empty_one():
    true = torch.zeros(3, 84, 84, dtype=torch.bool)
    true[:, 20:40, 30:50] = True
    assert experiment.mask_iou(true, true).tolist() == [1.0, 1.0, 1.0]
    assert experiment.mask_iou(torch.zeros_like(true), true).tolist() == [0.0, 0.0, 0.0]
    half = true.clone()
    half[:, 30:40] = False  # half of the robot found, nothing else claimed
    assert experiment.mask_iou(half, true).tolist() == pytest.approx([0.5] * 3)
    assert math.isnan(experiment.mask_iou(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4)).item())  # nothing to score


def test_psnr_of_a_known_error():
    target = torch.rand(2, 3, 84, 84) * 0.8
    assert experiment.psnr(target + 0.1, target).tolist() == pytest.approx([20.0, 20.0], abs=1e-4)  # mse 0.01
    assert experiment.psnr(torch.zeros(1, 3, 8, 8), torch.ones(1, 3, 8, 8)).item() == pytest.approx(0.0)


def test_eval_csv_has_decoder_metrics_for_sear_and_not_for_drq(tiny_runs):
    sear_rows, drq_rows = rows(tiny_runs["sear"] / "eval.csv"), rows(tiny_runs["drq"] / "eval.csv")
    assert [int(r["frame"]) for r in sear_rows] == [0, 16]
    for r in sear_rows:
        assert 0.0 <= float(r["mask_iou"]) <= 1.0
        assert float(r["mask_bce"]) > 0.0
        assert 0.0 < float(r["recon_psnr"]) < 60.0
    assert not {"mask_iou", "mask_bce", "recon_psnr"} & set(drq_rows[0])
    assert not (tiny_runs["drq"] / "videos").exists()  # no --save-video, no video


def test_save_video_writes_the_first_episode_of_each_evaluation(tiny_runs):
    import imageio.v2 as imageio
    videos = tiny_runs["sear"] / "videos"
    assert sorted(p.name for p in videos.iterdir()) == ["eval_0.mp4", "eval_16.mp4"]
    with imageio.get_reader(videos / "eval_16.mp4") as reader:
        frames = [frame for frame in reader]  # list() would trust its length: inf for ffmpeg
    # The reset frame and the 8 steps of episode 0 (episode 1 is not filmed); four panels of
    # 84 x 84 upscaled x4 under a 16-px strip of labels.
    assert len(frames) == 9
    assert frames[0].shape == (16 + 336, 4 * 336, 3)
    camera, true_mask = frames[4][16:, :336], frames[4][16:, 336:672]
    assert camera.std() > 10  # a picture, not a blank
    assert 0.0 < (true_mask[4:-4, 4:-4].mean(-1) > 128).mean() < 0.5  # the walker's mask: some white


@pytest.mark.parametrize("method, scores, panels", [
    ("drq", set(), 1),  # the camera alone: no mask rendered, no decoder; frames pass through unscored
    ("mae", {"recon_psnr"}, 2),  # camera | reconstruction
    ("sear", {"mask_iou", "mask_bce", "recon_psnr"}, 4),
])
def test_eval_watch_scores_and_films_what_a_method_has(tmp_path, method, scores, panels, device):
    pytest.importorskip("imageio_ffmpeg", reason="films need imageio-ffmpeg (requirements.txt; sear.py checks it at start)")
    import imageio.v2 as imageio
    cfg = train.Config(method=method, frame_stack=3, latent_dim=64, hidden_dim=32)
    agent = train.make_agent(cfg, 2, device)

    def obs(t):  # a moving square to film, on the robot's mask
        pixels, mask = np.zeros((9, 84, 84), np.uint8), np.zeros((3, 84, 84), np.uint8)
        pixels[:, 10:30, 10 + t:30 + t] = 200
        mask[:, 10:30, 10 + t:30 + t] = 1
        return {"pixels": pixels, "mask": mask}

    watch = experiment.EvalWatch(agent, str(tmp_path / "videos" / "eval_0.mp4"))
    # what train.evaluate shows it: two episodes of a reset and 5 steps; the first one filmed
    for _ in range(2):
        watch.see(obs(0), new_episode=True)
        for t in range(1, 6):
            watch.see(obs(t))
    assert set(watch.finish()) == scores
    assert all(len(v) == 2 for v in watch.values.values())  # every 10th observation: 0 and 10 of 12
    with imageio.get_reader(tmp_path / "videos" / "eval_0.mp4") as reader:
        frames = [frame for frame in reader]
    assert len(frames) == 6 and frames[0].shape == (16 + 336, panels * 336, 3)


# ---------------------------------------------------------------- activation maps
def test_maps_grid_shape_and_overlay():
    image = np.full((84, 84, 3), 100, np.uint8)
    maps = np.random.default_rng(0).random((32, 35, 35)).astype(np.float32)
    tiles = plot.overlay_maps(image, maps)
    assert tiles.shape == (32, 84, 84, 3) and tiles.dtype == np.uint8
    grid = plot.channel_grid(tiles, cols=8, pad=2)
    assert grid.shape == (4 * 84 + 3 * 2, 8 * 84 + 7 * 2, 3)
    assert (grid[84:86] == 255).all()  # the gap between the first two rows of tiles
    assert np.array_equal(grid[86:170, 86:170], tiles[9])  # row 1, column 1


def test_last_conv_maps_are_the_relu_output_of_the_last_convolution():
    cfg = train.Config(latent_dim=64, hidden_dim=32)
    agent = sear.Agent(cfg, 2, torch.device("cpu"))
    pixels = np.random.default_rng(0).integers(0, 255, (2, 9, 84, 84), dtype=np.uint8)
    maps = plot.last_conv_maps(agent, pixels, np.zeros((2, 3, 84, 84), bool))
    expected = agent.encoder.convs(torch.as_tensor(pixels).float() / 255.0 - 0.5)
    assert maps.shape == (2, 32, 35, 35) and maps.min() >= 0
    assert np.allclose(maps, expected.detach().numpy(), atol=1e-6)


def test_robot_share_of_synthetic_channels():
    masks = np.zeros((2, 84, 84), bool)
    masks[:, 20:50, 30:60] = True
    robot = plot.robot_units(masks, 35)
    assert robot.shape == (2, 35, 35)
    assert robot[0, 10, 12] == masks[0, 27, 31] and robot[0, 10, 12]  # unit j looks at pixel 2j + 7
    fraction = robot.mean()
    maps = np.zeros((2, 3, 35, 35))
    maps[:, 0] = robot * 3.0  # fires only on the robot
    maps[:, 1] = 1.0  # fires evenly everywhere
    share = plot.robot_share(maps, robot)
    assert share[0] == pytest.approx(1.0)
    assert share[1] == pytest.approx(fraction)
    assert np.isnan(share[2])  # never fires: no share at all


def test_plot_maps_cli_on_two_tiny_runs(tiny_runs, tmp_path):
    out = tmp_path / "maps.png"
    cmd = [sys.executable, str(ROOT / "plot.py"), "maps", str(tiny_runs["sear"]), str(tiny_runs["drq"]),
           "--out", str(out), "--frames", "2"]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = [line for line in r.stdout.splitlines() if line.startswith("| ") and "walker-walk__" in line]
    assert [line.split(" | ")[1] for line in table] == ["sear", "drq"]
    for line in table:  # robot + environment + dead channels: at most all 32
        robot, environment, dead = (int(x) for x in line.split(" | ")[3:6])
        assert robot + environment + dead <= 32
    # Refuses to overwrite its picture: one line, exit 2, the file untouched.
    before = out.read_bytes()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "refusing to overwrite" in r.stderr
    assert out.read_bytes() == before


def snapshot_junk(run_dir):
    (run_dir / "config.json").write_text("{}")
    (run_dir / "snapshot.pt").write_bytes(b"not a torch file")


@pytest.mark.parametrize("make, message", [
    (lambda run_dir: None, "is not a run directory (no config.json)"),
    (lambda run_dir: (run_dir / "config.json").write_text("{}"), "has no snapshot.pt"),
    (snapshot_junk, "cannot read"),
])
def test_plot_maps_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, make, message):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    make(run_dir)
    before = tree_digest(tmp_path)
    code = plot.main(["maps", str(run_dir), "--out", str(tmp_path / "maps.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message in err and "Traceback" not in err, err
    assert err.startswith("plot.py maps: error: ")
    assert tree_digest(tmp_path) == before


def test_plot_maps_refuses_runs_on_different_envs(tmp_path, capsys):
    """Maps compare channels on the same frames: runs on two envs are refused before anything is built."""
    dirs = []
    for env in ("walker-walk", "cheetah-run"):
        run_dir = tmp_path / env
        run_dir.mkdir()
        (run_dir / "config.json").write_text("{}")
        torch.save({"config": {"env": env}, "agent": {}}, run_dir / "snapshot.pt")
        dirs.append(str(run_dir))
    before = tree_digest(tmp_path)
    code = plot.main(["maps", *dirs, "--out", str(tmp_path / "maps.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "is on cheetah-run" in err and "same frames" in err, err
    assert tree_digest(tmp_path) == before
