"""Candidate starts of one patient pose (``starts.py``): greedy Refine's starts."""

from __future__ import annotations

import numpy as np
from register_helpers import RIG, _patient

from geopose.register.biplane import fuse_patient_poses
from geopose.register.init import InitStage
from geopose.register.starts import refine_starts


def test_refine_starts_pair_every_rotation_with_every_isocentre():
    pa, lat = _patient((6.0, -2.0, 1.0), (12.0, -3.0, 40.0)), _patient((-1.0, 4.0, -2.0), (-5.0, 30.0, 2.0))
    fused = fuse_patient_poses({"pa": pa, "lat": lat}, RIG)
    starts = refine_starts(InitStage({}, {"pa": pa, "lat": lat}, fused, 0.0))
    assert len(starts) == 9
    np.testing.assert_allclose(next(iter(starts.values())), fused, atol=1e-12)  # the fused pose comes first
    sources = {"fused": fused, "PA": pa, "LAT": lat}
    for r in sources:
        for t in sources:
            X = starts[f"rotation {r}, isocentre {t}"]
            np.testing.assert_allclose(X[:3, :3], sources[r][:3, :3], atol=1e-12)
            np.testing.assert_allclose(X[:3, 3], sources[t][:3, 3], atol=1e-12)
            np.testing.assert_allclose(X[3], [0, 0, 0, 1])
