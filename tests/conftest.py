"""Test-suite settings shared by every test file."""

import os

import torch

# The tests use small tensors: one intra-op thread is faster and avoids oversubscription when
# tests run beside other processes (OpenMP spin-waiting on 2 loaded cores is very slow).
torch.set_num_threads(int(os.environ.get("TORCHTRACK_TEST_THREADS", "1")))
