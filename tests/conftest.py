"""Shared fixtures.

`device`: the torch device of the tests that build agents and tensors, from SEAR_TEST_DEVICE (default
cpu). Those tests also carry the `device` marker, so `SEAR_TEST_DEVICE=cuda python -m pytest -m device`
runs exactly them on a GPU (benchmarks/gpu_check.sh); the sear.py subprocess tests pick CUDA by
themselves there (--device auto).
"""
import os

import pytest


def pytest_configure(config):
    config.addinivalue_line("markers", "device: takes the `device` fixture (SEAR_TEST_DEVICE)")


def pytest_collection_modifyitems(items):
    for item in items:
        if "device" in getattr(item, "fixturenames", ()):
            item.add_marker("device")


@pytest.fixture(scope="session")
def device():
    import torch  # here, not at the top: plot's and the toy's tests need no torch
    name = os.environ.get("SEAR_TEST_DEVICE", "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        pytest.exit(f"SEAR_TEST_DEVICE={name!r} is not a torch device (cpu, cuda, cuda:N)", returncode=2)
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.exit(f"SEAR_TEST_DEVICE={name} but torch sees no CUDA device", returncode=2)
    return dev
