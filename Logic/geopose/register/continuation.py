"""A TTO result that turned far from its start, optimised once more from where it ended (ours).

The TTO's rotation steps are small (``TTOSchedule.rotation_lr_rad``, annealed), so a start 20-25 deg off the truth
ends its 25 steps on the way, not at the optimum: on benchmark phantoms 5022 and 5030 the estimate lay 21 and 26 deg
off, the tournament's result (the run from the estimate) turned 8 and 15 deg and still lay 14 and 9 deg off. Where the
result turned more than :data:`CONTINUE_TURN_DEG` from its run's start, one more TTO run starts at the result, reading
the opacified vessels there (``opacified.py``), and every finalist and the new run are judged by that one objective
(``objective.py``, both views summed): the lowest wins (``tournament.chosen_result``, the DICOM angles' within the tie), so the result is
still never worse, by the objective, than the acquisition's own geometry optimised alike.
"""

from __future__ import annotations

from typing import Final, Mapping

import numpy as np

from ..dsa import PreparedDSA
from ..geometry.poses import rotation_angle_rad
from ..options import Objective, TTOSchedule
from ..render.renderer import Renderer, TorchRenderer
from .objective import pair_objective
from .opacified import selection_judge
from .progress import Monitor
from .tournament import Tournament, chosen_result
from .tto import test_time_optimise, traced_patient_pose, tto_views

__all__ = ["CONTINUE_TURN_DEG", "CONTINUED_START", "turn_deg", "continued"]

#: A tournament result turned more than this (deg) from its run's start runs on (see the module's account). Set on
#: validation phantoms 6010-6030, where the result was always the run from the networks' estimate
#: (experiments/tto_schedule/continuation.md).
CONTINUE_TURN_DEG: Final = 6.0
#: The name the continued run takes among the TTO's runs (the record's ``tto_start`` when it wins).
CONTINUED_START: Final = "continued"


def turn_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The rotation (deg) between the rotations of two poses ``(4, 4)``; their translations play no part."""
    return float(np.degrees(rotation_angle_rad(np.asarray(a, dtype=np.float64)[:3, :3] @ np.asarray(b, dtype=np.float64)[:3, :3].T)))


def continued(renderer: Renderer, tto_renderer: TorchRenderer, views: Mapping[str, PreparedDSA], tournament: Tournament,
              rig: Mapping[str, np.ndarray], schedule: TTOSchedule, objective: Objective,
              monitor: Monitor | None = None) -> Tournament:
    """``tournament`` as it is when its result (a patient pose) turned at most :data:`CONTINUE_TURN_DEG` from its run's
    start; else with one more run (``schedule``, ``objective``) from the result under :data:`CONTINUED_START`, its
    finalists and that run judged by the vessels the new run read (through ``renderer``, the engine's own kernel) and
    the lowest chosen."""
    result = tournament.result
    turned = turn_deg(result.patient_pose, traced_patient_pose(result.trace, rig, 0))
    if turned <= CONTINUE_TURN_DEG:
        return tournament
    monitor = monitor or Monitor()
    monitor.step("tto", 0.0, f"the result turned {turned:.1f} deg from its start: optimising on from it")
    run = test_time_optimise(tto_renderer, tto_views(views, result.poses), schedule, objective=objective, rig=rig,
                             monitor=monitor.part(0, 1, CONTINUED_START))
    selection = run.vessel_selection if run.vessel_selection is not None else tournament.vessel_selection
    judge = selection_judge(renderer, selection)
    runs = {**tournament.runs, CONTINUED_START: run}
    objectives = {name: pair_objective(judge, r.poses, views, objective) for name, r in runs.items() if r.stopped_at is None}
    return Tournament(runs, objectives, chosen_result(objectives), selection)
