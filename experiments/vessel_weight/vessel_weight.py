"""Should the CTA's vessel channel weigh each vessel voxel by its density, or by its contrast above blood?

The TTO's vessel term compares each run's vessel image with the DRR of the vessel channel: today the CTA's density
inside the vessel mask (``render/volume.py``). A run's vessel image shows iodine, the HU a voxel gains over unenhanced
blood; the density gives a partial-volume rim (150-200 HU) and a vein (160-360 HU in the phantom) nearly the weight of
an artery's lumen (250-600 HU). This script weighs each vessel voxel by ``max(HU - base, 0)`` instead (``--base-hu``;
omitted: today's density) and measures, per held-out phantom, the default TTO started at the true pose (the
benchmark's drift row; masks computed from the CTA, the opacified vessels read there), as
``selection_oracle.py`` does. One JSON line per phantom.

    .venv/bin/python experiments/vessel_weight/vessel_weight.py --seeds 6020-6031 --base-hu 40 --doc /tmp/w40.jsonl
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "vessel_mask"))

BASE_HU = None
if "--base-hu" in sys.argv:  # read before the shared parser sees the command line
    i = sys.argv.index("--base-hu")
    BASE_HU = float(sys.argv[i + 1])
    del sys.argv[i:i + 2]

from selection_oracle import DROPPED, drift_rows  # noqa: E402

from geopose.render import volume as V  # noqa: E402
from geopose.render.density import DensityScale  # noqa: E402


def excess(scale: DensityScale, hu: np.ndarray) -> np.ndarray:
    """``max(HU - BASE_HU, 0)`` in density units (the scale's span): a vessel voxel's contrast above blood."""
    return np.maximum(np.asarray(hu, dtype=np.float32) - np.float32(BASE_HU), 0.0) / np.float32(scale.span_hu)


def channels(self, factors, masked, total=True):
    """``RenderVolume._channels`` with the vessel channel weighted by :func:`excess`."""
    fi, fj, fk = factors
    K = self.cta.array.shape[0]
    masks = [self.mask(name) for name in V.CHANNELS[1:]] if masked else []
    step = V.SLAB_SLICES * fk
    parts = [[] for _ in range(int(total) + len(masks))]
    for k0 in range(0, K, step):
        k1 = min(K, k0 + step)
        dens = self.density_slab(k0, k1)
        if total:
            parts[0].append(V.block_mean(dens, (fk, fj, fi)))
        for c, (name, m) in enumerate(zip(V.CHANNELS[1:], masks), start=int(total)):
            values = excess(self.scale, self.cta.array[k0:k1]) if name == "vessels" else dens
            slab = values * m[k0:k1] if m is not None else np.zeros_like(dens)
            parts[c].append(V.block_mean(slab, (fk, fj, fi)))
    return np.stack([np.concatenate(p, axis=0) for p in parts])


def with_vessels(self, kept_kji):
    """``RenderVolume.with_vessels`` with the kept voxels weighted by :func:`excess`."""
    apply = DensityScale.apply
    DensityScale.apply = lambda scale, hu: excess(scale, hu)  # the method's one use of it: the kept voxels' values
    try:
        return ORIGINAL_WITH_VESSELS(self, kept_kji)
    finally:
        DensityScale.apply = apply


ORIGINAL_WITH_VESSELS = V.RenderVolume.with_vessels


def main() -> None:
    if BASE_HU is not None:
        V.RenderVolume._channels = channels
        V.RenderVolume.with_vessels = with_vessels

    def computed(read) -> None:
        read.drop = DROPPED["computed"]

    label = "density" if BASE_HU is None else f"excess over {BASE_HU:g} HU"
    drift_rows({label: computed}, __doc__.splitlines()[0], "6020-6031")


if __name__ == "__main__":
    main()
