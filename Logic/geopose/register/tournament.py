"""The test-time optimisation of one patient pose from several starts, one result kept (ours).

The DICOM angles' start, the best other distinct candidate starts by their objective (``starts.py``;
``options.TTOSchedule.starts`` in all) and the networks' estimate run the TTO's coarse steps. The vessels the
runs show opacified are read at the networks' estimate before any step, and the runs that start near it compare
those alone (``opacified.py``; read after the coarse steps at the pose of the start of lowest loss when too few
pass there); the DICOM angles' run and the best other after the coarse steps (``options.TTOSchedule.finalists``
in all) are the finalists. Judged there by one objective (the ranking too), a finalist
more than ``TTOSchedule.stop_behind`` behind the leader stops (a gap closed by at most 0.1 in the
remaining steps on validation phantoms); the others run to the end and are compared by that objective
(``objective.py``; the opacified vessels alone, when they were read): the lowest wins, the DICOM
angles' within :data:`OBJECTIVE_TIE` of it, so the result is never worse, by the objective, than the
acquisition's own geometry optimised alike (or, stopped, than where it stood after the coarse steps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..dsa import PreparedDSA
from ..render.renderer import Renderer, TorchRenderer
from .biplane import view_poses
from ..options import Objective, TTOSchedule
from .objective import pair_objective
from .opacified import VesselSelection, selection_judge
from .progress import Monitor
from .starts import DICOM_START, Starts, same_pose
from .tto import TTOImages, TTOResult, TTORun, TTOView, restrict_to_opacified, tto_views

__all__ = ["OBJECTIVE_TIE", "Tournament", "chosen_result", "optimise_from_starts", "run_tournament", "tried_starts"]

#: Objective difference (summed over both views) within which two TTO results tie; on a tie the
#: DICOM angles' result is kept. Finalists' objectives on the 40 benchmark phantoms differ by at
#: least 1.5e-3; a learned start that wins by 1e-5 is noise, and the acquisition's own geometry
#: is the safer of two equal answers (`git show 3967f60:docs/benchmark/bench.md`, its reading).
OBJECTIVE_TIE = 1e-3


def chosen_result(objectives: Mapping[str, float]) -> str:
    """The start whose TTO result is kept: the lowest final objective, the DICOM angles' on a tie
    (:data:`OBJECTIVE_TIE`)."""
    return min(objectives, key=lambda k: objectives[k] - (OBJECTIVE_TIE if k == DICOM_START else 0.0))


def optimise_from_starts(
    renderer: TorchRenderer,
    views: list[TTOView],
    starts: Mapping[str, np.ndarray],
    rig: Mapping[str, np.ndarray],
    schedule: TTOSchedule = TTOSchedule(),
    *,
    keep: Sequence[str] = (),
    objective: Objective = Objective(),
    read_at: tuple[str, np.ndarray] | None = None,
    monitor: Monitor | None = None,
) -> dict[str, TTOResult]:
    """One patient pose optimised from several starts ``{name: X}`` ``(4, 4)``: with ``objective.read_opacified``
    the opacified vessels are read (:func:`.tto.restrict_to_opacified`) at ``read_at`` (a name and a patient pose
    ``(4, 4)``: the networks' estimate) before any step, else (None, too few vessels passed there, or no start lies
    near it) after the coarse steps at the pose of the start of lowest loss; every start runs through the coarse steps (to its first
    full-size evaluation, after the first common-axis search); then the starts named in ``keep`` and the best
    others by the loss there (``schedule.finalists`` in all) run to the end, but for those more than
    ``schedule.stop_behind`` behind the best of them by one objective (:func:`_behind`). Returns every run by name; a
    run stopped after the coarse steps has ``stopped_at`` set (and ``behind``, when it was a finalist). ``views`` give the targets (their poses only choose
    the CTA level and whether a view has a vessel term)."""
    monitor = monitor or Monitor()
    names = list(starts)
    unknown = [k for k in keep if k not in starts]
    if not names or unknown:
        raise ValueError(f"need at least one start, and keep must name given starts (unknown: {unknown})")
    images = TTOImages(renderer, views, objective)
    runs = {name: TTORun(images, view_poses(X, rig), schedule, rig, False, renderer.device) for name, X in starts.items()}
    first = next(iter(runs.values()))
    read = bool(objective.read_opacified and read_at) and restrict_to_opacified(runs, starts, read_at, rig, 0)
    n_final = max(schedule.finalists, len(keep))
    ranking: dict[str, float] = {}
    behind: dict[str, float] = {}
    finalists, offset, parts = names, 0, len(names)
    if first.coarse > 0:  # every start through its first full-size evaluation (after the coarse steps and the first search)
        offset = len(names)
        parts = offset + min(n_final, len(names))
        for i, name in enumerate(names):
            runs[name].advance(first.coarse + 1, monitor.part(i, parts, f"from {name}"))
        there = {name: runs[name].trace[first.coarse]["loss"] for name in names}
        if len(names) > n_final:
            # ranked by one objective: a run near the estimate renders the opacified vessels alone, a far one all
            ranking = _judged(runs, names, images) if read else there
            ranked = sorted((k for k in names if k not in keep), key=ranking.get)
            finalists = list(keep) + ranked[:n_final - len(keep)]
        if objective.read_opacified and not read:
            leader = min(there, key=there.get)
            restrict_to_opacified({k: runs[k] for k in finalists}, {k: runs[k].patient_at(first.coarse) for k in finalists},
                                  (leader, runs[leader].patient_at(first.coarse)), rig, first.coarse)
        behind = _behind(runs, finalists, images)
        finalists = [k for k in finalists if behind[k] <= schedule.stop_behind or schedule.stop_behind <= 0]
    width = (parts - offset) / max(len(finalists), 1)  # the finalists left share what all were given
    for j, name in enumerate(finalists):
        runs[name].advance(first.n + 1, monitor.part(offset + j * width, parts, f"from {name}", width))
    out = {name: run.finish(stopped_at=None if name in finalists else run.it, ranking_loss=ranking.get(name),
                            behind=behind.get(name) if name not in finalists else None)
           for name, run in runs.items()}
    monitor.step("tto", 1.0, "done")
    return out


def _judged(runs: Mapping[str, TTORun], names: Sequence[str], images: TTOImages) -> dict[str, float]:
    """Per run, the best objective of its full-size poses so far judged by one objective: the images of a run that
    holds the opacified vessels (else ``images``), as the finalists are judged at the end."""
    judge = next((runs[k].images for k in names if runs[k].vessel_selection), images)
    return {k: runs[k].best_loss_by(judge) for k in names}


def _behind(runs: Mapping[str, TTORun], finalists: Sequence[str], images: TTOImages) -> dict[str, float]:
    """Per finalist, how far its best full-size pose so far lies behind the best of them (:func:`_judged`)."""
    if len(finalists) < 2:
        return {k: 0.0 for k in finalists}
    judged = _judged(runs, finalists, images)
    lead = min(judged.values())
    return {k: v - lead for k, v in judged.items()}


@dataclass(frozen=True)
class Tournament:
    """Every start's TTO run (``runs``; those not among the finalists stopped after the coarse steps), the
    finalists' final objective (``objectives``, by the opacified vessels alone when ``vessel_selection``
    was read) and the start whose result is kept (``chosen``)."""

    runs: Mapping[str, TTOResult]
    objectives: Mapping[str, float]
    chosen: str
    vessel_selection: VesselSelection | None

    @property
    def result(self) -> TTOResult:
        return self.runs[self.chosen]


def tried_starts(starts: Starts, count: int, estimate: str | None = None) -> dict[str, np.ndarray]:
    """The distinct starts (``Starts.distinct``) the TTO runs: the DICOM angles', the ``count - 1`` others of lowest
    objective and the networks' ``estimate`` (a start's name; ignored when not a candidate) when not among them, in
    their given order. The opacified vessels are read at the estimate; on a computed vessel mask a raw Init start can
    score better and lie degrees further off (5022, 5033, 5041 of the session-38 benchmark; validation 6077, 6088)."""
    distinct = starts.distinct()
    others = sorted((k for k in distinct if k != DICOM_START), key=starts.objectives.get)[:max(count - 1, 0)]
    if estimate in starts.poses:  # under the name of the first start at its pose
        others.append(next(k for k, X in distinct.items() if same_pose(X, starts.poses[estimate])))
    return {k: X for k, X in distinct.items() if k == DICOM_START or k in others}


def run_tournament(renderer: Renderer, tto_renderer: TorchRenderer, views: Mapping[str, PreparedDSA], starts: Starts,
                   rig: Mapping[str, np.ndarray], schedule: TTOSchedule, objective: Objective, monitor: Monitor, *,
                   estimate: tuple[str, np.ndarray] | None = None) -> Tournament:
    """The TTO (``schedule``, ``objective``) from the starts :func:`tried_starts` picks (``schedule.starts`` and the
    networks' ``estimate``, a name and a patient pose, where the opacified vessels are read), the DICOM angles' among
    the finalists; the finalists judged by the objective rendered through ``renderer`` (the engine's own kernel)."""
    tried = tried_starts(starts, schedule.starts, None if estimate is None else estimate[0])
    runs = optimise_from_starts(tto_renderer, tto_views(views, view_poses(np.eye(4), rig)), tried, rig, schedule,
                                keep=(DICOM_START,), objective=objective, read_at=estimate, monitor=monitor)
    selection = next((r.vessel_selection for r in runs.values() if r.vessel_selection), None)
    judge = selection_judge(renderer, selection)
    objectives = {name: pair_objective(judge, run.poses, views, objective) for name, run in runs.items()
                  if run.stopped_at is None}
    return Tournament(runs, objectives, chosen_result(objectives), selection)
