"""Which voxels of the computed vessel mask are arteries: a small per-voxel classifier.

The contrast-threshold mask (``masks.py``) holds every enhancing lumen: the arteries a DSA run shows, but also the
venous sinuses, the jugular veins and partial-volume rims (on phantoms about 70 % of it). Each of its voxels is
described by fourteen numbers, all in mm or HU and independent of which side of the head it lies on (the mirror test
compares a CTA with its mirror image): its HU, the mean HU of its 2 mm block and those means smoothed at 3 mm (a
vessel's size and brightness), the same three divided by the mask's median HU (the subject's own contrast, which varies
between patients and scans), its depth inside the mask and the deepest depth in the blocks around it (thickness),
its distance to dense bone, its depth inside the cranium mask and its distance outside it, and its place in the
cranium's box (left-right as the distance from the midline). A two-layer perceptron
(``Resources/Models/artery_classifier.json``, trained by ``geopose train arteries --phantoms 100-131 --spacing 1 2``
on phantoms whose arteries are known) gives each the probability of being artery; voxels at or above the file's
threshold are kept. Pure numpy: no torch at run time.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ..errors import InputError
from ..volume import Volume

__all__ = ["FEATURES", "ArteryClassifier", "artery_features", "keep_arteries", "load_artery_classifier",
           "default_classifier_path"]

#: The per-voxel features, in order (units: HU / 300, mm / 3 or mm / 10, a share of the cranium's half-extent; the
#: ``*_over_mask_median`` HU divided by the median HU of the mask's voxels).
FEATURES = ("hu", "block_mean_hu", "block_hu_smoothed_3mm", "depth_in_mask", "deepest_block_depth_within_2_blocks",
            "distance_to_dense_bone", "depth_in_cranium", "distance_outside_cranium",
            "distance_from_midline", "anterior", "superior",
            "hu_over_mask_median", "block_mean_hu_over_mask_median", "block_hu_smoothed_3mm_over_mask_median")
#: Dense bone (HU) for the bone-distance feature.
BONE_HU = 700.0
#: The features other than the HU and the depth inside the mask are measured on blocks of about this (mm).
BLOCK_MM = 2.0
#: Reach (blocks, a cube) over which the mask's deepest depth is taken; Gaussian smoothing of the blocks' HU (mm).
THICKNESS_REACH_BLOCKS, SMOOTHING_MM = 2, 3.0
#: Distances are capped here (mm): beyond it a voxel is simply far.
BONE_CAP_MM, CRANIUM_CAP_MM = 30.0, 40.0


def default_classifier_path() -> Path:
    from ..resources import default_models_dir
    return default_models_dir() / "artery_classifier.json"


@dataclass(frozen=True)
class ArteryClassifier:
    """A perceptron ``features -> probability of artery``: ``layers`` of (weight ``(out, in)``, bias ``(out,)``), ReLU
    between them, a logistic output; voxels at or above ``threshold`` are arteries. ``sha256`` of the file it came from."""

    layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    threshold: float
    sha256: str
    training: dict

    def probability(self, features: np.ndarray) -> np.ndarray:
        """Probability of artery for each row of ``features`` ``(N, len(FEATURES))`` (float32)."""
        h = np.asarray(features, np.float32)
        for n, (w, b) in enumerate(self.layers):
            h = h @ w.T + b
            if n < len(self.layers) - 1:
                np.maximum(h, 0.0, out=h)
        return 1.0 / (1.0 + np.exp(-h[:, 0]))

    def as_json(self) -> dict:
        return {"features": list(FEATURES), "threshold": self.threshold, "training": self.training,
                "layers": [{"weight": w.tolist(), "bias": b.tolist()} for w, b in self.layers]}


@lru_cache(maxsize=4)
def load_artery_classifier(path: str | Path | None = None) -> ArteryClassifier:
    """The classifier in ``path`` (default: the shipped one); an :class:`InputError` when it is unreadable or was made
    for other features."""
    path = Path(path) if path is not None else default_classifier_path()
    try:
        raw = path.read_bytes()
        data = json.loads(raw)
        layers = tuple((np.asarray(layer["weight"], np.float32), np.asarray(layer["bias"], np.float32)) for layer in data["layers"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"the artery classifier {path} cannot be read ({exc}): reinstall GeoPose or retrain it with "
                         "`geopose train arteries`") from None
    if tuple(data.get("features", ())) != FEATURES or layers[0][0].shape[1] != len(FEATURES):
        raise InputError(f"the artery classifier {path} was made for other features: retrain it with `geopose train arteries`")
    return ArteryClassifier(layers, float(data["threshold"]), hashlib.sha256(raw).hexdigest(), dict(data.get("training", {})))


def _image(array: np.ndarray, spacing_mm) -> sitk.Image:
    image = sitk.GetImageFromArray(np.ascontiguousarray(array))
    image.SetSpacing(tuple(float(s) for s in spacing_mm))
    return image


def _distance_mm(mask: np.ndarray, spacing_mm, inside: bool) -> np.ndarray:
    """ITK's signed Maurer distance (mm) to the outermost voxels of ``mask``: of the voxels inside it (``inside``; 0 on
    that layer, about the radius less a voxel at a tube's axis) or of those outside it (not ``inside``); 0 elsewhere."""
    d = sitk.SignedMaurerDistanceMap(_image(mask.astype(np.uint8), spacing_mm), insideIsPositive=inside,
                                     squaredDistance=False, useImageSpacing=True)
    return np.maximum(sitk.GetArrayFromImage(d), 0.0)


