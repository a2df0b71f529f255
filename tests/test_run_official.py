"""benchmarks/run_official.py: the official DrQ-v2 train.py on today's stack, adapted from outside.

Without a checkout and hydra (CI): the one-line errors and each adaptation on its own. With SEAR_DRQV2=<a
checkout of facebookresearch/drqv2> and hydra importable: a real run of the official code, read by
published_curve.load_official, and gpu_campaign.sh --quick with its official seeds."""
import os
import random
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from dm_env import specs

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import published_curve  # noqa: E402
import run_official  # noqa: E402

DRQV2 = os.environ.get("SEAR_DRQV2", "")  # a checkout of facebookresearch/drqv2, not part of this project


def hydra_importable() -> bool:
    try:
        import hydra  # noqa: F401
        import omegaconf  # noqa: F401
    except ImportError:
        return False
    return True


needs_official = pytest.mark.skipif(not (DRQV2 and hydra_importable()),
                                    reason="SEAR_DRQV2=<a checkout of facebookresearch/drqv2> and hydra "
                                           "(pip install hydra-core omegaconf antlr4-python3-runtime) not both given")


def fake_checkout(root: Path) -> Path:
    """The files run_official.py looks for, none of them run."""
    (root / "cfgs").mkdir(parents=True)
    for name in ("train.py", "dmc.py", "cfgs/config.yaml"):
        (root / name).write_text("")
    return root


def without_hydra(tmp_path: Path) -> dict:
    """An environment whose python fails to import hydra, as where it is not installed."""
    shadow = tmp_path / "shadow" / "hydra"
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise ImportError(\"No module named 'hydra'\")\n")
    return {**os.environ, "PYTHONPATH": str(shadow.parent), "MUJOCO_GL": "egl"}


def run(args, env=None, timeout=60):
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run_official.py"), *map(str, args)], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=timeout)


def test_a_missing_checkout_is_one_line(tmp_path):
    p = run(["--official", tmp_path / "nowhere", "--", "seed=1"])
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert p.stderr.startswith("run_official.py: error: --official ") and "not a checkout of facebookresearch/drqv2" in p.stderr


@pytest.mark.parametrize("args", [[], ["--official", "x", "--bogus"]])
def test_a_bad_flag_is_one_line(args):
    p = run(args)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and p.stderr.startswith("run_official.py: error: "), p.stderr


def test_missing_hydra_is_one_line_naming_the_packages(tmp_path):
    p = run(["--official", fake_checkout(tmp_path / "drqv2"), "--check"], env=without_hydra(tmp_path))
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr, p.stderr
    assert "the official code needs hydra" in p.stderr
    assert "pip install hydra-core omegaconf antlr4-python3-runtime PyYAML hydra-submitit-launcher" in p.stderr


def test_the_campaign_refuses_a_missing_checkout_or_hydra_in_one_line(tmp_path):
    env = {**without_hydra(tmp_path), "PYTHON": sys.executable}
    for official, message in [(tmp_path / "nowhere", "not a checkout of facebookresearch/drqv2"),
                              (fake_checkout(tmp_path / "drqv2"), "pip install hydra-core")]:
        p = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_campaign.sh"), "--quick", "--official", str(official),
                            "--out", str(tmp_path / "c")], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
        assert p.stderr.startswith("gpu_campaign.sh: error: ") and message in p.stderr, p.stderr
        assert not (tmp_path / "c").exists()


def test_the_action_spec_is_the_wrapped_dtype_and_the_actions_unchanged():
    """dm_control's action_scale.Wrapper over a float32 spec: float64 under NumPy 2 (what the replay storage
    asserts against), float32 once adapted; the actions it hands on are the wrapper's own either way."""
    from dm_control.suite.wrappers import action_scale

    class Inner:
        def __init__(self):
            self.got = []

        def action_spec(self):
            return specs.BoundedArray((2,), np.float32, np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32))

        def step(self, action):
            self.got.append(action)

    dmc = types.SimpleNamespace(action_scale=action_scale)
    run_official.float32_action_spec(dmc)
    assert action_scale.Wrapper(Inner(), -1.0, 1.0).action_spec().dtype == np.result_type(np.array(-1.0), np.float32)
    action = np.array([0.3, -0.7], np.float32)
    (old, a), (new, b) = [(cls(inner, -1.0, 1.0), inner) for cls, inner in
                          [(action_scale.Wrapper, Inner()), (dmc.action_scale.Wrapper, Inner())]]
    old.step(action)
    new.step(action)
    assert new.action_spec().dtype == np.float32 and np.all(new.action_spec().minimum == -1)
    assert a.got[0].dtype == b.got[0].dtype == np.float32 and np.array_equal(a.got[0], b.got[0])
    assert action_scale.Wrapper is not dmc.action_scale.Wrapper  # dm_control's own is left as it is


