"""Typed tracker options: configs/gmphd.yaml spells out the built-in defaults; the one YAML loader names bad
keys by their dotted path; the GM-PHD's defaults follow the input (velocities or positions only)."""

import dataclasses
import re
from pathlib import Path

import pytest
import torch

from torchtrack.config import from_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import (
    DEFAULTS,
    LABELLED_GMPHD,
    GMPHDConfig,
    GMPHDFilterOptions,
    load_tracker_configs,
    tracker_config,
)
from torchtrack.filters.trackers.protocol import make_tracker, tracker_names
from torchtrack.pipeline.config import SELECTED_TRACKERS

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_yaml_equals_the_built_in_defaults():
    assert set(DEFAULTS) == set(tracker_names())
    assert load_tracker_configs(ROOT / "configs" / "gmphd.yaml") == DEFAULTS
    assert load_tracker_configs(None) == {}


def test_paper_preset_by_name_is_the_paper_filter():
    assert list(load_tracker_configs("gmphd-paper")) == ["gmphd"]        # only the file's sections
    paper = load_tracker_configs("gmphd-paper")["gmphd"]
    assert paper.label_fix and not paper.merge_priority and paper.handover_frames == 0
    assert paper.filter.velocity_sigma is None and paper.positions_only == {}
    assert paper.birth == DEFAULTS["gmphd"].birth


def test_labelled_preset_is_the_plain_filter_with_the_same_filter_options():
    lab, enh = LABELLED_GMPHD, DEFAULTS["gmphd"]
    assert not lab.label_fix and lab.handover_frames == 0 and lab.coast_threshold is None and not lab.confirm_new
    assert not lab.birth.use_velocity_map and not lab.birth.use_detector_velocity
    assert lab.filter == dataclasses.replace(enh.filter, velocity_sigma=None)
    # a section changes only the keys it gives, over the preset
    assert tracker_config("labelled-gmphd", {"filter": {"q": 1.0}}).filter.q == 1.0
    assert tracker_config("labelled-gmphd", {"filter": {"q": 1.0}}).label_fix is False


def test_unknown_keys_are_named_by_their_dotted_path(tmp_path):
    bad = tmp_path / "t.yaml"
    bad.write_text("gmphd:\n  filter:\n    q_typo: 1\n")
    with pytest.raises(TorchtrackError, match=r"t\.yaml: unknown key\(s\) \['gmphd\.filter\.q_typo'\]"):
        load_tracker_configs(bad)
    bad.write_text("gmphd:\n  positions_only: {birth: {velocity_map: {cel: 3}}}\n")
    with pytest.raises(TorchtrackError, match=r"gmphd\.positions_only\.birth\.velocity_map\.cel"):
        load_tracker_configs(bad)
    bad.write_text("sortt: {}\n")
    with pytest.raises(TorchtrackError, match=r"t\.yaml: unknown tracker section\(s\) \['sortt'\]"):
        load_tracker_configs(bad)


def test_values_are_converted_or_refused_naming_the_key(tmp_path):
    path = tmp_path / "t.yaml"
    path.write_text("gmphd:\n  filter: {clutter_density: 3e-4, q: 1}\nsort: {max_age: 2}\n")   # PyYAML: '3e-4' a str
    cfg = load_tracker_configs(path)
    assert cfg["gmphd"].filter.clutter_density == 3e-4 and isinstance(cfg["gmphd"].filter.q, float)
    assert cfg["sort"].max_age == 2
    for text, key in [("gmphd: {filter: {q: fast}}", "gmphd.filter.q"), ("sort: {max_age: 1.5}", "sort.max_age"),
                      ("gmphd: {label_fix: 1}", "gmphd.label_fix"), ("gmphd: {filter: {p_detection: true}}",
                                                                      "gmphd.filter.p_detection"),
                      ("pmb: {region: [0, 0, 1]}", "pmb.region"), ("gmphd: {filter: 3}", "gmphd.filter")]:
        path.write_text(text + "\n")
        with pytest.raises(TorchtrackError, match=r"t\.yaml: " + re.escape(key)):
            load_tracker_configs(path)


def test_loader_merges_onto_a_base_and_keeps_unset_fields():
    base = GMPHDFilterOptions(q=5.0)
    got = from_mapping(GMPHDFilterOptions, {"sigma": "2"}, base=base)
    assert got == dataclasses.replace(base, sigma=2.0)
    assert from_mapping(GMPHDConfig, {"confirm_new": 3}).confirm_new == 3
    assert from_mapping(GMPHDConfig, {"coast_threshold": None}).coast_threshold is None


def _frames(velocities: bool, first: int = 1, last: int = 20):
    """Three targets crossing a 200 px scene at 6 px/frame, detected every frame (float64)."""
    start = torch.tensor([[10.0, 20.0], [10.0, 80.0], [190.0, 140.0]], dtype=torch.float64)
    vel = torch.tensor([[6.0, 0.0], [6.0, 1.0], [-6.0, 0.0]], dtype=torch.float64)
    for k in range(first, last + 1):
        yield k, start + k * vel, (vel.clone() if velocities else None)


def _run(tracker, frames, reset=True):
    if reset:
        tracker.reset()
    return [(ids.tolist(), pos.tolist()) for ids, pos in (tracker.step(k, z, v) for k, z, v in frames)]


