"""configs/pipeline.yaml documents exactly the embedded defaults; bad keys are named."""

from pathlib import Path

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.pipeline.config import PipelineConfig, load_pipeline_config

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_yaml_equals_defaults():
    assert load_pipeline_config(ROOT / "configs" / "pipeline.yaml") == PipelineConfig()


def test_online_yaml_differs_from_the_defaults_only_in_lag_gate_and_options():
    online = load_pipeline_config(ROOT / "configs" / "pipeline-online.yaml")
    assert online.output_lag == 0
    assert online.replace(output_lag=3, min_speed=2.0, trackers=PipelineConfig().trackers) == PipelineConfig()


@pytest.mark.parametrize("key, value", [("output_lag", -1), ("output_lag", 2.5), ("weak_distance", 0.0),
                                        ("lag_distance", -2.0), ("weak_threshold", 1.5), ("detector_tile", 1000),
                                        ("detector_tile", -16)])
def test_bad_lag_and_weak_settings_are_named(key, value):
    with pytest.raises(TorchtrackError, match=key):
        PipelineConfig(**{key: value})


def test_unknown_keys_are_named(tmp_path):
    bad = tmp_path / "p.yaml"
    bad.write_text("pipeline:\n  trakcer: sort\n")
    with pytest.raises(TorchtrackError, match=r"p\.yaml: unknown key\(s\) \['trakcer'\]"):
        load_pipeline_config(bad)
    bad.write_text("registration:\n  method: sift\n")
    with pytest.raises(TorchtrackError, match="registration.method"):
        load_pipeline_config(bad)
    with pytest.raises(TorchtrackError, match="no such file"):
        load_pipeline_config(tmp_path / "missing.yaml")


def test_device_is_checked_before_any_work():
    assert PipelineConfig().device == "cpu"
    with pytest.raises(TorchtrackError, match=r"PipelineConfig.device must be cpu, cuda or cuda:N; got 'gpu9'"):
        PipelineConfig(device="gpu9")
    if not torch.cuda.is_available():
        with pytest.raises(TorchtrackError, match="no CUDA device"):
            PipelineConfig(device="cuda")
