"""Our renders of a real head against DiffDRR 0.6.x on the published path: the CT read from a
NIfTI *file* by ``diffdrr.data.read`` (torchio), rendered by ``diffdrr.drr.DRR`` with its
defaults (Siddon, ``reverse_x_axis=True``) at poses built by ``convert(..., "euler_angles",
"ZYX")``, as the public GeoPose code does (``registration/pipeline.py``, ``initialization.py``).
Same image at every isopose, never its mirror; the published LAT+ isopose shows the face at
the first columns (docs/conventions.md, section 7).

Runs where DiffDRR imports (``benchmarks/setup_diffdrr_env.sh``:
``.venv-diffdrr/bin/python -m pytest Testing/Python/test_conventions_diffdrr.py``); skipped elsewhere.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("diffdrr.drr", reason="DiffDRR is not installed here (see benchmarks/setup_diffdrr_env.sh)")

from geopose import contract as C  # noqa: E402
from geopose.cta import load_cta, save_volume  # noqa: E402
from geopose.geometry import Detector, isopose  # noqa: E402
from geopose.render import DRR  # noqa: E402
from test_conventions import headsq  # noqa: E402,F401  (fixture)
from conventions_common import TEETH_HU, face_side_of_render  # noqa: E402  (on the path via test_conventions)

#: Siddon (nearest voxel) against trilinear on the 3.2 mm headsq grid (test_render_diffdrr: 0.98).
NCC_MIN = 0.98
DETECTOR_PX = 64
#: The render's dissimilarity (1 - NCC) to DiffDRR's must be this fraction of its mirror's at most.
MIRROR_RATIO = 0.2


def _ncc(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double().flatten(), b.double().flatten()
    a, b = (a - a.mean()) / a.std(), (b - b.mean()) / b.std()
    return float((a * b).mean())


@pytest.fixture(scope="module")
def nifti_files(headsq, tmp_path_factory):
    """headsq written as NIfTI files (CT in HU, teeth mask), as the published pipeline reads them."""
    cta, labels = headsq
    folder = tmp_path_factory.mktemp("nifti")
    ct_path = save_volume(cta, folder / "headsq_0000.nii.gz")
    mask_path = save_volume(cta.like((labels.array == 1).astype(np.uint8)), folder / "headsq_teeth.nii.gz")
    return ct_path, mask_path


def test_isopose_renders_match_diffdrr_read_from_a_nifti_file(nifti_files):
    from diffdrr.data import read
    from diffdrr.drr import DRR as DiffDRR

    torch.set_num_threads(2)
    ct_path, mask_path = nifti_files
    det = Detector.model().resized(DETECTOR_PX)
    theirs = DiffDRR(read(str(ct_path), str(mask_path), labels=[0, 1]), sdd=det.sdd_mm, height=det.rows, delx=det.spacing_mm[1])
    teeth = DiffDRR(read(str(ct_path), str(mask_path), labels=[1]), sdd=det.sdd_mm, height=det.rows, delx=det.spacing_mm[1])
    cta = load_cta(ct_path)  # our reader on the very same file
    ours = DRR.from_volume(cta, det)
    cols = torch.arange(det.cols, dtype=torch.float64)
    for view in (C.VIEW_LAT_MINUS, C.VIEW_PA, C.VIEW_LAT_PLUS):
        r = torch.tensor([[C.VIEW_ANCHOR_RAD[view], 0.0, 0.0]])
        t = torch.tensor([C.ISO_TRANSLATION_MM])
        with torch.no_grad():
            d = theirs(r, t, parameterization="euler_angles", convention="ZYX")[0, 0]
            d_teeth = teeth(r, t, parameterization="euler_angles", convention="ZYX")[0, 0].double()
            a = ours(torch.as_tensor(isopose(view))[None])[0, 0]
        same, mirrored = _ncc(a, d), _ncc(a.flip(-1), d)
        name = C.VIEW_NAMES[view]
        assert same >= NCC_MIN, f"{name}: NCC {same:.4f} with DiffDRR's render of the NIfTI file"
        # Far nearer the same image than its mirror (a head is nearly symmetric in a PA).
        assert 1 - same < MIRROR_RATIO * (1 - mirrored), f"{name}: NCC {same:.4f}, mirrored {mirrored:.4f}"
        # The face (teeth) on the same side in both; the published LAT+ isopose puts it at the first columns.
        their_teeth = float((d_teeth.sum(0) * cols).sum() / d_teeth.sum())
        their_head = float((d.double().sum(0) * cols).sum() / d.double().sum())
        if view != C.VIEW_PA:
            assert np.sign(their_teeth - their_head) == (-1.0 if view == C.VIEW_LAT_PLUS else 1.0), name


def test_teeth_side_agrees_with_our_label_channels(headsq):
    """The face-side measure of test_conventions (our label channels) on the same head:
    LAT+ first columns, LAT- last columns, as DiffDRR above."""
    cta, labels = headsq
    det = Detector.model().resized(DETECTOR_PX)
    assert (cta.array > TEETH_HU).any()
    plus = face_side_of_render(cta, labels, torch.as_tensor(isopose(C.VIEW_LAT_PLUS))[None], det)
    minus = face_side_of_render(cta, labels, torch.as_tensor(isopose(C.VIEW_LAT_MINUS))[None], det)
    assert plus < -5 and minus > 5
