"""Training pipeline: canonicalisation, pose sampling, augmentation, losses, trainer, DDP, manifest."""

from __future__ import annotations

import argparse
import csv
import json
import os
import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from geopose.contract import VIEW_LAT_MINUS, VIEW_LAT_PLUS, VIEW_PA
from geopose.geometry.rigid import axis_angle_to_matrix
from geopose.metrics import double_geodesic_mm
from geopose.nets import build_model, load_model, load_models, read_model_header
from geopose.nets.predictors import TorchInit
from geopose.training.poses import init_pose_tensor, residual_tensor
from geopose.phantom import labels as L
from geopose.phantom import make_subject
from geopose.training import recipe as R
from geopose.training.augment import augment, clahe, dsa_map
from geopose.training.canonical import align_to_template, nearest_rotation, resample_to_template, rigid_error
from geopose.training.losses import double_geodesic, log_se3_geodesic
from geopose.errors import InputError
from geopose.training.manifest import model_entry, verify_manifest, write_manifest
from geopose.training.population import FIDUCIALS, load_population, save_population, subject_from_volumes
from geopose.training.poses import sample_init_poses, sample_refine_perturbations, sample_views
from geopose.training import cli as training_cli
from geopose.training.trainer import CHECKPOINT_NAME, LOG_NAME, TrainConfig, init_encoder_from, train
from geopose.volume import Volume

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "Resources" / "Models"


# ------------------------------------------------------------ canonicalisation
def _head_mask(native_to_canonical: np.ndarray, n: int = 56, spacing: float = 4.0) -> Volume:
    """An asymmetric head-like mask (skull ellipsoid, jaw, notch) seen through a known transform."""
    ijk = np.diag([spacing, spacing, spacing, 1.0])
    ijk[:3, 3] = -(n - 1) / 2 * spacing + np.array([5.0, -7.0, 12.0])
    vol = Volume(np.zeros((n, n, n), np.uint8), ijk)
    k, j, i = np.meshgrid(*(np.arange(n),) * 3, indexing="ij")
    pts = np.stack([i, j, k, np.ones_like(i)], -1).reshape(-1, 4).astype(float) @ vol.ijk_to_centred.T
    q = pts @ native_to_canonical.T
    skull = (q[:, 0] / 70) ** 2 + (q[:, 1] / 90) ** 2 + (q[:, 2] / 60) ** 2 < 1
    jaw = (q[:, 0] / 25) ** 2 + ((q[:, 1] - 40) / 30) ** 2 + ((q[:, 2] + 60) / 45) ** 2 < 1
    notch = ((q[:, 0] - 30) / 15) ** 2 + ((q[:, 1] + 50) / 15) ** 2 + ((q[:, 2] - 30) / 15) ** 2 < 1
    return vol.like(((skull | jaw) & ~notch).reshape(n, n, n).astype(np.uint8))


def test_nearest_rotation_projects_a_scaled_sheared_rotation():
    Rm = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)).numpy()
    A = Rm @ np.array([[1.1, 0.05, 0.0], [0.0, 0.95, 0.02], [0.0, 0.0, 1.03]])
    P = nearest_rotation(A)
    assert np.allclose(P @ P.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(P), 1.0)
    assert np.degrees(np.arccos((np.trace(P.T @ Rm) - 1) / 2)) < 3.0


def test_alignment_recovers_a_known_rigid_transform():
    truth = np.eye(4)
    truth[:3, :3] = axis_angle_to_matrix(torch.tensor([0.15, -0.1, 0.2], dtype=torch.float64)).numpy()
    truth[:3, 3] = [6.0, -4.0, 9.0]
    template, moving = _head_mask(np.eye(4)), _head_mask(truth)
    alignment = align_to_template(moving, template)
    error = rigid_error(alignment.moving_to_template, truth)
    assert error["rotation_deg"] < 2.0 and error["translation_mm"] < 3.0  # true rotation is 15.4 deg
    out = resample_to_template(moving, template, alignment.moving_to_template, labels=True)
    assert out.array.dtype == np.uint8 and out.array.shape == template.array.shape
    dice = 2 * (out.array & template.array).sum() / (out.array.sum() + template.array.sum())
    assert dice > 0.95
    assert np.array_equal(moving.array, _head_mask(truth).array)  # input not altered


