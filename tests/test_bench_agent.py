"""benchmarks/bench_agent.py: --snapshot's settings (the flush-denormal contender and the malloc it names),
--profile's CUDA summary on fake profiler events, and what it does on a CPU without native bf16."""
import argparse
import functools
import sys
import types
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_agent  # noqa: E402

SUBNORMAL = 1e-39  # below float32's smallest normal, 1.18e-38


def test_flushed_update_sees_subnormals_as_zero_and_restores_the_flags():
    """--flush-denormal: inside the update a subnormal input reads as 0 (DAZ) and a subnormal result is
    0 (FTZ); after it, this thread computes subnormals again, so the other contenders are untouched."""
    if not torch.set_flush_denormal(False):
        pytest.skip("no FTZ/DAZ flags on this CPU (x86 with SSE3 only)")
    x = torch.tensor([SUBNORMAL, 1e-30])
    seen = {}

    def update(i):
        seen["input"], seen["result"] = (x[:1] * 1.0).item(), (x[1:] * 1e-9).item()
    bench_agent.flushed(update)(0)
    assert seen == {"input": 0.0, "result": 0.0}
    assert (x[:1] * 1.0).item() > 0 and (x[1:] * 1e-9).item() > 0


def test_snapshot_header_names_the_malloc(monkeypatch):
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    assert bench_agent.malloc_setting(argparse.Namespace(allocator="mallopt")).startswith("mallopt")
    assert bench_agent.malloc_setting(argparse.Namespace(allocator="none")) == "glibc's default"
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.mmap_max=0")
    assert bench_agent.malloc_setting(argparse.Namespace(allocator="none")) == "GLIBC_TUNABLES=glibc.malloc.mmap_max=0"


# --- --profile on CUDA: the summary of torch.profiler's events --------------------------------------
class Event:
    """The fields of a torch.profiler FunctionEvent that device_profile reads."""

    def __init__(self, name, device, activity, us=0.0, nbytes=None):
        self.name, self.activity_type = name, activity
        self.device_type = getattr(torch.autograd.DeviceType, device)
        self.time_range = torch.autograd.profiler_util.Interval(0, us)
        self.event_metadata = None if nbytes is None else types.SimpleNamespace(bytes=nbytes)


def two_updates():
    """What a profile of 2 updates holds: ops and runtime calls on the host, kernels and copies on the device."""
    per_update = [Event("aten::addmm", "CPU", "cpu_op", 50), Event("cudaLaunchKernel", "CPU", "cuda_runtime", 5),
                  Event("cudaMemcpyAsync", "CPU", "cuda_runtime", 9), Event("cudaStreamSynchronize", "CPU", "cuda_runtime", 80),
                  Event("sm90_gemm", "CUDA", "kernel", 300), Event("sm90_gemm", "CUDA", "kernel", 100),
                  Event("elementwise_relu", "CUDA", "kernel", 20),
                  Event("Memcpy HtoD (Pageable -> Device)", "CUDA", "gpu_memcpy", 40, nbytes=1_000_000),
                  Event("Memcpy DtoH (Device -> Pageable)", "CUDA", "gpu_memcpy", 2, nbytes=40),
                  Event("Memset (Device)", "CUDA", "gpu_memset", 1)]
    return per_update * 2


def test_device_profile_sums_kernels_copies_and_syncs_per_update():
    p = bench_agent.device_profile(two_updates(), updates=2, top=1)
    assert p.kernel_ms == pytest.approx(0.42) and p.kernels == 3
    assert p.h2d_bytes == 1_000_000 and p.h2d_copies == 1
    assert p.syncs == 1 and p.sync_calls == {"cudaStreamSynchronize": 1}
    assert p.top == [("sm90_gemm", pytest.approx(0.4), 2)]


def test_device_profile_leaves_out_the_benchmarks_own_sync():
    events = two_updates() + [Event("cudaDeviceSynchronize", "CPU", "cuda_runtime", 500)]
    p = bench_agent.device_profile(events, updates=2, own_syncs={"cudaDeviceSynchronize": 1})
    assert p.sync_calls == {"cudaStreamSynchronize": 1}


def test_device_profile_without_byte_counts_says_so():
    events = [e for e in two_updates() if not e.name.startswith("Memcpy HtoD")]
    events.append(Event("Memcpy HtoD (Pinned -> Device)", "CUDA", "gpu_memcpy", 40))  # no event_metadata
    p = bench_agent.device_profile(events, updates=2)
    assert p.h2d_bytes is None and p.h2d_copies == 0.5


