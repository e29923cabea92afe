"""Shared pytest set-up: every kernel test runs once per available device (CPU always, CUDA when present)."""

import pytest
import torch

from warpavatar._src.warp_utils import available_devices

DEVICES = available_devices()


def pytest_generate_tests(metafunc):
    # A test that takes a ``device`` argument is registered once per device: test_x[cpu], test_x[cuda:0].
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", DEVICES)


@pytest.fixture(autouse=True)
def _deterministic_seed():
    torch.manual_seed(0)
    yield
