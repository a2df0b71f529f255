"""benchmarks/gpu_check.sh and its speed table (benchmarks/bench_speed.py), where there is no GPU:
bad arguments in one line, the training modes' flags as sear.py parses them today, the table's
kernel counts on fake profiler events, its ring copy, and its --quick table on the CPU. CI runs
`bash benchmarks/gpu_check.sh --quick` itself (.ci/run)."""
import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_speed  # noqa: E402
from harness import cli  # noqa: E402
import train  # noqa: E402

SCRIPT = ROOT / "benchmarks" / "gpu_check.sh"


def gpu_check(*args, timeout=60):
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout)


@pytest.mark.parametrize("args, says", [
    (["--runs", "eager"], "unknown mode eager in --runs"),  # a mode of before: now plain, default
    (["--runs", "plain compile-tf32"], "unknown mode compile-tf32"),
    (["--skip", "nonsense"], "unknown step nonsense in --skip"),
    (["--out"], "--out needs a value"),
    (["--compile"], "unknown argument --compile"),
])
def test_gpu_check_refuses_bad_arguments_in_one_line(args, says):
    r = gpu_check(*args)
    assert r.returncode == 2 and r.stdout == "", r.stdout + r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("gpu_check.sh: error:")
    assert says in r.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is there")
def test_gpu_check_without_cuda_points_to_quick():
    r = gpu_check("--runs", "plain")
    assert r.returncode == 2 and "torch sees no CUDA device" in r.stderr and "--quick" in r.stderr
    assert r.stderr.count("\n") == 1


def mode_flags(mode: str) -> list[str]:
    """gpu_check.sh's mode_flags for `mode`, run by bash from the script's own text."""
    text = SCRIPT.read_text()
    function = text[text.index("mode_flags() {"):]
    function = function[:function.index("\n}\n") + 3]
    out = subprocess.run(["bash", "-c", f"{function}\nmode_flags {mode}"], capture_output=True,
                         text=True, check=True).stdout
    return out.split()


def script_modes() -> list[str]:
    line = next(line for line in SCRIPT.read_text().splitlines() if line.startswith("modes="))
    return line.split("=", 1)[1].strip('"').split()


def test_the_training_modes_are_these():
    assert script_modes() == ["plain", "default", "graph", "compile", "tf32", "bf16"]


@pytest.mark.parametrize("mode, expected", [
    ("plain", dict(compile="off", cuda_graph="off", replay_device="cpu", prefetch="off")),
    ("default", dict(compile="auto", cuda_graph="auto", replay_device="auto", prefetch="auto")),
    ("graph", dict(compile="off", cuda_graph="on")),
    ("compile", dict(compile="on", cuda_graph="off")),
    ("tf32", dict(compile="auto", cuda_graph="auto", tf32=True)),
    ("bf16", dict(compile="auto", cuda_graph="auto", precision="bf16")),
])
def test_each_mode_is_flags_sear_py_parses_today(mode, expected):
    """The rung's run with a mode's flags parses as sear.py parses it, each setting as named."""
    argv = ["--env", "cartpole-balance_sparse", "--method", "sear", *mode_flags(mode)]
    cfg, run, _ = cli.parse_args(argv, train.Config, train.METHODS)
    for name, value in expected.items():
        assert getattr(run if hasattr(run, name) else cfg, name) == value, (mode, name)


# --- bench_speed.py -------------------------------------------------------------------------
@pytest.mark.parametrize("argv, says", [
    (["--quick", "--rounds", "0"], "--rounds must be at least 1"),
    (["--quick", "--seeds-batch", "1"], "--seeds-batch must be at least 2"),
    (["--quick", "--ring-size", "999"], "--ring-size must be at least 1000"),
    (["--quick", "--methods", "nonsense"], "invalid choice: 'nonsense'"),
    (["--quick", "--batch-size", "8.5"], "not a whole number"),
    (["--cpu-compile"], "--cpu-compile goes with --quick"),
    (["--quick", "--bogus"], "unrecognized arguments: --bogus"),
])
def test_bench_speed_refuses_bad_arguments_in_one_line(argv, says, capsys):
    assert bench_speed.main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("bench_speed.py: error:")
    assert says in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is there")
def test_bench_speed_without_cuda_needs_quick(capsys):
    assert bench_speed.main([]) == 2
    assert "torch sees no CUDA device; on a CPU run --quick" in capsys.readouterr().err


class Event:
    """The fields of a torch.profiler FunctionEvent that count_kernels reads."""

    def __init__(self, name, device, activity=None):
        self.name, self.activity_type = name, activity
        self.device_type = getattr(torch.autograd.DeviceType, device)


