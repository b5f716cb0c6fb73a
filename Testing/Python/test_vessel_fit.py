"""The two-view emission fit (``register/vessel_fit.py``): which of the read vessel voxels the runs' images need."""

from __future__ import annotations

import numpy as np

from geopose.images import gaussian_blur
from geopose.register.vessel_fit import explaining, explaining_weights

SIZE = 64


def _views(points_xyz: np.ndarray) -> list[np.ndarray]:
    """Pixels (row, col) of points (x, y, z in px) in two orthogonal parallel views: PA sees (z, x), LAT (z, y)."""
    x, y, z = points_xyz.T
    return [np.c_[z, x + SIZE / 2], np.c_[z, y + SIZE / 2]]


def _images(points_xyz: np.ndarray) -> list[np.ndarray]:
    """Each view's image of ``points_xyz``: unit splats at their pixels, blurred by 0.7 px."""
    out = []
    for at in _views(points_xyz):
        image = np.zeros((SIZE, SIZE))
        np.add.at(image, (np.round(at[:, 0]).astype(int), np.round(at[:, 1]).astype(int)), 1.0)
        out.append(gaussian_blur(image, (0.7, 0.7)))
    return out


def test_a_sleeve_round_an_artery_is_left_out_and_the_artery_kept():
    """An artery 2 px wide along z, wrapped by a sleeve 2 px out (a cavernous sinus round the ICA): every sleeve voxel
    projects off the artery in at least one view, so images drawn from the artery alone need the artery, not the sleeve."""
    z = np.arange(8, 56)
    artery = np.array([(x, y, k) for k in z for x in (0, 1) for y in (0, 1)], dtype=float)
    ring = [(x, y) for x in range(-2, 4) for y in range(-2, 4) if x in (-2, 3) or y in (-2, 3)]
    sleeve = np.array([(x, y, k) for k in z for x, y in ring], dtype=float)
    points = np.r_[artery, sleeve]
    keep = explaining(_views(points), _images(artery))
    assert keep[: len(artery)].mean() > 0.95, keep[: len(artery)].mean()
    assert keep[len(artery):].mean() < 0.1, keep[len(artery):].mean()
    # The fit reproduces the images: its projections explain them far better than the read's equal weights do.
    fitted = _misfit(points, explaining_weights(_views(points), _images(artery)), _images(artery))
    equal = _misfit(points, np.ones(len(points)), _images(artery))
    assert fitted < 0.2 and fitted < 0.5 * equal, (fitted, equal)


def _misfit(points: np.ndarray, weights: np.ndarray, images: list[np.ndarray]) -> float:
    """Summed over the views: |drawn - image| / |image|, each scaled to max 1, the points drawn with ``weights``."""
    total = 0.0
    for at, image in zip(_views(points), images):
        drawn = np.zeros((SIZE, SIZE))
        np.add.at(drawn, (np.round(at[:, 0]).astype(int), np.round(at[:, 1]).astype(int)), weights)
        drawn, image = gaussian_blur(drawn, (0.7, 0.7)), image / image.max()
        total += np.abs(drawn / drawn.max() - image).sum() / image.sum()
    return total


def test_no_voxels_none_kept():
    assert explaining([np.zeros((0, 2)), np.zeros((0, 2))], [np.ones((4, 4)), np.ones((4, 4))]).shape == (0,)
