"""Which of the CTA's vessels the runs show opacified (``opacified.py``), on a phantom with a selective
left ICA injection."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import _prepared

from geopose.geometry import invert
from geopose.phantom.cli import written_injected_arteries
from geopose.register.biplane import nominal_poses


def test_the_opacified_vessels_read_near_the_truth_are_the_injected_ones(unilateral_case):
    """Read at the true pose, the kept vessel voxels are mostly the injected arteries (against a fifth
    of all vessels), most of those are kept; read 60 mm off, too few pass and all vessels stay."""
    from geopose.register.opacified import read_opacified, vessel_shift_mm

    truth, runs, prep, _ = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    views = [(k, prep.views[k].tto_vessels, prep.views[k].tto_detector) for k in rig]
    vessels, injected = prep.volume.mask("vessels"), written_injected_arteries(unilateral_case)
    X = truth.poses["pa"] @ invert(rig["pa"])
    selection = read_opacified(prep.volume, X, rig, views)
    kept = selection.keep
    assert selection.applied and not (kept & ~vessels).any()
    base = injected[vessels].mean()
    precision, recall = injected[kept].mean(), kept[injected & vessels].mean()
    assert base < 0.3 and precision > 0.6 and recall > 0.5, (base, precision, recall)
    np.testing.assert_array_equal(selection.volume.mask("vessels"), kept)
    # How far a run's pose places the kept vessels from where they were read: a 10 mm shift is 10 mm.
    far = X.copy()
    far[:3, 3] += [6.0, 0.0, 8.0]
    assert vessel_shift_mm(prep.volume, selection, X) == pytest.approx(0.0, abs=1e-9)
    assert vessel_shift_mm(prep.volume, selection, far) == pytest.approx(10.0, abs=1e-6)
    far[:3, 3] += [54.0, 0.0, 52.0]
    missed = read_opacified(prep.volume, far, rig, views)
    assert not missed.applied and missed.keep.sum() == vessels.sum() and missed.volume is None
    assert read_opacified(prep.volume, X, rig, [(k, np.zeros_like(v), d) for k, v, d in views]) is None
