"""Overlay pictures of a registration: the DSA MAP with the projected CTA vessels
(and carotid centrelines, when known) after Init, after refinement and at the end."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import viz
from ..dsa.preprocess import resample_to_detector
from ..geometry.detector import Detector
from ..geometry.poses import project_points
from ..outputs import OutputFolder, atomic_write
from .evaluate import vessel_mask
from .results import CaseRegistration

__all__ = ["OVERLAY_NAMES", "write_overlays"]

#: The overlay files of a PA + lateral registration.
OVERLAY_NAMES = ("overlay_pa.png", "overlay_lat.png")

VESSEL_COLOUR = (255, 60, 40)
CENTRELINE_COLOUR = (60, 220, 255)
STAGE_TITLES = {"init": "after Init", "refine": "after refinement", "final": "final"}
#: Overlay size (pixels along the detector's longer side).
OVERLAY_PX = 384


def overlay_detector(detector: Detector, px: int = OVERLAY_PX) -> Detector:
    """The acquisition detector's field of view sampled on about ``px`` pixels."""
    scale = px / max(detector.shape)
    return detector.resized(max(1, round(detector.rows * scale)), max(1, round(detector.cols * scale)))


def _panel(case: CaseRegistration, key: str, stage: str, map_rgb: np.ndarray, det: Detector, carotid_mm: np.ndarray | None) -> np.ndarray:
    pose = case.views[key].stage_poses[stage]
    vessels = case.renderer.render(pose, det, ("vessels",))[0]
    rgb = map_rgb
    if vessels.max() > 0:
        rgb = viz.overlay_mask(rgb, vessel_mask(vessels), VESSEL_COLOUR, alpha=0.55)
    if carotid_mm is not None and len(carotid_mm):
        rc, _ = project_points(pose, det, carotid_mm)
        rgb = viz.draw_points(rgb, rc[::3], CENTRELINE_COLOUR, radius=0.8)
    return viz.label_panel(rgb, f"{key.upper()}: {STAGE_TITLES[stage]}")


def write_overlays(case: CaseRegistration, out: OutputFolder | str | Path, carotid_mm: np.ndarray | None = None) -> list[Path]:
    """One PNG per view (``overlay_pa.png``, ``overlay_lat.png``): three stages side by side, each
    written atomically (into an :class:`~geopose.outputs.OutputFolder`, or a plain folder)."""
    written = []
    for key, view in case.views.items():
        det = overlay_detector(view.prepared.tto_detector)
        source = view.prepared.tto_detector.resized(*view.prepared.map.shape)
        map_rgb = viz.to_rgb(resample_to_detector(view.prepared.map * view.prepared.mask, source, det))
        image = viz.hstack([_panel(case, key, stage, map_rgb, det, carotid_mm) for stage in STAGE_TITLES])
        name = f"overlay_{key}.png"
        if isinstance(out, OutputFolder):
            written.append(out.write_file(name, lambda p: viz.save_png(image, p)))
        else:
            Path(out).mkdir(parents=True, exist_ok=True)
            written.append(atomic_write(Path(out) / name, lambda p: viz.save_png(image, p)))
    return written
