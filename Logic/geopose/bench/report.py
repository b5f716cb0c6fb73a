"""Benchmark tables (Markdown + JSON) and the TTO convergence figure.

Per-view metrics are first averaged within a subject (PA and LAT), then
reported as mean (sd) over subjects, as in the paper; the success rate counts
view observations with mPCD below ``SUCCESS_MPCD_MM``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from ..options import TTOSchedule
from ..register.evaluate import SUCCESS_MPCD_MM
from .run import DRIFT_ROW, INSTANT_ROW, LEARNED_ROW, NATIVE_TTO_ROW, SEARCH_ROW, UPPER_BOUND_ROW

__all__ = ["summarise", "markdown", "convergence_figure", "flag_confusion", "TARGETS", "PAPER_RUNTIME_MS"]

#: Targets on held-out phantoms: (description, row, statistic, comparison, value); ``{n}`` in a
#: row name is the short TTO budget.
TARGETS = (
    ("greedy + {n} TTO: mean mPCD <= 1.0 mm", LEARNED_ROW, "mpcd_mm", "<=", 1.0),
    ("greedy + {n} TTO: >= 97.5 % of views under 5 mm", LEARNED_ROW, "success", ">=", 0.975),
    ("greedy + {n} TTO: rotation error <= 1.5 deg", LEARNED_ROW, "rotation_error_deg", "<=", 1.5),
    ("greedy + {n} TTO: translation error <= 10 mm", LEARNED_ROW, "translation_error_norm_mm", "<=", 10.0),
    ("instant, the result before the TTO (greedy + search): mean mPCD <= 4 mm", SEARCH_ROW, "mpcd_mm", "<=", 4.0),
    ("networks alone (greedy Refine, no search, no TTO): mean mPCD <= 5 mm", INSTANT_ROW, "mpcd_mm", "<=", 5.0),
    ("TTO from the truth: mean drift <= 0.5 mm", DRIFT_ROW, "mpcd_mm", "<=", 0.5),
    ("view accuracy 100 %", "", "view_accuracy", ">=", 1.0),
)
#: The default row may be at most this much (mean mPCD, mm) worse than its truth-mask upper bound.
UPPER_BOUND_GAP_MM = 0.3
#: Outcome classes of a view by its final mPCD (mm): (label, lower bound inclusive).
OUTCOMES = (("< 2 mm", 0.0), ("2-5 mm", 2.0), ("> 5 mm", 5.0))
FLAGS = ("ok", "doubtful", "failed")
#: Flag targets: at least this share of the views under 2 mm are "ok" (and no view over 5 mm is).
OK_SHARE_OF_GOOD = 0.8
#: The stages the paper times together as "calibrated Init", and that sum's row label.
CALIBRATED_INIT_STAGES = ("calibration (biplane)", "init (biplane)")
CALIBRATED_INIT = "calibrated Init (calibration + Init)"
#: A registration's time per case, and the most the slowest case may take in medians of it (issue 33: a case's time
#: should not depend much on the CTA and the C-arm's settings).
TOTAL_STAGE = "total (biplane)"
SLOWEST_OVER_MEDIAN = 2.0
#: The paper's H100 runtimes (ms) for the stages it reports.
PAPER_RUNTIME_MS = {CALIBRATED_INIT: 21.8, "refine (independent)": 147.0, "tto (independent)": 2000.0}
#: Per-view metrics averaged per subject in the summary.
SUMMARY_KEYS = ("ncc", "mpcd_mm", "cldice", "silhouette_dice", "rotation_error_deg", "translation_error_norm_mm",
                "source_distance_mm", "in_plane_mm", "depth_mm", "in_plane_rotation_deg", "out_of_plane_rotation_deg")
VIEWS = ("pa", "lat")
#: (column label, metric key, digits) of the accuracy table.
COLUMNS = (("NCC", "ncc", 3), ("mPCD (mm)", "mpcd_mm", 1), ("clDice", "cldice", 2))


def _finite(values) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def _stat(values) -> dict:
    v = _finite(values)
    if not v:
        return {"mean": None, "sd": None, "n": 0}
    return {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0, "n": len(v)}


def _spread(values, names: list[str]) -> dict:
    """:func:`_stat` of per-case seconds with their median and the slowest case (``names``: the cases, in order)."""
    out = _stat(values)
    finite = [(v, n) for v, n in zip(values, names) if v is not None and math.isfinite(v)]
    if finite:
        slowest, case = max(finite, key=lambda vn: vn[0])  # the first of equals
        out |= {"median": float(np.median([v for v, _ in finite])), "max": float(slowest), "slowest": case}
    return out


def summarise(cases: list[dict], iterations: int = TTOSchedule.iterations) -> dict:
    """Subject-level statistics per row and metric, view accuracy, runtimes and the
    targets (``iterations``: the short TTO budget the rows were run with)."""
    rows: dict[str, dict] = {}
    for row in dict.fromkeys(r for c in cases for r in c["rows"]):
        have = [c for c in cases if row in c["rows"]]
        out = {"subjects": len(have)}
        for key in SUMMARY_KEYS:
            per_view = {v: [c["rows"][row][v].get(key) for c in have] for v in VIEWS}
            avg = [np.mean(_finite(vals)) if _finite(vals) else None for vals in zip(*per_view.values())]
            out[key] = {**{v: _stat(per_view[v]) for v in VIEWS}, "avg": _stat(avg)}
        flags = [c["rows"][row][v]["success"] for c in have for v in VIEWS if "success" in c["rows"][row][v]]
        out["success"] = float(np.mean(flags)) if flags else None
        rows[row] = out
    views = [(c["views"][v]["true_view"], c["views"][v]["init_view"]) for c in cases for v in VIEWS]
    accuracy = float(np.mean([t == p for t, p in views])) if views else None
    stages = [s for c in cases for s in c["runtimes_s"]]
    names = [c["case"] for c in cases]
    runtimes = {s: _spread([c["runtimes_s"].get(s) for c in cases], names) for s in dict.fromkeys(stages)}
    runtimes[CALIBRATED_INIT] = _spread([sum(c["runtimes_s"].get(s, math.nan) for s in CALIBRATED_INIT_STAGES)
                                         for c in cases], names)
    starts = [c.get("start", {}).get("chosen") for c in cases]
    refine_starts = [c.get("start", {}).get("refine") for c in cases]
    flags = [f for c in cases for f in c.get("quality", {}).values()]
    summary = {"rows": rows, "view_accuracy": accuracy, "views": len(views), "runtimes_s": runtimes,
               "starts": {s_: starts.count(s_) for s_ in dict.fromkeys(starts) if s_},
               "refine_starts": {s_: refine_starts.count(s_) for s_ in dict.fromkeys(refine_starts) if s_},
               "quality": {f: flags.count(f) for f in FLAGS},
               "flag_confusion": flag_confusion(cases, iterations),
               "case_tests": [{"case": c["case"], "mirror": c.get("mirror"), "pairing": c.get("pairing"),
                               "quality": c.get("quality", {})} for c in cases]}
    summary["targets"] = _targets(summary, iterations)
    return summary


def _outcome(mpcd_mm: float) -> str:
    return [label for label, low in OUTCOMES if mpcd_mm >= low][-1]


def flag_confusion(cases: list[dict], n: int) -> dict[str, dict[str, int]]:
    """``{flag: {outcome: views}}``: the default registration's quality flag of each view against
    its final carotid mPCD class (:data:`OUTCOMES`; the result before the TTO when no TTO ran);
    views without carotid points are left out."""
    table = {flag: {label: 0 for label, _ in OUTCOMES} for flag in FLAGS}
    for c in cases:
        row = c["rows"].get(LEARNED_ROW.format(n=n)) or c["rows"].get(SEARCH_ROW) or c["rows"].get(INSTANT_ROW)
        for v, flag in c.get("quality", {}).items():
            got = None if row is None else row[v].get("mpcd_mm")
            if got is not None:
                table[flag][_outcome(got)] += 1
    return table


def _flag_targets(confusion: dict[str, dict[str, int]]) -> list[dict]:
    bad, good = OUTCOMES[-1][0], OUTCOMES[0][0]
    ok_bad = confusion["ok"][bad]
    good_views = sum(confusion[f][good] for f in FLAGS)
    share = confusion["ok"][good] / good_views if good_views else None
    return [
        {"target": f"quality flag: no view {bad} is \"ok\"", "measured": ok_bad, "met": ok_bad == 0},
        {"target": f"quality flag: >= {100 * OK_SHARE_OF_GOOD:.0f} % of views {good} are \"ok\"", "measured": share,
         "met": share is not None and share >= OK_SHARE_OF_GOOD},
    ]


def _targets(summary: dict, n: int) -> list[dict]:
    rows = summary["rows"]
    out = []
    for text, row, stat, op, value in TARGETS:
        row = row.format(n=n)
        if stat == "view_accuracy":
            got = summary["view_accuracy"]
        elif stat == "success":
            got = rows.get(row, {}).get("success")
        else:
            got = rows.get(row, {}).get(stat, {}).get("avg", {}).get("mean")
        met = got is not None and (got >= value if op == ">=" else got <= value)
        out.append({"target": text.format(n=n), "measured": got, "met": bool(met)})
    native, learned = NATIVE_TTO_ROW.format(n=n), LEARNED_ROW.format(n=n)
    a, b = (rows.get(r, {}).get("mpcd_mm", {}).get("avg", {}).get("mean") for r in (native, learned))
    out.append({
        "target": f"the networks add something: {native} worse than {learned} (mPCD ratio > 1)",
        "measured": None if a is None or b is None else a / max(b, 1e-9),
        "met": a is not None and b is not None and a > b,
    })
    upper = rows.get(UPPER_BOUND_ROW.format(n=n), {}).get("mpcd_mm", {}).get("avg", {}).get("mean")
    gap = None if upper is None or b is None else b - upper
    out.append({
        "target": f"the user's path within {UPPER_BOUND_GAP_MM:g} mm of the truth masks' upper bound "
                  f"({learned} minus {UPPER_BOUND_ROW.format(n=n)}, mean mPCD)",
        "measured": gap, "met": gap is not None and gap <= UPPER_BOUND_GAP_MM,
    })
    total = summary["runtimes_s"].get(TOTAL_STAGE, {})
    ratio = total["max"] / total["median"] if total.get("median") else None
    out.append({
        "target": f"no case slower than {SLOWEST_OVER_MEDIAN:g}x the median ({TOTAL_STAGE}, slowest / median)",
        "measured": ratio, "met": ratio is not None and ratio <= SLOWEST_OVER_MEDIAN,
    })
    return out + _flag_targets(summary["flag_confusion"])


def _cell(s: dict, digits: int) -> str:
    return "-" if s["mean"] is None else f"{s['mean']:.{digits}f} ({s['sd']:.{digits}f})"


def markdown(summary: dict, header: str, real: list[dict] | None = None, n: int = TTOSchedule.iterations,
             dense: list[dict] | None = None, mirrored: list[dict] | None = None,
             crossed: list[dict] | None = None) -> str:
    """The benchmark as Markdown: accuracy table, pose-error parts, view accuracy, targets,
    runtimes, the real-anatomy rows (``real``: cases of real head CTs with simulated runs), the
    densely opacified phantoms (``dense``), the mirror test on the subjects and their CTAs mirrored (``mirrored``) and
    the wrong pairings (``crossed``: one subject's CTA with the next one's runs)."""
    cols = [f"{label} {v.upper()}" for label, _, _ in COLUMNS for v in (*VIEWS, "avg")]
    lines = [header, "", "## Accuracy (mean (sd) over subjects; avg = PA and LAT averaged within each subject)", ""]
    lines += ["| row | n | " + " | ".join(cols) + " | rot. err. (deg) | transl. err. (mm) | success |"]
    lines += ["|---|---:|" + "---:|" * (len(cols) + 3)]
    for row, s in summary["rows"].items():
        cells = [_cell(s[key][v], d) for _, key, d in COLUMNS for v in (*VIEWS, "avg")]
        success = "-" if s["success"] is None else f"{100 * s['success']:.0f} %"
        lines.append(
            f"| {row} | {s['subjects']} | " + " | ".join(cells)
            + f" | {_cell(s['rotation_error_deg']['avg'], 1)} | {_cell(s['translation_error_norm_mm']['avg'], 1)} | {success} |"
        )
    lines += ["", "## Pose errors by what a view sees (mean (sd) over subjects, views averaged)", "",
              "| row | in-plane (mm) | depth (mm) | in-plane rotation (deg) | out-of-plane rotation (deg) | source position (mm) |",
              "|---|---:|---:|---:|---:|---:|"]
    for row, s_ in summary["rows"].items():
        lines.append(f"| {row} | " + " | ".join(_cell(s_[k]["avg"], 1) for k in (
            "in_plane_mm", "depth_mm", "in_plane_rotation_deg", "out_of_plane_rotation_deg", "source_distance_mm")) + " |")
    acc = summary["view_accuracy"]
    lines += ["", f"View accuracy (the network's class against the acquisition's view, independent views): "
              f"{'-' if acc is None else f'{100 * acc:.1f} %'} of {summary['views']} views.", ""]
    if summary.get("starts"):
        lines += ["Start the default registration's result came from (every distinct start through the TTO's coarse "
                  "steps, the DICOM angles and the best other to the end; the lower objective wins): "
                  + ", ".join(f"{k} {v}" for k, v in summary["starts"].items()) + " (subjects).", ""]
    if summary.get("refine_starts"):
        lines += ["Start the default registration's greedy Refine ended best from (every combination of a rotation "
                  "and an isocentre of the fused Init and each view's; the highest mean mNCC wins): "
                  + ", ".join(f"{k} {v}" for k, v in summary["refine_starts"].items()) + " (subjects).", ""]
    if summary.get("quality"):
        lines += ["Quality flags of the default registration: "
                  + ", ".join(f"{k} {v}" for k, v in summary["quality"].items()) + " (views).", ""]
    if summary.get("flag_confusion"):
        lines += confusion_markdown(summary["flag_confusion"])
    lines += ["## Targets", "", "| target | measured | met |", "|---|---:|:---:|"]
    for t in summary["targets"]:
        got = "-" if t["measured"] is None else f"{t['measured']:.3g}"
        lines.append(f"| {t['target']} | {got} | {'yes' if t['met'] else 'NO'} |")
    lines += ["", "## Runtimes per case (s)", "", "| stage | mean (sd) | median | slowest | paper, H100 (s) |",
              "|---|---:|---:|---|---:|"]
    for stage, s in summary["runtimes_s"].items():
        paper = PAPER_RUNTIME_MS.get(stage)
        median, slowest = ("-", "-") if "median" not in s else (f"{s['median']:.2f}", f"{s['max']:.2f} ({s['slowest']})")
        lines.append(f"| {stage} | {_cell(s, 2)} | {median} | {slowest} | {'' if paper is None else f'{paper / 1000:.3f}'} |")
    if real:
        lines += real_heads_markdown(real, n)
    if dense:
        lines += dense_markdown(dense, n)
    if mirrored:
        lines += mirrored_markdown(summary["case_tests"], mirrored)
    if crossed:
        lines += crossed_markdown(summary["case_tests"], crossed)
    return "\n".join(lines) + "\n"


def confusion_markdown(confusion: dict[str, dict[str, int]]) -> list[str]:
    """The flag-against-outcome table (views)."""
    labels = [label for label, _ in OUTCOMES]
    lines = ["Quality flag against the final carotid mPCD (views):", "",
             "| flag | " + " | ".join(labels) + " |", "|---|" + "---:|" * len(labels)]
    lines += [f"| {flag} | " + " | ".join(str(confusion[flag][label]) for label in labels) + " |" for flag in FLAGS]
    return lines + [""]


#: What the mirror test (``register/mirror.py``) said of a case: the result failed (the CTA mirrored left-right explains
#: the runs better), the sides-alike note (the runs do not tell the sides apart), passed, or not run.
MIRROR_OUTCOMES = ("failed", "sides alike", "passed", "not run")


def mirror_outcome(case: dict) -> str:
    """One case's :data:`MIRROR_OUTCOMES` entry, from its ``mirror`` record (``MirrorTest.as_dict``)."""
    test = case.get("mirror")
    if test is None:
        return "not run"
    return "failed" if test["mirrored"] else "sides alike" if test["sides_alike"] else "passed"