@pytest.mark.parametrize("velocities", [True, False])
def test_each_frame_runs_with_the_options_of_its_input(velocities):
    config = tracker_config("gmphd", {"dtype": "float64"})
    tracker = make_tracker("gmphd", config)
    out = _run(tracker, _frames(velocities))
    chosen = config.for_input(velocities)
    assert tracker.active is (tracker.with_velocity if velocities else tracker.positions_only)
    assert tracker.active.options.fix_separation == chosen.fix_separation
    assert tracker.active.phd.motion.q().item() == pytest.approx(chosen.filter.q)
    # same output as a tracker built from the chosen options alone
    alone = make_tracker("gmphd", dataclasses.replace(chosen, positions_only={}))
    assert _run(alone, _frames(velocities)) == out
    assert all(sorted(ids) == [1, 2, 3] for ids, _ in out[3:])      # one label per target, kept


def test_a_switch_of_input_carries_the_mixture_and_labels_over():
    tracker = make_tracker("gmphd", {"dtype": "float64"})
    before = _run(tracker, _frames(True, 1, 10))
    assert tracker.active is tracker.with_velocity
    after = _run(tracker, _frames(False, 11, 20), reset=False)
    assert tracker.active is tracker.positions_only and tracker.active.options.fix_separation == 12.0
    assert sorted(before[-1][0]) == [1, 2, 3]
    assert all(sorted(ids) == [1, 2, 3] for ids, _ in after)          # the same labels, no new track
    back = _run(tracker, _frames(True, 21, 25), reset=False)
    assert tracker.active is tracker.with_velocity and all(sorted(ids) == [1, 2, 3] for ids, _ in back)
    with pytest.raises(TorchtrackError, match="frames must increase"):
        tracker.step(25, torch.zeros(0, 2), None)                       # the last frame carried over too


def test_positions_only_options_apply_over_the_others():
    cfg = GMPHDConfig(fix_separation=3.0, positions_only={"filter": {"q": 0.5}})
    pos = cfg.for_input(False)
    assert pos.filter.q == 0.5 and pos.fix_separation == 3.0 and pos.positions_only == {}
    assert cfg.for_input(True) is cfg
    assert DEFAULTS["gmphd"].for_input(False).fix_separation == 12.0


def test_pipeline_selected_trackers_keep_their_validated_values():
    """The video pipeline's options were chosen on validation sequences against the earlier built-in defaults
    (position-only update, fix_separation 12): the keys it sets still decide the values that moved."""
    cfg = {name: tracker_config(name, options) for name, options in SELECTED_TRACKERS.items()}
    g = cfg["gmphd"]
    assert (g.fix_separation, g.filter.velocity_sigma, g.filter.velocity_outlier, g.tone_sigma) == (4.0, 1.0, 0.3, 4.0)
    assert (g.filter.prune_threshold, g.filter.merge_threshold) == (5e-3, 9.0)
    assert g.for_input(False) is g               # the same options on the first frame, which has no velocities
    assert cfg["labelled-gmphd"].filter.velocity_sigma is None and not cfg["labelled-gmphd"].label_fix


def test_every_section_goes_through_the_one_loader(tmp_path):
    """Video, detector and pipeline YAML: numeric strings become floats, lists become typed tuples, unknown
    keys and wrong types are refused by their dotted path, naming the file."""
    from torchtrack.detector.config import load_config
    from torchtrack.pipeline.config import load_pipeline_config
    from torchtrack.sim.video_config import load_video_config

    path = tmp_path / "s.yaml"
    path.write_text("video:\n  jitter_perspective: 2e-06\n  building_size: [10, 40]\n  frames: 12\n")
    video = load_video_config(path)
    assert video.jitter_perspective == 2e-6 and video.building_size == (10.0, 40.0) and video.frames == 12
    path.write_text("frames: twelve\n")
    with pytest.raises(TorchtrackError, match=r"s\.yaml: frames must be a whole number"):
        load_video_config(path)
    path.write_text("model: {widths: [8, 8, 8]}\ntrain: {lr: 1e-3}\n")
    det = load_config(path)
    assert det.model.widths == (8, 8, 8) and det.train.lr == 1e-3
    path.write_text("model: {widths: [8, 8]}\n")
    with pytest.raises(TorchtrackError, match=r"s\.yaml: model\.widths must be a list of 3"):
        load_config(path)
    path.write_text("pipeline:\n  registration: {featurs: 10}\n")
    with pytest.raises(TorchtrackError, match=r"s\.yaml: unknown key\(s\) \['registration\.featurs'\]"):
        load_pipeline_config(path)
    path.write_text("pipeline:\n  trackers: {gmphd: {filter: {qq: 1}}}\n")
    with pytest.raises(TorchtrackError, match=r"s\.yaml: trackers: unknown key\(s\) \['gmphd\.filter\.qq'\]"):
        load_pipeline_config(path)
    path.write_text("pipeline:\n  snapshots: [1, 5]\n  min_speed: 3\n")
    cfg = load_pipeline_config(path)
    assert cfg.snapshots == (1, 5) and cfg.min_speed == 3.0
