"""Progress reporting and cancellation (``progress.py``): the cancel hook, a stage's parts, the console bar."""

from __future__ import annotations

import pytest
from conftest import blob_renderer
from register_helpers import ORACLE_RENDER_PX, OracleRefine

from geopose import contract as C
from geopose.geometry import isopose
from geopose.register import ConsoleProgress, Monitor, RegistrationCancelled, greedy_refine, render_model_view


def test_cancel_hook_stops_a_stage():
    renderer = blob_renderer()
    T = isopose(C.VIEW_PA)
    target = render_model_view(renderer, T, ORACLE_RENDER_PX)
    with pytest.raises(RegistrationCancelled, match="refine"):
        greedy_refine(renderer, target, T, C.VIEW_PA, OracleRefine([]), ORACLE_RENDER_PX, monitor=Monitor(cancel=lambda: True))


def test_a_part_of_a_stage_reports_within_its_share():
    """Two TTO runs in one stage: the second's progress runs from 50 % to 100 %, labelled."""
    seen = []
    monitor = Monitor(lambda stage, f, m: seen.append((stage, f, m)))
    for i, name in enumerate(("Refine", "DICOM angles")):
        part = monitor.part(i, 2, f"from {name}")
        for f in (0.0, 0.5, 1.0, 1.5):
            part.step("tto", f, "iteration")
    assert [f for _, f, _ in seen] == [0.0, 0.25, 0.5, 0.5, 0.5, 0.75, 1.0, 1.0]
    assert seen[4] == ("tto", 0.5, "from DICOM angles: iteration")
    with pytest.raises(RegistrationCancelled, match="tto"):
        Monitor(cancel=lambda: True).part(1, 2, "x").step("tto", 0.1)


def test_console_bar_ends_its_line_when_a_stage_stops():
    """An error during a stage prints on a line of its own, not after the bar."""
    import io

    stream = io.StringIO()
    bar = ConsoleProgress(stream)
    bar("prepare", 0.5, "DSA LAT")
    bar.finish()
    assert stream.getvalue().endswith("DSA LAT".ljust(50) + "\n")
    bar.finish()  # nothing open: nothing written
    assert stream.getvalue().count("\n") == 1