def mirror_outcomes(cases: list[dict]) -> dict[str, int]:
    """Cases per :data:`MIRROR_OUTCOMES` entry."""
    outcomes = [mirror_outcome(c) for c in cases]
    return {o: outcomes.count(o) for o in MIRROR_OUTCOMES}


def mirrored_markdown(as_given_cases: list[dict], mirrored: list[dict]) -> list[str]:
    """The mirror test on the subjects' CTAs as given (``as_given_cases``: the benchmark's cases, or their
    ``summary["case_tests"]``) and mirrored left-right (``mirrored``: ``run.evaluate_mirrored`` cases): outcomes,
    flags, targets, margins."""
    as_given, counts = mirror_outcomes(as_given_cases), mirror_outcomes(mirrored)
    flags = [f for c in mirrored for f in c["quality"].values()]
    failed_both = sum(set(c["quality"].values()) == {"failed"} for c in mirrored)
    lines = ["", "## The mirror test: the CTA as given and mirrored left-right", "",
             f"The first {len(mirrored)} subjects were registered again with the CTA's array flipped left-right and the "
             "header kept (a CTA whose header swaps the sides), on the user's path. Outcome of the mirror test (cases):",
             "", "| CTA | cases | " + " | ".join(MIRROR_OUTCOMES) + " |", "|---|---:|" + "---:|" * len(MIRROR_OUTCOMES)]
    lines += [f"| {name} | {sum(n.values())} | " + " | ".join(str(n[o]) for o in MIRROR_OUTCOMES) + " |"
              for name, n in (("as given (correct)", as_given), ("mirrored left-right", counts))]
    lines += ["", "Flags of the mirrored CTAs' views: " + ", ".join(f"{f} {flags.count(f)}" for f in FLAGS) + ".", "",
              "| target | measured | met |", "|---|---:|:---:|",
              f"| a mirrored CTA comes out failed (both views; by any test) | {failed_both} of {len(mirrored)} | "
              f"{'yes' if failed_both == len(mirrored) else 'NO'} |",
              f"| of them failed by the mirror test | {counts['failed']} of {len(mirrored)} | - |",
              f"| no mirrored CTA passes the mirror test without the sides-alike note | {counts['passed']} | "
              f"{'yes' if counts['passed'] == 0 else 'NO'} |",
              f"| no correct CTA failed by the mirror test | {as_given['failed']} | {'yes' if as_given['failed'] == 0 else 'NO'} |",
              "", "Margins, against the result / with equal effort (the mirrored hypothesis's objective less the "
              "result's / less the CTA's own short fit's, both views summed; negative: the CTA's mirror image explains "
              "the runs better; \"-\": not run, the first already failed the result). Correct CTAs not passed: "
              + ("; ".join(_margins(c) for c in as_given_cases if mirror_outcome(c) != "passed") or "none")
              + ". Mirrored CTAs: " + "; ".join(_margins(c) for c in mirrored if c.get("mirror")) + "."]
    return lines + [""]


