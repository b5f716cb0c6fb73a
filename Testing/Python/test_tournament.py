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


def test_the_tto_tries_the_dicom_angles_and_the_best_other_starts():
    """``tried_starts`` keeps the DICOM angles' start whatever its objective, then the others of lowest
    objective, a repeated pose once, in the given order."""
    import numpy as np

    from geopose.register.starts import DICOM_START, Starts
    from geopose.register.tournament import tried_starts

    def moved(mm: float) -> np.ndarray:
        X = np.eye(4)
        X[0, 3] = mm
        return X

    poses = {DICOM_START: moved(0), "Init": moved(5), "Init PA": moved(9), "Init LAT": moved(5), "Refine + search": moved(2)}
    objectives = {DICOM_START: -0.1, "Init": -0.4, "Init PA": -0.3, "Init LAT": -0.9, "Refine + search": -0.5}
    starts = Starts(poses, objectives)
    assert list(tried_starts(starts, 2)) == [DICOM_START, "Refine + search"]  # Init LAT repeats Init's pose
    assert list(tried_starts(starts, 3)) == [DICOM_START, "Init", "Refine + search"]
    assert list(tried_starts(starts, 1)) == [DICOM_START]
    assert list(tried_starts(starts, 100)) == list(starts.distinct()) == [DICOM_START, "Init", "Init PA", "Refine + search"]
