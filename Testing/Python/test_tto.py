"""The test-time optimisation (``tto.py``) on the phantom's simulated DSA pair: it reaches the truth on
a consistent target, its schedule (coarse to fine, OneCycle rates), the common-axis search run
through it, its drift from the truth, and the opacified vessels it reads at its start."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import _perturb, _prepared

from geopose import contract as C
from geopose.errors import InputError
from geopose.geometry import invert
from geopose.geometry.poses import matrix_to_axis_angle
from geopose.register import PAPER_SCHEDULE, TTOSchedule, TTOView, test_time_optimise as run_tto
from geopose.register.biplane import common_axis, nominal_poses, turned_about
from geopose.register.evaluate import evaluate_pose
from geopose.register.objective import PAPER_OBJECTIVE, Objective, clip_like_target
from geopose.register.tto import tto_views


#: mPCD (mm at the detector) the TTO must reach from a 5 deg / 10 mm perturbation when the
#: target is consistent with the objective (the DRR at the true pose): the issue's bar.
TTO_CONSISTENT_MPCD_MM = 1.0


def test_tto_reaches_one_mm_on_a_consistent_target(phantom_case):
    """TTO from the true pose perturbed by ~4.7 deg / 9.8 mm, against targets rendered
    at the true pose (so the objective's optimum is the truth), reaches <= 1 mm mPCD."""
    truth, runs, prep, renderer = _prepared(phantom_case)
    views = []
    for key in ("pa", "lat"):
        p = prep.views[key]
        total, vessels = renderer.render(truth.poses[key], p.tto_detector, ("total", "vessels"))
        target = clip_like_target(total, p.tto_mask > 0, C.MAP_CLIP_PERCENTILES)
        views.append(TTOView(key, target, p.tto_mask, vessels, p.tto_detector, _perturb(truth.poses[key])))
    # The silhouette and vessel terms (the Dice term compares the CTA's cranium with the DSA's head mask).
    result = run_tto(renderer, views, TTOSchedule(), objective=Objective(ncc_weight=1.0),
                     rig=nominal_poses(runs))
    for view in views:
        run, true_pose = runs[view.name], truth.poses[view.name]
        before = evaluate_pose(view.pose, true_pose, run.detector, run.angles.sod_mm, truth.carotid_points_mm)
        after = evaluate_pose(result.poses[view.name], true_pose, run.detector, run.angles.sod_mm, truth.carotid_points_mm)
        assert before["mpcd_mm"] > 5.0, before
        assert after["mpcd_mm"] <= TTO_CONSISTENT_MPCD_MM, (view.name, before["mpcd_mm"], after["mpcd_mm"])
        assert after["rotation_error_deg"] < 0.5
    # The trace says which steps ran at half size (coarse to fine) and keeps the best full-size pose.
    sizes = [e["size"] for e in result.trace]
    assert sizes[: TTOSchedule().coarse_steps()] == ["half"] * TTOSchedule().coarse_steps() and sizes[-1] == "full"
    # The OneCycle peaks at the schedule's rates (rad, mm) and anneals to its final share of them, not to 0.
    rates = np.array([e["learning_rates"] for e in result.trace[:-1]])
    peak = np.array([TTOSchedule().rotation_lr_rad, TTOSchedule().translation_lr_mm])
    assert result.trace[-1]["learning_rates"] is None
    np.testing.assert_allclose(rates.max(axis=0), peak, rtol=0.05)
    np.testing.assert_allclose(rates[-1], TTOSchedule.final_lr_fraction * peak, rtol=1e-6)
    with pytest.raises(InputError, match="tto.final_lr_fraction = 0.0 is outside the plausible range"):
        TTOSchedule(final_lr_fraction=0.0)


def test_common_axis_search_turns_the_patient_back(phantom_case):
    """On the simulated DSA pair, the patient turned 8 deg about the axis both image planes
    contain (out of plane in both views): the rotation prior holds most of that turn without the
    common-axis search (3 deg are left), and the search (two parabola steps of the default
    schedule) brings it back to <= 2 deg."""
    truth, runs, prep, renderer = _prepared(phantom_case)
    rig = nominal_poses(runs)
    X_true = truth.poses["pa"] @ invert(rig["pa"])
    X = turned_about(X_true, common_axis({k: X_true for k in rig}, rig), np.radians(8.0))
    views = tto_views(prep.views, {k: X @ A for k, A in rig.items()})

    def turn_deg(result) -> float:
        return float(np.degrees(np.linalg.norm(matrix_to_axis_angle(result.patient_pose[:3, :3] @ X_true[:3, :3].T))))

    held = run_tto(renderer, views, TTOSchedule(axis_search_at=()), rig=rig)
    searched = run_tto(renderer, views, TTOSchedule(), rig=rig)
    assert held.axis_searches == () and turn_deg(held) > 2.5, turn_deg(held)  # measured: 3.0 deg
    assert [s["iteration"] for s in searched.axis_searches] == [15, 20]
    # turned back, not further (measured -1.8 deg on the realistic phantom world, below -2 on the cleaner one)
    assert searched.axis_searches[0]["chosen_deg"] < -1.5, searched.axis_searches
    assert turn_deg(searched) <= 2.0, (turn_deg(searched), searched.axis_searches)  # measured: 1.5 deg


#: Drift (mPCD, mm at the detector) a TTO started at the truth may reach on the phantom's simulated
#: MAPs with the default objective: the issue's target is 0.5 mm mean over the benchmark; the bench
#: measures it (row "truth + 25 TTO (drift)"), this bounds one case per view.
TTO_DRIFT_BOUND_MM = 1.5


def test_tto_started_at_the_truth_stays_near_it(phantom_case):
    """The default objective's optimum on a simulated DSA pair lies near the truth: one patient pose,
    25 steps from the true pose, ends within TTO_DRIFT_BOUND_MM per view; the paper's objective, per
    view, drifts further on the same case."""
    truth, runs, prep, renderer = _prepared(phantom_case)

    def drift(poses: dict) -> dict[str, float]:
        return {k: evaluate_pose(poses[k], truth.poses[k], runs[k].detector, runs[k].angles.sod_mm,
                                 truth.carotid_points_mm)["mpcd_mm"] for k in runs}

    ours = drift(run_tto(renderer, tto_views(prep.views, truth.poses), rig=nominal_poses(runs)).poses)
    published = run_tto(renderer, tto_views(prep.views, truth.poses), PAPER_SCHEDULE, objective=PAPER_OBJECTIVE)
    paper = drift(published.poses)
    # The published schedule keeps PyTorch's OneCycle: it anneals to 1 / (25 x 1e4) of its peak.
    assert published.trace[-2]["learning_rates"] == [pytest.approx(PAPER_SCHEDULE.paper_lr * PAPER_SCHEDULE.final_lr_fraction)]
    assert max(ours.values()) <= TTO_DRIFT_BOUND_MM, ours
    assert sum(ours.values()) < sum(paper.values()), (ours, paper)


def test_tto_from_the_truth_stays_with_the_opacified_vessels(unilateral_case):
    """The arteries a selective injection leaves empty pull the TTO off the truth when the vessel term
    compares all of the CTA's; the TTO reads the opacified ones at its start, before any step, keeps
    those, and then ends nearer the truth (experiments/tto_objective/objective.md). Started 80 mm off,
    where too few vessels land on the runs' contrast, it reads them after its coarse steps instead."""
    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)

    def drift(result) -> float:
        return max(evaluate_pose(result.poses[k], truth.poses[k], runs[k].detector, runs[k].angles.sod_mm,
                                 truth.carotid_points_mm)["mpcd_mm"] for k in runs)

    read = run_tto(renderer, tto_views(prep.views, truth.poses), rig=rig)
    every = run_tto(renderer, tto_views(prep.views, truth.poses), rig=rig, objective=Objective(read_opacified=False))
    selection = read.vessel_selection
    assert every.vessel_selection is None
    assert selection.applied and selection.iteration == 0 and selection.start == "start"
    np.testing.assert_allclose(selection.patient_pose, truth.poses["pa"] @ invert(rig["pa"]), atol=1e-9)
    assert 0.05 < selection.kept_fraction < 0.5
    assert drift(read) <= 0.5 and drift(read) < drift(every) - 0.3, (drift(read), drift(every))
    far = truth.poses["pa"] @ invert(rig["pa"])
    far[:3, 3] += [60.0, 0.0, 60.0]
    late = run_tto(renderer, tto_views(prep.views, {k: far @ rig[k] for k in rig}), TTOSchedule(iterations=5), rig=rig)
    assert late.vessel_selection is None or late.vessel_selection.iteration == TTOSchedule(iterations=5).coarse_steps(), \
        late.vessel_selection.summary()


