"""Overlay pictures of a registration: the DSA MAP with the projected CTA vessels
(and carotid centrelines, when known) after Init, after refinement and at the end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .. import viz
from ..geometry import project_points
from .pipeline import VESSEL_CHANNEL, CaseRegistration

__all__ = ["write_overlays"]

VESSEL_COLOUR = (255, 60, 40)
CENTRELINE_COLOUR = (60, 220, 255)
STAGE_TITLES = {"init": "after Init", "refine": "after refinement", "final": "final"}


def _panel(case: CaseRegistration, key: str, stage: str, carotid_mm: np.ndarray | None) -> np.ndarray:
    view = case.views[key]
    det = view.prepared.tto_detector
    pose = view.stage_poses[stage]
    with torch.no_grad():
        vessels = case.drr(pose.float(), detector=det, channels=(VESSEL_CHANNEL,))[0, 0].cpu().numpy()
    rgb = viz.to_rgb(view.prepared.tto_image)
    if vessels.max() > 0:
        rgb = viz.overlay_mask(rgb, vessels > 0.05 * vessels.max(), VESSEL_COLOUR, alpha=0.55)
    if carotid_mm is not None and len(carotid_mm):
        rc, _ = project_points(pose.detach().cpu().double(), det, torch.as_tensor(carotid_mm, dtype=torch.float64))
        rgb = viz.draw_points(rgb, rc[0].numpy()[::3], CENTRELINE_COLOUR, radius=0.8)
    return viz.label_panel(rgb, f"{key.upper()} {STAGE_TITLES[stage]}")


def write_overlays(case: CaseRegistration, out_dir: str | Path, carotid_mm: np.ndarray | None = None) -> list[Path]:
    """One PNG per view (``overlay_pa.png``, ``overlay_lat.png``): three stages side by side."""
    out = []
    for key in case.views:
        panels = [_panel(case, key, stage, carotid_mm) for stage in STAGE_TITLES]
        out.append(viz.save_png(viz.hstack(panels), Path(out_dir) / f"overlay_{key}.png"))
    return out
