"""The TTO tournament's choice of result (``tournament.py``)."""

from __future__ import annotations


def test_the_dicom_angles_result_is_kept_on_a_tie():
    """The lowest final objective wins; within OBJECTIVE_TIE of it, the DICOM angles' result does."""
    from geopose.register.starts import DICOM_START
    from geopose.register.tournament import OBJECTIVE_TIE, chosen_result

    assert chosen_result({DICOM_START: -0.46458, "Init PA": -0.46460}) == DICOM_START
    assert chosen_result({DICOM_START: -0.40, "Init": -0.40 - 2 * OBJECTIVE_TIE}) == "Init"
    assert chosen_result({"Init": -0.30, DICOM_START: -0.50}) == DICOM_START
    assert chosen_result({"Refine": -0.7}) == "Refine"
