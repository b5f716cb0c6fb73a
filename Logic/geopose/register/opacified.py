"""Which of the CTA's vessels the DSA runs show opacified (numpy).

A CTA shows every artery; a run shows those its injection fills (one carotid's territory
for a selective injection). The vessel term compares the MAP's vessel image with the DRR's
vessel channel, so the arteries the run does not show pull the pose towards where they
would overlap the opacified ones: with the vessel channel restricted to the injected
arteries (the phantom's labels, an oracle) the TTO started at the true pose no longer
moves (experiments/tto_objective/objective.md). Without labels, each vessel voxel of the CTA is projected into
every view at a patient pose close to the truth and kept when every view's vessel image
shows contrast where it lands (:func:`read_opacified`): a vessel the run does not fill lands
on background in at least one of two orthogonal views, unless it overlaps a filled one in
both. The test-time optimisation reads the selection once, before its first step, at the
networks' estimate (greedy Refine + search), and the runs that start near that pose use it from
their first step (``tournament.optimise_from_starts``); far runs keep every vessel, whose wider
net guides them better. Read after the coarse steps at the pose of the best start (the earlier
design), the selection agreed with wherever that start had gone: on validation phantoms
6010-6019, default path, reading it at the estimate alone took the median carotid mPCD from
1.89 to 1.00 mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..geometry.detector import Detector
from ..geometry.poses import project_points
from ..images import bilinear_sample, gaussian_blur
from ..render.renderer import Renderer, make_renderer
from ..render.volume import RenderVolume

__all__ = ["OPACIFIED_BLUR_PX", "OPACIFIED_THRESHOLD", "OPACIFIED_MIN_FRACTION", "OPACIFIED_NEAR_MM", "VesselSelection",
           "read_opacified", "selection_judge", "vessel_shift_mm"]

#: Which of the CTA's vessels the runs show opacified (``register/opacified.py``). A vessel voxel is
#: kept when, in every view with a vessel image, that image (blurred by ``OPACIFIED_BLUR_PX`` at the TTO
#: size, scaled to max 1) reaches ``OPACIFIED_THRESHOLD`` where the voxel projects; when fewer than
#: ``OPACIFIED_MIN_FRACTION`` of the voxels pass, the pose is taken as too far off and all are kept (on a computed
#: mask, veins and bone included, 4-15 % pass at the networks' estimate on validation phantoms 6010-6029).
OPACIFIED_BLUR_PX = 2.0
OPACIFIED_THRESHOLD = 0.02
OPACIFIED_MIN_FRACTION = 0.02
#: A TTO run continues with the opacified vessels only when its patient pose places the CTA's vessels
#: within this mean distance (mm) of where the selection was read; a farther run keeps all of them
#: (they guide a far start better).
OPACIFIED_NEAR_MM = 5.0



@dataclass(frozen=True)
class VesselSelection:
    """The vessel voxels kept (``keep``, ``[k, j, i]`` bool on the CTA grid: the vessel mask of ``volume``, or the
    CTA's own when not applied; never a copy), out of ``vessel_voxels``;
    where it was read (``start`` name, TTO ``iteration``, the patient pose ``(4, 4)``); ``applied``:
    False when too few passed (``OPACIFIED_MIN_FRACTION``) and all vessels stay in the objective;
    ``kept_kji``: the kept voxels' ``[k, j, i]`` indices ``(N, 3)``; ``volume``: the CTA's render volume whose vessel
    channel holds the kept voxels alone (when applied)."""

    keep: np.ndarray
    vessel_voxels: int
    kept_voxels: int
    applied: bool
    start: str
    iteration: int
    patient_pose: np.ndarray
    kept_kji: np.ndarray
    volume: RenderVolume | None = None

    @property
    def kept_fraction(self) -> float:
        return self.kept_voxels / max(self.vessel_voxels, 1)

    def summary(self) -> dict:
        """The record's view of it (no voxel array)."""
        return {"applied": self.applied, "vessel_voxels": self.vessel_voxels, "kept_voxels": self.kept_voxels,
                "kept_fraction": round(self.kept_fraction, 4), "start": self.start, "iteration": self.iteration,
                "patient_pose": np.asarray(self.patient_pose).tolist(), "blur_px": OPACIFIED_BLUR_PX,
                "threshold": OPACIFIED_THRESHOLD}


def vessel_shift_mm(volume: RenderVolume, selection: VesselSelection, patient: np.ndarray) -> float:
    """Mean distance (mm) the kept vessels lie, in the isocentre frame, at patient pose ``patient`` from
    where they lay at the pose the selection was read at."""
    points = volume.centred_points(selection.kept_kji)
    if not len(points):
        return 0.0
    moved = np.linalg.solve(np.asarray(patient, dtype=np.float64), np.c_[points, np.ones(len(points))].T)
    read = np.linalg.solve(selection.patient_pose, np.c_[points, np.ones(len(points))].T)
    return float(np.linalg.norm((moved - read)[:3], axis=0).mean())


def read_opacified(
    volume: RenderVolume,
    patient: np.ndarray,
    rig: Mapping[str, np.ndarray],
    views: Sequence[tuple[str, np.ndarray, Detector]],
    *,
    start: str = "",
    iteration: int = 0,
) -> VesselSelection | None:
    """The vessel voxels of ``volume`` that every view's vessel image shows at patient pose ``patient``
    (``T_v = patient @ rig[v]``; ``views``: ``(name, vessel image (h, w), detector)``). None when the
    CTA has no vessel voxels or no view a vessel image (nothing to select by)."""
    vessels = volume.mask("vessels")
    images = [(name, np.asarray(image, dtype=np.float64), det) for name, image, det in views if np.max(image) > 0]
    if vessels is None or not vessels.any() or not images:
        return None
    kji = volume.mask_voxels("vessels")
    points_mm = volume.centred_points(kji)
    shown = np.full(len(kji), np.inf)
    for name, image, det in images:
        smooth = gaussian_blur(image, (OPACIFIED_BLUR_PX, OPACIFIED_BLUR_PX))
        smooth /= max(float(smooth.max()), 1e-12)
        pixels, _ = project_points(np.asarray(patient, dtype=np.float64) @ rig[name], det, points_mm)
        shown = np.minimum(shown, bilinear_sample(smooth, pixels[:, 0], pixels[:, 1]))
    passed = shown >= OPACIFIED_THRESHOLD
    applied = passed.mean() >= OPACIFIED_MIN_FRACTION
    kept = kji[passed] if applied else kji
    subset = volume.with_vessels(kept) if applied else None
    keep = subset.mask("vessels") if applied else vessels  # shared, not copied
    return VesselSelection(keep, len(kji), int(passed.sum()) if applied else len(kji), bool(applied), start, iteration,
                           np.asarray(patient, dtype=np.float64), kept, subset)


def selection_judge(renderer: Renderer, selection: VesselSelection | None) -> Renderer:
    """What a result read with ``selection`` is judged by: ``renderer``, or (the selection applied) a renderer of its
    engine and device whose vessel channel holds the kept vessels alone."""
    if selection is None or not selection.applied:
        return renderer
    return make_renderer(selection.volume, renderer.engine, str(getattr(renderer, "device", "cpu")))