@pytest.mark.parametrize("total_steps, pct_start", [(25, 0.3), (12, 0.3), (1, 0.3), (7, 0.05)])
def test_one_cycle_nadam_steps_as_torch_optim(total_steps, pct_start):
    """The TTO's optimiser makes torch.optim's NAdam + OneCycleLR (cos, no momentum cycling) moves, bit for bit,
    two groups of float64 parameters on a non-quadratic loss; its learning rates are the scheduler's."""
    import torch

    from geopose.register.nadam import OneCycleNAdam

    rng = np.random.default_rng(total_steps)
    start = [torch.as_tensor(rng.normal(size=3)), torch.as_tensor(rng.normal(size=(1, 4)))]
    target = torch.as_tensor(rng.normal(size=7))
    ours_params = [t.clone().requires_grad_(True) for t in start]
    ref_params = [t.clone().requires_grad_(True) for t in start]
    groups = lambda ps: [{"params": [ps[0]], "lr": 0.02}, {"params": [ps[1]], "lr": 4.0}]  # noqa: E731
    kw = dict(total_steps=total_steps, pct_start=pct_start, div_factor=25.0, final_div_factor=1e4)
    ours = OneCycleNAdam(groups(ours_params), **kw)
    ref = torch.optim.NAdam(groups(ref_params), lr=0.02)
    sched = torch.optim.lr_scheduler.OneCycleLR(ref, max_lr=[0.02, 4.0], cycle_momentum=False, **kw)

    def loss(ps):
        x = torch.cat([ps[0], ps[1].reshape(-1)])
        return (torch.sin(x) * target + (x - target) ** 2).sum()

    for _ in range(total_steps):
        assert ours.learning_rates == [g["lr"] for g in ref.param_groups]
        for opt, ps in ((ours, ours_params), (ref, ref_params)):
            opt.zero_grad()
            loss(ps).backward()
            opt.step()
        sched.step()
        for a, b in zip(ours_params, ref_params):
            assert torch.equal(a, b)
    assert not torch.equal(ours_params[1], start[1])
    with pytest.raises(ValueError, match="all were taken"):
        ours.step()


