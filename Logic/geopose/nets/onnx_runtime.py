"""GeoPose-Init and GeoPose-Refine on onnxruntime with numpy in and out (no PyTorch).

The graphs come from :func:`geopose.nets.export_onnx` (shipped beside the torch
files, see ``manifest.py``). The view rule and the decoding of raw outputs into
poses are the numpy twins of ``decoding.py`` (same contract constants, checked
against it in ``Testing/Python/test_torch_free.py``). Poses are camera-to-world
``(B, 4, 4)`` float64 in the centred CTA frame (mm).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

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
from ..geometry.numpy_poses import pose_from_params
from .manifest import verify_manifest
from .preprocess import normalize_minmax

__all__ = [
    "KIND_METADATA_KEY", "OnnxInit", "OnnxRefine", "onnx_predictors", "mirror_averaged_logits", "select_view", "decode_init_pose",
    "residual_from_raw",
]

#: Key of the ONNX metadata entry that records the network kind (written by ``export_onnx``).
KIND_METADATA_KEY = "geopose_kind"


def mirror_averaged_logits(logits: np.ndarray, mirrored_logits: np.ndarray) -> np.ndarray:
    """``(B, 3)`` logits averaged with those of the column-mirrored images, re-indexed by ``MIRRORED_VIEW``."""
    return 0.5 * (logits + mirrored_logits[:, list(MIRRORED_VIEW)])


def select_view(logits: np.ndarray, is_lateral: np.ndarray | bool | None) -> np.ndarray:
    """View labels ``(B,)`` from ``(B, 3)`` logits: metadata PA stays PA, lateral takes the
    larger of LAT-/LAT+; without metadata (``None``) the argmax over all three."""
    if is_lateral is None:
        return logits.argmax(axis=1)
    lateral = np.broadcast_to(np.asarray(is_lateral, dtype=bool).reshape(-1), (logits.shape[0],))
    side = np.where(logits[:, VIEW_LAT_PLUS] > logits[:, VIEW_LAT_MINUS], VIEW_LAT_PLUS, VIEW_LAT_MINUS)
    return np.where(lateral, side, VIEW_PA)


def decode_init_pose(raw: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Init raw ``(B, 6)`` + views ``(B,)`` -> poses: Euler ZYX ``raw[:3] + (anchor, 0, 0)`` rad,
    ``t = raw[3:] * INIT_TRANSLATION_SCALE_MM + ISO_TRANSLATION_MM`` (rotated frame, mm)."""
    raw = np.asarray(raw, dtype=np.float64)
    r = raw[:, :3].copy()
    r[:, 0] += np.asarray(VIEW_ANCHOR_RAD)[view]
    return pose_from_params(r, raw[:, 3:] * INIT_TRANSLATION_SCALE_MM + np.asarray(ISO_TRANSLATION_MM))


def residual_from_raw(raw: np.ndarray) -> np.ndarray:
    """Refine raw ``(B, 6)`` -> residuals ``D`` ``(B, 4, 4)`` (axis-angle rad, rotated-frame mm);
    apply as ``inverse(D) @ T``."""
    raw = np.asarray(raw, dtype=np.float64)
    w = raw[:, :3] * np.asarray(REFINE_ROTATION_SCALE_RAD)
    dt = raw[:, 3:] * np.asarray(REFINE_TRANSLATION_SCALE_MM)
    return pose_from_params(w, dt, rotation="axis_angle")


