"""Test-time optimisation (paper section 2.3.3), in torch: the objective of ``objective.py``
(:func:`.objective.view_terms`, differentiable), summed over views (optionally plus the biplanar
term), minimised through the differentiable renderer.

Two parameterisations:

* one *patient pose* for both views (``rig`` given: the arms' poses ``A_v`` about the
  isocentre, ``T_v = X @ A_v``; ``X`` moves by a rotation about the isocentre (rad) and a
  shift of the isocentre (mm), learning rates in those units; :mod:`.biplane`);
* per view, the paper's: Euler ZYX (rad) and translation / 200 (mm), OneCycle max 1e-2
  (the published independent-views behaviour).

NAdam with a OneCycle schedule (``nadam.py``). Coarse to fine: the first ``coarse_fraction`` of the steps
render at half the image size (a coarser CTA level, a quarter of the rays), the rest at
full size. The result is the pose of best full-size objective seen, the start included
(per view for independent views, jointly for a patient pose; the paper's schedule keeps
each view's best mNCC). A patient pose's vessel term keeps the vessels the runs show opacified
(:func:`restrict_to_opacified`, ``opacified.py``): read before the first step, at the networks' estimate in
the tournament and at its own start in a single run; the common-axis
search (``axis_search.py``) moves it along the valley the objective is flattest in; several
starts run as a tournament (``tournament.py``). Poses in and out are numpy
``(4, 4)`` (centred CTA frame, mm); this is the one stage that needs PyTorch.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping

import numpy as np

from ..geometry.detector import Detector
from ..images import resize_bilinear
from ..render.renderer import TorchRenderer
from .axis_search import best_turn, valley_turn
from .biplane import common_axis, patient_pose, view_poses
from .nadam import OneCycleNAdam
from ..options import Objective, TTOSchedule
from .objective import view_terms
from .opacified import OPACIFIED_NEAR_MM, VesselSelection, read_opacified, vessel_shift_mm
from .progress import Monitor

if TYPE_CHECKING:
    from ..dsa import PreparedDSA

__all__ = ["TTOView", "TTOSchedule", "PAPER_SCHEDULE", "TTOResult", "TTOImages", "TTORun", "test_time_optimise",
           "restrict_to_opacified", "traced_patient_pose", "biplanar_penalty", "tto_views"]

#: The render channels the objective uses: the total density, the cranium and the vessels.
TTO_CHANNELS = ("total", "cranium", "vessels")
#: The published per-view parameterisation's translation scale: the TTO moves translation / 200 (mm).
PAPER_TRANSLATION_SCALE_MM = 200.0
#: Weight of the PA/lateral orthogonality term (``RegistrationOptions.biplanar``, independent views).
BIPLANAR_WEIGHT = 0.1
#: Most points (vessel voxel centres) the common-axis search projects to find its valley.
VALLEY_POINTS = 3000


@dataclass
class TTOView:
    """One view: target ``(h, w)`` (the preprocessed MAP at the acquisition SDD), the DSA
    cranium mask and the MAP's vessel image of the same shape, the acquisition detector
    sampled on ``h x w``, and the start pose ``(4, 4)``."""

    name: str
    target: np.ndarray
    mask: np.ndarray
    vessels: np.ndarray
    detector: Detector
    pose: np.ndarray


def tto_views(views: Mapping[str, "PreparedDSA"], poses: Mapping[str, np.ndarray]) -> list[TTOView]:
    """The preprocessed ``views`` set up for :func:`test_time_optimise`, starting from ``poses``."""
    return [TTOView(k, v.tto_image, v.tto_mask, v.tto_vessels, v.tto_detector, poses[k]) for k, v in views.items()]


#: The paper's schedule, all steps at full size (independent views).
PAPER_SCHEDULE = TTOSchedule(coarse_fraction=0.0, paper=True, axis_search_at=(),
                             final_lr_fraction=1.0 / (TTOSchedule.div_factor * 1e4))


@dataclass(frozen=True)
class TTOResult:
    """Best pose per view, its mNCC and iteration; the patient pose when one was optimised;
    ``trace``: per iteration the loss, the image size, the learning rate of each parameter group that
    step used (rad and mm for a patient pose; None on the last, which only evaluates) and per view
    the mNCC, Dice loss and pose;
    ``axis_searches``: per common-axis search its iteration, turns (deg), losses, choice and direction;
    ``stopped_at``: the iteration a start of :func:`.tournament.optimise_from_starts` stopped at when it
    was not among the finalists (None: it ran to the end); ``ranking_loss``: the full-size loss
    at the first full-size iteration it was ranked by there (None without a ranking);
    ``vessel_selection``: the opacified vessels this run's vessel term kept from then on (None: all);
    ``behind``: for a finalist stopped after the coarse steps, how far its best full-size pose was behind the
    leader's there, judged by one objective (``TTOSchedule.stop_behind``)."""

    poses: dict[str, np.ndarray]
    best_mncc: dict[str, float]
    best_iteration: dict[str, int]
    patient_pose: np.ndarray | None = None
    trace: tuple[dict, ...] = ()
    axis_searches: tuple[dict, ...] = ()
    stopped_at: int | None = None
    ranking_loss: float | None = None
    vessel_selection: VesselSelection | None = None
    behind: float | None = None