def test_one_cycle_nadam_takes_a_warm_up_of_one_step():
    """Where ``OneCycleLR`` divides by zero (its warm-up ends at step 0: one step, all of it warm-up), the schedule
    starts at its peak and the step is taken."""
    import torch

    from geopose.register.nadam import OneCycleNAdam

    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = OneCycleNAdam([{"params": [w], "lr": 0.02}], total_steps=1, pct_start=1.0, div_factor=25.0, final_div_factor=1e4)
    assert opt.learning_rates == [pytest.approx(0.02)]
    (w - 1.0).square().sum().backward()
    opt.step()
    assert torch.all(w > 0)


def test_a_run_renders_each_seen_pose_once_per_objective(phantom_case):
    """A patient-pose run scores its start when it first compares it (a read at the start changes the objective
    first), and an objective that has scored a full-size pose is not rendered again for it: judging twice renders
    nothing the second time, and another objective renders every pose once, to the same numbers."""
    from geopose.register.progress import Monitor
    from geopose.register.tto import TTOImages, TTORun
    from geopose.render.work import counting

    truth, runs, prep, renderer = _prepared(phantom_case)
    rig = nominal_poses(runs)
    images = TTOImages(renderer, tto_views(prep.views, truth.poses), Objective())
    with counting() as work:
        run = TTORun(images, {k: _perturb(p) for k, p in truth.poses.items()}, TTOSchedule(iterations=5), rig, False, "cpu")
    assert work.renders == 0 and run.start_pending
    run.advance(run.coarse + 1, Monitor())  # the coarse steps and the first full-size evaluation
    assert [it for _, it, _ in run.seen] == [0, run.coarse] and not run.start_pending and "patient" in run.best
    with counting() as work:
        judged = run.best_loss_by(images)
    assert work.renders == 0
    with counting() as work:
        again = run.best_loss_by(images.rebound(renderer))
    assert work.renders == 2 * len(run.seen) and again == judged


def test_the_step_after_a_common_axis_search_reuses_the_chosen_turn(phantom_case):
    """The common-axis search scores its turns with gradients and hands the chosen one's evaluation to the step that
    follows: one full-size render per view fewer than rendering it again, and the same trace, bit for bit."""
    from geopose.register.progress import Monitor
    from geopose.register.tto import TTOImages, TTORun
    from geopose.render.work import counting

    class RendersAgain(TTORun):
        def _axis_search(self, it, keep):
            return super()._axis_search(it, keep=False)

    truth, runs, prep, renderer = _prepared(phantom_case)
    rig = nominal_poses(runs)
    start = {k: _perturb(p) for k, p in truth.poses.items()}
    schedule = TTOSchedule(iterations=8, axis_search_at=(0.75,))  # the search before step 6, a full-size step
    traces, renders = [], []
    for kind in (TTORun, RendersAgain):
        run = kind(TTOImages(renderer, tto_views(prep.views, truth.poses), Objective()), start, schedule, rig, False, "cpu")
        with counting() as work:
            run.advance(run.n + 1, Monitor())
        assert [s["iteration"] for s in run.axis_searches] == [6] and run.coarse < 6 < run.n
        traces.append([(t["loss"], [t["views"][k]["pose"] for k in sorted(t["views"])]) for t in run.trace])
        renders.append(work.renders)
    assert traces[0] == traces[1]
    assert renders[0] == renders[1] - len(rig)
