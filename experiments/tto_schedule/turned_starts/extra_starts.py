"""The default path (``default_path_rows.py``) with starts derived from the networks' estimate along the common-axis
valley (``axis_search.valley_turn``), patched into the TTO tournament. The rows in this folder ran at 60a693c (session
43); the product has no such starts (tried in d832a0f and reverted).

* ``replace`` / ``extra``: a single-pose scan every STEP deg within +-16 (each turn scored by the objective with the
  vessels read opacified there); the best turn replaces the estimate, or joins the starts (not kept);
* ``blind`` / ``keep-estimate``: the estimate turned -STEP and +STEP deg join the starts; ``keep-estimate`` also keeps
  the estimate's own run among the finalists.

Usage, from the repository root:

    .venv/bin/python experiments/tto_schedule/turned_starts/extra_starts.py 6030,6031 OUT.jsonl keep-estimate 8
"""
import sys
import time
from dataclasses import replace

import numpy as np

import geopose  # noqa: F401  (before torch)
from default_path_rows import run_seeds
from geopose.register import pipeline, tournament
from geopose.register.axis_search import valley_turn
from geopose.register.biplane import moved_by, view_poses
from geopose.register.objective import pair_objective
from geopose.register.opacified import read_opacified, selection_judge
from geopose.register.starts import Starts

MODE, STEP = sys.argv[3], float(sys.argv[4])
INFO: dict = {}
ADDED = "added"  # the prefix of the starts this script adds


def with_extra_starts(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, *, estimate=None):
    """``tournament.run_tournament`` with the variant's starts."""
    t0 = time.perf_counter()
    name, X = estimate
    volume = renderer.volume
    kji = volume.mask_voxels("vessels")
    if len(kji):
        points = volume.centred_points(kji[:: max(1, len(kji) // 2000)])
        rotation, shift = valley_turn(X, rig, {k: views[k].tto_detector for k in rig}, points)
        turned = lambda deg: moved_by(X, rotation * np.radians(deg), shift * np.radians(deg))  # noqa: E731
        poses, objectives = dict(starts.poses), dict(starts.objectives)
        if MODE in ("replace", "extra"):
            turns = np.arange(-16, 16.01, STEP)
            read = [(k, views[k].tto_vessels, views[k].tto_detector) for k in rig]
            scores = [pair_objective(selection_judge(renderer, read_opacified(volume, turned(t), rig, read)),
                                     view_poses(turned(t), rig), views, objective) for t in turns]
            best = int(np.argmin(scores))
            INFO.update(turn=float(turns[best]), gain=scores[len(turns) // 2] - scores[best])
            added = {} if turns[best] == 0 else {name if MODE == "replace" else f"{ADDED} scan": turned(turns[best])}
        else:
            added = {f"{ADDED} {sign * STEP:+g}": turned(sign * STEP) for sign in (-1.0, 1.0)}
        for key, Y in added.items():
            poses[key], objectives[key] = Y, pair_objective(renderer, view_poses(Y, rig), views, objective)
        starts = Starts(poses, objectives)
        X = poses[name]
    INFO["scan_s"] = time.perf_counter() - t0
    return run_tournament(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, estimate=(name, X))


def tried_with_added(starts, count, estimate=None):
    """``tournament.tried_starts``, the added starts always tried."""
    return tried_starts(starts, count, estimate) | {k: X for k, X in starts.poses.items() if k.startswith(ADDED)}


def optimise_keeping_estimate(renderer, views, starts, rig, schedule, *, keep=(), **kwargs):
    """``tournament.optimise_from_starts`` with the estimate's run among the finalists (``keep-estimate``)."""
    if MODE == "keep-estimate" and kwargs.get("read_at") and kwargs["read_at"][0] in starts:
        keep = tuple(keep) + (kwargs["read_at"][0],)
        schedule = replace(schedule, finalists=max(schedule.finalists, len(keep) + 1))
    return optimise_from_starts(renderer, views, starts, rig, schedule, keep=keep, **kwargs)


run_tournament, tried_starts, optimise_from_starts = pipeline.run_tournament, tournament.tried_starts, tournament.optimise_from_starts
pipeline.run_tournament, tournament.tried_starts = with_extra_starts, tried_with_added
tournament.optimise_from_starts = optimise_keeping_estimate
run_seeds([int(s) for s in sys.argv[1].split(",")], sys.argv[2], MODE, INFO)
