"""The registration objective (``objective.py``): the numpy score and the TTO's torch loss are one
objective, its view terms agree on numpy and torch arrays, and the fitted silhouette model."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import _perturb, _prepared

from geopose import contract as C
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.metrics import mncc
from geopose.phantom import labels as L
from geopose.register import TTOSchedule, prepare_case, test_time_optimise as run_tto
from geopose.register.biplane import nominal_poses
from geopose.register.objective import (SILHOUETTE_MODELS, SILHOUETTE_NOISE_EXPONENT, SILHOUETTE_NORM_PERCENTILE,
                                        Objective, clip_like_target, combine, fit_like_target, objective_value,
                                        silhouette_features, view_terms)
from geopose.register.tto import tto_views
from geopose.render.renderer import NumpyRenderer, TorchRenderer


def test_the_objective_is_the_same_in_numpy_and_in_the_tto(phantom_case):
    """The numpy score that picks the TTO's start and the torch loss the TTO minimises are one
    objective: every term agrees at the DICOM-angle pose and 5 deg / 10 mm away."""
    case = phantom_case
    cta = load_cta(case / "cta.nii.gz")
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    runs = {k: read_dsa(case / f"dsa_{k}.dcm") for k in ("pa", "lat")}
    prep = prepare_case(cta, runs, segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)), tto_px=96)
    rig = nominal_poses(runs)
    numpy_renderer, torch_renderer = NumpyRenderer(prep.volume), TorchRenderer(prep.volume)
    for X in (np.eye(4), _perturb(np.eye(4))):
        poses = {k: X @ rig[k] for k in rig}
        # every vessel in both (the TTO would read the opacified ones at its start)
        trace = run_tto(torch_renderer, tto_views(prep.views, poses), TTOSchedule(0), rig=rig,
                        objective=Objective(read_opacified=False)).trace[0]
        total = 0.0
        for key in rig:
            value = objective_value(numpy_renderer, poses[key], prep.views[key])
            got = trace["views"][key]
            # 3e-3: the two kernels' sampling differs most at the DSA mask's edge (2.6e-3 on the silhouette
            # mNCC once the mask stopped following the vessels, dsa.preprocess.dsa_cranium_mask)
            assert value.vessel_ncc is not None and got["vessel_ncc"] == pytest.approx(value.vessel_ncc, abs=3e-3)
            assert got["mncc"] == pytest.approx(value.mncc, abs=3e-3)
            assert got["dice_loss"] == pytest.approx(value.dice_loss, abs=3e-3)
            total += value.loss
        assert trace["loss"] == pytest.approx(total, abs=4e-3)


def test_view_terms_agree_on_numpy_and_torch_arrays_for_every_silhouette_model():
    """The one objective (objective.view_terms) on the same images gives the same terms in numpy and torch:
    only the similarity kernels are written twice. The torch loss also carries a gradient."""
    import torch

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:48, :40]
    total = np.exp(-((yy - 24) ** 2 + (xx - 20) ** 2) / 200.0) * 5 + rng.normal(0, 0.05, (48, 40))
    cranium = total * 4 - 2
    vessels = np.maximum(0, np.sin(xx / 3.0)) * (total > 1)
    target = np.clip(total + rng.normal(0, 0.3, total.shape), 0.5, 4)
    mask = total > 0.8
    vessel_target = vessels + rng.normal(0, 0.1, vessels.shape)
    for model in SILHOUETTE_MODELS:
        objective = Objective(silhouette=model)
        ours = view_terms(total, cranium, vessels, target, mask, vessel_target, objective)
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        image = t(total).requires_grad_(True)
        theirs = view_terms(image, t(cranium), t(vessels), t(target), t(mask), t(vessel_target), objective,
                            vessel_term=True, xp=torch)
        for a, b in zip(ours, theirs):
            assert float(b.detach()) == pytest.approx(float(a), abs=2e-4), model
        theirs[0].sum().backward()
        assert float(image.grad.abs().sum()) > 0, model
    no_vessels = view_terms(total, cranium, np.zeros_like(vessels), target, mask, vessel_target, Objective())
    assert no_vessels[3] is None and no_vessels[0] == pytest.approx(combine(Objective(), *no_vessels[1:3], None))


def test_the_fitted_silhouette_is_the_least_squares_combination_of_its_basis():
    """A target made of the basis (u, exp(2 min(u, 1)), 1; u the DRR over its 99.5th percentile in
    the mask) with non-negative weights is recovered exactly, zero outside the mask, in numpy and in
    the TTO's torch; a target that inverts the DRR gets no inverted image (only its mean); an unknown
    silhouette model is refused when the objective is built."""
    import torch

    rng = np.random.default_rng(3)
    drr = rng.gamma(2.0, 1.5, (40, 52))
    mask = np.zeros(drr.shape)
    mask[4:36, 6:48] = 1
    u = drr / np.quantile(drr[mask > 0], SILHOUETTE_NORM_PERCENTILE / 100)
    target = (0.4 + 1.3 * u + 0.25 * np.exp(SILHOUETTE_NOISE_EXPONENT * np.minimum(u, 1.0))) * mask
    np.testing.assert_allclose(silhouette_features(drr, mask)[1], np.exp(2.0 * np.minimum(u, 1.0)))
    fitted = fit_like_target(drr, target + 5.0 * (1 - mask), mask)  # what lies outside the mask is not fitted
    np.testing.assert_allclose(fitted, target, atol=1e-9)
    as_t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    np.testing.assert_allclose(fit_like_target(as_t(drr), as_t(target), as_t(mask), xp=torch).numpy(), target, atol=1e-4)
    inverted = fit_like_target(drr, (3.0 - u) * mask, mask)
    np.testing.assert_allclose(inverted[mask > 0], np.mean(3.0 - u[mask > 0]))
    with pytest.raises(ValueError, match="silhouette must be one of"):
        Objective(silhouette="clip")


def test_the_fitted_silhouette_explains_the_map_better_than_the_clipped_drr(phantom_case):
    """At the true pose of a simulated run, the noise-level model fitted to the MAP's silhouette
    matches it better (mNCC) than the DRR clipped like it, in both views."""
    truth, runs, prep, _ = _prepared(phantom_case)
    renderer = NumpyRenderer(prep.volume)
    for key, view in prep.views.items():
        (total,) = renderer.render(truth.poses[key], view.tto_detector, ("total",))
        mask = view.tto_mask > 0
        clipped = mncc(view.tto_image, clip_like_target(total, mask, C.MAP_CLIP_PERCENTILES))
        fitted = mncc(view.tto_image, fit_like_target(total, view.tto_image, mask))
        assert fitted > clipped + 0.03, (key, clipped, fitted)
