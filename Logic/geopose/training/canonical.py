"""Canonical population: rigid alignment of training CTAs to one template CTA.

As in the paper, each CTA is registered to the template with an *affine*
transform on binary masks (cranium or brain), and the affine's linear part is
projected to the nearest rotation (SVD); the image is then resampled on the
template grid (linear for HU, nearest for labels). No ground truth is used.

Frames: transforms returned here map *centred* points of the moving CTA
(RAS axes, origin at its voxel-grid centre, mm) to centred points of the
template, i.e. they are estimates of a phantom's ``native_to_canonical`` when
the template is a canonical CTA.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from ..cta.io import sitk_from_volume, volume_from_sitk
from ..volume import Volume

#: HU written where a resampled CTA has no data (air).
OUTSIDE_HU = -1024.0
#: The masks are compared as signed distance maps clamped to this range (mm).
DISTANCE_CLAMP_MM = 20.0
#: Multi-resolution pyramid: shrink factors and smoothing sigmas (voxels).
SHRINK_FACTORS = (2, 1)
SMOOTHING_SIGMAS = (1.0, 0.0)
#: Masks are registered on grids of at least this voxel size (mm).
REGISTRATION_SPACING_MM = 4.0
#: Optimiser iterations per pyramid level and initial step (physical-shift scaled).
ITERATIONS = 200
LEARNING_RATE = 0.5
#: RAS <-> LPS (SimpleITK's physical frame): flip x and y.
_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation (det +1) nearest to a 3x3 matrix in the Frobenius norm (SVD projection)."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=float))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _distance_image(mask: Volume) -> sitk.Image:
    """Signed distance (mm, negative inside) to the mask surface, clamped to +-DISTANCE_CLAMP_MM."""
    image = sitk_from_volume(mask.like((mask.array > 0).astype(np.uint8)))
    spacing = np.asarray(image.GetSpacing())
    if spacing.min() < REGISTRATION_SPACING_MM:
        coarse = np.maximum(spacing, REGISTRATION_SPACING_MM)
        size = [max(1, int(round(n * s / c))) for n, s, c in zip(image.GetSize(), spacing, coarse)]
        origin = np.asarray(image.TransformContinuousIndexToPhysicalPoint([(c / s - 1) / 2 for s, c in zip(spacing, coarse)]))
        image = sitk.Resample(
            sitk.Cast(image, sitk.sitkFloat32), size, sitk.Transform(), sitk.sitkLinear, tuple(origin),
            tuple(float(c) for c in coarse), image.GetDirection(), 0.0, sitk.sitkFloat32,
        ) > 0.5
    dist = sitk.SignedMaurerDistanceMap(image, insideIsPositive=False, squaredDistance=False, useImageSpacing=True)
    return sitk.Clamp(sitk.Cast(dist, sitk.sitkFloat32), sitk.sitkFloat32, -DISTANCE_CLAMP_MM, DISTANCE_CLAMP_MM)


def _mask_centroid_ras(mask: Volume) -> np.ndarray:
    idx = np.argwhere(mask.array > 0)
    if len(idx) == 0:
        raise ValueError("the mask is empty: canonicalisation needs a non-empty cranium or brain mask")
    kji = idx.mean(0)
    return (mask.ijk_to_ras @ np.array([kji[2], kji[1], kji[0], 1.0]))[:3]


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`align_to_template`.

    ``moving_to_template`` (4x4, rigid) maps centred moving points to centred
    template points (mm); ``affine_moving_to_template`` is the affine before the
    rotation projection; ``metric`` the final mean-squares value of the masks.
    """

    moving_to_template: np.ndarray
    affine_moving_to_template: np.ndarray
    metric: float


def _ras_affine_from_sitk(transform: sitk.AffineTransform) -> np.ndarray:
    """SimpleITK's fixed(LPS)->moving(LPS) affine as a 4x4 in RAS (fixed -> moving)."""
    A = np.asarray(transform.GetMatrix(), dtype=float).reshape(3, 3)
    c = np.asarray(transform.GetCenter(), dtype=float)
    t = np.asarray(transform.GetTranslation(), dtype=float)
    m = np.eye(4)
    m[:3, :3] = A
    m[:3, 3] = c + t - A @ c
    return _LPS @ m @ _LPS


