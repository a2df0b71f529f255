"""segment.py (the learned robot mask) and sear.py --mask-source learned:PATH.

Tiny networks and budgets: the IoU-vs-labels numbers live in benchmarks/bench_segment.py.
"""
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest
import torch
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import envs  # noqa: E402
import sear  # noqa: E402
import train  # noqa: E402
import segment  # noqa: E402

TINY = ["--frames", "24", "--seed-frames", "12", "--batch-size", "4", "--eval-every", "24",
        "--eval-episodes", "1", "--max-episode-steps", "6", "--replay-size", "100",
        "--latent-dim", "64", "--hidden-dim", "32", "--render-quality", "fast", "--threads", "1"]


def shapes(n, size=48, seed=0):
    """Synthetic labelled frames: a "robot" (an orange bar and a disc, random pose) on a noisy
    background with grey distractor blocks."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    images = rng.integers(0, 120, (n, 3, size, size), dtype=np.uint8)
    masks = np.zeros((n, size, size), bool)
    for i in range(n):
        cy, cx, r = *rng.integers(12, size - 12, 2), rng.integers(4, 8)
        y0, x0 = rng.integers(0, size - 10, 2)
        images[i, :, y0:y0 + 8, x0:x0 + 8] = 150   # a distractor, not robot
        mask = ((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r) | ((abs(yy - cy) <= 1) & (xx >= cx) & (xx < cx + 12))
        images[i][:, mask] = np.array([230, 140, 30], np.uint8)[:, None]
        masks[i] = mask
    return images, masks


def constant_model(path, robot: bool):
    """A mask model that calls every pixel robot (or none): its masks differ from any rendered one."""
    net = segment.UNet((4, 8))
    with torch.no_grad():
        net.head.weight.zero_()
        net.head.bias.fill_(10.0 if robot else -10.0)
    segment.MaskModel(net, {"labels": 0}).save(str(path))
    return path


def test_unet_overfits_a_tiny_labelled_set():
    images, masks = shapes(8)
    model = segment.train_model(images, masks, steps=150, batch_size=8, lr=3e-3, channels=(8, 16), seed=0)
    assert segment.iou(segment.predict(model, images), masks) > 0.9


def test_model_file_round_trip_and_predictions(tmp_path):
    images, _ = shapes(3)
    model = segment.MaskModel(segment.UNet((4, 8, 16)), {"labels": 3})
    model.save(str(tmp_path / "m.pt"))
    loaded = segment.load_model(str(tmp_path / "m.pt"))
    assert loaded.net.channels == (4, 8, 16) and loaded.meta == {"labels": 3}
    assert np.array_equal(loaded(images), model(images))
    assert loaded(images[0]).shape == (48, 48) and loaded(images[0]).dtype == bool


def test_folder_round_trip_and_train_cli(tmp_path, capsys):
    images, masks = shapes(6)
    segment.write_folder(str(tmp_path / "labels"), images, masks)
    got_images, got_masks, names = segment.read_folder(str(tmp_path / "labels"), size=48)
    assert np.array_equal(got_images, images) and np.array_equal(got_masks, masks) and len(names) == 6
    # Any size is brought to 84 x 84, the observation size (mask by area, then threshold).
    assert segment.read_folder(str(tmp_path / "labels"))[0].shape == (6, 3, 84, 84)
    out = tmp_path / "m.pt"
    assert segment.main(["train", "--folder", str(tmp_path / "labels"), "--out", str(out), "--steps", "2",
                         "--channels", "4,8", "--force"]) == 0   # 2 steps: below the IoU floor, forced
    meta = segment.load_model(str(out)).meta
    assert meta["labels"] == 5 and set(meta["iou"]) == {"train", "held-out"}   # 1 of 6 held out
    assert segment.main(["train", "--folder", str(tmp_path / "labels"), "--out", str(out)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err


def test_train_refuses_a_model_below_the_iou_floor_unless_forced(tmp_path, capsys):
    """The case that set the floor: a model that finds no robot (IoU ~0 after 1 step) is one line, exit 2, no file;
    --force writes it and the file records that it was forced below the floor."""
    images, masks = shapes(10)
    segment.write_folder(str(tmp_path / "labels"), images, masks)
    out = tmp_path / "m.pt"
    train = ["train", "--folder", str(tmp_path / "labels"), "--out", str(out), "--steps", "1", "--channels", "4,8"]
    assert segment.main(train) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("segment.py: error: the model's held-out IoU is 0.") \
        and f"below the floor {segment.IOU_FLOOR}" in err and "--force" in err, err
    assert not out.exists() and not list(tmp_path.glob("*.tmp"))
    assert segment.main([*train, "--force"]) == 0
    meta = segment.load_model(str(out)).meta
    assert meta["forced_below_floor"] is True and meta["iou_floor"] == segment.IOU_FLOOR
    assert meta["iou"]["held-out"] < segment.IOU_FLOOR
    assert "written because of --force" in capsys.readouterr().err
    # No held-out pairs (--holdout 0): the training frames' IoU is held to the floor instead.
    assert segment.main([*train, "--holdout", "0", "--out", str(tmp_path / "n.pt")]) == 2
    assert "the model's train IoU is 0." in capsys.readouterr().err and not (tmp_path / "n.pt").exists()


def test_a_model_above_the_floor_is_written_and_says_so(tmp_path, capsys):
    images, masks = shapes(10)
    segment.write_folder(str(tmp_path / "labels"), images, masks)
    out = tmp_path / "m.pt"
    assert segment.main(["train", "--folder", str(tmp_path / "labels"), "--out", str(out), "--steps", "60",
                         "--batch-size", "8", "--lr", "3e-3", "--channels", "8,16", "--holdout", "0"]) == 0
    assert "held-out IoU not measured" in capsys.readouterr().out
    meta = segment.load_model(str(out)).meta
    assert meta["iou"]["train"] >= segment.IOU_FLOOR and "forced_below_floor" not in meta


def bad_folder(tmp_path, case):
    folder = tmp_path / case
    folder.mkdir()
    rgb = np.zeros((32, 32, 3), np.uint8)
    Image.fromarray(rgb).save(folder / "a.png")
    mask = np.zeros((32, 32), np.uint8)
    mask[4:9, 4:9] = 255
    if case == "size":
        mask = np.zeros((30, 32), np.uint8)
    if case == "grey":
        mask[10, 10] = 128
    if case == "colour":
        mask = np.stack([mask, 0 * mask, mask], axis=-1)
    Image.fromarray(mask).save(folder / "a_mask.png")
    if case == "corrupt":
        (folder / "a.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    if case == "unpaired":
        Image.fromarray(rgb).save(folder / "b.png")
    if case == "empty":
        for p in folder.iterdir():
            p.unlink()
    return folder


@pytest.mark.parametrize("case, message", [
    ("missing", "does not exist"), ("empty", "no <name>.png"), ("size", "they must match"),
    ("grey", "not binary"), ("colour", "not binary"), ("corrupt", "not a readable image"),
    ("unpaired", "without their pair")])
def test_bad_label_folders_are_one_line_exit_2(tmp_path, capsys, case, message):
    folder = tmp_path / "nowhere" if case == "missing" else bad_folder(tmp_path, case)
    out = tmp_path / "m.pt"
    assert segment.main(["train", "--folder", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("segment.py: error: ") and message in err, err
    assert not out.exists()


@pytest.mark.parametrize("where", ["a file in the way", "file size limit"])
def test_a_storage_error_writing_the_model_is_one_line_and_leaves_nothing(tmp_path, where):
    """--out under a file (ENOTDIR), or a 4 kB RLIMIT_FSIZE the model file exceeds (EFBIG): one line
    naming the path, exit 2, no model and no .tmp left."""
    import resource
    images, masks = shapes(6)
    segment.write_folder(str(tmp_path / "labels"), images, masks)
    (tmp_path / "afile").write_text("")
    out = tmp_path / "afile" / "m.pt" if where == "a file in the way" else tmp_path / "models" / "m.pt"
    limit = 4096
    p = subprocess.run([sys.executable, str(ROOT / "segment.py"), "train", "--folder", str(tmp_path / "labels"),
                        "--out", str(out), "--steps", "1", "--channels", "4,8", "--force"], capture_output=True, text=True,
                       timeout=300, preexec_fn=None if where == "a file in the way" else
                       lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    expected = (f"segment.py: error: cannot write '{out}': '{tmp_path / 'afile'}' is a file, not a folder"
                if where == "a file in the way" else
                f"segment.py: error: cannot write '{out}': File too large (EFBIG)")
    assert p.stderr.strip() == expected
    assert not out.exists() and not list(tmp_path.rglob("*.tmp"))


def test_cli_process_exit_code_and_single_line(tmp_path):
    p = subprocess.run([sys.executable, str(ROOT / "segment.py"), "train", "--folder", str(tmp_path / "no"),
                        "--out", str(tmp_path / "m.pt")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr


def test_learned_mask_replaces_the_simulator_and_noise_composes(tmp_path):
    model = segment.load_model(str(constant_model(tmp_path / "all.pt", robot=True)))
    env = envs.make_env("walker-walk", seed=0, render_quality="fast", render_mask=False, mask_model=model)
    obs, info = env.reset(seed=0)
    obs, *_, info = env.step(np.zeros(env.action_space.shape))
    assert obs["mask"].all() and "true_mask" not in info and env.segmentation_renders == 0
    env.close()
    env = envs.make_env("walker-walk", seed=0, render_quality="fast", render_mask=True, mask_model=model,
                        mask_noise=0.5)
    obs, info = env.reset(seed=0)
    # The simulator's mask is only reported; the noise corrupts the learned mask (about half of it).
    assert 0.03 < info["true_mask"].mean() < 0.3 and 0.4 < obs["mask"].mean() < 0.6
    env.close()


def run_sear(tmp_path, capsys, *extra):
    code = train.main(["--env", "walker-walk", "--run-root", str(tmp_path / "runs"), *TINY, *extra])
    return code, capsys.readouterr()


@pytest.mark.parametrize("metric", [True, False])
def test_a_learned_run_never_trains_on_a_rendered_mask(tmp_path, capsys, monkeypatch, metric):
    """Every mask the replay holds (the targets and RGBM's inputs) is the model's (all ones here), and
    the segmentation render runs only in evaluation, for the metric, or (metric off) never."""
    renders = {"train": 0, "eval": 0}
    original = envs.SEAREnv.segmentation

    def counted(self):
        renders["eval" if self.split_name == "eval" else "train"] += 1
        return original(self)

    made = envs.make_env

    def tagged(*args, **kwargs):
        env = made(*args, **kwargs)
        env.split_name = kwargs.get("split", "train")
        return env

    monkeypatch.setattr(envs.SEAREnv, "segmentation", counted)
    monkeypatch.setattr(envs, "make_env", tagged)
    path = constant_model(tmp_path / "all.pt", robot=True)
    code, out = run_sear(tmp_path, capsys, "--mask-source", f"learned:{path}", "--save-buffer",
                         "--learned-mask-iou" if metric else "--no-learned-mask-iou")
    assert code == 0, out.err
    run_dir = next((tmp_path / "runs").iterdir())
    buffer = np.load(run_dir / "buffer.npz")
    assert len(buffer["masks"]) > 0 and (buffer["masks"] == 255).all()   # packed bits: all robot
    assert renders["train"] == 0
    assert json.loads((run_dir / "config.json").read_text())["mask_source"] == f"learned:{path}"
    with open(run_dir / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    if metric:
        assert renders["eval"] > 0
        assert all(0 < float(r["learned_mask_iou"]) < 0.5 for r in rows)   # all-ones vs a walker
    else:
        assert renders["eval"] == 0 and "learned_mask_iou" not in rows[0]
    # --resume keeps the mask source; changing it is refused before anything happens.
    code, out = run_sear(tmp_path, capsys, "--resume", str(run_dir), "--mask-source", "sim")
    assert code == 2 and "--mask-source cannot change on --resume" in out.err


@pytest.mark.parametrize("content, message", [(None, "does not exist"),
                                              (b"garbage", "is not a segment.py model file (not a torch file"),
                                              ("dict", "not a segment.py model file")])
def test_missing_or_corrupt_model_is_one_line_before_any_run_dir(tmp_path, capsys, content, message):
    path = tmp_path / "m.pt"
    if content == "dict":
        torch.save({"weights": 1}, path)
    elif content is not None:
        path.write_bytes(content)
    code, out = run_sear(tmp_path, capsys, "--mask-source", f"learned:{path}")
    assert code == 2 and out.err.count("\n") == 1 and message in out.err, out.err
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def model_with(path, **meta):
    segment.MaskModel(segment.UNet((4, 8)), meta).save(str(path))
    return path


@pytest.mark.parametrize("meta, said", [
    ({"iou": {"train": 0.95, "held-out": 0.912}, "iou_floor": 0.5}, "mask model: held-out IoU 0.912 (floor 0.5)"),
    ({"labels": 3}, "mask model: held-out IoU not recorded"),   # an older file, or no held-out pairs
    ({"iou": {"train": 0.2, "held-out": float("nan")}}, "mask model: held-out IoU not recorded")])
def test_sear_prints_the_models_recorded_held_out_iou(tmp_path, capsys, meta, said):
    from harness import runenvs
    cfg = train.Config(env="walker-walk", mask_source=f"learned:{model_with(tmp_path / 'm.pt', **meta)}")
    assert runenvs.load_mask_model(cfg) is not None
    out = capsys.readouterr()
    assert out.out.startswith(said) and out.out.count("\n") == 1 and out.err == "", out


def test_sear_warns_on_a_model_forced_below_the_floor(tmp_path, capsys):
    from harness import runenvs
    path = model_with(tmp_path / "m.pt", iou={"train": 0.01, "held-out": 0.0}, iou_floor=0.5, forced_below_floor=True)
    assert runenvs.load_mask_model(train.Config(env="walker-walk", mask_source=f"learned:{path}")) is not None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sear.py: warning: --mask-source: the mask model was written "
                                                    "below the IoU floor 0.5 with segment.py train --force"), err
    assert "held-out 0.000" in err


def test_sear_refuses_a_recorded_held_out_iou_below_the_floor(tmp_path, capsys):
    """Only an older segment.py wrote such a file unforced: one line, exit 2, before any run dir."""
    path = model_with(tmp_path / "m.pt", iou={"train": 0.0, "held-out": 0.0})
    code, out = run_sear(tmp_path, capsys, "--mask-source", f"learned:{path}")
    assert code == 2 and out.err == ("sear.py: error: --mask-source: the mask model's held-out IoU is 0.000, below the "
                                     "floor 0.5; train a better one with python segment.py train (more labels or "
                                     "--steps)\n"), out.err
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_iou_watch_warns_once_when_two_evaluations_in_a_row_are_below_the_floor():
    watch = segment.IoUWatch()
    # One low evaluation (the untrained policy's frames, say) is not enough; a good one resets the count;
    # an evaluation without a score (NaN) neither counts nor resets.
    assert [watch.see(v, f) for v, f in ((0.1, 0), (0.9, 1000), (0.2, 2000), (float("nan"), 3000))] == [None] * 4
    message = watch.see(0.3, 4000)
    assert message.startswith("learned_mask_iou has stayed below 0.5 for 2 evaluations (0.200 at frame 2000, "
                              "0.300 at frame 4000): the learned masks have more pixels wrong"), message
    assert watch.see(0.0, 5000) is None and watch.see(0.0, 6000) is None   # once
    watch = segment.IoUWatch()
    assert watch.see(0.5) is None and watch.see(0.5) is None   # the floor itself passes
    # The run's watch lives on its eval env, the one LearnedMaskIoU of the run.
    env = envs.make_env("walker-walk", seed=0, render_quality="fast")
    assert isinstance(segment.LearnedMaskIoU(env).low_iou, segment.IoUWatch)
    env.close()


def test_mask_source_flag_is_checked(tmp_path, capsys):
    code, out = run_sear(tmp_path, capsys, "--mask-source", "learned:")
    assert code == 2 and "--mask-source must be sim or learned:PATH" in out.err
    code, out = run_sear(tmp_path, capsys, "--mask-source", f"learned:{tmp_path}/m.pt", "--method", "drq")
    assert code == 2 and "for methods that use the robot mask" in out.err
