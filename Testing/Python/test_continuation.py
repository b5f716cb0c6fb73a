"""A TTO result that turned far from its start runs on from where it ended (``continuation.py``)."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import _prepared

from geopose.geometry import invert
from geopose.geometry.poses import pose_from_params
from geopose.options import Objective
from geopose.register import TTOSchedule, test_time_optimise as run_tto
from geopose.register.biplane import nominal_poses
from geopose.register.continuation import CONTINUED_START, continued, turn_deg
from geopose.register.objective import pair_objective
from geopose.register.opacified import selection_judge
from geopose.register.tournament import Tournament
from geopose.register.tto import tto_views


def _turned(X: np.ndarray, deg: float, axis=(0.3, 0.2, 0.93)) -> np.ndarray:
    """``X`` ``(4, 4)`` with its rotation turned ``deg`` about ``axis`` (its translation kept)."""
    out = X.copy()
    axis = np.asarray(axis) / np.linalg.norm(axis)
    out[:3, :3] = pose_from_params(np.radians(deg) * axis, np.zeros(3), rotation="axis_angle")[:3, :3] @ X[:3, :3]
    return out


def test_the_turn_between_two_poses_is_their_rotation_alone():
    X = np.eye(4)
    X[:3, 3] = [10.0, -4.0, 7.0]
    assert turn_deg(_turned(X, 9.0), X) == pytest.approx(9.0) == turn_deg(X, _turned(X, 9.0))
    moved = X.copy()
    moved[:3, 3] += 50.0
    assert turn_deg(moved, X) == pytest.approx(0.0, abs=1e-6)


def test_a_result_that_turned_far_runs_on_and_the_lowest_objective_of_one_judge_wins(unilateral_case, monkeypatch):
    """A short TTO started 12 deg off the truth ends on the way. A result that turned at most CONTINUE_TURN_DEG from
    its start is left as it is; one that turned more runs on: the continued run ends nearer the truth, and it and the
    first run are judged by the vessels the continued run read, the lowest chosen."""
    from geopose.register import continuation

    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    X = truth.poses["pa"] @ invert(rig["pa"])
    start = _turned(X, 12.0)
    first = run_tto(renderer, tto_views(prep.views, {k: start @ A for k, A in rig.items()}), TTOSchedule(6), rig=rig)
    tournament = Tournament({"start": first}, {"start": pair_objective(selection_judge(renderer, first.vessel_selection),
                                                                       first.poses, prep.views)}, "start", first.vessel_selection)
    turned = turn_deg(first.patient_pose, start)
    assert turned > 1.0
    monkeypatch.setattr(continuation, "CONTINUE_TURN_DEG", turned + 0.5)
    assert continued(renderer, renderer, prep.views, tournament, rig, TTOSchedule(12), Objective()) is tournament
    monkeypatch.setattr(continuation, "CONTINUE_TURN_DEG", turned - 0.5)
    out = continued(renderer, renderer, prep.views, tournament, rig, TTOSchedule(12), Objective())
    assert set(out.runs) == {"start", CONTINUED_START} and set(out.objectives) == {"start", CONTINUED_START}
    assert out.chosen == min(out.objectives, key=out.objectives.get)
    judge = selection_judge(renderer, out.vessel_selection)
    for name, value in out.objectives.items():
        assert value == pytest.approx(pair_objective(judge, out.runs[name].poses, prep.views))
    assert turn_deg(out.runs[CONTINUED_START].patient_pose, X) < turn_deg(first.patient_pose, X)
