"""benchmarks/step_counts.py: one agent step of N seeds makes one host->device copy (the seeds'
observations) and one host read (their actions), whatever N, and one copy of all seeds' replay writes
into rings on a GPU; a worker's answer is the newest frame and
its bit-packed mask, ~22 KB; the workers import no torch."""
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_step_of_n_seeds_copies_once_and_reads_once():
    import argparse
    import step_counts
    counts = [step_counts.measure(argparse.Namespace(seeds=n, steps=3, method="sear", env="")) for n in (2, 4)]
    for m in counts:
        assert m["h2d"] <= 2 and m["syncs"] <= 1, m
        shared, pipe = m["answer"]
        assert shared + pipe <= 23_000 and shared == 3 * 84 * 84 + 84 * 84 // 8, m
        assert m["workers"] >= 2 * m["seeds"]
        # rings on a GPU: put copies frame, mask and action seed by seed; the staged writes once
        assert m["ring copies"] == {"put": 3 * m["seeds"], "staged": 1}, m
    assert counts[0]["h2d"] == counts[1]["h2d"] and counts[0]["syncs"] == counts[1]["syncs"]
    workers = [pid for pid in step_counts.children(os.getpid())
               if b"multiprocessing.spawn" in Path(f"/proc/{pid}/cmdline").read_bytes()]
    assert workers == [], "workers outlived their envs"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_load_no_torch(tmp_path):
    """A group's env workers (sear.py imports torch, the workers import only what builds the env):
    no libtorch in their memory maps."""
    import subprocess
    code = ("import sys, os; sys.path[:0] = [{root!r}, {bench!r}]\n"
            "import torch, train, step_counts\n"
            "from harness import cli, runenvs\n"
            "cfg = train.Config(env='cartpole-balance', render_quality='fast')\n"
            "configs = [cli.config_dict(train.Config(**{{**vars(cfg), 'seed': k}}), cli.RunConfig()) for k in (1, 2)]\n"
            "envs = runenvs.SeedEnvs(configs, False, workers=True)\n"
            "kids = [p for p in step_counts.children(os.getpid())\n"
            "        if b'multiprocessing.spawn' in open(f'/proc/{{p}}/cmdline', 'rb').read()]\n"
            "print(len(kids), sum('libtorch' in open(f'/proc/{{p}}/maps').read() for p in kids))\n"
            "envs.close()\n").format(root=str(ROOT), bench=str(ROOT / "benchmarks"))
    script = tmp_path / "main.py"
    script.write_text(code)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                       env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split()[-2:] == ["4", "0"], r.stdout