def case_flag(case: dict) -> str:
    """A case's worst view flag (failed > doubtful > ok)."""
    flags = list(case["quality"].values())
    return next(f for f in reversed(FLAGS) if f in flags) if flags else "-"


def _gain(case: dict) -> str:
    """``name gain (flag)`` of one case's pairing test (``register/pairing.py``)."""
    test = case.get("pairing")
    gain = "not run" if test is None or test.get("gain") is None else f"x{test['gain']:.3f}"
    return f"{case['case']} {gain} ({case_flag(case)})"


def crossed_markdown(correct_cases: list[dict], crossed: list[dict]) -> list[str]:
    """The wrong pairings (``crossed``: ``run.evaluate_crossed`` cases) against the subjects registered with their own
    CTA (``correct_cases``: the benchmark's cases or ``summary["case_tests"]``): flags, the pairing test, targets."""
    worst = [case_flag(c) for c in crossed]
    loose = [c for c in correct_cases if (c.get("pairing") or {}).get("loose")]
    flags = [f for c in crossed for f in c["quality"].values()]
    lines = ["", "## A wrong pairing: one subject's CTA with the next subject's runs", "",
             f"{len(crossed)} subjects' CTAs were each registered with the next subject's two runs, on the user's path (as "
             "a user who picked another patient's CTA would: anonymised runs, or a CTA without identifiers, pass the "
             "identifier check). The pairing test (`register/pairing.py`) fails a result whose vessels fit the runs' only "
             "loosely. Cases by their worst view's flag: " + ", ".join(f"{f} {worst.count(f)}" for f in FLAGS)
             + "; views: " + ", ".join(f"{f} {flags.count(f)}" for f in FLAGS) + ".", "",
             "| target | measured | met |", "|---|---:|:---:|",
             f"| a wrong pairing comes out failed (both views) | {sum(set(c['quality'].values()) == {'failed'} for c in crossed)} "
             f"of {len(crossed)} | {'yes' if all(set(c['quality'].values()) == {'failed'} for c in crossed) else 'NO'} |",
             f"| no correct pairing failed by the pairing test | {len(loose)} | {'yes' if not loose else 'NO'} |",
             "", "Blur gains (the vessel NCC with both images blurred over the NCC as registered, the views' mean; above "
             "the bar the result fails). Wrong pairings: " + "; ".join(_gain(c) for c in crossed) + ". Correct pairings, "
             "the highest five: " + "; ".join(_gain(c) for c in sorted(correct_cases, key=lambda c: -((c.get("pairing") or {})
                                                                                                  .get("gain") or 0))[:5]) + "."]
    return lines + [""]