def biplanar_penalty(R_pa, R_lat):
    """``|angle(R_lat^T R_pa) - pi/2|`` (rad, torch): PA and lateral arms should be orthogonal."""
    from ..geometry.rigid import rotation_angle_rad

    return (rotation_angle_rad(R_lat.transpose(-1, -2) @ R_pa) - math.pi / 2).abs()


def _half(view: TTOView) -> tuple[np.ndarray, np.ndarray, np.ndarray, Detector]:
    """The view's target, mask, vessel image and detector at half the size (same field of view)."""
    det = view.detector.resized(max(16, view.detector.rows // 2), max(16, view.detector.cols // 2))
    target, vessels = resize_bilinear(np.stack((view.target, view.vessels)).astype(np.float32), det.shape)
    mask = resize_bilinear((view.mask > 0).astype(np.float32)[None], det.shape)[0] > 0.5
    return target, mask, vessels, det


class TTOImages:
    """Each view's target, mask, detector and DRR kernel at full and half size, and the objective."""

    def __init__(self, renderer: TorchRenderer, views: list[TTOView], objective: Objective) -> None:
        self.objective, self.views = objective, views
        self.channels = renderer.channel_index(TTO_CHANNELS)
        self.vessel_term: dict[str, bool] = {}
        self.bind(renderer)

    def rebound(self, renderer: TorchRenderer) -> "TTOImages":
        """The same targets and terms rendered through ``renderer`` (e.g. one whose vessel channel
        holds the opacified vessels only)."""
        other = copy.copy(self)
        other.bind(renderer)
        return other

    def bind(self, renderer: TorchRenderer) -> None:
        """Render through ``renderer``."""
        import torch

        self.renderer = renderer
        self._valley_points: np.ndarray | None = None
        as_t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32), device=renderer.device)[None, None]  # noqa: E731
        self.levels = {}
        for v in self.views:
            for size, (target, mask, vessels, det) in (("full", (v.target, v.mask, v.vessels, v.detector)), ("half", _half(v))):
                drr = renderer.drr(renderer.level_for_pose(v.pose, det))
                m = (as_t(mask) > 0).float()
                self.levels[v.name, size] = (as_t(target), m, as_t(vessels), det, drr)
            if v.name in self.vessel_term:  # a new vessel channel keeps the terms the objective had
                continue
            # The vessel term only where the CTA has vessels in this view (its channel is not empty).
            with torch.no_grad():
                _, _, _, det, drr = self.levels[v.name, "full"]
                start = torch.as_tensor(v.pose, dtype=torch.float64, device=renderer.device)[None]
                self.vessel_term[v.name] = self.objective.vessel_weight > 0 and bool(
                    drr(start, detector=det, channels=(self.channels[2],)).amax() > 0)

    def valley_points(self) -> np.ndarray:
        """At most ``VALLEY_POINTS`` voxel centres (mm, centred CTA frame) of the vessels the objective
        renders (the cranium's without vessels), evenly strided: what the common-axis search keeps
        still (:func:`.axis_search.valley_turn`)."""
        if self._valley_points is None:
            volume = self.renderer.volume
            kji = volume.mask_voxels("vessels")
            if not len(kji):
                kji = volume.mask_voxels("cranium")
            self._valley_points = volume.centred_points(kji[:: max(1, -(-len(kji) // VALLEY_POINTS))])
        return self._valley_points

    def loss(self, name: str, pose, size: str):
        """(loss, mNCC, Dice loss, vessel NCC or None) of view ``name`` at ``pose`` ``(1, 4, 4)``
        (torch, differentiable; :func:`.objective.view_terms`)."""
        import torch

        target, mask, vessels, det, drr = self.levels[name, size]
        img = drr(pose, detector=det, channels=self.channels)
        return view_terms(img[0, 0], img[0, 1], img[0, 2], target[0, 0], mask[0, 0], vessels[0, 0], self.objective,
                          coarse=size != "full", vessel_term=self.vessel_term[name], xp=torch)


class _PatientParams:
    """``T_v = X @ A_v`` with ``X = [[R(w) R0, p0 + v], [0, 1]]``: ``w`` (rad, axis-angle about the
    isocentre, CTA frame) and ``v`` (mm, isocentre shift)."""

    def __init__(self, X0: np.ndarray, rig: Mapping[str, np.ndarray], device,
                 prior_per_rad2: float = TTOSchedule.rotation_prior_per_rad2) -> None:
        import torch

        self.X0 = torch.as_tensor(X0, dtype=torch.float64, device=device)
        self.rig = {k: torch.as_tensor(A, dtype=torch.float64, device=device) for k, A in rig.items()}
        self.w = torch.zeros(3, dtype=torch.float64, device=device, requires_grad=True)
        self.v = torch.zeros(3, dtype=torch.float64, device=device, requires_grad=True)
        self.w_ref = torch.zeros(3, dtype=torch.float64, device=device)
        self.prior_per_rad2 = prior_per_rad2
        axis = common_axis({k: X0 for k in rig}, rig)
        self.prior_axis = None if axis is None else torch.as_tensor(axis, dtype=torch.float64, device=device)

    def rotation_prior(self):
        """``prior_per_rad2 * ((w - w_ref) . common axis)^2`` (all of ``|w - w_ref|^2`` without a
        common axis); ``w_ref`` is 0, or where the last common-axis search moved ``w``."""
        d = self.w - self.w_ref
        w2 = (d ** 2).sum() if self.prior_axis is None else (d @ self.prior_axis) ** 2
        return self.prior_per_rad2 * w2

    @staticmethod
    def moved(start: tuple, direction: tuple[np.ndarray, np.ndarray], angle_rad: float) -> tuple:
        """The ``start`` ``(w, v)`` moved by ``angle_rad`` along ``direction`` (rotation rad/rad, shift mm/rad:
        :func:`.axis_search.valley_turn`), as :func:`.biplane.moved_by` does: new tensors ``(w, v)``."""
        import torch

        from ..geometry.rigid import axis_angle_to_matrix, matrix_to_axis_angle

        w0, v0 = start
        rotation, shift = (torch.as_tensor(np.asarray(a) * angle_rad, dtype=w0.dtype, device=w0.device)
                           for a in direction)
        return matrix_to_axis_angle(axis_angle_to_matrix(rotation) @ axis_angle_to_matrix(w0)), v0 + shift

    def move_along(self, start: tuple, direction: tuple[np.ndarray, np.ndarray], angle_rad: float) -> None:
        """Set ``w, v`` to :meth:`moved` (in place: the optimiser holds them)."""
        w, v = self.moved(start, direction, angle_rad)
        self.w.copy_(w)
        self.v.copy_(v)

    def groups(self, schedule: TTOSchedule) -> list[dict]:
        return [{"params": [self.w], "lr": schedule.rotation_lr_rad}, {"params": [self.v], "lr": schedule.translation_lr_mm}]

    def patient(self, w=None, v=None):
        """The patient pose ``(4, 4)`` at the parameters (or at ``w, v``, e.g. a turn the common-axis search scores)."""
        import torch

        from ..geometry.rigid import axis_angle_to_matrix

        w, v = (self.w, self.v) if w is None else (w, v)
        top = torch.cat((axis_angle_to_matrix(w) @ self.X0[:3, :3], (self.X0[:3, 3] + v)[:, None]), dim=1)
        return torch.cat((top, self.X0[3:]), dim=0)

    def poses(self, w=None, v=None) -> dict:
        X = self.patient(w, v)
        return {k: (X @ A)[None] for k, A in self.rig.items()}


class _ViewParams:
    """Per view, the paper's parameters: Euler ZYX (rad) and rotated-frame translation / 200 (mm)."""

    def __init__(self, poses: Mapping[str, np.ndarray], device) -> None:
        import torch

        from ..geometry.rigid import params_from_pose

        self.scale = PAPER_TRANSLATION_SCALE_MM
        self.params = {}
        for name, pose in poses.items():
            r, t = params_from_pose(torch.as_tensor(pose, dtype=torch.float64, device=device)[None])
            self.params[name] = torch.cat((r, t / self.scale), dim=-1).clone().requires_grad_(True)

    def groups(self, schedule: TTOSchedule) -> list[dict]:
        return [{"params": list(self.params.values()), "lr": schedule.paper_lr}]

    def poses(self) -> dict:
        from ..geometry.rigid import pose_from_params

        return {k: pose_from_params(p[:, :3], p[:, 3:] * self.scale) for k, p in self.params.items()}


class TTORun:
    """One optimisation from one start over shared :class:`TTOImages`: its parameters, NAdam with
    the OneCycle schedule, the best pose seen and the trace; :meth:`advance` runs it on in pieces."""

    def __init__(self, images: TTOImages, poses: Mapping[str, np.ndarray], schedule: TTOSchedule,
                 rig: Mapping[str, np.ndarray] | None, biplanar: bool, device) -> None:
        import torch

        self.images, self.schedule, self.rig, self.biplanar, self.device = images, schedule, rig, biplanar, device
        self.names = list(poses)
        self.n = schedule.iterations
        if self.n < 0:
            raise ValueError(f"iterations must be >= 0, got {self.n}")
        self.joint = rig is not None
        if self.joint:
            X0 = patient_pose(poses[self.names[0]], rig[self.names[0]])
            self.params = _PatientParams(X0, {k: rig[k] for k in self.names}, device, schedule.rotation_prior_per_rad2)
        else:
            self.params = _ViewParams(poses, device)
        self.coarse = schedule.coarse_steps() if self.n > 0 else 0
        self.searches = (schedule.axis_search_iterations() if self.joint and self.params.prior_axis is not None
                         else set())
        # best[...] = (objective loss, per-view mNCC, per-view pose, iteration, prior); one entry for a patient
        # pose, whose full-size evaluations are kept in ``seen`` (poses, iteration, prior) to be scored again, and
        # their terms by the images that scored them in ``scored`` (index in seen -> [(images, terms)]; an images
        # object keeps its objective: :meth:`TTOImages.rebound` makes a new one)
        self.best: dict = {}
        self.seen: list[tuple[dict, int, float]] = []
        self.scored: dict[int, list[tuple[TTOImages, dict]]] = {}
        self.trace: list[dict] = []
        self.axis_searches: list[dict] = []
        self.vessel_selection: VesselSelection | None = None
        self.it = 0
        self.start_pending = False
        if self.coarse > 0 and self.joint:  # the start, scored at full size when first compared (the coarse steps are
            # not compared with it), by the images the run holds then: a read at the start changes them first
            self.seen.append(({k: p.detach()[0].cpu().numpy() for k, p in self.params.poses().items()}, 0,
                              float(self.params.rotation_prior().detach())))
            self.start_pending = True
        elif self.coarse > 0:
            with torch.no_grad():
                _, losses, current = self._evaluate("full")
            self._record_best(losses, current, 0)
        self.optimiser = None
        if self.n > 0:
            self.optimiser = OneCycleNAdam(
                self.params.groups(schedule), total_steps=self.n, pct_start=schedule.warmup_fraction,
                div_factor=schedule.div_factor, final_div_factor=1.0 / (schedule.div_factor * schedule.final_lr_fraction))

    def _evaluate(self, size: str, views: tuple | None = None) -> tuple:
        """``(total, losses, poses)`` at the parameters: the views' losses (:meth:`_views`, or ``views`` already
        rendered there), the arms' orthogonality and the rotation prior."""
        total, losses, poses, tensors = views or self._views(size)
        if self.biplanar and len(self.names) == 2:
            rotations = [tensors[name][:, :3, :3] for name in self.names]
            total = total + BIPLANAR_WEIGHT * biplanar_penalty(*rotations).sum()
        if self.joint:
            total = total + self.params.rotation_prior()
        return total, losses, poses

    def _views(self, size: str, w=None, v=None) -> tuple:
        """The views' summed loss (torch), their terms (floats), poses (numpy) and pose tensors at the parameters (or,
        for a patient pose, at ``w, v``)."""
        import torch

        tensors = self.params.poses() if w is None else self.params.poses(w, v)
        losses = {}
        total = torch.zeros((), dtype=torch.float64, device=self.device)
        for name in self.names:
            view_loss, sim, dice, vessel = self.images.loss(name, tensors[name], size)
            losses[name] = (float(view_loss.detach()), float(sim.detach()), float(dice.detach()),
                            None if vessel is None else float(vessel.detach()))
            total = total + view_loss
        return total, losses, {k: p.detach()[0].cpu().numpy() for k, p in tensors.items()}, tensors

    def _consider(self, key: str, loss: float, scores: dict, poses: dict, it: int, prior: float = 0.0) -> None:
        if key not in self.best or loss < self.best[key][0]:
            self.best[key] = (loss, scores, poses, it, prior)

    def _consider_patient(self, poses: dict, it: int, prior: float, terms: dict) -> None:
        """Keep a full-size patient pose if its objective (the views' losses, ``terms[view][0]``, plus ``prior``) is
        the lowest so far."""
        self._consider("patient", sum(v[0] for v in terms.values()) + prior, {k: v[1] for k, v in terms.items()},
                       poses, it, prior)

    def _record_best(self, losses: dict, poses: dict, it: int) -> None:
        if self.joint:
            self._score_start()
            prior = float(self.params.rotation_prior().detach())
            self.seen.append((poses, it, prior))
            self.scored[len(self.seen) - 1] = [(self.images, {k: list(v[:2]) for k, v in losses.items()})]
            self._consider_patient(poses, it, prior, losses)
        else:  # per view; the paper keeps the pose of best mNCC
            for name in self.names:
                key = -losses[name][1] if self.schedule.paper else losses[name][0]
                self._consider(name, key, {name: losses[name][1]}, {name: poses[name]}, it)

    def patient_at(self, it: int) -> np.ndarray:
        """The patient pose ``(4, 4)`` this run evaluated at iteration ``it`` (a patient-pose run)."""
        return traced_patient_pose(self.trace, self.rig, it)

    def _seen_losses(self, images: TTOImages, count: int | None = None):
        """Per full-size patient pose seen so far (the first ``count``): (poses, iteration, prior, per view
        ``images.loss`` terms (loss, mNCC) as floats), rendered where ``images`` have not scored it yet."""
        import torch

        for index, (poses, it, prior) in enumerate(self.seen[:count]):
            terms = next((t for by, t in self.scored.get(index, ()) if by is images), None)
            if terms is None:
                with torch.no_grad():
                    terms = {k: [float(v) for v in images.loss(
                        k, torch.as_tensor(poses[k], dtype=torch.float64, device=self.device)[None], "full")[:2]]
                        for k in self.names}
                self.scored.setdefault(index, []).append((images, terms))
            yield poses, it, prior, terms

    def _score_start(self) -> None:
        """Score the start (a patient-pose run's first seen pose) if it waits to be."""
        if self.start_pending:
            self.start_pending = False
            for seen in self._seen_losses(self.images, 1):
                self._consider_patient(*seen)

    def rescore_best(self) -> None:
        """Score the full-size patient poses seen so far again with the objective the images hold now
        (their vessel channel changed) and keep the best, so that later iterations are compared with
        them on equal terms."""
        self.best.pop("patient", None)
        self.start_pending = False
        for seen in self._seen_losses(self.images):
            self._consider_patient(*seen)

    def best_loss_by(self, images: TTOImages) -> float:
        """The lowest objective (views summed, no prior) ``images`` give the full-size patient poses this run has
        evaluated: its runs compared on one objective (:func:`.tournament.optimise_from_starts`)."""
        return min(sum(v[0] for v in losses.values()) for _, _, _, losses in self._seen_losses(images))

    def _axis_search(self, it: int, keep: bool) -> tuple | None:
        """Move the patient along the common-axis valley (:func:`.axis_search.valley_turn`: the turn
        about the common axis with the other parameters' compensation) to the objective's best
        (``TTOSchedule``), and centre the rotation prior there. ``keep``: the turns are scored with gradients and
        the chosen one's evaluation is returned (:meth:`_views`, with its leaves ``w, v``), which the step that follows
        would otherwise render again; at most two full-size graphs are alive, the lowest so far and the one scored."""
        import torch

        params, step = self.params, self.schedule.axis_search_step_deg
        start = (params.w.detach().clone(), params.v.detach().clone())
        X = params.patient().detach().cpu().numpy()
        rig = {k: A.cpu().numpy() for k, A in params.rig.items()}
        detectors = {k: self.images.levels[k, "full"][3] for k in self.names}
        direction = valley_turn(X, rig, detectors, self.images.valley_points())
        if direction is None:  # no points to project: the bare turn
            direction = (params.prior_axis.cpu().numpy(), np.zeros(3))
        lowest: dict = {}

        def score(deg: float) -> float:
            w, v = (t.requires_grad_(keep) for t in params.moved(start, direction, math.radians(deg)))
            with torch.set_grad_enabled(keep):
                views = self._views("full", w, v)
            value = sum(terms[0] for terms in views[1].values())
            if keep and ("value" not in lowest or value < lowest["value"]):  # the first lowest, as best_turn's choice
                lowest.update(deg=deg, value=value, views=views, leaves=(w, v))
            return value

        with torch.no_grad():
            turns, scores, chosen = best_turn(score, step)
            params.move_along(start, direction, math.radians(chosen))
            params.w_ref.copy_(params.w.detach())
        self.axis_searches.append({
            "iteration": it, "turn_deg": turns, "loss": scores, "chosen_deg": chosen,
            "rotation_per_rad": np.asarray(direction[0]).tolist(),
            "shift_mm_per_rad": np.asarray(direction[1]).tolist()})
        return (lowest["views"], lowest["leaves"]) if keep and lowest["deg"] == chosen else None

    def advance(self, until: int, monitor: Monitor) -> None:
        """Run iterations up to (not including) ``until`` (at most the last, ``n``): evaluate, record,
        step; the last iteration only evaluates. ``monitor`` sees the fraction of this call's work."""
        import torch

        begin, end = self.it, min(until, self.n + 1)
        while self.it < end:
            it, final = self.it, self.it == self.n
            size = "half" if it < self.coarse else "full"
            searched = self._axis_search(it, keep=size == "full" and not final) if it in self.searches else None
            monitor.step("tto", (it - begin) / max(end - begin, 1), f"iteration {it}/{self.n} ({size} size)")
            with torch.set_grad_enabled(not final):
                total, losses, poses = self._evaluate(size, searched[0] if searched else None)
            self.trace.append({
                "iteration": it, "size": size, "loss": float(total.detach()),
                "learning_rates": None if final else self.optimiser.learning_rates,
                "views": {k: {"mncc": losses[k][1], "dice_loss": losses[k][2], "vessel_ncc": losses[k][3],
                              "pose": poses[k].tolist()} for k in self.names},
            })
            if size == "full":
                self._record_best(losses, poses, it)
            if not final:
                self.optimiser.zero_grad()
                total.backward()
                if searched:  # the views' gradient reached the search's leaves (at the parameters' values): add it
                    for param, leaf in zip((self.params.w, self.params.v), searched[1]):
                        param.grad = leaf.grad if param.grad is None else param.grad + leaf.grad
                self.optimiser.step()
            self.it += 1

    def finish(self, **fields) -> TTOResult:
        """The result: the best pose seen (per view, or of the patient pose), the trace, and ``fields``
        (``stopped_at``, ``ranking_loss``)."""
        self._score_start()
        poses, best_mncc, best_iteration = {}, {}, {}
        for _, scores, best_poses, it, _ in self.best.values():
            for name, pose in best_poses.items():
                poses[name], best_mncc[name], best_iteration[name] = pose, scores[name], it
        patient = patient_pose(poses[self.names[0]], self.rig[self.names[0]]) if self.joint else None
        return TTOResult(poses, best_mncc, best_iteration, patient, tuple(self.trace), tuple(self.axis_searches),
                         vessel_selection=self.vessel_selection, **fields)


def traced_patient_pose(trace, rig: Mapping[str, np.ndarray], it: int) -> np.ndarray:
    """The patient pose ``(4, 4)`` a patient-pose run evaluated at iteration ``it`` of its ``trace`` (a
    :class:`TTORun`'s or :attr:`TTOResult.trace`), read from its first view's pose and that arm's ``rig`` pose."""
    seen = trace[it]["views"]
    name = next(iter(seen))
    return patient_pose(np.asarray(seen[name]["pose"]), rig[name])


def restrict_to_opacified(runs: Mapping[str, TTORun], patients: Mapping[str, np.ndarray], at: tuple[str, np.ndarray],
                          rig: Mapping[str, np.ndarray], it: int) -> bool:
    """Read the opacified vessels (``opacified.read_opacified``) at ``at`` (a name and a patient pose ``(4, 4)``: a
    start's, or where a run reached at iteration ``it``); each of ``runs`` (patient-pose runs over one
    :class:`TTOImages`) whose pose in ``patients`` places the vessels within ``OPACIFIED_NEAR_MM`` of it renders the
    vessel channel from them alone from now on, its best pose so far scored again with that objective, and holds the
    selection (:attr:`TTOResult.vessel_selection`). Returns whether a run took a selection."""
    images = next(iter(runs.values())).images
    views = [(v.name, v.vessels, v.detector) for v in images.views if images.vessel_term[v.name]]
    if not views:
        return False
    selection = read_opacified(images.renderer.volume, at[1], rig, views, start=at[0], iteration=it)
    if selection is None or not selection.applied:
        return False
    near = [key for key in runs if vessel_shift_mm(images.renderer.volume, selection, patients[key]) <= OPACIFIED_NEAR_MM]
    restricted = images.rebound(TorchRenderer(selection.volume, images.renderer.device)) if near else None
    for key in near:
        runs[key].images = restricted
        runs[key].rescore_best()
        runs[key].vessel_selection = selection
    return bool(near)


def test_time_optimise(
    renderer: TorchRenderer,
    views: list[TTOView],
    schedule: TTOSchedule = TTOSchedule(),
    *,
    objective: Objective = Objective(),
    rig: Mapping[str, np.ndarray] | None = None,
    biplanar: bool = False,
    monitor: Monitor | None = None,
) -> TTOResult:
    """Optimise the poses of ``views`` through ``renderer``'s differentiable kernel: one patient
    pose when ``rig`` (``{view: A_v}``) is given (the views' start poses must be ``X @ A_v`` of one
    ``X``; with ``objective.read_opacified`` the vessel term keeps the vessels the runs show opacified, read
    at the start, or after the coarse steps where too few pass there), else each view's own (``schedule.paper`` for the published schedule).
    ``tournament.optimise_from_starts`` runs one patient pose from several starts."""
    monitor = monitor or Monitor()
    images = TTOImages(renderer, views, objective)
    if rig is None:
        run = TTORun(images, {v.name: v.pose for v in views}, schedule, None, biplanar, renderer.device)
        run.advance(run.n + 1, monitor)
    else:
        X = patient_pose(views[0].pose, rig[views[0].name])
        run = TTORun(images, view_poses(X, rig), schedule, rig, False, renderer.device)
        read = objective.read_opacified and restrict_to_opacified({"start": run}, {"start": X}, ("start", X), rig, 0)
        parts = 2 if run.coarse > 0 else 1
        if run.coarse > 0:
            run.advance(run.coarse + 1, monitor.part(0, parts, "coarse"))
            if objective.read_opacified and not read:
                reached = run.patient_at(run.coarse)
                restrict_to_opacified({"start": run}, {"start": reached}, ("start", reached), rig, run.coarse)
        run.advance(run.n + 1, monitor.part(parts - 1, parts, "full size"))
    monitor.step("tto", 1.0, "done")
    return run.finish()
