"""Held-out validation of trained networks on rendered phantom views (model geometry).

Poses are drawn like the training poses (isopose + recipe noise) with a fixed
seed; Init runs with the inference view rule (PA/lateral from metadata, side
from the logits); Refine is applied once to the Init poses.
"""

from __future__ import annotations

import numpy as np
import torch

from ..contract import VIEW_PA
from ..metrics import pose_errors, view_accuracy
from ..nets import InitNet, RefineNet
from ..nets.predictors import TorchInit, TorchRefine
from .data import OnTheFlySource, Renderer
from .losses import TOTAL
from .population import TrainingSubject

#: Images per forward pass during evaluation.
EVAL_CHUNK = 8


def _summary(errors) -> dict[str, float]:
    out = {}
    for name in ("rotation_deg", "translation_norm_mm", "source_distance_mm", "double_geodesic_mm"):
        values = getattr(errors, name)
        out[f"{name}_median"] = float(np.median(values))
        out[f"{name}_mean"] = float(values.mean())
    return out


@torch.no_grad()
def evaluate(
    init: InitNet,
    subjects: list[TrainingSubject],
    *,
    samples: int,
    seed: int,
    render_px: int,
    refine: RefineNet | None = None,
) -> dict:
    """Init (and Init + Refine x1) errors on ``samples`` views of held-out ``subjects``.

    Returns JSON-ready metrics: view accuracy (with the metadata rule and from logits
    alone), pose errors (deg, mm; median and mean) and, with ``refine``, the errors
    after one Refine step and the relative reduction of the median double geodesic.
    """
    renderer = Renderer(subjects, render_px)
    source = OnTheFlySource(renderer, "init")
    gen = torch.Generator(subjects[0].channels.device).manual_seed(seed)
    init_p = TorchInit(init)
    refine_p = TorchRefine(refine) if refine is not None else None
    poses, refs, views, chosen, argmax, refined = [], [], [], [], [], []
    for start in range(0, samples, EVAL_CHUNK):
        batch = source.batch(min(EVAL_CHUNK, samples - start), gen)
        target = batch.target[:, TOTAL : TOTAL + 1]
        pose, view, logits = init_p.predict(target.cpu().numpy(), (batch.view != VIEW_PA).cpu().numpy())
        pose, view, logits = (torch.as_tensor(a, device=target.device) for a in (pose, view, logits))
        poses.append(pose)
        refs.append(batch.pose)
        views.append(batch.view)
        chosen.append(view)
        argmax.append(logits.argmax(1))
        if refine_p is not None:
            render = renderer(batch.subject, pose.float(), slice(TOTAL, TOTAL + 1))
            D = refine_p.predict_residual(target.cpu().numpy(), render.cpu().numpy(), view.cpu().numpy())
            refined.append(torch.linalg.inv(torch.as_tensor(D, device=pose.device)) @ pose)
    ref = torch.cat(refs)
    metrics: dict = {
        "samples": samples,
        "subjects": [s.name for s in subjects],
        "seed": seed,
        "view_accuracy_with_metadata": view_accuracy(torch.cat(chosen).cpu(), torch.cat(views).cpu()),
        "view_accuracy_logits_only": view_accuracy(torch.cat(argmax).cpu(), torch.cat(views).cpu()),
        "init": _summary(pose_errors(torch.cat(poses).cpu(), ref.cpu())),
    }
    if refine is not None:
        after = _summary(pose_errors(torch.cat(refined).cpu(), ref.cpu()))
        metrics["init_refine1"] = after
        before = metrics["init"]["double_geodesic_mm_median"]
        metrics["refine_reduction_double_geodesic_median"] = 1.0 - after["double_geodesic_mm_median"] / before
    return metrics