def _margins(case: dict) -> str:
    """``name margin / equal-effort margin (outcome)`` of one case's mirror test."""
    test = case["mirror"]
    if test is None:
        return f"{case['case']} (not run)"
    equal = "-" if test.get("equal_effort_margin") is None else f"{test['equal_effort_margin']:+.3f}"
    return f"{case['case']} {test['margin']:+.3f} / {equal} ({mirror_outcome(case)})"


#: Real heads with arteries: the final rotation error (deg) at most this in every view.
REAL_HEAD_ARTERIES_ROTATION_DEG = 1.5
#: Plain real heads: the final pose may be at most this much further from the truth than the DICOM
#: angles' (rotation deg, source position mm) before it counts as worse.
NO_WORSE_TOLERANCE = (0.25, 2.0)


#: Densely opacified phantoms: the final mPCD (mm) and rotation error (deg) at most these, mean over the cases.
DENSE_MPCD_MM = 2.0
DENSE_ROTATION_DEG = 2.0


def dense_markdown(dense: list[dict], n: int) -> list[str]:
    """Per densely opacified phantom, mPCD (mm) / rotation error (deg) of each view at each row, the
    quality flags, and the targets (means over cases and views)."""
    rows = list(dict.fromkeys(r for c in dense for r in c["rows"]))
    lines = ["", "## Densely opacified runs (held-out phantoms; every artery, a nidus or a late venous phase)", "",
             "Carotid mPCD (mm) / rotation error (deg), PA; LAT.", ""]
    lines += _case_table(dense, rows, lambda r: "; ".join(
        f"{r[v]['mpcd_mm']:.1f} / {r[v]['rotation_error_deg']:.1f}" for v in VIEWS))
    lines += ["", "Quality flags, PA / LAT: " + "; ".join(
        f"{c['case']} {c['quality']['pa']} / {c['quality']['lat']}" for c in dense if "quality" in c) + ".", ""]
    final = LEARNED_ROW.format(n=n)
    views = [c["rows"][final][v] for c in dense if final in c["rows"] for v in VIEWS]
    if views:
        mpcd_mm = float(np.mean([v["mpcd_mm"] for v in views]))
        rotation = float(np.mean([v["rotation_error_deg"] for v in views]))
        lines += ["| target (dense opacification) | measured | met |", "|---|---:|:---:|",
                  f"| {final}: mean mPCD <= {DENSE_MPCD_MM:g} mm | {mpcd_mm:.2f} | {'yes' if mpcd_mm <= DENSE_MPCD_MM else 'NO'} |",
                  f"| {final}: mean rotation error <= {DENSE_ROTATION_DEG:g} deg | {rotation:.2f} | "
                  f"{'yes' if rotation <= DENSE_ROTATION_DEG else 'NO'} |"]
    return lines


