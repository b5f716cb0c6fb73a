"""``geopose bench``: aggregation on hand-made results, seed hygiene, and one tiny run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from geopose.options import RegistrationOptions
from geopose.bench import BenchSettings, convergence_figure, markdown, row_names, seed_range, summarise, training_seeds
from geopose.cli import main


def _view(ncc, mpcd, cldice=0.5, rot=1.0, trans=2.0):
    return {"ncc": ncc, "mpcd_mm": mpcd, "cldice": cldice, "silhouette_dice": 0.9, "rotation_error_deg": rot,
            "translation_error_norm_mm": trans, "success": mpcd < 5.0}


def _case(name, rows, views=((1, 1), (2, 2))):
    curves = {"native + 25 TTO": {v: {"mncc": [0.1, 0.2, 0.3], "mpcd_mm": [9.0, 6.0, 3.0]} for v in ("pa", "lat")}}
    return {
        "case": name, "rows": rows, "curves": curves, "runtimes_s": {"calibration": 0.5, "Init (both views)": 0.25},
        "views": {"pa": {"true_view": views[0][0], "init_view": views[0][1]}, "lat": {"true_view": views[1][0], "init_view": views[1][1]}},
    }


def test_summary_averages_views_within_subjects_then_over_subjects():
    a = _case("a", {"Init + greedy Refine": {"pa": _view(0.8, 2.0), "lat": _view(0.6, 4.0)}})
    b = _case("b", {"Init + greedy Refine": {"pa": _view(0.7, 6.0), "lat": _view(0.5, 8.0)}}, views=((1, 1), (2, 0)))
    s = summarise([a, b])
    row = s["rows"]["Init + greedy Refine"]
    assert row["subjects"] == 2
    assert row["mpcd_mm"]["pa"]["mean"] == pytest.approx(4.0)
    assert row["mpcd_mm"]["avg"]["mean"] == pytest.approx(5.0)  # subject means 3 and 7
    assert row["mpcd_mm"]["avg"]["sd"] == pytest.approx(np.std([3.0, 7.0], ddof=1))
    assert row["success"] == pytest.approx(0.5)  # 2.0 and 4.0 below 5 mm, 6.0 and 8.0 not
    assert s["view_accuracy"] == pytest.approx(0.75)
    target = {t["target"]: t for t in s["targets"]}
    assert target["Init + greedy Refine mean mPCD <= 3 mm"]["measured"] == pytest.approx(5.0)
    assert not target["Init + greedy Refine mean mPCD <= 3 mm"]["met"]
    assert not target["view accuracy 100 %"]["met"]
    assert s["runtimes_s"]["calibrated Init (calibration + Init)"]["mean"] == pytest.approx(0.75)
    text = markdown(s, "# header")
    assert "| calibrated Init (calibration + Init) | 0.75 (0.00) | 0.022 |" in text
    assert "| Init + greedy Refine | 2 | 0.750 (0.071)" in text and "| NO |" in text


def test_missing_metrics_are_left_out_not_zeroed():
    a = _case("a", {"Init": {"pa": _view(0.8, 2.0, cldice=None), "lat": _view(0.6, 4.0, cldice=0.4)}})
    s = summarise([a])
    assert s["rows"]["Init"]["cldice"]["pa"] == {"mean": None, "sd": None, "n": 0}
    assert s["rows"]["Init"]["cldice"]["avg"]["mean"] == pytest.approx(0.4)


def test_seed_ranges_are_inclusive_and_bad_text_names_the_remedy():
    assert seed_range("5000-5003") == [5000, 5001, 5002, 5003]
    assert seed_range("6028") == [6028]
    with pytest.raises(ValueError, match="FIRST-LAST"):
        seed_range("5000..5039")


def test_convergence_figure_is_written(tmp_path):
    path = convergence_figure([_case("a", {}), _case("b", {})], ["native + 25 TTO"], tmp_path / "c.png")
    img = np.asarray(Image.open(path))
    assert img.shape[0] > 200 and img.shape[1] > 2 * img.shape[0]


def test_rows_follow_the_paper_table():
    rows = row_names(BenchSettings(RegistrationOptions(iterations=25), long_iterations=400))
    assert rows[:4] == ["native", "Init", "Init + Refine x1", "Init + greedy Refine"]
    assert rows[4:8] == [r + " + 25 TTO" for r in rows[:4]]
    assert rows[-1] == "native + 400 TTO"
    assert "native + 400 TTO" not in row_names(BenchSettings(long_iterations=0))


def test_training_seeds_are_read_from_the_manifest_and_refused(tmp_path, capsys):
    manifest = {"models": {"init": {"training": {"data": {"seeds": [7, 8], "template_seed": 0}}}}}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    assert training_seeds(tmp_path / "manifest.json") == {0, 7, 8}
    shipped = Path(__file__).resolve().parents[2] / "Resources" / "Models" / "manifest.json"
    seed = min(training_seeds(shipped))
    code = main(["bench", "--subjects", "1", "--seed-start", str(seed), "--out", str(tmp_path / "b")])
    assert code == 2
    assert "were used to train these models" in capsys.readouterr().err


def test_tiny_bench_run_writes_tables_and_figure(tmp_path):
    out = tmp_path / "bench"
    code = main(["bench", "--subjects", "1", "--seed-start", "777001", "--spacing-mm", "4", "--iterations", "2",
                 "--long-iterations", "3", "--device", "cpu", "--tto-px", "48", "--out", str(out)])
    assert code == 0
    data = json.loads((out / "bench.json").read_text())
    case = data["cases"][0]
    assert set(case["rows"]) == set(row_names(BenchSettings(RegistrationOptions(iterations=2), long_iterations=3)))
    for row in case["rows"].values():
        for metrics in row.values():
            assert metrics["mpcd_mm"] >= 0 and -1 <= metrics["ncc"] <= 1
    # the native row is the DICOM-angle pose; Init rows start TTO runs of 2 + 1 entries
    assert len(case["curves"]["Init + greedy Refine + 2 TTO"]["pa"]["mncc"]) == 3
    assert len(case["curves"]["native + 3 TTO"]["lat"]["mpcd_mm"]) == 4
    assert "## Targets" in (out / "bench.md").read_text()
    assert (out / "tto_convergence.png").stat().st_size > 10_000
    assert (out / "cases" / "phantom-777001.json").is_file()  # resumable