def test_phantom_canonicalisation_against_known_native_to_canonical():
    _, template_labels = make_subject(0, spacing_mm=4.0).canonical(4.0)
    template = template_labels.like(L.cranium_mask(template_labels.array).astype(np.uint8))
    subject = make_subject(5, spacing_mm=4.0)
    mask = subject.labels.like(L.cranium_mask(subject.labels.array).astype(np.uint8))
    error = rigid_error(align_to_template(mask, template).moving_to_template, subject.native_to_canonical)
    assert error["rotation_deg"] < 4.0 and error["translation_mm"] < 6.0


def test_alignment_rejects_an_empty_mask():
    empty = _head_mask(np.eye(4)).like(np.zeros((56, 56, 56), np.uint8))
    with pytest.raises(ValueError, match="empty"):
        align_to_template(_head_mask(np.eye(4)), empty)


# -------------------------------------------------------------- pose sampling
def test_init_pose_sampling_follows_the_recipe_and_decodes_back():
    gen = torch.Generator().manual_seed(0)
    views = sample_views(6000, gen)
    frac = [(views == v).float().mean().item() for v in (VIEW_LAT_MINUS, VIEW_PA, VIEW_LAT_PLUS)]
    assert abs(frac[1] - R.PA_PROBABILITY) < 0.03 and abs(frac[0] - frac[2]) < 0.04
    pose, raw = sample_init_poses(views, gen)
    assert torch.allclose(init_pose_tensor(raw, views), pose, atol=1e-4)
    sd = raw.std(0)
    assert torch.allclose(sd[:3], torch.tensor(R.INIT_ROTATION_SD_RAD), rtol=0.06)
    assert torch.allclose(sd[3:] * 100, torch.tensor(R.INIT_TRANSLATION_SD_MM), rtol=0.06)


def test_refine_perturbation_raw_targets_rebuild_the_residual():
    gen = torch.Generator().manual_seed(1)
    views = sample_views(4000, gen)
    D, raw = sample_refine_perturbations(views, gen)
    assert torch.allclose(residual_tensor(raw), D, atol=1e-4)
    pa = views == VIEW_PA
    scale = torch.tensor(R.REFINE_PA_ROTATION_SD_RAD) / torch.tensor((0.13, 0.10, 0.14))
    assert torch.allclose(raw[pa, :3].std(0), scale, rtol=0.08)


# --------------------------------------------------------------- augmentation
def test_augmentation_shapes_ranges_and_reproducibility():
    x = torch.rand(6, 1, 64, 64) * 40.0
    cranium = torch.rand(6, 1, 64, 64) * 5.0
    before = x.clone()
    a = augment(x, torch.Generator().manual_seed(3), cranium)
    b = augment(x, torch.Generator().manual_seed(3), cranium)
    c = augment(x, torch.Generator().manual_seed(4), cranium)
    assert a.shape == x.shape and a.dtype == torch.float32
    assert torch.isfinite(a).all() and a.amin() >= 0 and a.amax() <= 1
    assert torch.allclose(a.flatten(1).amax(1), torch.ones(6))  # min-max per image
    assert torch.equal(a, b) and not torch.allclose(a, c)
    assert torch.equal(x, before)
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        augment(torch.rand(2, 3, 64, 64), torch.Generator())


def test_dsa_look_is_masked_clipped_and_shows_the_vessels():
    """augment.dsa_map: outside the head mask 0, the noise follows the attenuation (brighter where the
    head is thicker), the vessels stand out, and the same seed gives the same images."""
    yy, xx = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    head = torch.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / (2 * 14.0**2))
    x = head.expand(4, 1, 64, 64).clone()
    vessels = torch.zeros_like(x)
    vessels[..., 20:44, 30:32] = 1.0
    a = dsa_map(x, vessels, torch.Generator().manual_seed(1), (2.0, 98.0))
    b = dsa_map(x, vessels, torch.Generator().manual_seed(1), (2.0, 98.0))
    assert torch.equal(a, b) and a.shape == x.shape and a.amin() >= 0 and a.amax() <= 1
    outside = head.expand_as(x) < 0.05  # below every mask level the recipe draws
    assert (a[outside] == 0).all()
    centre, rim = a[..., 28:36, 20:28].mean(), a[..., 28:36, 6:12].mean()
    assert centre > rim  # thicker head, stronger noise maximum
    assert a[..., 24:40, 30:32].mean() > a[..., 24:40, 26:28].mean()  # the vessel column against its neighbour
    # augment sends exactly that share through it (dsa_p = 1: every image masked to 0 outside).
    c = augment(x, torch.Generator().manual_seed(2), vessels=vessels, dsa_p=1.0, clip=(2.0, 98.0))
    assert c.shape == x.shape and torch.isfinite(c).all()


