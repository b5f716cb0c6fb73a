"""Network outputs -> poses: shared by the torch modules and the ONNX runners.

Raw outputs are the heads' unscaled 6-vectors; poses are camera-to-world
``(B, 4, 4)`` matrices in the centred CTA frame (mm, rad), see CONVENTIONS 1, 4.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..contract import (
    INIT_TRANSLATION_SCALE_MM,
    MIRRORED_VIEW,
    ISO_TRANSLATION_MM,
    REFINE_ROTATION_SCALE_RAD,
    REFINE_TRANSLATION_SCALE_MM,
    VIEW_ANCHOR_RAD,
    VIEW_LAT_MINUS,
    VIEW_LAT_PLUS,
    VIEW_NAMES,
    VIEW_PA,
)
from ..geometry.rigid import RigidTransform, pose_from_params

NUM_VIEWS = len(VIEW_NAMES)


def as_view_labels(view: Tensor | int, batch: int, device: torch.device | None = None) -> Tensor:
    """Validate view labels (0 LAT-, 1 PA, 2 LAT+) -> int64 ``(batch,)``; an int is broadcast."""
    labels = torch.as_tensor(view, dtype=torch.int64, device=device)
    if labels.ndim == 0:
        labels = labels.expand(batch)
    if labels.shape != (batch,):
        raise ValueError(f"view labels must be a scalar or shape ({batch},), got {tuple(labels.shape)}")
    if bool(((labels < 0) | (labels >= NUM_VIEWS)).any()):
        raise ValueError(f"view labels must be in 0..{NUM_VIEWS - 1} ({', '.join(VIEW_NAMES)}), got {labels.tolist()}")
    return labels


def mirror_averaged_logits(logits: Tensor, mirrored_logits: Tensor) -> Tensor:
    """View logits ``(B, 3)`` averaged with those of the column-mirrored images, re-indexed
    by :data:`MIRRORED_VIEW`: the LAT+ - LAT- margin becomes antisymmetric under mirroring,
    so a bias of the network towards one side cancels."""
    return 0.5 * (logits + mirrored_logits[:, list(MIRRORED_VIEW)])


def select_view(logits: Tensor, is_lateral: Tensor | None) -> Tensor:
    """Inference view rule from ``(B, 3)`` logits -> labels ``(B,)``.

    Metadata PA (``is_lateral`` False) stays PA; lateral takes the larger of the
    LAT-/LAT+ logits. Without metadata (``None``) the argmax over all three views.
    """
    if is_lateral is None:
        return logits.argmax(dim=1)
    lateral = torch.as_tensor(is_lateral, dtype=torch.bool, device=logits.device).reshape(-1)
    if lateral.numel() == 1:
        lateral = lateral.expand(logits.shape[0])
    if lateral.shape[0] != logits.shape[0]:
        raise ValueError(f"is_lateral has {lateral.shape[0]} entries for a batch of {logits.shape[0]} images")
    side = torch.where(logits[:, VIEW_LAT_PLUS] > logits[:, VIEW_LAT_MINUS], VIEW_LAT_PLUS, VIEW_LAT_MINUS)
    return torch.where(lateral, side, torch.full_like(side, VIEW_PA))


def decode_init_pose(raw: Tensor, view: Tensor) -> Tensor:
    """Init raw ``(B, 6)`` + view labels ``(B,)`` -> pose ``(B, 4, 4)``.

    ``r = raw[0:3] + (anchor(view), 0, 0)`` rad (Euler ZYX),
    ``t = raw[3:6] * INIT_TRANSLATION_SCALE_MM + ISO_TRANSLATION_MM`` (rotated frame, mm).
    """
    anchors = torch.tensor(VIEW_ANCHOR_RAD, dtype=raw.dtype, device=raw.device)[view]
    r = raw[:, 0:3] + torch.stack((anchors, torch.zeros_like(anchors), torch.zeros_like(anchors)), dim=1)
    iso = torch.tensor(ISO_TRANSLATION_MM, dtype=raw.dtype, device=raw.device)
    t = raw[:, 3:6] * INIT_TRANSLATION_SCALE_MM + iso
    return pose_from_params(r, t, rotation="euler_zyx")


def residual_from_raw(raw: Tensor) -> Tensor:
    """Refine raw ``(B, 6)`` -> residual ``D = [[R(w), R(w) dt], [0, 1]]`` ``(B, 4, 4)``.

    ``w = raw[0:3] * REFINE_ROTATION_SCALE_RAD`` (axis-angle, rad),
    ``dt = raw[3:6] * REFINE_TRANSLATION_SCALE_MM`` (mm). Apply as ``inverse(D) @ T``.
    """
    w = raw[:, 0:3] * torch.tensor(REFINE_ROTATION_SCALE_RAD, dtype=raw.dtype, device=raw.device)
    dt = raw[:, 3:6] * torch.tensor(REFINE_TRANSLATION_SCALE_MM, dtype=raw.dtype, device=raw.device)
    return RigidTransform.from_axis_angle(w, dt).matrix
