"""Training batches rendered from a population in the model geometry, on the population's device.

Images are rendered on a detector with the model's field of view (256 x 1.2 mm,
SDD 1020 mm) sampled at ``render_px`` pixels and resized (bilinear) to
``image_px``: rendering at a lower resolution trades detail for speed on CPUs.
A *bank* pre-renders a fixed set of samples once and draws batches from it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import torch
from torch import Tensor
from torch.nn import functional as F

from ..contract import MODEL_DETECTOR_PX
from ..geometry.carm import project_points_tensor
from ..geometry.detector import Detector
from ..geometry.rigid import RigidTransform
from ..render import DRR
from .population import CHANNELS, TrainingSubject
from .poses import PerturbationScale, sample_init_poses, sample_refine_perturbations, sample_views


@dataclass
class Batch:
    """One training batch (B samples) on the training device.

    ``target``: ``(B, C, H, W)`` line integrals (density x mm) at the true pose,
    channels as ``CHANNELS``; ``pose`` the true poses ``(B, 4, 4)``; ``raw`` the
    head's raw target ``(B, 6)``; for Refine ``render`` is the total-density DRR
    ``(B, 1, H, W)`` at ``noisy_pose = D @ pose``.
    """

    subject: Tensor
    view: Tensor
    pose: Tensor
    raw: Tensor
    target: Tensor
    render: Tensor | None = None
    noisy_pose: Tensor | None = None

    def index(self, idx: Tensor) -> "Batch":
        return Batch(**{f.name: (None if getattr(self, f.name) is None else getattr(self, f.name)[idx]) for f in fields(self)})

    def to(self, device: torch.device | str) -> "Batch":
        return Batch(**{f.name: (None if getattr(self, f.name) is None else getattr(self, f.name).to(device)) for f in fields(self)})


class Renderer:
    """One DRR module per subject; renders ``(B, C, image_px, image_px)`` for (subject, pose) pairs."""

    def __init__(self, subjects: list[TrainingSubject], render_px: int, image_px: int = MODEL_DETECTOR_PX) -> None:
        if not subjects:
            raise ValueError("the training population is empty")
        self.subjects = subjects
        self.detector = Detector.model().resized(render_px)
        self.image_detector = Detector.model().resized(image_px)
        self.image_px = image_px
        self.drrs = [DRR(s.channels, s.ijk_to_world, self.detector, channel_names=CHANNELS) for s in subjects]

    def __call__(self, subject: Tensor, pose: Tensor, channels: slice = slice(None)) -> Tensor:
        out = None
        for index in torch.unique(subject).tolist():
            sel = (subject == index).nonzero().squeeze(1)
            drr = self.drrs[index]
            images = drr(RigidTransform(pose[sel].to(drr.density.dtype)))[:, channels]
            if out is None:
                out = images.new_zeros(len(subject), images.shape[1], *images.shape[-2:])
            out = out.index_copy(0, sel, images)
        if self.detector.rows != self.image_px:
            out = F.interpolate(out, size=(self.image_px, self.image_px), mode="bilinear", align_corners=False)
        return out

    def project_fiducials(self, subject: Tensor, pose: Tensor) -> Tensor:
        """Pixels ``(B, N, 2)`` (row, col) of each subject's vessel fiducials on the image detector."""
        points = torch.stack([self.subjects[i].fiducials_mm for i in subject.tolist()]).to(pose.dtype)
        return project_points_tensor(RigidTransform(pose), self.image_detector, points)[0]


class OnTheFlySource:
    """Fresh poses and renders every batch (the GPU path)."""

    def __init__(self, renderer: Renderer, kind: str, perturbation: PerturbationScale | None = None) -> None:
        self.renderer = renderer
        self.kind = kind
        self.perturbation = perturbation or PerturbationScale()

    def batch(self, size: int, gen: torch.Generator) -> Batch:
        device = self.renderer.subjects[0].channels.device
        subject = torch.randint(0, len(self.renderer.subjects), (size,), generator=gen, device=device)
        view = sample_views(size, gen, device)
        pose, raw = sample_init_poses(view, gen)
        with torch.no_grad():
            target = self.renderer(subject, pose)
            if self.kind == "init":
                return Batch(subject, view, pose, raw, target)
            D, raw = sample_refine_perturbations(view, gen, self.perturbation)
            noisy = D @ pose
            render = self.renderer(subject, noisy, slice(0, 1))
        return Batch(subject, view, pose, raw, target, render, noisy)


class BankSource:
    """``size`` samples pre-rendered once (stored float16), batches drawn with replacement (the CPU path)."""

    def __init__(
        self, source: OnTheFlySource, size: int, gen: torch.Generator, chunk: int = 8,
        progress: Callable[[int, int], None] | None = None,
    ) -> None:
        """``progress(done, size)`` is called after each rendered chunk."""
        if size < 1:
            raise ValueError(f"bank size must be positive, got {size}")
        parts = []
        for start in range(0, size, chunk):
            parts.append(source.batch(min(chunk, size - start), gen))
            if progress is not None:
                progress(start + len(parts[-1].view), size)
        self.renderer = source.renderer
        self.bank = Batch(
            **{
                f.name: (
                    None
                    if getattr(parts[0], f.name) is None
                    else torch.cat([getattr(p, f.name) for p in parts]).to(
                        torch.float16 if f.name in ("target", "render") else getattr(parts[0], f.name).dtype
                    )
                )
                for f in fields(Batch)
            }
        )
        self.size = size

    def batch(self, size: int, gen: torch.Generator) -> Batch:
        device = self.bank.view.device
        idx = torch.randint(0, self.size, (size,), generator=gen, device=device)
        out = self.bank.index(idx)
        out.target = out.target.float()
        if out.render is not None:
            out.render = out.render.float()
        return out
