"""The data-set locator: data/ (cwd, then checkout), then $TORCHTRACK_WPAFB, then ../shared/data; the
one-line message where the data is absent; the names and paths that configs give."""

import json
from pathlib import Path

import pytest
import yaml

from torchtrack.config import preset_names, preset_path
from torchtrack.errors import TorchtrackError
from torchtrack.io.datasets import WPAFB, checkout_root, locate, search_path, wpafb_truth_csv

ENV = WPAFB.env


def make_copy(folder: Path) -> Path:
    """A folder that counts as the data set (its marker file only)."""
    folder.mkdir(parents=True)
    (folder / WPAFB.marker).write_text("Frame Number\n")
    return folder


@pytest.fixture
def roots(tmp_path):
    """Two roots (``cwd`` and ``checkout``) under one parent, as a user's folder and a checkout."""
    cwd, checkout = tmp_path / "work" / "here", tmp_path / "repo" / "torchtrack"
    cwd.mkdir(parents=True), checkout.mkdir(parents=True)
    return cwd, checkout


def test_search_order_is_data_then_env_then_shared(roots, tmp_path):
    cwd, checkout = roots
    env = {ENV: str(tmp_path / "elsewhere")}
    assert search_path(WPAFB, [cwd, checkout], env) == [
        ("data", cwd / "data" / "wpafb-aoi02"), ("data", checkout / "data" / "wpafb-aoi02"),
        ("env", tmp_path / "elsewhere"),
        ("shared", cwd.parent / "shared" / "data" / "wpafb-aoi02"),
        ("shared", checkout.parent / "shared" / "data" / "wpafb-aoi02")]
    assert [w for w, _ in search_path(WPAFB, [cwd, cwd], {})] == ["data", "shared"]   # no duplicates


def test_each_place_is_found_and_the_first_one_wins(roots, tmp_path):
    cwd, checkout = roots
    env = {ENV: str(tmp_path / "elsewhere")}
    shared_checkout = make_copy(checkout.parent / "shared" / "data" / "wpafb-aoi02")
    assert locate(WPAFB, [cwd, checkout], {}) == shared_checkout
    shared_cwd = make_copy(cwd.parent / "shared" / "data" / "wpafb-aoi02")
    assert locate(WPAFB, [cwd, checkout], {}) == shared_cwd
    elsewhere = make_copy(tmp_path / "elsewhere")
    assert locate(WPAFB, [cwd, checkout], env) == elsewhere
    in_checkout = make_copy(checkout / "data" / "wpafb-aoi02")
    assert locate(WPAFB, [cwd, checkout], env) == in_checkout
    in_cwd = make_copy(cwd / "data" / "wpafb-aoi02")
    assert locate(WPAFB, [cwd, checkout], env) == in_cwd


def test_a_folder_without_the_truth_csv_does_not_count(roots):
    cwd, checkout = roots
    (cwd / "data" / "wpafb-aoi02" / "frames").mkdir(parents=True)    # e.g. frames copied by hand
    shared = make_copy(cwd.parent / "shared" / "data" / "wpafb-aoi02")
    assert locate(WPAFB, [cwd, checkout], {}) == shared


def test_a_wrong_environment_variable_is_an_error_not_skipped(roots, tmp_path):
    cwd, checkout = roots
    make_copy(cwd.parent / "shared" / "data" / "wpafb-aoi02")
    with pytest.raises(TorchtrackError, match=rf"^{ENV}=.*nowhere: no transformed_object_states.csv there"):
        locate(WPAFB, [cwd, checkout], {ENV: str(tmp_path / "nowhere")})
    assert locate(WPAFB, [cwd, checkout], {ENV: ""}).parent.name == "data"          # empty = unset


def test_absent_data_says_how_to_get_it_in_one_line(roots):
    with pytest.raises(TorchtrackError) as exc:
        locate(WPAFB, list(roots), {})
    message = str(exc.value)
    assert "\n" not in message
    assert "torchtrack data fetch wpafb" in message and ENV in message and "data/wpafb-aoi02" in message


def test_config_values_name_the_data_set_or_a_path(tmp_path, monkeypatch):
    copy = make_copy(tmp_path / "copy")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(ENV, str(copy))
    monkeypatch.setattr("torchtrack.io.datasets.checkout_root", lambda: None)
    assert wpafb_truth_csv("wpafb") == copy / WPAFB.marker              # the name: located ($ENV here)
    assert wpafb_truth_csv() == copy / WPAFB.marker
    assert wpafb_truth_csv("copy") == Path("copy") / WPAFB.marker       # a folder, relative to the cwd
    assert wpafb_truth_csv(copy / WPAFB.marker) == copy / WPAFB.marker  # the CSV itself
    with pytest.raises(TorchtrackError, match="^missing: no transformed_object_states.csv there"):
        wpafb_truth_csv("missing")


def test_the_shipped_configs_name_the_data_set_not_a_path(tmp_path, monkeypatch):
    from torchtrack.cli._wpafb_benchmark import truth_csv

    copy = make_copy(tmp_path / "copy")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(ENV, str(copy))
    monkeypatch.setattr("torchtrack.io.datasets.checkout_root", lambda: None)
    benchmark = yaml.safe_load(preset_path("wpafb-benchmark").read_text())
    assert benchmark["truth"] == "wpafb" and truth_csv(benchmark) == copy / WPAFB.marker
    tune = yaml.safe_load(preset_path("tune-gmphd-wpafb").read_text())
    assert tune["data"]["wpafb"] == "wpafb"
    for name in preset_names():                                                     # values, not comments
        assert "shared" not in json.dumps(yaml.safe_load(preset_path(name).read_text())), name


def test_the_checkout_is_found_from_a_source_tree_and_not_from_an_installed_package():
    import torchtrack

    package_parent = Path(torchtrack.__file__).resolve().parents[1]
    from_source = (package_parent / "pyproject.toml").is_file()
    assert checkout_root() == (package_parent if from_source else None)