def test_clahe_equalises_a_low_contrast_image():
    x = 0.4 + 0.1 * torch.rand(1, 1, 64, 64)
    y = clahe(x, torch.tensor([10.0]))
    assert y.shape == x.shape and y.amin() >= 0 and y.amax() <= 1
    assert y.std() > 3 * x.std()


# --------------------------------------------------------------------- losses
def test_geodesics_are_zero_at_the_truth_and_match_the_metric():
    gen = torch.Generator().manual_seed(2)
    views = sample_views(8, gen)
    pose, _ = sample_init_poses(views, gen)
    other, _ = sample_init_poses(views, gen)
    pred = pose.clone().requires_grad_(True)
    g = log_se3_geodesic(pred, pose) + double_geodesic(pred, pose)
    assert g.max() < 1e-3
    g.sum().backward()
    assert torch.isfinite(pred.grad).all()
    np.testing.assert_allclose(double_geodesic(other.double(), pose.double()).numpy(), double_geodesic_mm(other.numpy(), pose.numpy()), rtol=1e-4)
    assert (log_se3_geodesic(other, pose) > 0.05).all()


# ---------------------------------------------------------- population/trainer
@pytest.fixture(scope="module")
def tiny_population():
    subjects = []
    for seed in (1, 2):
        cta, labels = make_subject(seed, spacing_mm=5.0).canonical(5.0)
        subjects.append(subject_from_volumes(f"phantom-{seed}", cta, L.cranium_mask(labels.array), L.vessel_mask(labels.array), seed))
    return subjects


TINY = dict(batch_size=2, accumulation=2, depth=18, base_width=8, render_px=32, image_px=64, seed=5, checkpoint_every=1)


def test_population_cache_round_trip(tiny_population, tmp_path):
    path = save_population(tmp_path / "pop.pt", tiny_population, {"seeds": [1, 2]})
    subjects, recipe = load_population(path)
    assert recipe == {"seeds": [1, 2]} and [s.name for s in subjects] == ["phantom-1", "phantom-2"]
    assert subjects[0].channels.shape[0] == 3 and subjects[0].fiducials_mm.shape == (FIDUCIALS, 3)
    assert torch.allclose(subjects[0].channels, tiny_population[0].channels, atol=1e-3)
    with pytest.raises(InputError, match="does not exist"):
        load_population(tmp_path / "missing.pt")


def _rows(path: Path) -> list[dict]:
    with open(path) as handle:
        return list(csv.DictReader(handle))


def test_training_runs_logs_checkpoints_and_resumes(tiny_population, tmp_path):
    out = tmp_path / "run"
    config = TrainConfig("init", steps=2, **TINY)
    path = train(config, tiny_population, out, progress=False)
    rows = _rows(out / LOG_NAME)
    assert [int(r["step"]) for r in rows] == [1, 2]
    assert all(np.isfinite(float(r["loss"])) for r in rows) and {"view_ce", "geodesic", "fiducial"} <= set(rows[0])
    assert torch.load(out / CHECKPOINT_NAME, weights_only=True)["step"] == 2
    train(TrainConfig("init", steps=3, **TINY), tiny_population, out, progress=False)
    assert [int(r["step"]) for r in _rows(out / LOG_NAME)] == [1, 2, 3]
    assert torch.load(out / CHECKPOINT_NAME, weights_only=True)["step"] == 3
    header = read_model_header(path)
    assert header["metadata"]["training"]["steps_run"] == 3 and header["metadata"]["training"]["config"]["seed"] == 5
    net = load_model(path)
    pose, view, _ = TorchInit(net).predict(np.random.rand(1, 1, 64, 64))
    assert pose.shape == (1, 4, 4)
    with pytest.raises(ValueError, match="different configuration"):
        train(TrainConfig("init", steps=4, **{**TINY, "seed": 6}), tiny_population, out, progress=False)


def test_refine_training_starts_from_the_init_encoder(tiny_population, tmp_path, capsys):
    init_path = train(TrainConfig("init", steps=1, **TINY), tiny_population, tmp_path / "init", progress=False)
    config = TrainConfig("refine", steps=1, init_model=str(init_path), calibration_samples=4, bank_size=12, **TINY)
    path = train(config, tiny_population, tmp_path / "refine")
    # The bank is pre-rendered in chunks of 8, each reported (off a terminal: one line per tenth).
    err = capsys.readouterr().err
    assert "8/12 samples pre-rendered" in err and "12/12 samples pre-rendered" in err
    meta = read_model_header(path)["metadata"]["training"]
    lo, hi = R.CALIBRATION_CLAMP
    for got, base in zip(meta["perturbation"]["lat_translation_mm"], R.REFINE_LAT_TRANSLATION_SD_MM):
        assert lo * base - 1e-6 <= got <= hi * base + 1e-6
    assert len(_rows(tmp_path / "refine" / LOG_NAME)) == 1
    with pytest.raises(ValueError, match="init-model"):
        TrainConfig("refine", steps=1)