def test_the_worker_seed_is_the_int_of_the_numpy_one():
    """random.seed(numpy uint32) fails from Python 3.11; the adapted seed() gives the state of its int."""
    if sys.version_info >= (3, 11):
        with pytest.raises(TypeError):
            random.seed(np.uint32(12345))
    replay_buffer = types.SimpleNamespace(random=random)
    run_official.int_worker_seed(replay_buffer)
    replay_buffer.random.seed(np.uint32(12345))
    got = [replay_buffer.random.choice(range(1000)) for _ in range(5)]
    random.seed(12345)
    assert got == [random.choice(range(1000)) for _ in range(5)]
    assert replay_buffer.random is not random and random.seed is not replay_buffer.random.seed


def test_the_stand_ins_say_what_they_stand_for():
    termcolor = run_official.stub("termcolor", "console colours", colored=lambda text, *_, **__: text)
    assert termcolor.colored("eval", "green") == "eval"
    cv2 = run_official.stub("cv2", "videos need opencv-python-headless")
    with pytest.raises(AttributeError, match="cv2.resize: cv2 is a stand-in of run_official.py .videos need"):
        cv2.resize
    assert not hasattr(cv2, "__file__")  # inspect and others probe modules with hasattr


@needs_official
def test_the_official_code_runs_and_its_run_dir_is_read(tmp_path):
    """Seed 1 to its first evaluation (one episode) on the CPU: eval.csv, read as the official code's run."""
    d = tmp_path / "official-1"
    p = run(["--official", DRQV2, "--", "task@_global_=cartpole_balance_sparse", "seed=1", "device=cpu",
             "save_video=false", "use_tb=false", f"hydra.run.dir={d}", "num_train_frames=2", "num_eval_episodes=1"],
            env={**os.environ, "MUJOCO_GL": "egl", "OMP_NUM_THREADS": "1"}, timeout=300)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert (d / "eval.csv").is_file()
    runs = published_curve.load_official([str(tmp_path / "official-*")], "cartpole_balance_sparse")
    assert list(runs) == [1] and list(runs[1]["frames"]) == [0.0] and runs[1]["values"][0] > 0


@needs_official
def test_the_campaign_runs_the_official_seeds_after_ours(tmp_path):
    """gpu_campaign.sh --quick --official: the official code's seeds after our group, one at a time, within the
    budget; each one started has its run dir (read by the rule) and logs, in --copy-to's tarball too; each one
    not started is named; nothing is left running."""
    out, copy = tmp_path / "c", tmp_path / "copy"
    p = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_campaign.sh"), "--quick", "--parallel", "1",
                        "--official", DRQV2, "--out", str(out), "--copy-to", str(copy)], cwd=ROOT,
                       env={**os.environ, "PYTHON": sys.executable, "MUJOCO_GL": "egl"}, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    summary = (out / "summary.md").read_text()
    assert "then the official code on seeds 1-2 (facebookresearch/drqv2 " in summary
    assert "1 at a time" in summary and "num_train_frames=202 eval_every_frames=100 num_eval_episodes=2" in summary
    assert f"--official {out}/runs/official-*" in summary  # the rule read them
    assert (out / "runs" / "official-1" / "eval.csv").is_file()  # the first starts when our group has ended
    assert "FAILED" not in summary and "ended below F" not in summary  # how far it got: its evaluations too
    for seed in (1, 2):
        unstarted = f"| official-{seed} | not started (budget) |" in summary
        named = any(line.startswith("official seeds not started") and f" {seed}" in line for line in summary.splitlines())
        assert unstarted == named and unstarted != (out / "runs" / f"official-{seed}").is_dir(), summary
    listing = subprocess.run(["tar", "-tzf", str(copy / "seeds1-2_logs.tar.gz")], capture_output=True, text=True).stdout
    assert "runs/official-1/eval.csv" in listing and "logs/official-1.log" in listing
    assert subprocess.run(["pgrep", "-f", f"run_official.py.*{out}"], capture_output=True).returncode == 1