def test_update_profile_runs_where_there_is_no_gpu(capsys):
    """The wiring of --profile's CUDA table, on the CPU (no kernels there; the copy is the batch's)."""
    bench_agent.update_profile(argparse.Namespace(batch_size=2, updates=1, device="cpu", precisions=["fp32"],
                                                  methods=["drq"]))
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| drq | fp32 |")]
    cells = row[0].split("|")
    assert len(row) == 1 and [cells[i] for i in (6, 8, 9)] == [" 0 "] * 3  # kernels, copies, syncs: none


# --- native bf16 -------------------------------------------------------------------------------------
def test_native_bf16_can_be_denied(monkeypatch):
    monkeypatch.setenv("SEAR_ASSUME_NO_BF16", "1")
    native, why = bench_agent.native_bf16()
    assert not native and "SEAR_ASSUME_NO_BF16" in why


def test_native_bf16_reads_the_cpu_flags_and_onednns_isa(monkeypatch):
    monkeypatch.delenv("SEAR_ASSUME_NO_BF16", raising=False)
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.setattr(bench_agent, "cpu_flags", lambda: {"avx2", "avx512f"})
    assert not bench_agent.native_bf16()[0]
    monkeypatch.setattr(bench_agent, "cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    assert bench_agent.native_bf16()[0]
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx512_core_amx")
    assert bench_agent.native_bf16()[0]
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")  # oneDNN kept to AVX2: it emulates bf16
    assert not bench_agent.native_bf16()[0]


def test_emulated_bf16_is_left_out_unless_asked(monkeypatch, capsys):
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.setenv("SEAR_ASSUME_NO_BF16", "1")
    args = argparse.Namespace(device="cpu", precisions=None)
    bench_agent.choose_precisions(args)
    assert args.precisions == ["fp32"] and capsys.readouterr().out.startswith("bf16: skipped")
    args = argparse.Namespace(device="cpu", precisions=["fp32", "bf16"])
    bench_agent.choose_precisions(args)
    assert args.precisions == ["fp32", "bf16"] and capsys.readouterr().out.startswith("bf16: emulated")
    monkeypatch.delenv("SEAR_ASSUME_NO_BF16")
    monkeypatch.setattr(bench_agent, "cpu_flags", lambda: {"amx_bf16"})
    args = argparse.Namespace(device="cpu", precisions=None)
    bench_agent.choose_precisions(args)
    assert args.precisions == ["fp32", "bf16"] and capsys.readouterr().out == ""


def test_the_benchmark_without_native_bf16_times_no_bf16(monkeypatch, capsys):
    """The default benchmark on a CPU that emulates bf16: no bf16 GEMM peak, no bf16 update."""
    monkeypatch.setenv("SEAR_ASSUME_NO_BF16", "1")
    monkeypatch.setattr(bench_agent, "gemm_size", lambda device: (256, 1))
    monkeypatch.setattr(sys, "argv", ["bench_agent.py", "--device", "cpu", "--methods", "drq", "--batch-size", "2",
                                      "--updates", "1", "--split-steps", "0", "--allocator", "none", "--threads", "1"])
    threads = torch.get_num_threads()
    try:
        bench_agent.main()
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert out.startswith("bf16: skipped") and "bf16" not in out.split("\n", 1)[1]
    assert "| drq | fp32 |" in out


def test_a_bf16_agent_runs_its_conv_networks_under_autocast_as_a_run_does(monkeypatch):
    """make_agent's bf16 agent is the run's (speed.bf16 on its encoder and decoders), not an fp32
    agent with a bf16 label."""
    tiny = functools.partial(bench_agent.train.Config, latent_dim=64, hidden_dim=32, feature_dim=16)
    monkeypatch.setattr(bench_agent.train, "Config", tiny)
    bf16, fp32 = (bench_agent.make_agent("sear", p, 2) for p in ("bf16", "fp32"))
    assert "forward" in vars(bf16.encoder) and "forward" in vars(bf16.aux)
    assert "forward" not in vars(fp32.encoder)
    seen = []
    conv = next(m for m in bf16.encoder.modules() if isinstance(m, torch.nn.Conv2d))
    conv.register_forward_hook(lambda m, i, out: seen.append(out.dtype))
    latent = bf16.encoder(torch.zeros(2, 9, 84, 84))
    assert seen == [torch.bfloat16] and latent.dtype == torch.float32