def test_a_stacked_refine_at_its_own_input_size_trains_ships_and_runs(tiny_population, tmp_path, capsys):
    init_path = train(TrainConfig("init", steps=1, **TINY), tiny_population, tmp_path / "init", progress=False)
    config = TrainConfig("refine", steps=1, init_model=str(init_path), calibration_samples=0, pairing="stacked",
                         **{**TINY, "image_px": 32})
    net = build_model(config.net_config())
    init_encoder_from(net, load_model(init_path))
    w = load_model(init_path).net.conv1.weight
    assert torch.equal(net.net.backbone.conv1.weight, torch.cat((w, -w), dim=1))  # starts out seeing differences
    refine_path = train(config, tiny_population, tmp_path / "refine", progress=False)
    models = tmp_path / "models"
    args = argparse.Namespace(init=init_path, refine=refine_path, metrics=None, models_dir=models, note=None)
    assert training_cli._ship(args) == 0
    manifest = json.loads((models / "manifest.json").read_text())["models"]
    assert manifest["refine"]["input"]["image_px"] == 32 and manifest["init"]["input"]["image_px"] == 64
    assert manifest["refine"]["input"]["pairing"] == "stacked"
    image = np.random.default_rng(4).random((2, 1, 256, 256)).astype(np.float32)
    residuals = {}
    for runtime in ("torch", "onnxruntime"):
        loaded = load_models(models, runtime=runtime)
        assert loaded.files["refine"]["image_px"] == 32 and loaded.files["init"]["image_px"] == 64
        residuals[runtime] = loaded.refine.predict_residual(image, image[..., ::-1], np.array([1, 2]))
    np.testing.assert_allclose(residuals["torch"], residuals["onnxruntime"], atol=2e-2)  # fp16 graph weights
    # Shipping one network keeps the other's entry (and file) as it was.
    init_entry = json.loads((models / "manifest.json").read_text())["models"]["init"]
    assert training_cli._ship(argparse.Namespace(**{**vars(args), "note": "first ship"})) == 0
    assert training_cli._ship(argparse.Namespace(**{**vars(args), "init": None, "note": "refine again"})) == 0
    manifest = json.loads((models / "manifest.json").read_text())
    assert manifest["models"]["init"] == init_entry
    assert manifest["note"] == "refine again" and manifest["previous_ship"]["note"] == "first ship"
    assert set(verify_manifest(models)) == {"init", "refine"}
    with pytest.raises(InputError, match="--init, --refine or both"):
        training_cli._ship(argparse.Namespace(**{**vars(args), "init": None, "refine": None}))
    with pytest.raises(ValueError, match="divisor of 256"):
        TrainConfig("init", steps=1, **{**TINY, "image_px": 100})


def test_a_run_can_start_from_a_model_of_the_same_architecture(tiny_population, tmp_path):
    first = train(TrainConfig("init", steps=1, **TINY), tiny_population, tmp_path / "a", progress=False)
    # A vanishing learning rate: the one step leaves the starting weights as they were (batch-norm
    # statistics, not weights, move with every batch).
    tuned = train(TrainConfig("init", steps=1, lr=1e-12, start_from=str(first), **{**TINY, "seed": 9}), tiny_population,
                  tmp_path / "b", progress=False)
    for (name, w0), (_, w1) in zip(load_model(first).named_parameters(), load_model(tuned).named_parameters()):
        assert torch.allclose(w0.float(), w1.float(), atol=1e-6), name
    with pytest.raises(InputError, match="--width"):
        train(TrainConfig("init", steps=1, start_from=str(first), **{**TINY, "base_width": 16}), tiny_population,
              tmp_path / "c", progress=False)


