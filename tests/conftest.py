"""Test-suite settings shared by every test file."""

import os

import pytest
import torch

# The tests use small tensors: one intra-op thread is faster and avoids oversubscription when
# tests run beside other processes (OpenMP spin-waiting on 2 loaded cores is very slow).
torch.set_num_threads(int(os.environ.get("TORCHTRACK_TEST_THREADS", "1")))


@pytest.fixture
def wpafb_data():
    """The WPAFB AOI 02 folder as the commands locate it (torchtrack.io.datasets); the test is skipped,
    saying how to get the data, where it is absent."""
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.datasets import wpafb_folder

    try:
        return wpafb_folder()
    except TorchtrackError as exc:
        pytest.skip(str(exc))
