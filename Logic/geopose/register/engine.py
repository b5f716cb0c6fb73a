"""What a registration runs on (:class:`Engine`) and the case it runs on, set up together by
:func:`start_case`; :class:`StageClock` times the stages.

Both engines run the same stages: ``backend="torch"`` renders with the torch kernel and runs the
torch networks, ``"onnxruntime"`` renders with the numpy kernel and runs the shipped ONNX graphs;
only the kernel and the network runtime differ. The test-time optimisation needs PyTorch: on the
torch-free engine it is skipped with a note.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator, Mapping

import numpy as np

from ..dependencies import torch_available
from ..dsa import DSARun
from ..errors import InputError
from ..nets.predictors import ModelSet, load_models, resolve_torch_device
from ..options import TTO_PX_CPU, TTO_PX_CUDA, RegistrationOptions
from ..render.renderer import Renderer, TorchRenderer, make_renderer
from ..render.volume import RENDER_GRID_MM
from ..render.work import counting
from ..volume import Volume
from .case import PreparedCase, prepare_case
from .progress import Monitor

__all__ = ["NO_TORCH_TTO_NOTE", "SPINNING_THREADS_NOTE", "Engine", "StageClock", "engine_notes", "resolve_engine",
           "finest_level_mm", "start_case", "torch_renderer_for"]

#: Said (progress, record, Slicer table) when the test-time optimisation cannot run.
NO_TORCH_TTO_NOTE = ("PyTorch is not installed: calibration, Init and Refine ran on onnxruntime; the test-time "
                     "optimisation needs PyTorch and was skipped")
#: Said when PyTorch's idle OpenMP threads spin (``geopose.OPENMP_THREADS_SLEEP`` False).
SPINNING_THREADS_NOTE = ("PyTorch was imported before GeoPose without OMP_WAIT_POLICY=PASSIVE, so its idle threads "
                         "spin: with other work on this machine a registration can take 10x longer (two at once on 2 "
                         "cores: 173 s each, against 15 s alone); set OMP_WAIT_POLICY=PASSIVE before starting Python "
                         "(or Slicer), or import geopose before torch")


def engine_notes() -> list[str]:
    """What the user should know about how this process computes (:data:`SPINNING_THREADS_NOTE`), for the record."""
    from .. import OPENMP_THREADS_SLEEP  # read when called

    return [SPINNING_THREADS_NOTE] if torch_available() and not OPENMP_THREADS_SLEEP else []


def torch_renderer_for(renderer: Renderer) -> TorchRenderer | None:
    """The differentiable renderer of ``renderer``'s volume (itself when it is one; on the CPU,
    sharing the volume's arrays, when it is the numpy one); None without PyTorch."""
    if isinstance(renderer, TorchRenderer):
        return renderer
    return TorchRenderer(renderer.volume, "cpu") if torch_available() else None


class Engine:
    """The renderer, the networks, the size (px) of the DRRs the networks see, and (when PyTorch is
    there) the differentiable renderer of the test-time optimisation."""

    def __init__(self, renderer: Renderer, models: ModelSet, render_px: int) -> None:
        self.renderer = renderer
        self.models = models
        self.render_px = render_px
        self.tto_renderer = torch_renderer_for(renderer)

    @property
    def device(self) -> str:
        return str(getattr(self.renderer, "device", "cpu"))

    def synchronize(self) -> None:
        """Wait for queued CUDA work, so a timing boundary measures it (no-op on the CPU)."""
        if self.device.startswith("cuda"):
            import torch

            torch.cuda.synchronize(self.device)

    def describe(self, options: RegistrationOptions, case: PreparedCase) -> dict:
        """The engine as the result record states it."""
        return {
            "backend": self.models.runtime,
            "renderer": self.renderer.engine,
            "device": self.device,
            "tto": "torch" if self.tto_renderer is not None else "skipped (PyTorch not installed)",
            "render_px": self.render_px,
            "tto_px": case.views["pa"].tto_detector.shape,
            "model_clip_percentiles": list(options.model_clip_percentiles or self.models.clip_percentiles),
            "models": self.models.files,
            "cta_render_grid_mm": [round(s, 3) for s in case.volume.cta.spacing_mm],
            "finest_level_mm": case.volume.finest_spacing_mm,
            "cta_levels_mm": {"x".join(map(str, f)): [round(s, 3) for s in lvl.spacing_mm]
                              for f, lvl in case.volume.levels.items()},
        }