def _case_table(cases: list[dict], rows: list[str], cell: Callable[[dict], str]) -> list[str]:
    """A Markdown table with a line per row and a column per case; ``cell`` writes one case's
    ``{view: metrics}`` of a row, "-" where the case lacks the row."""
    lines = ["| row | " + " | ".join(c["case"] for c in cases) + " |", "|---|" + "---:|" * len(cases)]
    for row in rows:
        cells = ["-" if row not in c["rows"] else cell(c["rows"][row]) for c in cases]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines


def real_heads_markdown(real: list[dict], n: int) -> list[str]:
    """Per real-head case, the rotation and source-position error of each view at each row, the
    carotid mPCD of the cases with arteries, the quality flags, and the targets: heads with arteries
    within :data:`REAL_HEAD_ARTERIES_ROTATION_DEG`, plain heads never further from the truth than
    the DICOM angles."""
    rows = list(dict.fromkeys(r for c in real for r in c["rows"]))
    lines = ["", "## Real anatomy (real head CTs, runs simulated from them)", ""]
    lines += [f"- {note}" for note in dict.fromkeys(note for c in real for note in c["notes"])] + [""]
    lines += ["Rotation error (deg) / source-position error (mm), PA; LAT.", ""]
    lines += _case_table(real, rows, lambda r: "; ".join(
        f"{r[v]['rotation_error_deg']:.1f} / {r[v]['source_distance_mm']:.0f}" for v in VIEWS))
    with_arteries = [c for c in real
                     if any(r[v].get("mpcd_mm") is not None for r in c["rows"].values() for v in VIEWS)]
    if with_arteries:
        lines += ["", "Carotid mPCD (mm) of the cases with arteries, PA; LAT.", ""]
        lines += _case_table(with_arteries, rows, lambda r: "; ".join(
            "-" if r[v].get("mpcd_mm") is None else f"{r[v]['mpcd_mm']:.1f}" for v in VIEWS))
    final = LEARNED_ROW.format(n=n)
    lines += ["", "Quality flags of the default registration, PA; LAT: " + "; ".join(
        f"{c['case']} {c['quality']['pa']} / {c['quality']['lat']}" for c in real if "quality" in c) + ".", ""]
    arteried = [c["rows"][final][v]["rotation_error_deg"] for c in with_arteries if final in c["rows"] for v in VIEWS]
    plain = [c for c in real if c not in with_arteries and final in c["rows"]]
    worse = [f"{c['case']} {v.upper()}" for c in plain for v in VIEWS
             if c["rows"][final][v]["rotation_error_deg"] > c["rows"]["DICOM angles"][v]["rotation_error_deg"] + NO_WORSE_TOLERANCE[0]
             or c["rows"][final][v]["source_distance_mm"] > c["rows"]["DICOM angles"][v]["source_distance_mm"] + NO_WORSE_TOLERANCE[1]]
    lines += ["| target (real heads) | measured | met |", "|---|---:|:---:|"]
    if arteried:
        worst = max(arteried)
        lines.append(f"| with arteries: final rotation error <= {REAL_HEAD_ARTERIES_ROTATION_DEG:g} deg (worst view) | "
                     f"{worst:.1f} | {'yes' if worst <= REAL_HEAD_ARTERIES_ROTATION_DEG else 'NO'} |")
    if plain:
        lines.append(f"| plain: never further from the truth than the DICOM angles (views more than "
                     f"{NO_WORSE_TOLERANCE[0]:g} deg or {NO_WORSE_TOLERANCE[1]:g} mm source position further) | "
                     f"{len(worse)} of {2 * len(plain)}{': ' + ', '.join(worse) if worse else ''} | "
                     f"{'yes' if not worse else 'NO'} |")
    return lines


