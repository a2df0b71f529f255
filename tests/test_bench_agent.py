"""benchmarks/bench_agent.py --snapshot's settings: the flush-denormal contender and the malloc it names."""
import argparse
import sys
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
