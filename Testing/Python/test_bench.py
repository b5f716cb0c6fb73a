"""``geopose bench``: aggregation on hand-made results, seed hygiene, and one tiny run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from geopose.options import RegistrationOptions, SearchOptions, TTOSchedule
from geopose.bench import BenchSettings, convergence_figure, markdown, row_names, seed_range, summarise, training_seeds
from geopose.bench.run import INSTANT_ROW, LEARNED_ROW, SEARCH_ROW
from geopose.cli import main


def _view(ncc, mpcd, cldice=0.5, rot=1.0, trans=2.0):
    return {"ncc": ncc, "mpcd_mm": mpcd, "cldice": cldice, "silhouette_dice": 0.9, "rotation_error_deg": rot,
            "translation_error_norm_mm": trans, "success": mpcd < 5.0}


def _case(name, rows, views=((1, 1), (2, 2)), start="Refine", quality=("ok", "ok")):
    curves = {"DICOM angles + 25 TTO": {v: {"mncc": [0.1, 0.2, 0.3], "mpcd_mm": [9.0, 6.0, 3.0]} for v in ("pa", "lat")}}
    return {
        "case": name, "rows": rows, "curves": curves,
        "runtimes_s": {"calibration (biplane)": 0.5, "init (biplane)": 0.25, "tto (biplane)": 3.0},
        "views": {"pa": {"true_view": views[0][0], "init_view": views[0][1]}, "lat": {"true_view": views[1][0], "init_view": views[1][1]}},
        "start": {"chosen": start}, "quality": dict(zip(("pa", "lat"), quality)),
    }


FINAL = LEARNED_ROW.format(n=25)


def test_summary_averages_views_within_subjects_then_over_subjects():
    a = _case("a", {FINAL: {"pa": _view(0.8, 2.0), "lat": _view(0.6, 4.0)}, INSTANT_ROW: {"pa": _view(0.7, 3.0), "lat": _view(0.6, 3.0)}})
    b = _case("b", {FINAL: {"pa": _view(0.7, 6.0), "lat": _view(0.5, 8.0)}}, views=((1, 1), (2, 0)), start="DICOM angles",
              quality=("ok", "doubtful"))
    s = summarise([a, b])
    row = s["rows"][FINAL]
    assert row["subjects"] == 2 and s["rows"][INSTANT_ROW]["subjects"] == 1
    assert row["mpcd_mm"]["pa"]["mean"] == pytest.approx(4.0)
    assert row["mpcd_mm"]["avg"]["mean"] == pytest.approx(5.0)  # subject means 3 and 7
    assert row["mpcd_mm"]["avg"]["sd"] == pytest.approx(np.std([3.0, 7.0], ddof=1))
    assert row["success"] == pytest.approx(0.5)  # 2.0 and 4.0 below 5 mm, 6.0 and 8.0 not
    assert s["view_accuracy"] == pytest.approx(0.75)
    assert s["starts"] == {"Refine": 1, "DICOM angles": 1}
    assert s["quality"] == {"ok": 3, "doubtful": 1, "failed": 0}
    # flags against the final mPCD: a's 2.0 / 4.0 mm views "ok", b's 6.0 "ok" and 8.0 "doubtful"
    assert s["flag_confusion"] == {"ok": {"< 2 mm": 0, "2-5 mm": 2, "> 5 mm": 1},
                                   "doubtful": {"< 2 mm": 0, "2-5 mm": 0, "> 5 mm": 1},
                                   "failed": {"< 2 mm": 0, "2-5 mm": 0, "> 5 mm": 0}}
    target = {t["target"]: t for t in s["targets"]}
    assert target["greedy + 25 TTO: mean mPCD <= 1.0 mm"]["measured"] == pytest.approx(5.0)
    assert not target["greedy + 25 TTO: mean mPCD <= 1.0 mm"]["met"]
    assert target["networks alone (greedy Refine, no search, no TTO): mean mPCD <= 5 mm"]["met"]  # 3.0, one subject
    assert target['quality flag: no view > 5 mm is "ok"']["measured"] == 1
    assert not target['quality flag: no view > 5 mm is "ok"']["met"]
    assert target['quality flag: >= 80 % of views < 2 mm are "ok"']["measured"] is None  # no view under 2 mm
    assert not target["view accuracy 100 %"]["met"]
    assert s["runtimes_s"]["calibrated Init (calibration + Init)"]["mean"] == pytest.approx(0.75)
    text = markdown(s, "# header")
    assert "| calibrated Init (calibration + Init) | 0.75 (0.00) | 0.75 | 0.75 (a) | 0.022 |" in text
    assert f"| {FINAL} | 2 | 0.750 (0.071)" in text and "| NO |" in text
    assert "Refine 1, DICOM angles 1 (subjects)" in text
    assert "| ok | 0 | 2 | 1 |" in text and "| doubtful | 0 | 0 | 1 |" in text


def test_the_slowest_case_is_measured_against_the_median():
    """The total time's median and slowest case per stage, and the target: no case over twice the median."""
    cases = [_case(name, {FINAL: {"pa": _view(0.8, 1.0), "lat": _view(0.8, 1.0)}}) for name in "abc"]
    for case, total_s in zip(cases, (10.0, 12.0, 25.0)):
        case["runtimes_s"]["total (biplane)"] = total_s
    s = summarise(cases)
    total = s["runtimes_s"]["total (biplane)"]
    assert (total["median"], total["max"], total["slowest"]) == (12.0, 25.0, "c")
    target = {t["target"].split(" (")[0]: t for t in s["targets"]}["no case slower than 2x the median"]
    assert target["measured"] == pytest.approx(25.0 / 12.0) and not target["met"]
    cases[2]["runtimes_s"]["total (biplane)"] = 24.0
    target = {t["target"].split(" (")[0]: t for t in summarise(cases)["targets"]}["no case slower than 2x the median"]
    assert target["met"]
    assert "| total (biplane) | 15.33 (7.57) | 12.00 | 24.00 (c) |" in markdown(summarise(cases), "# header")