def _ddp_worker(rank: int, port: int, subjects, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2", LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    train(TrainConfig("init", steps=2, **TINY), subjects, out, device="cpu", progress=False)
    assert not torch.distributed.is_initialized()  # train() created the group and destroyed it


def test_two_process_gloo_ddp_smoke_run(tiny_population, tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mp.spawn(_ddp_worker, args=(port, tiny_population, str(tmp_path)), nprocs=2, join=True)
    rows = _rows(tmp_path / LOG_NAME)
    assert [int(r["step"]) for r in rows] == [1, 2]
    ckpt = torch.load(tmp_path / CHECKPOINT_NAME, weights_only=True)
    assert ckpt["step"] == 2 and len(ckpt["data_rng"]) == 2
    assert read_model_header(tmp_path / "init.pt")["metadata"]["training"]["world_size"] == 2


# ------------------------------------------------------------------ manifest
def test_manifest_verification_detects_corruption(tiny_population, tmp_path):
    path = train(TrainConfig("init", steps=1, **TINY), tiny_population, tmp_path / "run", progress=False)
    models = tmp_path / "models"
    models.mkdir()
    target = models / "geopose_init.pt"
    target.write_bytes(path.read_bytes())
    write_manifest(models, {"init": model_entry(target)})
    assert verify_manifest(models) == {"init": target}
    data = bytearray(target.read_bytes())
    data[-10] ^= 0xFF
    target.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="SHA-256"):
        verify_manifest(models)
    with pytest.raises(InputError, match="manifest.json"):
        verify_manifest(tmp_path)
    with pytest.raises(InputError, match="no ONNX file for the init network"):
        verify_manifest(models, fmt="onnx")


def test_shipped_models_verify_and_load():
    files = verify_manifest(MODELS)
    graphs = verify_manifest(MODELS, fmt="onnx")
    assert set(files) == set(graphs) == {"init", "refine"}
    manifest = json.loads((MODELS / "manifest.json").read_text())
    assert sum(e["bytes"] + e["onnx"]["bytes"] for e in manifest["models"].values()) <= 40 * 1024 * 1024
    image = np.random.default_rng(0).random((2, 1, 256, 256)).astype(np.float32)
    for kind, path in files.items():
        net = load_model(path)
        assert net.config.kind == kind and read_model_header(path)["storage_dtype"] == "float16"
        assert manifest["models"][kind]["training"]["config"]["seed"] is not None
    # The shipped ONNX graphs compute what the torch files do.
    torch_models, onnx_models = load_models(MODELS, runtime="torch"), load_models(MODELS, runtime="onnxruntime")
    np.testing.assert_allclose(torch_models.init.predict(image)[2], onnx_models.init.predict(image)[2], atol=1e-2)
    residuals = [m.refine.predict_residual(image, image[..., ::-1], 1) for m in (torch_models, onnx_models)]
    np.testing.assert_allclose(residuals[0][:, :3, :3], residuals[1][:, :3, :3], atol=1e-2)
    np.testing.assert_allclose(residuals[0][:, :3, 3], residuals[1][:, :3, 3], atol=0.05)  # mm
    assert "view_accuracy_with_metadata" in manifest["validation"]


def test_cli_trains_on_several_populations_together(tiny_population, tmp_path):
    from geopose.cli import main
    from geopose.nets import read_model_header

    first = save_population(tmp_path / "a.pt", tiny_population[:1], {"source": "phantom", "seeds": [1]})
    second = save_population(tmp_path / "b.pt", tiny_population[1:], {"source": "folder", "folder": "heads"})
    assert main(["train", "init", "--population", str(first), str(second), "--out", str(tmp_path / "run"), "--steps", "1",
                 "--batch-size", "2", "--accumulation", "1", "--width", "8", "--render-px", "32", "--image-px", "64",
                 "--checkpoint-every", "1", "--device", "cpu"]) == 0
    header = read_model_header(tmp_path / "run" / "init.pt")
    assert header["metadata"]["training"]["data"] == {
        "populations": [{"source": "phantom", "seeds": [1]}, {"source": "folder", "folder": "heads"}]}


def test_cli_reports_bad_training_input(tmp_path, capsys):
    from geopose.cli import main

    assert main(["train", "population", "--folder", str(tmp_path / "nowhere"), "--out", str(tmp_path / "p.pt")]) == 2
    assert "does not exist" in capsys.readouterr().err
    cta = make_subject(1, spacing_mm=5.0).cta
    from geopose.cta.io import save_volume

    save_volume(cta, tmp_path / "case1.nii.gz")
    assert main(["train", "population", "--folder", str(tmp_path), "--out", str(tmp_path / "p.pt")]) == 2
    assert "case1_vessels.nii.gz" in capsys.readouterr().err
    assert main(["train", "init", "--population", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "run")]) == 2
    assert "population cache" in capsys.readouterr().err
