"""Projection-space calibration and calibrated Init (``calibration.py``) with an oracle Init network."""

from __future__ import annotations

import numpy as np
from conftest import blob_renderer
from register_helpers import ORACLE_RENDER_PX, OracleInit

from geopose import contract as C
from geopose.geometry import isopose, pose_from_params
from geopose.register import calibrate, calibrated_init, render_model_view


def test_calibration_with_perfect_network_recovers_native_pose():
    renderer = blob_renderer()
    g = np.random.default_rng(5)
    A = pose_from_params(g.normal(0, 0.2, 3), g.normal(0, 20, 3))
    t_cal = isopose(C.VIEW_PA)
    T_true = pose_from_params(np.array([1.5, 0.05, -0.1]), np.array([3.0, 700.0, -5.0]))
    A_inv = np.linalg.inv(A)
    oracle = OracleInit([A_inv @ t_cal, A_inv @ T_true])
    cal = calibrate(renderer, oracle, ORACLE_RENDER_PX)
    np.testing.assert_allclose(cal.frame_transfer, A, atol=1e-9)
    # The calibration image is the min-max DRR at the PA isopose in the model geometry.
    assert oracle.images[0].shape == (1, 1, C.MODEL_DETECTOR_PX, C.MODEL_DETECTOR_PX)
    np.testing.assert_allclose(oracle.images[0], render_model_view(renderer, t_cal, ORACLE_RENDER_PX))
    est = calibrated_init(np.random.rand(1, 1, 256, 256), True, oracle, cal)
    np.testing.assert_allclose(est.pose_native, T_true, atol=1e-9)
    assert est.view == C.VIEW_LAT_PLUS
