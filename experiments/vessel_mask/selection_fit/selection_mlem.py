"""Drift of the default TTO started at the truth (masks computed, as ``selection_oracle.py``) when the opacified read's
selection is thinned by a two-view emission fit: the kept voxels' weights w >= 0 fitted by MLEM so that their
projections (bilinear splats, blurred by ``--blur``) explain each view's vessel image; a voxel stays when its weight
reaches a share of the weights' 90th percentile. Veins that wrap an artery project outside its lumen in at least one
view, where the artery alone explains the image. One JSON line per seed (the "selection" counts after the fit).

    .venv/bin/python experiments/vessel_mask/selection_fit/selection_mlem.py --seeds 6020-6028 --doc OUT.jsonl
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tto_schedule" / "turned_starts"))  # default_path_rows

from selection_oracle import ARTERIES, L, OracleRead, VEINS, drift_rows  # noqa: E402

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.geometry.poses import project_points  # noqa: E402
from geopose.images import gaussian_blur  # noqa: E402
from geopose.register import opacified  # noqa: E402

ITERATIONS = 30


def pipeline_parser(description: str, blur_px: float) -> argparse.ArgumentParser:
    """The pipeline variants' shared options: the fit's ``--blur`` (px) and ``--share``, ``--seeds``, ``--out``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--blur", type=float, default=blur_px)
    ap.add_argument("--share", type=float, default=0.05)
    ap.add_argument("--seeds", type=seed_range, default=seed_range("6030-6049"))
    ap.add_argument("--out", required=True)
    return ap


