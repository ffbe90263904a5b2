"""Property-based tests (Hypothesis) at the edges where hostile input arrives: the MOTChallenge reader, the
config loader and the command-line numbers. Whatever the input, the answer is a value or a
:class:`~torchtrack.errors.TorchtrackError` (a one-line error) — never another exception, a crash or a hang."""

import argparse
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchtrack.cli._common import SEED, bounded, positive_float
from torchtrack.config import from_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import GLMBConfig, GMPHDConfig, PMBConfig, SORTConfig
from torchtrack.io.mot import format_lines, from_points, read_mot
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.sim.video import VideoConfig

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

numbers = st.one_of(st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from(["nan", "inf", "-inf", "1e400", "", "x", "3.5", "-1", "0x10", "1_0"]))
field = numbers.map(str)
line = st.lists(field, min_size=0, max_size=12).map(",".join)


@FAST
@given(st.lists(line, max_size=8), st.sampled_from(["\n", "\r\n"]))
def test_the_mot_reader_reads_or_names_the_line(tmp_path, lines, newline):
    path = tmp_path / "any.txt"
    path.write_text(newline.join(lines))
    try:
        data = read_mot(path)
    except TorchtrackError as exc:
        assert str(path) in str(exc)
        return
    assert np.all(data.frame >= 0) and np.all(data.id >= -1)
    assert all(np.all(np.isfinite(a)) for a in (data.x, data.y, data.w, data.h, data.conf))


@FAST
@given(st.binary(max_size=200))
def test_the_mot_reader_on_any_bytes(tmp_path, raw):
    path = tmp_path / "bytes.txt"
    path.write_bytes(raw)
    try:
        read_mot(path)
    except TorchtrackError:
        pass


@FAST
@given(st.lists(st.tuples(st.integers(0, 2**40), st.integers(0, 10**6),
                          st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)), max_size=20, unique_by=lambda t: t[:2]))
def test_what_is_written_reads_back(tmp_path, rows):
    frames, ids, xs, ys = (list(c) for c in zip(*rows)) if rows else ([], [], [], [])
    data = from_points(frames, ids, xs, ys)
    path = tmp_path / "round.txt"
    path.write_text(format_lines(data))
    back = read_mot(path)
    assert back.size == data.size
    np.testing.assert_array_equal(np.sort(back.frame), np.sort(data.frame))


values = st.recursive(numbers | st.booleans() | st.none() | st.text(max_size=5),
                      lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                                   max_size=3), max_leaves=6)


@pytest.mark.parametrize("cls", [GMPHDConfig, SORTConfig, PMBConfig, GLMBConfig, PipelineConfig, VideoConfig])
@FAST
@given(data=st.data())
def test_the_config_loader_builds_or_names_the_key(cls, data):
    import dataclasses

    names = [f.name for f in dataclasses.fields(cls)] + ["not_an_option"]
    mapping = data.draw(st.dictionaries(st.sampled_from(names), values, max_size=4))
    try:
        config = from_mapping(cls, mapping, "test.yaml")
    except TorchtrackError as exc:
        assert "test.yaml" in str(exc)
        return
    for f in dataclasses.fields(config):                    # what is accepted is finite where it is a number
        value = getattr(config, f.name)
        if isinstance(value, float):
            assert math.isfinite(value), f.name


@FAST
@given(st.text(max_size=30) | numbers.map(str))
def test_command_line_numbers_parse_or_are_usage_errors(text):
    for parse in (SEED, positive_float, bounded(int, ge=1), bounded(float, gt=0, le=1)):
        try:
            value = parse(text)
        except argparse.ArgumentTypeError:
            continue
        assert math.isfinite(value)
    try:
        seed = SEED(text)
    except argparse.ArgumentTypeError:
        return
    import torch

    torch.Generator().manual_seed(seed)           # every accepted seed is one torch's generator takes
    np.random.default_rng(seed)