def test_the_user_path_is_compared_with_its_truth_mask_upper_bound():
    upper = "upper bound (truth masks): greedy Refine + 25 TTO"
    a = _case("a", {FINAL: {"pa": _view(0.8, 1.4), "lat": _view(0.6, 1.1)}, upper: {"pa": _view(0.8, 1.0), "lat": _view(0.6, 1.0)}},
              quality=("ok", "failed"))
    target = {t["target"].split(" (")[0]: t for t in summarise([a])["targets"]}
    gap = target["the user's path within 0.3 mm of the truth masks' upper bound"]
    assert gap["measured"] == pytest.approx(0.25) and gap["met"]
    assert target['quality flag: >= 80 % of views < 2 mm are "ok"']["measured"] == pytest.approx(0.5)


def test_missing_metrics_are_left_out_not_zeroed():
    a = _case("a", {"biplane: Init": {"pa": _view(0.8, 2.0, cldice=None), "lat": _view(0.6, 4.0, cldice=0.4)}})
    s = summarise([a])
    assert s["rows"]["biplane: Init"]["cldice"]["pa"] == {"mean": None, "sd": None, "n": 0}
    assert s["rows"]["biplane: Init"]["cldice"]["avg"]["mean"] == pytest.approx(0.4)
    # A target whose row was not run is not met and says so (measured None).
    assert {t["target"]: t["measured"] for t in s["targets"]}["greedy + 25 TTO: mean mPCD <= 1.0 mm"] is None


def test_seed_ranges_are_inclusive_and_bad_text_names_the_remedy():
    assert seed_range("5000-5003") == [5000, 5001, 5002, 5003]
    assert seed_range("6028") == [6028]
    with pytest.raises(ValueError, match="FIRST-LAST"):
        seed_range("5000..5039")


def test_convergence_figure_is_written(tmp_path):
    path = convergence_figure([_case("a", {}), _case("b", {})], ["DICOM angles + 25 TTO"], tmp_path / "c.png")
    img = np.asarray(Image.open(path))
    assert img.shape[0] > 200 and img.shape[1] > 2 * img.shape[0]


