"""Test-suite settings shared by every test file."""

import os
import subprocess
import sys
from pathlib import Path

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


@pytest.fixture
def run_on_two_ranks():
    """``run(script)``: the Python file ``script`` on two ``torchrun --standalone`` ranks on this machine (the
    repository on ``PYTHONPATH``, one thread each); fails the test, with the ranks' stderr, unless both exit 0."""
    def run(script: Path) -> None:
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
        torchrun = Path(sys.executable).with_name("torchrun")
        proc = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node", "2", str(script)],
                              env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
    return run
