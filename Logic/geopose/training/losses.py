"""Training losses of Init and Refine (docs/conventions.md section 6, plus a documented supervised term).

Poses are camera-to-world ``(B, 4, 4)`` (mm, rad). Each loss returns the scalar
total and a dict of detached per-term means for logging.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor
from torch.nn import functional as F

from ..contract import MODEL_SDD_MM
from ..metrics.losses import generalized_dice_loss, mncc_similarity
from ..images import normalize_minmax
from . import recipe as R
from .data import Batch, Renderer
from .population import CHANNELS
from .poses import init_pose_tensor, residual_tensor

_EPS = 1e-9
#: Regulariser of the rotation-vector norm (keeps gradients finite at zero rotation).
_ROT_EPS = 1e-12
#: Line-integral scale (density x mm) of the soft vessel mask ``1 - exp(-v / scale)``.
VESSEL_SOFT_SCALE = 1.0
TOTAL, CRANIUM, VESSELS = (CHANNELS.index(c) for c in ("total", "cranium", "vessels"))


@dataclass(frozen=True)
class LossWeights:
    """Term weights. ``render`` enables the terms that render the predicted pose
    (-mNCC and soft vessel Dice); ``param`` is the supervised smooth-L1 on raw outputs."""

    mncc: float = R.W_MNCC
    geodesic: float = R.W_GEODESIC
    vessel: float = R.W_VESSEL
    view: float = R.W_VIEW
    param: float = 1.0
    render: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


def _rotation_log(Rm: Tensor) -> tuple[Tensor, Tensor]:
    """Axis-angle vector ``(B, 3)`` and angle ``(B,)`` (rad) of rotations, with finite gradients at 0."""
    v = torch.stack((Rm[:, 2, 1] - Rm[:, 1, 2], Rm[:, 0, 2] - Rm[:, 2, 0], Rm[:, 1, 0] - Rm[:, 0, 1]), dim=1)
    norm = torch.sqrt((v * v).sum(1) + _ROT_EPS)
    cos = (Rm.diagonal(dim1=1, dim2=2).sum(1) - 1) / 2
    angle = torch.atan2(norm / 2, cos)
    return v * (angle / norm)[:, None], angle


def log_se3_geodesic(pred: Tensor, ref: Tensor) -> Tensor:
    """``|log(ref^-1 pred)|`` ``(B,)``: norm of the se(3) twist (rad and mm components together)."""
    rel = torch.linalg.inv(ref) @ pred
    omega, angle = _rotation_log(rel[:, :3, :3])
    W = torch.zeros_like(rel[:, :3, :3])
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -omega[:, 2], omega[:, 1], -omega[:, 0]
    W = W - W.transpose(1, 2)
    a2 = angle * angle
    small = a2 < 1e-6
    safe = torch.where(small, torch.ones_like(angle), angle)
    coef = torch.where(small, torch.full_like(angle, 1.0 / 12.0), (1 - safe * torch.sin(safe) / (2 * (1 - torch.cos(safe)))) / safe**2)
    V_inv = torch.eye(3, dtype=rel.dtype, device=rel.device) - 0.5 * W + coef[:, None, None] * (W @ W)
    rho = (V_inv @ rel[:, :3, 3:4])[..., 0]
    return torch.sqrt((omega * omega).sum(1) + (rho * rho).sum(1) + _EPS)


def double_geodesic(pred: Tensor, ref: Tensor, sdd_mm: float = MODEL_SDD_MM) -> Tensor:
    """``sqrt((SDD/2 * angle)^2 + |c_pred - c_ref|^2)`` ``(B,)`` mm, c = source position; differentiable."""
    _, angle = _rotation_log(pred[:, :3, :3].transpose(1, 2) @ ref[:, :3, :3])
    shift = ((pred[:, :3, 3] - ref[:, :3, 3]) ** 2).sum(1)
    return torch.sqrt((sdd_mm / 2 * angle) ** 2 + shift + _EPS)


def soft_vessel_mask(vessel_integral: Tensor) -> Tensor:
    """Soft vessel silhouette in [0, 1) from the vessel-channel line integral."""
    return 1 - torch.exp(-vessel_integral.clamp_min(0) / VESSEL_SOFT_SCALE)


def init_loss(
    raw: Tensor, logits: Tensor, batch: Batch, renderer: Renderer, weights: LossWeights
) -> tuple[Tensor, dict[str, float]]:
    """Init objective: -mNCC and vessel Dice at the predicted pose (if ``weights.render``),
    log-SE3 + double geodesic, projected vessel-fiducial distance (fraction of the image
    width), view cross-entropy and the supervised raw term. ``raw`` is the pose head for the true view."""
    raw = raw.float()
    pred = init_pose_tensor(raw, batch.view)
    true = batch.pose.to(pred.dtype)
    terms: dict[str, Tensor] = {}
    terms["param"] = F.smooth_l1_loss(raw, batch.raw, reduction="none").sum(1).mean()
    terms["geodesic"] = (log_se3_geodesic(pred, true) + double_geodesic(pred, true)).mean()
    px_pred = renderer.project_fiducials(batch.subject, pred)
    px_true = renderer.project_fiducials(batch.subject, true)
    terms["fiducial"] = ((px_pred - px_true).norm(dim=-1).mean(1) / renderer.image_px).mean()
    terms["view_ce"] = F.cross_entropy(logits.float(), batch.view)
    total = weights.param * terms["param"] + weights.geodesic * terms["geodesic"] + weights.view * terms["view_ce"]
    total = total + weights.vessel * terms["fiducial"]
    if weights.render:
        rendered = renderer(batch.subject, pred)
        terms["mncc"] = mncc_similarity(normalize_minmax(rendered[:, TOTAL : TOTAL + 1]), normalize_minmax(batch.target[:, TOTAL : TOTAL + 1])).mean()
        terms["vessel_dice"] = generalized_dice_loss(
            soft_vessel_mask(rendered[:, VESSELS : VESSELS + 1]), soft_vessel_mask(batch.target[:, VESSELS : VESSELS + 1])
        ).mean()
        total = total - weights.mncc * terms["mncc"] + weights.vessel * terms["vessel_dice"]
    return total, {k: float(v.detach()) for k, v in terms.items()}


def refine_loss(raw: Tensor, batch: Batch, weights: LossWeights) -> tuple[Tensor, dict[str, float]]:
    """Refine objective: supervised raw residual term and the double geodesic of the corrected pose
    ``inverse(D_pred) @ noisy`` to the true pose."""
    raw = raw.float()
    terms: dict[str, Tensor] = {}
    terms["param"] = F.smooth_l1_loss(raw, batch.raw, reduction="none").sum(1).mean()
    corrected = torch.linalg.inv(residual_tensor(raw)) @ batch.noisy_pose.to(raw.dtype)
    terms["geodesic"] = double_geodesic(corrected, batch.pose.to(raw.dtype)).mean()
    total = weights.param * terms["param"] + weights.geodesic * terms["geodesic"]
    return total, {k: float(v.detach()) for k, v in terms.items()}