def test_rows_compare_the_biplane_method_with_the_published_pipeline():
    rows = row_names(BenchSettings(RegistrationOptions(tto=TTOSchedule(iterations=25)), long_iterations=400))
    assert rows[:2] == ["DICOM angles", "DICOM angles + 25 TTO"]
    assert rows[2:6] == ["biplane: Init", INSTANT_ROW, SEARCH_ROW, FINAL]
    assert rows[6:10] == ["independent: Init", "independent: Init + Refine x1", "independent: greedy Refine",
                          "independent: greedy Refine + 25 TTO"]
    assert rows[10] == "truth + 25 TTO (drift)" and rows[-1] == "DICOM angles + 400 TTO"
    assert rows[11:13] == ["upper bound (truth masks): greedy Refine + search", "upper bound (truth masks): greedy Refine + 25 TTO"]
    assert "DICOM angles + 400 TTO" not in row_names(BenchSettings(long_iterations=0))
    assert SEARCH_ROW not in row_names(BenchSettings(RegistrationOptions(search=SearchOptions(enabled=False))))


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
    code = main(["bench", "--subjects", "2", "--seed-start", "777001", "--spacing-mm", "4", "--iterations", "2",
                 "--long-iterations", "3", "--device", "cpu", "--tto-px", "48", "--mirrored-subjects", "1", "--native-runs",
                 "--crossed-subjects", "1", "--out", str(out)])
    assert code == 0
    data = json.loads((out / "bench.json").read_text())
    case = data["cases"][0]
    assert set(case["rows"]) == set(row_names(BenchSettings(RegistrationOptions(tto=TTOSchedule(iterations=2)), long_iterations=3)))
    for row in case["rows"].values():
        for metrics in row.values():
            assert metrics["mpcd_mm"] >= 0 and -1 <= metrics["ncc"] <= 1
    # TTO rows keep their curves: 2 (or 3) steps and the start
    assert len(case["curves"][LEARNED_ROW.format(n=2)]["pa"]["mncc"]) == 3
    assert len(case["curves"]["DICOM angles + 3 TTO"]["lat"]["mpcd_mm"]) == 4
    assert case["start"]["chosen"] in ("DICOM angles", "Init", "Init PA", "Init LAT", "Refine + search")
    assert "## Targets" in (out / "bench.md").read_text()
    assert (out / "tto_convergence.png").stat().st_size > 10_000
    assert (out / "cases" / "phantom-777001.json").is_file()  # resumable
    # the default rows ran the user's path: masks computed from the CTA, not the phantom's labels
    assert case["masks"]["vessels"].startswith("computed from the CTA") and case["masks"]["cranium"].startswith("computed")
    # the same subject registered again with its CTA mirrored left-right, and the mirror test's section
    (mirrored,) = data["mirrored"]
    assert mirrored["case"] == "phantom-777001-mirrored" and set(mirrored["quality"]) == {"pa", "lat"}
    assert (out / "cases" / "phantom-777001-mirrored.json").is_file()
    assert "## The mirror test: the CTA as given and mirrored left-right" in (out / "bench.md").read_text()
    assert "--mirrored-subjects 1" in (out / "bench.md").read_text()
    # the first subject's CTA registered with the second subject's runs (a wrong pairing), and its section
    (crossed,) = data["crossed"]
    assert crossed["case"] == "phantom-777001-cta+phantom-777002-runs" and set(crossed["quality"]) == {"pa", "lat"}
    assert (out / "cases" / "phantom-777001-cta+phantom-777002-runs.json").is_file()
    assert "## A wrong pairing: one subject's CTA with the next subject's runs" in (out / "bench.md").read_text()
    assert "--crossed-subjects 1" in (out / "bench.md").read_text()
    # the runs were written native and read subtracted, as the header and the command to reproduce say
    assert "with runs archived native" in (out / "bench.md").read_text() and "--native-runs --out" in (out / "bench.md").read_text()


def test_dense_opacification_cases_get_their_own_section_and_targets():
    from geopose.bench.report import dense_markdown

    a = _case("phantom-5000-all", {FINAL: {"pa": _view(0.8, 1.0, rot=1.0), "lat": _view(0.6, 2.0, rot=2.0)}})
    b = _case("phantom-5001-all", {FINAL: {"pa": _view(0.8, 4.0, rot=3.0), "lat": _view(0.6, 3.0, rot=4.0)}},
              quality=("doubtful", "failed"))
    text = "\n".join(dense_markdown([a, b], 25))
    assert "| row | phantom-5000-all | phantom-5001-all |" in text and f"| {FINAL} | 1.0 / 1.0; 2.0 / 2.0 | 4.0 / 3.0; 3.0 / 4.0 |" in text
    assert "phantom-5001-all doubtful / failed" in text
    assert f"| {FINAL}: mean mPCD <= 2 mm | 2.50 | NO |" in text and f"| {FINAL}: mean rotation error <= 2 deg | 2.50 | NO |" in text


