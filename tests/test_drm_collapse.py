"""benchmarks/drm_collapse.py: the criterion fixed before the DrM run's result, applied as written."""
import importlib.util
import os
import subprocess
import sys

import pytest

from tests.test_plot import PNG_MAGIC

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_spec = importlib.util.spec_from_file_location("drm_collapse", os.path.join(ROOT, "benchmarks", "drm_collapse.py"))
drm_collapse = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(drm_collapse)


def write_run(tmp_path, saturated, returns, last=40000):
    """A run dir: an episode row per 1000 frames from 5000 (the first update's episode) to `last`."""
    run = tmp_path / "run"
    run.mkdir()
    rows = ["frame,return,actor_saturated,action_spread,dormant_ratio,expl_std,drm_lambda"]
    rows += [f"{f},10,{saturated(f)},0.5,0.1,0.9,0.5" for f in range(5000, last + 1, 1000)]
    (run / "train.csv").write_text("\n".join(rows) + "\n")
    (run / "config.json").write_text("{}")
    (run / "eval.csv").write_text("frame,return\n" + "".join(f"{f},{r}\n" for f, r in returns.items()))
    results = tmp_path / "results.csv"
    results.write_text("method,seed,task,frame,return,wall_time,source\n"
                       "drq,2,cartpole_balance_sparse,0,35.0,,\ndrq,2,cartpole_balance_sparse,40000,179.9,,\n")
    return run, results


@pytest.mark.parametrize("saturated, returns, last, want", [
    (lambda f: 0.5, {0: 35.0, 40000: 1000.0}, 40000, "PREVENTED"),
    (lambda f: 0.5, {0: 35.0, 40000: 300.0}, 40000, "PREVENTED, TASK NOT LEARNED"),
    (lambda f: 0.95 if 12000 < f <= 16000 else 0.1, {0: 35.0, 40000: 1000.0}, 40000, "NOT PREVENTED"),
    (lambda f: 0.95 if f > 12000 else 0.1, {0: 35.0, 10000: 11.4}, 13000, "RUNNING"),  # its block not complete
    (lambda f: 0.89, {0: 35.0, 10000: 11.4}, 20000, "RUNNING"),
])
def test_the_criterion_as_fixed_before_the_result(tmp_path, saturated, returns, last, want):
    run, results = write_run(tmp_path, saturated, returns, last)
    out = tmp_path / "fig.png"
    got = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "drm_collapse.py"), str(run),
                          "--results", str(results), "--out", str(out)], capture_output=True, text=True)
    assert got.returncode == 0, got.stderr
    assert f"Does DrM prevent the collapse here? {want} (" in got.stdout
    # a failed (a) names its block and mean: the margin is part of the verdict
    assert ("(12k–16k: mean actor_saturated 0.950 >= 0.9)" in got.stdout) == (want == "NOT PREVENTED")
    assert out.read_bytes().startswith(PNG_MAGIC)


def test_blocks_place_an_episode_in_the_block_it_ran_in():
    train = {f: {"actor_saturated": f / 100000, "action_spread": 0.5} for f in range(5000, 13001, 1000)}
    b = drm_collapse.blocks(train)
    assert sorted(b) == [4000, 8000, 12000]
    assert b[8000][0] == pytest.approx(sum(f / 100000 for f in range(9000, 13000, 1000)) / 4)  # 9k..12k: 8k-12k
    assert b[8000][2] and not b[12000][2]


def test_a_missing_run_is_one_line(tmp_path):
    got = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "drm_collapse.py"), str(tmp_path / "no")],
                         capture_output=True, text=True)
    assert got.returncode == 2 and got.stderr.count("\n") == 1 and "drm_collapse.py: error:" in got.stderr
