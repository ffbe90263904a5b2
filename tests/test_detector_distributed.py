"""Two-process ``torchrun`` (gloo, loopback) training equals single-process training on the same
global batch."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import torch
import yaml

from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.inference import Detector

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_torchrun_two_processes_match_single_process(tmp_path):
    cfg = {
        "model": {"widths": [8, 12, 16], "head": 8},
        "data": {"train_sequences": 2, "val_sequences": 1, "frames": 3, "cache": str(tmp_path / "cache"),
                 "crop": 64, "video": {"height": 96, "width": 96, "margin": 16, "trees": 20, "speckles": 10,
                                       "buildings": 2, "car_parks": 1, "highways": 1, "local_roads": 1}},
        # SGD: Adam's update ~ lr * sign(g) turns float-rounding differences of near-zero gradients into
        # visible parameter differences; with SGD the parameters differ only as much as the gradients do
        # (the shipped architecture, model.fine 0: with the optional stride-2 branch, rounding grows to 1e-4
        # over three steps at this lr)
        "train": {"epochs": 1, "steps_per_epoch": 3, "batch": 4, "val_frames": 2, "optimizer": "sgd", "lr": 0.05},
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    # both runs on the CPU (a GPU machine would train the single process on its GPU, the ranks too where each has one)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo",
           "CUDA_VISIBLE_DEVICES": ""}
    common = ["-m", "torchtrack", "train-detector", "--config", str(path), "--no-progress", "--seed", "3"]
    single = subprocess.run([sys.executable, *common, "--out", str(tmp_path / "one")], env=env, cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert single.returncode == 0, single.stderr[-2000:]
    two = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", "2",
                          "--master_addr", "127.0.0.1", "--master_port", str(_free_port()),
                          *common, "--out", str(tmp_path / "two")], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert two.returncode == 0, two.stderr[-2000:]
    a = load_checkpoint(tmp_path / "one" / "last.pt")["model"]
    b = load_checkpoint(tmp_path / "two" / "last.pt")["model"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)
    # and training did move the parameters away from their (seeded) initial values
    torch.manual_seed(3)
    init = Detector(load_checkpoint(tmp_path / "one" / "last.pt")["config"]).net.state_dict()
    assert max(float((a[k] - init[k]).abs().max()) for k in a) > 1e-3