class _Session:
    """An onnxruntime session of one GeoPose graph, checked for its kind and image size."""

    kind = ""

    def __init__(self, model: bytes | str | os.PathLike, use_cuda: bool = False) -> None:
        import onnxruntime as ort

        providers = ["CPUExecutionProvider"]
        if use_cuda:
            if "CUDAExecutionProvider" in ort.get_available_providers():
                providers.insert(0, "CUDAExecutionProvider")
            else:
                warnings.warn("onnxruntime has no CUDA provider here; running on CPU (install onnxruntime-gpu for CUDA)")
        self.session = ort.InferenceSession(model if isinstance(model, bytes) else os.fspath(model), providers=providers)
        kind = self.session.get_modelmeta().custom_metadata_map.get(KIND_METADATA_KEY)
        if kind is None:
            raise ValueError(f"the ONNX model has no '{KIND_METADATA_KEY}' entry; export it with geopose.nets.export_onnx")
        if kind != self.kind:
            raise ValueError(f"this ONNX model is a GeoPose-{kind.title()} network, not GeoPose-{self.kind.title()}")
        self.image_shape = tuple(self.session.get_inputs()[0].shape[1:])

    def images(self, name: str, image: np.ndarray) -> np.ndarray:
        """``(B, 1, H, W)`` min-max normalised float32, with the (H, W) the graph was exported for."""
        image = np.asarray(image)
        if image.ndim != 4 or tuple(image.shape[1:]) != self.image_shape:
            raise ValueError(
                f"{name} must be a (B, {', '.join(map(str, self.image_shape))}) batch for this ONNX model, got shape "
                f"{image.shape}; resample to the model detector or export the model for this size"
            )
        return normalize_minmax(image.astype(np.float32))


class OnnxInit(_Session):
    """GeoPose-Init: image ``(B, 1, 256, 256)`` -> pose ``(B, 4, 4)``, view ``(B,)``, logits ``(B, 3)``."""

    kind = "init"

    def predict(
        self, image: np.ndarray, is_lateral: np.ndarray | bool | None = None, mirror: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``mirror``: view logits averaged with the column-mirrored images' (see ``InitNet.predict``)."""
        image = self.images("image", image)
        batch = len(image)
        if mirror:
            image = np.concatenate((image, image[..., ::-1]))
        raw_all, logits = self.session.run(None, {"image": np.ascontiguousarray(image)})
        raw_all, logits = raw_all[:batch], (mirror_averaged_logits(logits[:batch], logits[batch:]) if mirror else logits)
        view = select_view(logits, is_lateral)
        return decode_init_pose(raw_all[np.arange(len(view)), view], view), view, logits


class OnnxRefine(_Session):
    """GeoPose-Refine: (target, render ``(B, 1, 256, 256)``, view) -> residual ``D`` ``(B, 4, 4)``."""

    kind = "refine"

    def predict_residual(self, target: np.ndarray, render: np.ndarray, view: np.ndarray | int) -> np.ndarray:
        target, render = self.images("target", target), self.images("render", render)
        if len(target) != len(render):
            raise ValueError(f"target has {len(target)} images and render {len(render)}; pass pairs")
        labels = np.broadcast_to(np.asarray(view, dtype=np.int64).reshape(-1), (len(target),)).copy()
        if ((labels < 0) | (labels >= len(VIEW_NAMES))).any():
            raise ValueError(f"view labels must be in 0..{len(VIEW_NAMES) - 1} ({', '.join(VIEW_NAMES)}), got {labels.tolist()}")
        (raw,) = self.session.run(None, {"target": target, "render": render, "view": labels})
        return residual_from_raw(raw)


def onnx_predictors(
    source: str | os.PathLike | Mapping[str, bytes | str | os.PathLike], use_cuda: bool = False
) -> tuple[OnnxInit, OnnxRefine]:
    """Init and Refine runners from a model folder (ONNX files checked against its manifest)
    or from ``{"init": graph, "refine": graph}`` (paths or bytes)."""
    if isinstance(source, Mapping):
        if set(source) != {"init", "refine"}:
            raise ValueError(f"ONNX graphs must be given for both 'init' and 'refine', got {sorted(source)}")
        files = dict(source)
    else:
        files = verify_manifest(Path(source), fmt="onnx")
    return OnnxInit(files["init"], use_cuda), OnnxRefine(files["refine"], use_cuda)