class StageClock:
    """Seconds per stage (``times``), each measured to the end of its queued GPU work, and the rendering each
    stage did (``work``: renders, rays, ray points and ns per point, ``render.work``)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.times: dict[str, float] = {}
        self.work: dict[str, dict] = {}

    @contextmanager
    def __call__(self, name: str, engine: Engine | None = None) -> Iterator[None]:
        t0 = time.perf_counter()
        with counting() as work:
            yield
            if engine is not None:
                engine.synchronize()
        self.times[name] = time.perf_counter() - t0
        self.work[name] = work.as_dict(self.times[name])

    def elapsed_s(self) -> float:
        """Seconds since the clock started."""
        return time.perf_counter() - self.start

    def total(self) -> dict[str, float]:
        """The stage times with ``total``, the seconds since the clock started."""
        return self.times | {"total": self.elapsed_s()}


def resolve_engine(
    options: RegistrationOptions, models: str | ModelSet | None = None, *, allow_unverified: bool = False
) -> tuple[str, str, ModelSet]:
    """``(backend, device, models)`` for ``options``: ``auto`` takes torch when it is installed,
    CUDA when present; the networks come from ``models`` (a folder, default the shipped models,
    or an already loaded :class:`ModelSet`, which must match the backend; ``allow_unverified``:
    a folder without a manifest)."""
    has_torch = torch_available()
    backend = options.backend if options.backend != "auto" else ("torch" if has_torch else "onnxruntime")
    if backend == "torch" and not has_torch:
        raise InputError("backend 'torch' was asked for but PyTorch is not installed: install PyTorch, or use "
                         "backend 'onnxruntime' (Init + Refine without the test-time optimisation)")
    if backend == "torch":
        device = str(resolve_torch_device(options.device))
    else:
        device = "cuda" if options.device.startswith("cuda") else "cpu"
    if isinstance(models, ModelSet):
        if models.runtime != backend:
            raise InputError(f"the loaded models run on {models.runtime} but backend {backend!r} was asked for; "
                             "load them with the same runtime")
        return backend, device, models
    return backend, device, load_models(models, runtime=backend, device=device, allow_unverified=allow_unverified)


def finest_level_mm(tto_px: int) -> float:
    """The finest CTA level (mm) the renderers sample unless ``options.work_spacing_mm`` says: the render grid
    (:data:`RENDER_GRID_MM`) for TTO images at the models' resolution (:data:`TTO_PX_CUDA`), coarser in proportion
    to smaller ones (2 mm at a CPU's 128 px). A level is chosen per view from its pixels' footprint at the head; at
    128 px that footprint is 1.2-1.9 mm, so 1.5 footprints straddle the 2 mm level's bound and, without this bound,
    the few geometries below it rendered the 1 mm level: twice the ray points and 1.3-2x the registration's time, for
    0.007 mm of mean accuracy on validation phantoms (``experiments/render_level/render_level.md``)."""
    return RENDER_GRID_MM * TTO_PX_CUDA / tto_px


def start_case(
    cta: Volume, dsa: Mapping[str, DSARun], options: RegistrationOptions, models: str | ModelSet | None, *,
    cranium_mask: Volume | None, segmentation: Volume | None, dsa_masks: Mapping[str, np.ndarray] | None,
    monitor: Monitor,
) -> tuple[Engine, PreparedCase]:
    """The engine ``options`` ask for and the case prepared for it (``case.py``; the TTO images at
    256 px on CUDA, 128 on a CPU, unless ``options.tto.px`` says; the finest level :func:`finest_level_mm`
    unless ``options.work_spacing_mm`` says); the CTA's masks are being made on another thread
    (``RenderVolume.make_masks_ahead``)."""
    backend, device, model_set = resolve_engine(options, models)
    tto_px = options.tto.px or (TTO_PX_CUDA if device.startswith("cuda") else TTO_PX_CPU)
    case = prepare_case(
        cta, dsa, cranium_mask=cranium_mask, segmentation=segmentation, dsa_masks=dsa_masks, tto_px=tto_px,
        model_clip_percentiles=options.model_clip_percentiles or model_set.clip_percentiles,
        work_spacing_mm=options.work_spacing_mm or finest_level_mm(tto_px), monitor=monitor,
    )
    case.volume.make_masks_ahead()  # on another thread while calibration, Init, Refine and the search render
    renderer = make_renderer(case.volume, "torch" if backend == "torch" else "numpy", device)
    return Engine(renderer, model_set, options.render_px or model_set.render_px), case