def test_the_mirror_test_is_reported_on_correct_and_mirrored_ctas():
    """Outcomes counted per CTA (failed, the sides-alike note, passed, not run), and the three targets."""
    from geopose.bench.report import mirror_outcomes, mirrored_markdown

    def test(margin, alike=False, equal=None):
        return {"margin": margin, "equal_effort_margin": equal, "mirrored": margin < -0.05, "sides_alike": alike}

    correct = [_case(f"phantom-{s}", {}) | {"mirror": m} for s, m in
               ((5000, test(0.2)), (5001, test(0.01, alike=True)), (5002, test(-0.1)), (5003, None))]
    assert mirror_outcomes(correct) == {"failed": 1, "sides alike": 1, "passed": 1, "not run": 1}
    mirrored = [_case("phantom-5000-mirrored", {}, quality=("failed", "failed")) | {"mirror": test(-0.2)},
                _case("phantom-5001-mirrored", {}, quality=("ok", "doubtful")) | {"mirror": test(0.08, equal=0.03)}]
    text = "\n".join(mirrored_markdown(correct, mirrored))
    assert "| as given (correct) | 4 | 1 | 1 | 1 | 1 |" in text and "| mirrored left-right | 2 | 1 | 0 | 1 | 0 |" in text
    assert "| a mirrored CTA comes out failed (both views; by any test) | 1 of 2 | NO |" in text
    assert "| of them failed by the mirror test | 1 of 2 | - |" in text
    assert "| no mirrored CTA passes the mirror test without the sides-alike note | 1 | NO |" in text
    assert "| no correct CTA failed by the mirror test | 1 | NO |" in text
    assert "Flags of the mirrored CTAs' views: ok 1, doubtful 1, failed 2." in text
    assert "Correct CTAs not passed: phantom-5001 +0.010 / - (sides alike); phantom-5002 -0.100 / - (failed); phantom-5003 (not run)." in text
    assert "Mirrored CTAs: phantom-5000-mirrored -0.200 / - (failed); phantom-5001-mirrored +0.080 / +0.030 (passed)." in text


def test_wrong_pairings_are_reported_against_the_correct_ones():
    """Cases counted by their worst view, both targets, and the gains listed."""
    from geopose.bench.report import crossed_markdown

    def pairing(gain):
        return {"gain": gain, "verdict": "failed" if gain > 1.2 else "doubtful" if gain > 1.16 else "ok",
                "loose": gain > 1.2}

    correct = [_case(f"phantom-{s}", {}) | {"pairing": pairing(g)} for s, g in ((5000, 1.05), (5001, 1.24), (5002, 1.10))]
    crossed = [_case("phantom-5000-cta+phantom-5001-runs", {}, quality=("failed", "failed")) | {"pairing": pairing(1.30)},
               _case("phantom-5001-cta+phantom-5002-runs", {}, quality=("ok", "doubtful")) | {"pairing": pairing(1.18)}]
    text = "\n".join(crossed_markdown(correct, crossed))
    assert "Cases by their worst view's flag: ok 0, doubtful 1, failed 1; views: ok 1, doubtful 1, failed 2." in text
    assert "| a wrong pairing comes out failed (both views) | 1 of 2 | NO |" in text
    assert "| no correct pairing failed by the pairing test | 1 | NO |" in text
    assert "Wrong pairings: phantom-5000-cta+phantom-5001-runs x1.300 (failed); phantom-5001-cta+phantom-5002-runs x1.180 (doubtful)." in text
    assert "the highest five: phantom-5001 x1.240 (ok); phantom-5002 x1.100 (ok); phantom-5000 x1.050 (ok)." in text


def test_a_wrong_pairing_needs_a_next_subject(tmp_path, capsys):
    code = main(["bench", "--subjects", "2", "--crossed-subjects", "2", "--out", str(tmp_path / "b")])
    assert code == 2 and "--crossed-subjects must lie between 0 and --subjects - 1 (1)" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()  # refused before any work
