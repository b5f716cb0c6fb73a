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
    objective and the networks' estimate, a repeated pose once, in the given order."""
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
    # the networks' estimate runs whatever its objective; one at a repeated pose runs under the first name of that pose
    assert list(tried_starts(starts, 2, "Init PA")) == [DICOM_START, "Init PA", "Refine + search"]
    assert list(tried_starts(starts, 2, "Refine + search")) == [DICOM_START, "Refine + search"]
    assert list(tried_starts(starts, 1, "Init LAT")) == [DICOM_START, "Init"]
    assert list(tried_starts(Starts({DICOM_START: moved(0)}, {DICOM_START: -0.1}), 2, "Refine + search")) == [DICOM_START]


def test_the_opacified_vessels_are_read_at_the_networks_estimate_before_any_step(unilateral_case):
    """With ``read_at`` (the networks' estimate) the tournament reads the opacified vessels there before its first
    step: the run that starts there holds that selection (iteration 0, the estimate's name), a start 20 mm off keeps
    every vessel; read 80 mm off (too few pass), or where no start lies near, the selection is read after the coarse
    steps instead, at the start of lowest loss."""
    from register_helpers import _prepared

    from geopose.geometry import invert
    from geopose.register import TTOSchedule
    from geopose.register.biplane import nominal_poses
    from geopose.register.tournament import optimise_from_starts
    from geopose.register.tto import tto_views

    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    X = truth.poses["pa"] @ invert(rig["pa"])
    off = X.copy()
    off[:3, 3] += [12.0, 0.0, 16.0]
    schedule = TTOSchedule(iterations=5)
    views = tto_views(prep.views, truth.poses)
    starts = {"estimate": X, "DICOM angles": off}
    out = optimise_from_starts(renderer, views, starts, rig, schedule, keep=("DICOM angles",), read_at=("estimate", X))
    selection = out["estimate"].vessel_selection
    assert selection is not None and selection.applied and selection.iteration == 0 and selection.start == "estimate"
    assert out["DICOM angles"].vessel_selection is None
    far = X.copy()
    far[:3, 3] += [60.0, 0.0, 60.0]
    late = optimise_from_starts(renderer, views, starts, rig, schedule, keep=("DICOM angles",), read_at=("far", far))
    read = next(r.vessel_selection for r in late.values() if r.vessel_selection is not None)
    assert read.iteration == schedule.coarse_steps() and read.start in starts
    alone = optimise_from_starts(renderer, views, {"DICOM angles": off}, rig, schedule, keep=("DICOM angles",),
                                 read_at=("estimate", X))
    assert alone["DICOM angles"].vessel_selection.iteration == schedule.coarse_steps()


def test_a_finalist_far_behind_after_the_coarse_steps_stops_there(unilateral_case):
    """The DICOM angles' run 20 mm off the networks' estimate (at the truth) is, after the coarse steps and judged by
    the objective the finalists are judged by, more than ``stop_behind`` behind: it stops there with its gap
    recorded and the estimate's run goes on to the end; with ``stop_behind`` 0 both run to the end."""
    from register_helpers import _prepared

    from geopose.geometry import invert
    from geopose.register import TTOSchedule
    from geopose.register.biplane import nominal_poses
    from geopose.register.tournament import optimise_from_starts
    from geopose.register.tto import tto_views

    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    X = truth.poses["pa"] @ invert(rig["pa"])
    off = X.copy()
    off[:3, 3] += [12.0, 0.0, 16.0]
    views = tto_views(prep.views, truth.poses)
    starts = {"estimate": X, "DICOM angles": off}
    schedule = TTOSchedule(iterations=5)
    out = optimise_from_starts(renderer, views, starts, rig, schedule, keep=("DICOM angles",), read_at=("estimate", X))
    dicom, estimate = out["DICOM angles"], out["estimate"]
    assert dicom.stopped_at == schedule.coarse_steps() + 1 and dicom.behind > schedule.stop_behind
    assert estimate.stopped_at is None and estimate.behind is None and len(estimate.trace) == schedule.iterations + 1
    both = optimise_from_starts(renderer, views, starts, rig, TTOSchedule(iterations=5, stop_behind=0.0), keep=("DICOM angles",),
                                read_at=("estimate", X))
    assert all(r.stopped_at is None and len(r.trace) == 6 for r in both.values())


def test_starts_are_ranked_after_the_coarse_steps_by_one_objective(unilateral_case):
    """With more starts than finalists, the runs are ranked after the coarse steps by the objective on the opacified
    vessels (read at the networks' estimate), also a run far from it that renders every vessel: its ranking loss is
    not its own loss there, and the estimate's run (at the truth) ranks first and goes on."""
    from register_helpers import _prepared

    from geopose.geometry import invert
    from geopose.register import TTOSchedule
    from geopose.register.biplane import nominal_poses
    from geopose.register.tournament import optimise_from_starts
    from geopose.register.tto import tto_views

    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    X = truth.poses["pa"] @ invert(rig["pa"])
    off, far = X.copy(), X.copy()
    off[:3, 3] += [12.0, 0.0, 16.0]
    far[:3, 3] += [-20.0, 10.0, 0.0]
    schedule = TTOSchedule(iterations=5, stop_behind=0.0)
    out = optimise_from_starts(renderer, tto_views(prep.views, truth.poses), {"estimate": X, "DICOM angles": off, "far": far},
                               rig, schedule, keep=("DICOM angles",), read_at=("estimate", X))
    coarse = schedule.coarse_steps()
    assert out["far"].vessel_selection is None and out["estimate"].vessel_selection is not None
    assert abs(out["far"].ranking_loss - out["far"].trace[coarse]["loss"]) > 1e-3
    assert out["estimate"].ranking_loss < out["far"].ranking_loss
    assert out["estimate"].stopped_at is None and out["far"].stopped_at == coarse + 1
