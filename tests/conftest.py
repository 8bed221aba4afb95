"""Shared fixtures: every engine test runs on the CPU and, when a GPU is present, on CUDA."""

import pytest
import warp as wp

wp.config.log_level = wp.LOG_WARNING

DEVICES = [
    pytest.param("cpu", id="cpu"),
    pytest.param("cuda", id="cuda", marks=pytest.mark.skipif(not wp.is_cuda_available(),
                                                             reason="no CUDA device on this machine")),
]


@pytest.fixture(params=DEVICES)
def device(request):
    """A Warp device name: "cpu", and "cuda" when available."""
    return request.param