def splats(pixels: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices and weights ``(N, 4)`` of each point's bilinear splat (0 weight outside the image)."""
    h, w = shape
    r0, c0 = np.floor(pixels[:, 0]), np.floor(pixels[:, 1])
    fr, fc = pixels[:, 0] - r0, pixels[:, 1] - c0
    idx, wts = [], []
    for dr, wr in ((0, 1 - fr), (1, fr)):
        for dc, wc in ((0, 1 - fc), (1, fc)):
            r, c = r0.astype(int) + dr, c0.astype(int) + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            idx.append(np.where(inside, np.clip(r, 0, h - 1) * w + np.clip(c, 0, w - 1), 0))
            wts.append(np.where(inside, wr * wc, 0.0))
    return np.stack(idx, 1), np.stack(wts, 1)


def best_shift(image: np.ndarray, target: np.ndarray, max_px: float) -> np.ndarray:
    """The (row, col) shift (px, within ``max_px``) of ``image`` that best correlates it with ``target``: the peak of
    their circular cross-correlation, refined by a parabola per axis."""
    a, b = image - image.mean(), target - target.mean()
    corr = np.real(np.fft.ifft2(np.conj(np.fft.fft2(a)) * np.fft.fft2(b)))
    h, w = corr.shape
    r = np.fft.fftfreq(h, 1 / h)[:, None]
    c = np.fft.fftfreq(w, 1 / w)[None, :]
    corr = np.where((np.abs(r) <= max_px) & (np.abs(c) <= max_px), corr, -np.inf)
    i, j = np.unravel_index(np.argmax(corr), corr.shape)
    out = []
    for axis_corr, k, n in ((corr[:, j], i, h), (corr[i, :], j, w)):
        lo, mid, hi = axis_corr[(k - 1) % n], axis_corr[k], axis_corr[(k + 1) % n]
        den = lo - 2 * mid + hi
        out.append((k if k <= n // 2 else k - n) + (0.5 * (lo - hi) / den if np.isfinite(den) and den < 0 else 0.0))
    return np.array(out)


def mlem_weights(points_mm, patient, rig, views, blur_px: float, iterations: int = ITERATIONS,
                 shift_px: float = 0.0) -> np.ndarray:
    """Per point, its MLEM weight explaining every view's vessel image (``views``: name, image, detector); with
    ``shift_px`` each view's projections first moved by the shift (within it) that best aligns them with the image."""
    systems = []
    for name, image, det in views:
        y = np.clip(np.asarray(image, dtype=np.float64), 0, None)
        y /= max(y.max(), 1e-12)
        pixels, _ = project_points(np.asarray(patient) @ rig[name], det, points_mm)
        if shift_px > 0:
            idx, wts = splats(pixels, y.shape)
            drawn = gaussian_blur(np.bincount(idx.ravel(), wts.ravel(), y.size).reshape(y.shape), (max(blur_px, 1.0),) * 2)
            pixels = pixels + best_shift(drawn, y, shift_px)
        idx, wts = splats(pixels, y.shape)
        sens = _back(np.ones_like(y), idx, wts, blur_px)
        systems.append((y, idx, wts, sens))
    w = np.ones(len(points_mm))
    for _ in range(iterations):
        ratio_sum, sens_sum = 0.0, 0.0
        for y, idx, wts, sens in systems:
            forward = gaussian_blur(np.bincount(idx.ravel(), (wts * w[:, None]).ravel(), y.size).reshape(y.shape),
                                    (blur_px, blur_px)) if blur_px > 0 else \
                np.bincount(idx.ravel(), (wts * w[:, None]).ravel(), y.size).reshape(y.shape)
            ratio_sum = ratio_sum + _back(y / np.maximum(forward, 1e-6 * forward.max()), idx, wts, blur_px)
            sens_sum = sens_sum + sens
        w = w * ratio_sum / np.maximum(sens_sum, 1e-12)
    return w


def _back(image: np.ndarray, idx: np.ndarray, wts: np.ndarray, blur_px: float) -> np.ndarray:
    image = gaussian_blur(image, (blur_px, blur_px)) if blur_px > 0 else image
    return (image.ravel()[idx] * wts).sum(1)


def keeping(selection: opacified.VesselSelection, volume, kept: np.ndarray) -> opacified.VesselSelection:
    """``selection`` (as read) with only the voxels ``kept`` (``[k, j, i]`` rows) in its vessel channel."""
    subset = volume.with_vessels(kept)
    return opacified.VesselSelection(subset.mask("vessels"), selection.vessel_voxels, len(kept), True, selection.start,
                                     selection.iteration, selection.patient_pose, kept, subset)


def thinned(volume, patient, rig, views, blur_px: float, share: float, **kwargs) -> opacified.VesselSelection | None:
    """The opacified read at ``patient`` (``opacified.read_opacified``), thinned to the voxels whose MLEM weight reaches
    ``share`` of the 90th percentile; as read where it was not applied."""
    selection = opacified.read_opacified(volume, patient, rig, views, **kwargs)
    if selection is None or not selection.applied:
        return selection
    images = [(n, im, det) for n, im, det in views if np.max(im) > 0]
    w = mlem_weights(volume.centred_points(selection.kept_kji), patient, rig, images, blur_px)
    return keeping(selection, volume, selection.kept_kji[w >= share * np.percentile(w, 90)])


class FittedRead(OracleRead):
    """The default read, then the MLEM fit keeps the voxels with weight >= ``share`` x the 90th percentile."""

    def __init__(self) -> None:
        super().__init__()
        self.share: float | None = None
        self.blur_px = 1.0
        self.shift_px = 0.0

    def __call__(self, volume, patient, rig, views, **kwargs):
        selection = opacified.read_opacified(volume, patient, rig, views, **kwargs)
        if selection is None or not selection.applied:
            return selection
        kept = selection.kept_kji
        if self.share is not None:
            images = [(n, im, det) for n, im, det in views if np.max(im) > 0]
            w = mlem_weights(volume.centred_points(kept), patient, rig, images, self.blur_px, shift_px=self.shift_px)
            kept = kept[w >= self.share * np.percentile(w, 90)]
        lab = self.labels[tuple(kept.T)]
        self.composition = {"arteries": int(np.isin(lab, ARTERIES).sum()), "veins outside the cranium":
                            int((lab == L.VENOUS_SINUS).sum()), "veins inside the cranium":
                            int((lab == L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET).sum()),
                            "other": int((~np.isin(lab, ARTERIES + VEINS)).sum())}
        return keeping(selection, volume, kept)


def fitting(share: float | None, blur_px: float = 1.0):
    def setup(read: FittedRead) -> None:
        read.share, read.blur_px = share, blur_px
    return setup


VARIANTS = {"computed": fitting(None), "mlem 0.05": fitting(0.05, 0.7), "mlem 0.1": fitting(0.1, 0.7)}

if __name__ == "__main__":
    drift_rows(VARIANTS, __doc__.splitlines()[0], "6020-6028", read=FittedRead())