def _register(fixed: sitk.Image, moving: sitk.Image, initial: sitk.Transform) -> tuple[sitk.Transform, float]:
    """Multi-resolution mean-squares registration from ``initial``; the optimised transform and metric."""
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMeanSquares()
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(
        learningRate=LEARNING_RATE, minStep=1e-4, numberOfIterations=ITERATIONS, relaxationFactor=0.7
    )
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(list(SHRINK_FACTORS))
    reg.SetSmoothingSigmasPerLevel(list(SMOOTHING_SIGMAS))
    reg.SetInitialTransform(initial, inPlace=False)
    result = reg.Execute(fixed, moving)
    return sitk.CompositeTransform(result).GetNthTransform(0), float(reg.GetMetricValue())


def align_to_template(moving_mask: Volume, template_mask: Volume) -> Alignment:
    """Affine registration of two binary masks (as clamped signed distance maps, mean squares), projected to a rigid transform.

    A rigid stage (moments initialisation) starts the affine stage.
    The rotation is the SVD projection of the affine's linear part; the translation
    keeps the image of the template mask's centroid, so the rigid and affine maps
    agree there.
    """
    fixed = _distance_image(template_mask)
    moving = _distance_image(moving_mask)
    rigid_init = sitk.CenteredTransformInitializer(
        fixed, moving, sitk.Euler3DTransform(), sitk.CenteredTransformInitializerFilter.MOMENTS
    )
    rigid_stage, _ = _register(fixed, moving, rigid_init)
    affine_init = sitk.AffineTransform(3)
    affine_init.SetCenter(rigid_stage.GetCenter())
    affine_init.SetMatrix(rigid_stage.GetMatrix())
    affine_init.SetTranslation(rigid_stage.GetTranslation())
    affine_t, metric = _register(fixed, moving, affine_init)
    affine_t = sitk.AffineTransform(affine_t)
    template_to_moving_ras = _ras_affine_from_sitk(affine_t)  # template RAS -> moving RAS (affine)
    R_inv = nearest_rotation(template_to_moving_ras[:3, :3])
    anchor = _mask_centroid_ras(template_mask)
    rigid = np.eye(4)
    rigid[:3, :3] = R_inv
    rigid[:3, 3] = (template_to_moving_ras @ np.append(anchor, 1.0))[:3] - R_inv @ anchor
    # centred frames: x_ras = centred_to_ras @ x_centred
    moving_to_template = np.linalg.inv(template_mask.centred_to_ras) @ np.linalg.inv(rigid) @ moving_mask.centred_to_ras
    affine = np.linalg.inv(template_mask.centred_to_ras) @ np.linalg.inv(template_to_moving_ras) @ moving_mask.centred_to_ras
    return Alignment(moving_to_template, affine, metric)


def resample_to_template(volume: Volume, template: Volume, moving_to_template: np.ndarray, *, labels: bool = False) -> Volume:
    """``volume`` resampled on the template grid through a centred moving->template transform.

    Linear interpolation with ``OUTSIDE_HU`` outside for images; nearest neighbour
    and 0 outside for label maps (``labels=True``, voxel type kept).
    """
    # template RAS -> moving RAS
    ras_map = volume.centred_to_ras @ np.linalg.inv(moving_to_template) @ np.linalg.inv(template.centred_to_ras)
    lps_map = _LPS @ ras_map @ _LPS
    transform = sitk.AffineTransform(3)
    transform.SetMatrix(tuple(float(v) for v in lps_map[:3, :3].ravel()))
    transform.SetTranslation(tuple(float(v) for v in lps_map[:3, 3]))
    reference = sitk_from_volume(template.like(np.zeros(template.array.shape, dtype=np.uint8)))
    source = sitk_from_volume(volume)
    out = sitk.Resample(
        source,
        reference,
        transform,
        sitk.sitkNearestNeighbor if labels else sitk.sitkLinear,
        0.0 if labels else OUTSIDE_HU,
        source.GetPixelID(),
    )
    result = volume_from_sitk(out, {**volume.metadata, "frame": "canonical"})
    array = result.array.astype(volume.array.dtype, copy=False)
    return Volume(array, template.ijk_to_ras.copy(), result.metadata)


def rigid_error(estimate: np.ndarray, truth: np.ndarray, radius_mm: float = 80.0) -> dict[str, float]:
    """Rotation error (deg), translation error at the origin (mm) and the largest
    displacement (mm) over a sphere of ``radius_mm`` about the origin (head-sized)."""
    delta = estimate @ np.linalg.inv(truth)
    cos = np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1.0, 1.0)
    angle = float(np.arccos(cos))
    shift = float(np.linalg.norm(delta[:3, 3]))
    return {
        "rotation_deg": float(np.degrees(angle)),
        "translation_mm": shift,
        "max_displacement_mm": shift + 2 * radius_mm * float(np.sin(angle / 2)),
    }
