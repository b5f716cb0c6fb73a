"""Network outputs -> poses and view labels, for inference (numpy, float64).

Raw outputs are the heads' unscaled 6-vectors; poses are camera-to-world
``(B, 4, 4)`` matrices in the centred CTA frame (mm, rad), see docs/conventions.md
sections 1 and 4. Training decodes the same way, differentiably, in
``geopose.training.poses``.
"""

from __future__ import annotations

import numpy as np

from ..contract import (
    INIT_TRANSLATION_SCALE_MM,
    ISO_TRANSLATION_MM,
    MIRRORED_VIEW,
    REFINE_ROTATION_SCALE_RAD,
    REFINE_TRANSLATION_SCALE_MM,
    VIEW_ANCHOR_RAD,
    VIEW_LAT_MINUS,
    VIEW_LAT_PLUS,
    VIEW_NAMES,
    VIEW_PA,
)
from ..geometry.poses import pose_from_params

__all__ = ["NUM_VIEWS", "view_labels", "mirror_averaged_logits", "select_view", "decode_init_pose", "residual_from_raw"]

NUM_VIEWS = len(VIEW_NAMES)


def view_labels(view: np.ndarray | int, batch: int) -> np.ndarray:
    """Validate view labels (0 LAT-, 1 PA, 2 LAT+) -> int64 ``(batch,)``; an int is broadcast."""
    labels = np.asarray(view, dtype=np.int64)
    labels = np.broadcast_to(labels, (batch,)).copy() if labels.ndim == 0 else labels
    if labels.shape != (batch,):
        raise ValueError(f"view labels must be a scalar or shape ({batch},), got {labels.shape}")
    if ((labels < 0) | (labels >= NUM_VIEWS)).any():
        raise ValueError(f"view labels must be in 0..{NUM_VIEWS - 1} ({', '.join(VIEW_NAMES)}), got {labels.tolist()}")
    return labels


def mirror_averaged_logits(logits: np.ndarray, mirrored_logits: np.ndarray) -> np.ndarray:
    """View logits ``(B, 3)`` averaged with those of the column-mirrored images, re-indexed by
    :data:`~geopose.contract.MIRRORED_VIEW`: the LAT+ - LAT- margin becomes antisymmetric under
    mirroring, so a bias of the network towards one side cancels."""
    return 0.5 * (logits + mirrored_logits[:, list(MIRRORED_VIEW)])


def select_view(logits: np.ndarray, is_lateral: np.ndarray | bool | None) -> np.ndarray:
    """View labels ``(B,)`` from ``(B, 3)`` logits: metadata PA stays PA, lateral takes the larger of
    the LAT-/LAT+ logits; without metadata (``None``) the argmax over all three."""
    if is_lateral is None:
        return logits.argmax(axis=1)
    lateral = np.asarray(is_lateral, dtype=bool).reshape(-1)
    if lateral.size not in (1, logits.shape[0]):
        raise ValueError(f"is_lateral has {lateral.size} entries for a batch of {logits.shape[0]} images")
    lateral = np.broadcast_to(lateral, (logits.shape[0],))
    side = np.where(logits[:, VIEW_LAT_PLUS] > logits[:, VIEW_LAT_MINUS], VIEW_LAT_PLUS, VIEW_LAT_MINUS)
    return np.where(lateral, side, VIEW_PA)


def decode_init_pose(raw: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Init raw ``(B, 6)`` + views ``(B,)`` -> poses: Euler ZYX ``raw[:3] + (anchor, 0, 0)`` rad,
    ``t = raw[3:] * INIT_TRANSLATION_SCALE_MM + ISO_TRANSLATION_MM`` (rotated frame, mm)."""
    raw = np.asarray(raw, dtype=np.float64)
    r = raw[:, :3].copy()
    r[:, 0] += np.asarray(VIEW_ANCHOR_RAD)[np.asarray(view)]
    return pose_from_params(r, raw[:, 3:] * INIT_TRANSLATION_SCALE_MM + np.asarray(ISO_TRANSLATION_MM))


def residual_from_raw(raw: np.ndarray) -> np.ndarray:
    """Refine raw ``(B, 6)`` -> residuals ``D = [[R(w), R(w) dt], [0, 1]]`` ``(B, 4, 4)`` with
    ``w = raw[:3] * REFINE_ROTATION_SCALE_RAD`` (axis-angle) and ``dt = raw[3:] * REFINE_TRANSLATION_SCALE_MM``;
    apply as ``inverse(D) @ T``."""
    raw = np.asarray(raw, dtype=np.float64)
    w = raw[:, :3] * np.asarray(REFINE_ROTATION_SCALE_RAD)
    dt = raw[:, 3:] * np.asarray(REFINE_TRANSLATION_SCALE_MM)
    return pose_from_params(w, dt, rotation="axis_angle")
