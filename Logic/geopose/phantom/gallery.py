"""``geopose phantom-gallery``: the picture ``docs/phantoms.png`` of a few phantom subjects.

Per subject (one row): axial, coronal and sagittal CTA slices, PA and lateral
DRRs (model geometry, isoposes), and for the simulated PA and LAT runs one
DSA frame (attenuation-like, at the bolus peak) and the MAP. Row ``n`` shows the
run ``ROW_RUNS[n % len(ROW_RUNS)]``: two routine injections, then the dense runs
(the ``avm`` row's subject is drawn with its AVM).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from ..geometry.detector import Detector
from ..geometry.poses import isopose
from ..render import DRR
from .. import contract as C
from .dsa import DENSE_RUNS, dsa_renderer, sample_biplane, simulate_dsa
from .subject import make_subject

__all__ = ["make_gallery", "register"]

COLUMNS = ("axial", "coronal", "sagittal", "DRR PA", "DRR LAT", "DSA frame PA", "MAP PA", "DSA frame LAT", "MAP LAT")
ROW_RUNS = ("cca_left", "ica_right", "all_territories", "avm", "late_venous")


def make_gallery(seeds: list[int], out: Path, *, spacing_mm: float = 1.0) -> Path:
    """Render the gallery of subjects ``seeds`` to ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(seeds), len(COLUMNS), figsize=(2.2 * len(COLUMNS), 2.4 * len(seeds)))
    axes = np.atleast_2d(axes)
    for row, seed in enumerate(seeds):
        injection = ROW_RUNS[row % len(ROW_RUNS)]
        s = make_subject(seed, spacing_mm=spacing_mm, pathology=DENSE_RUNS[injection].pathology if injection in DENSE_RUNS else None)
        hu = s.cta.array
        K, J, I = hu.shape
        iso = np.rint(np.linalg.inv(s.cta.ijk_to_centred) @ np.append(s.isocentre_native_mm, 1.0))[:3].astype(int)
        sp = s.cta.spacing_mm
        win = dict(cmap="gray", vmin=-100, vmax=500, origin="lower")
        axes[row, 0].imshow(hu[min(K - 1, iso[2] + int(35 / sp[2]))], **win)
        axes[row, 1].imshow(hu[:, iso[1]], aspect=sp[2] / sp[0], **win)
        axes[row, 2].imshow(hu[:, :, iso[0]], aspect=sp[2] / sp[1], **win)
        drr = DRR.from_volume(s.cta, Detector.model(), step_mm=1.5)
        imgs = drr(torch.as_tensor(np.stack([isopose(C.VIEW_PA), isopose(C.VIEW_LAT_PLUS)])))[:, 0].detach().numpy()
        for n in range(2):
            axes[row, 3 + n].imshow(imgs[n], cmap="gray")
        rng = np.random.default_rng([seed, 2])
        acqs, iso_mm = sample_biplane(rng, s)
        ren = dsa_renderer(s, injection)
        for n, acq in enumerate(acqs):
            sim = simulate_dsa(s, acq, acq.pose(iso_mm), rng, injection=injection, drr=ren, max_matrix_px=512)
            att = sim.run.attenuation()
            peak = int(np.argmax(att.reshape(len(att), -1).mean(1)))
            axes[row, 5 + 2 * n].imshow(att[peak], cmap="gray")
            axes[row, 6 + 2 * n].imshow(sim.map, cmap="gray")
        axes[row, 0].set_ylabel(f"seed {seed}\n{injection}")
    for c, name in enumerate(COLUMNS):
        axes[0, c].set_title(name, fontsize=9)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def _run(args: argparse.Namespace) -> int:
    print(make_gallery(args.seeds, Path(args.out), spacing_mm=args.spacing_mm))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("phantom-gallery", help="render docs/phantoms.png: slices, DRRs, DSA frames and MAPs of phantom subjects")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="one row each; the runs cycle through ROW_RUNS")
    p.add_argument("--out", default="docs/phantoms.png")
    p.add_argument("--spacing-mm", type=float, default=1.0)
    p.set_defaults(func=_run)