def test_kernels_are_counted_per_call_with_the_graph_launches():
    per_call = [Event("aten::addmm", "CPU", "cpu_op"),
                Event("cudaGraphLaunch", "CPU", "cuda_runtime"),
                Event("sm90_gemm", "CUDA", "kernel"), Event("elementwise_relu", "CUDA", "kernel"),
                Event("Memcpy HtoD (Pinned -> Device)", "CUDA", "gpu_memcpy"),
                Event("Memset (Device)", "CUDA", "gpu_memset")]
    assert bench_speed.count_kernels(per_call * 3, calls=3) == (2, 1)
    # a torch whose events carry no activity: every device event but copies and memsets
    bare = [Event(e.name, "CUDA" if e.device_type != torch.autograd.DeviceType.CPU else "CPU")
            for e in per_call]
    assert bench_speed.count_kernels(bare, calls=1) == (2, 1)


def test_the_kernels_cell_says_what_the_profiler_saw():
    assert bench_speed.kernels_cell(812.0, 0) == "812"
    assert bench_speed.kernels_cell(812.0, 1) == "812 in 1 graph launch"
    assert bench_speed.kernels_cell(0, 1) == "not seen (1 graph launch)"


def small_args(**given):
    args = dict(quick=True, cpu_compile=False, batch_size=2, seeds_batch=2, rounds=1, updates=1,
                warmup=0, ring_size=1000, action_dim=1, device=torch.device("cpu"))
    return argparse.Namespace(**{**args, **given})


def test_the_device_ring_samples_what_the_host_ring_does():
    """device_ring copies the whole ring (arrays, episodes): the same draws give the same batch."""
    args = small_args()
    host = bench_speed.filled_ring(args, train.Config())
    copy = bench_speed.device_ring(host, torch.device("cpu"))
    assert copy.frames.data_ptr() != host.frames.data_ptr() and copy.t == host.t == 1001
    drawn = [ring.sample(16, np.random.default_rng(4)) for ring in (host, copy)]
    for a, b in zip(*drawn):
        assert torch.equal(a, b)


def test_the_ring_and_prefetcher_rows_run_where_there_is_no_gpu():
    """Their CUDA wiring on the CPU (`full`): each row a time, the device's a gain over its
    reference."""
    args = small_args()
    host = bench_speed.filled_ring(args, train.Config())
    rows = bench_speed.ring_rows(args, host, full=True)
    rows += bench_speed.prefetch_rows(args, "drq", host, full=True)
    assert [r.against for r in rows] == ["", "host ring", "", "in turn, same column"]
    for r in rows:
        float(r.cells[0])
    assert rows[1].cells[1].endswith("×") and rows[3].cells[1].endswith("×")


def test_the_quick_table(capsys):
    """--quick on the CPU: the ring's two rows once, each method's eight, what needs CUDA saying
    so."""
    argv = ["--quick", "--methods", "drq", "--batch-size", "2", "--seeds-batch", "2", "--rounds",
            "1", "--ring-size", "1000", "--warmup", "0"]
    threads = torch.get_num_threads()
    try:
        assert bench_speed.main(argv) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    rows = {line.split(" | ")[1]: line.split(" | ") for line in out.splitlines()
            if line.startswith("| drq |") or line.startswith("| (any) |")}
    assert len(rows) == 10 and out.rstrip().splitlines()[-1].startswith("Gain:")
    plain = rows["plain: eager, fp32, the batch on the device"]
    assert float(plain[3]) > 0 and plain[5] == plain[7] == "needs CUDA"
    assert rows["--cuda-graph"][3] == rows["--compile + --cuda-graph"][3] == "needs CUDA"
    assert rows["--compile"][3] == "with --cpu-compile"
    assert float(rows["host ring: sample 2"][3]) > 0
    batched = rows["--batch-seeds: 2 seeds as one SeedBatch.update, per seed-update"]
    assert float(batched[3]) > 0 and batched[4].endswith("×")


def test_a_method_that_draws_inside_its_update_is_neither_graphed_nor_batched():
    assert "draws inside" in bench_speed.why_not_graphed("mae")
    assert bench_speed.why_not_graphed("sear") is None
    assert "seed by seed" in bench_speed.why_not_batched("ef")
    assert bench_speed.why_not_batched("drq") is None


def test_the_tables_agents_are_the_runs_at_the_asked_sizes():
    agent = bench_speed.make_agent(small_args(), "drq")
    assert (agent.cfg.hidden_dim, agent.cfg.feature_dim, agent.cfg.batch_size) == (32, 16, 2)
    assert agent.action_dim == 1 and isinstance(agent.rng, torch.Generator)