def _blocks(array: np.ndarray, factors: tuple[int, int, int], reduce: np.ufunc) -> np.ndarray:
    """``array`` ([k, j, i]) reduced over blocks of ``factors`` (k, j, i) voxels by ``reduce`` (``np.add``: the mean;
    ``np.maximum``), the grid padded with its edge values to whole blocks."""
    pad = [(0, (-n) % f) for n, f in zip(array.shape, factors)]
    a = np.pad(array, pad, mode="edge") if any(p for _, p in pad) else array
    parts = [a[dk::factors[0], dj::factors[1], di::factors[2]]
             for dk in range(factors[0]) for dj in range(factors[1]) for di in range(factors[2])]
    if reduce is np.add:
        return np.add.reduce([p.astype(np.float32) for p in parts]) / len(parts)
    return reduce.reduce(parts)


def artery_features(hu: Volume, mask: np.ndarray, cranium: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`FEATURES` ``(N, 14)`` float32 of the ``N`` voxels of ``mask`` ([k, j, i] bool on ``hu``'s grid), and
    their indices ``(N, 3)`` [k, j, i]. ``cranium`` ([k, j, i] bool): the cranium mask (``cranium_mask_from_cta``).
    The depth inside the mask is measured on ``hu``'s grid, the rest on blocks of about :data:`BLOCK_MM` (their mean
    HU; a block is mask, bone or cranium where any of its voxels is): 0.6 s on the 1 mm 256^3 phantom 6010, 2 cores."""
    a = np.asarray(hu.array, np.float32)
    spacing = np.asarray(hu.spacing_mm, float)  # i, j, k
    idx = np.argwhere(mask)
    if not len(idx) or not cranium.any():
        return np.zeros((len(idx), len(FEATURES)), np.float32), idx
    factors = tuple(max(1, int(round(BLOCK_MM / s))) for s in spacing[::-1])  # k, j, i
    coarse_spacing = spacing * np.asarray(factors[::-1])
    k, j, i = idx.T
    kc, jc, ic = (idx // np.asarray(factors)).T
    to_centred = hu.ijk_to_centred
    head_blocks = _blocks(cranium, factors, np.maximum)
    block_centres = np.argwhere(head_blocks) * np.asarray(factors) + (np.asarray(factors) - 1) / 2.0  # [k, j, i]
    head = block_centres[:, ::-1] @ to_centred[:3, :3].T + to_centred[:3, 3]
    centre = head.mean(axis=0)
    half = np.maximum((np.percentile(head, 98, axis=0) - np.percentile(head, 2, axis=0)) / 2.0, 1.0)
    place = ((idx[:, ::-1] @ to_centred[:3, :3].T + to_centred[:3, 3]) - centre) / half
    place[:, 0] = np.abs(place[:, 0])
    box = tuple(slice(max(0, int(lo) - 1), int(hi) + 2) for lo, hi in zip(idx.min(axis=0), idx.max(axis=0)))
    depth = np.zeros(a.shape, np.float32)
    depth[box] = _distance_mm(mask[box], spacing, inside=True)
    deepest = sitk.GetArrayFromImage(sitk.GrayscaleDilate(_image(_blocks(depth, factors, np.maximum), coarse_spacing),
                                                          [THICKNESS_REACH_BLOCKS] * 3, sitk.sitkBox))
    mean_hu = _blocks(a, factors, np.add)
    smoothed = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(_image(mean_hu, coarse_spacing), SMOOTHING_MM))
    bone = _blocks(a > BONE_HU, factors, np.maximum)
    bone_mm = np.minimum(_distance_mm(bone, coarse_spacing, inside=False), BONE_CAP_MM) if bone.any() \
        else np.full(bone.shape, BONE_CAP_MM, np.float32)
    inside = np.minimum(_distance_mm(head_blocks, coarse_spacing, inside=True), CRANIUM_CAP_MM)
    outside = np.minimum(_distance_mm(head_blocks, coarse_spacing, inside=False), CRANIUM_CAP_MM)
    hu_columns = [a[k, j, i] / 300.0, mean_hu[kc, jc, ic] / 300.0, smoothed[kc, jc, ic] / 300.0]
    contrast = max(float(np.median(hu_columns[0])), 0.5)  # the mask's median HU / 300, at least the tree's 150 HU floor
    columns = [*hu_columns, depth[k, j, i] / 3.0, deepest[kc, jc, ic] / 3.0, bone_mm[kc, jc, ic] / 10.0,
               inside[kc, jc, ic] / 10.0, outside[kc, jc, ic] / 10.0, place[:, 0], place[:, 1], place[:, 2],
               *(c / contrast for c in hu_columns)]
    return np.stack(columns, axis=1).astype(np.float32), idx


def keep_arteries(hu: Volume, tree: np.ndarray, cranium: np.ndarray,
                  classifier: ArteryClassifier | None = None) -> tuple[np.ndarray, float]:
    """The voxels of ``tree`` ([k, j, i] bool, the contrast-threshold mask on ``hu``'s grid) the classifier (default:
    the shipped one) calls artery, as a bool array, and the share of ``tree`` they are."""
    classifier = classifier or load_artery_classifier()
    features, idx = artery_features(hu, tree, cranium)
    kept = np.zeros(tree.shape, dtype=bool)
    if len(idx):
        keep = classifier.probability(features) >= classifier.threshold
        kept[tuple(idx[keep].T)] = True
    return kept, float(kept.sum() / max(int(tree.sum()), 1))
