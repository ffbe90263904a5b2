"""Whole-benchmark evaluation (``eval --gt-folder/--pred-folder``): sequences combined as TrackEval combines them.

Independent truths: TrackEval's own ``HOTA.combine_sequences`` on its per-sequence results (test-only), and the
scores of one long sequence made of the sequences one after another (ids and frames kept apart), which must
equal the combination — CLEAR-MOT counts add, IDF1's global matching cannot pair ids of different sequences,
and HOTA's association of a TP depends on its id pair only.
"""

import json
import warnings

import numpy as np
import pytest
from test_metrics_hota import random_tracks

from torchtrack.bench.hota import trackeval_data, trackeval_hota
from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import concat_mot, read_mot, write_motdata
from torchtrack.metrics.clear_mot import KEYS
from torchtrack.metrics.evaluation import EvalOptions, benchmark_sequences, combine, evaluate
from torchtrack.metrics.hota import KEYS as HOTA_KEYS


def sequences(n=3, threshold_noise=3.0):
    return [random_tracks(seed, frames=20 + 5 * seed, noise=threshold_noise) for seed in range(n)]


def one_long_sequence(parts):
    """The sequences one after another: frames shifted past the previous ones, ids made distinct."""
    gts, preds, frame0, id0 = [], [], 0, 0
    for gt, pred in parts:
        gts.append(gt._replace(frame=gt.frame + frame0, id=gt.id + id0))
        preds.append(pred._replace(frame=pred.frame + frame0, id=pred.id + id0))
        frame0 += int(max(gt.frame.max(), pred.frame.max())) + 10
        id0 += int(max(gt.id.max(), pred.id.max())) + 1
    return concat_mot(gts), concat_mot(preds)


@pytest.mark.parametrize("options", [EvalOptions(threshold=10.0), EvalOptions(threshold=4.0), EvalOptions(iou=0.5)])
def test_combined_scores_equal_those_of_the_sequences_end_to_end(options):
    parts = sequences()
    combined = combine([evaluate(gt, pred, options) for gt, pred in parts]).scores()
    whole = evaluate(*one_long_sequence(parts), options).scores()
    for key in (*KEYS, "IDP", "IDR", "GT_objects", "predictions", "IDTP", *HOTA_KEYS):
        assert combined[key] == pytest.approx(whole[key], abs=1e-12, rel=0), key


@pytest.mark.parametrize("iou", [None, 0.5])
def test_hota_combination_equals_trackevals(iou):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trackeval = pytest.importorskip("trackeval")
    parts = sequences(4)
    options = EvalOptions(iou=iou)
    ours = combine([evaluate(gt, pred, options) for gt, pred in parts]).hota
    per_sequence = {f"s{k}": trackeval_hota(trackeval_data(gt, pred, iou=iou)) for k, (gt, pred) in enumerate(parts)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = trackeval.metrics.HOTA().combine_sequences(per_sequence)
    for key in HOTA_KEYS:
        np.testing.assert_allclose(ours["per_alpha"][key], ref[key], rtol=0, atol=1e-9, err_msg=key)
        assert ours[key] == pytest.approx(float(np.mean(ref[key])), abs=1e-9, rel=0), key


def test_one_sequence_combines_to_itself():
    gt, pred = random_tracks(7)
    one = evaluate(gt, pred, EvalOptions(ospa=20.0))
    both = combine([one])
    assert both.scores() == pytest.approx(one.scores(), abs=1e-12, nan_ok=True)


def write_benchmark(root, parts, missing=None):
    for k, (gt, pred) in enumerate(parts):
        (root / "gt" / f"SEQ-{k}" / "gt").mkdir(parents=True)
        write_motdata(root / "gt" / f"SEQ-{k}" / "gt" / "gt.txt", gt)
        (root / "pred").mkdir(exist_ok=True)
        if k != missing:
            write_motdata(root / "pred" / f"SEQ-{k}.txt", pred)


def test_eval_cli_folders_rows_and_json(tmp_path, capsys):
    parts = sequences()
    write_benchmark(tmp_path, parts)
    out = tmp_path / "eval.json"
    assert main(["eval", "--gt-folder", str(tmp_path / "gt"), "--pred-folder", str(tmp_path / "pred"),
                 "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "3 sequences" in printed and printed.count("COMBINED") == 2 and "SEQ-2" in printed
    got = json.loads(out.read_text())
    assert sorted(got["sequences"]) == ["SEQ-0", "SEQ-1", "SEQ-2"]
    listed = benchmark_sequences(tmp_path / "gt", tmp_path / "pred")
    written = [(read_mot(gt), read_mot(pred)) for _, gt, pred in listed]
    ref = combine([evaluate(gt, pred) for gt, pred in written]).scores()
    for key in (*KEYS, *HOTA_KEYS):
        assert got["combined"][key] == pytest.approx(ref[key], abs=1e-12), key
        assert got["sequences"]["SEQ-1"][key] == pytest.approx(evaluate(*written[1]).scores()[key], abs=1e-12), key
    assert f"{100 * ref['HOTA']:.2f}" in printed


def test_eval_cli_folder_errors_are_one_line(tmp_path, capsys):
    write_benchmark(tmp_path, sequences(2), missing=1)
    assert main(["eval", "--gt-folder", str(tmp_path / "gt"), "--pred-folder", str(tmp_path / "pred")]) == 2
    assert "SEQ-1.txt: no tracker output for sequence SEQ-1" in capsys.readouterr().err
    assert main(["eval", "--gt-folder", str(tmp_path / "gt")]) == 2
    assert "give --gt and --pred, or --gt-folder and --pred-folder" in capsys.readouterr().err
    assert main(["eval", "--gt-folder", str(tmp_path / "pred"), "--pred-folder", str(tmp_path / "pred")]) == 2
    assert "no sequence" in capsys.readouterr().err
    with pytest.raises(TorchtrackError, match="not a folder"):
        benchmark_sequences(tmp_path / "absent", tmp_path / "pred")


def test_eval_does_not_import_torch_without_ospa(tmp_path):
    """``torchtrack eval`` starts in a fraction of torch's import time: nothing on its path imports torch."""
    import subprocess
    import sys

    parts = sequences(1)
    write_motdata(tmp_path / "gt.txt", parts[0][0])
    write_motdata(tmp_path / "pred.txt", parts[0][1])
    code = ("import sys; from torchtrack.cli import main; "
            f"main(['eval', '--gt', r'{tmp_path / 'gt.txt'}', '--pred', r'{tmp_path / 'pred.txt'}']); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("False")