def _mean_curve(cases: list[dict], row: str, key: str) -> tuple[np.ndarray, np.ndarray] | None:
    per_case = []
    for c in cases:
        curves = c["curves"].get(row)
        if not curves or any(curves[v][key] is None for v in VIEWS):
            continue
        per_case.append(np.mean([curves[v][key] for v in VIEWS], axis=0))
    if not per_case:
        return None
    arr = np.asarray([c[:min(len(c) for c in per_case)] for c in per_case])  # the iterations every case reached
    return arr.mean(0), arr.std(0, ddof=1) / np.sqrt(len(arr)) if len(arr) > 1 else np.zeros(arr.shape[1])


def convergence_figure(cases: list[dict], rows: list[str], path: str | Path) -> Path:
    """mNCC and mPCD against TTO iteration (subject means, +- one standard error) for ``rows``."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, key, label in ((axes[0], "mncc", "mNCC (TTO objective term)"), (axes[1], "mpcd_mm", "carotid mPCD (mm)")):
        for row in rows:
            curve = _mean_curve(cases, row, key)
            if curve is None:
                continue
            mean, se = curve
            it = np.arange(len(mean))
            ax.plot(it, mean, label=row)
            ax.fill_between(it, mean - se, mean + se, alpha=0.2)
        ax.set_xscale("symlog", linthresh=25)
        ax.set_xlabel("TTO iteration")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[1].axhline(SUCCESS_MPCD_MM, color="grey", lw=0.8, ls="--")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
