"""GeoPose-Init/Refine modules, model files, checkpoint import, ONNX parity and backends."""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SHARED

from geopose import contract as C
from geopose.contract import (
    INIT_TRANSLATION_SCALE_MM,
    ISO_TRANSLATION_MM,
    REFINE_ROTATION_SCALE_RAD,
    REFINE_TRANSLATION_SCALE_MM,
    VIEW_ANCHOR_RAD,
    VIEW_LAT_MINUS,
    VIEW_LAT_PLUS,
    VIEW_PA,
)
from geopose.errors import InputError
from geopose.geometry.poses import invert, isopose, params_from_pose, rotation_angle_rad
from geopose.images import normalize_minmax
from geopose.nets import (
    BackboneConfig,
    InitNet,
    NetConfig,
    RefineNet,
    export_onnx,
    load_model,
    load_models,
    parameter_count,
    read_model_header,
    save_model,
)
from geopose.nets.decoding import decode_init_pose
from geopose.nets.manifest import verify_models
from geopose.nets.predictors import ModelInput, OnnxInit, OnnxRefine, TorchInit, TorchRefine, _model_input
from geopose.resources import default_models_dir
from geopose.training.poses import init_pose_tensor, residual_tensor
from geopose.nets.checkpoint import (
    published_manifest_path,
    import_checkpoint,
    read_checkpoint_state_dict,
    register,
)

REFERENCE = SHARED / "reference"
TENSOR_LIST = REFERENCE / "geopose_checkpoint_tensors.json"
SMALL = BackboneConfig(depth=18, base_width=8)
BN_STATS = ("running_mean", "running_var", "num_batches_tracked")


def small_init() -> InitNet:
    return _randomise_bn(InitNet(NetConfig("init", SMALL)))


def small_refine() -> RefineNet:
    return _randomise_bn(RefineNet(NetConfig("refine", SMALL)))


def _randomise_bn(module):
    """Non-trivial batch-norm statistics so that eval-mode outputs exercise them."""
    gen = torch.Generator().manual_seed(0)
    for m in module.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.randn(m.running_mean.shape, generator=gen) * 0.1)
            m.running_var.copy_(torch.rand(m.running_var.shape, generator=gen) + 0.5)
    return module.eval()


def published_state(name: str) -> dict[str, torch.Tensor]:
    if not TENSOR_LIST.is_file():
        pytest.skip(f"{TENSOR_LIST} not available")
    gen = torch.Generator().manual_seed(1)
    state = {}
    for entry in json.loads(TENSOR_LIST.read_text())["files"][name]:
        dtype = getattr(torch, entry["dtype"])
        shape = entry["shape"]
        state[entry["name"]] = (
            torch.randn(shape, generator=gen).to(dtype) if dtype.is_floating_point else torch.randint(0, 99, shape, generator=gen)
        )
    return state


# ------------------------------------------------------------------ layouts
@pytest.mark.parametrize("name, cls", [("geopose_init.ckpt", InitNet), ("geopose_refine.ckpt", RefineNet)])
def test_published_state_dicts_load_strictly(name, cls):
    state = published_state(name)
    kept = {k: v for k, v in state.items() if not k.startswith("criterion.")}
    module = cls()
    module.load_state_dict(kept, strict=True)
    assert set(module.state_dict()) == set(kept)
    for key, value in module.state_dict().items():
        assert torch.equal(value, kept[key]), key
    listed_params = sum(v.numel() for k, v in kept.items() if not k.endswith(BN_STATS))
    assert parameter_count(module) == listed_params


def test_smaller_backbones_and_feature_dims():
    r18 = InitNet(NetConfig("init", BackboneConfig(depth=18)))
    r34 = InitNet()
    assert parameter_count(r18) < 0.6 * parameter_count(r34)
    narrow = RefineNet(NetConfig("refine", BackboneConfig(depth=18, base_width=32)))
    assert narrow.net.fusion[0].in_features == 5 * 32 * 8
    with pytest.raises(ValueError, match="depth 50"):
        BackboneConfig(depth=50)
    with pytest.raises(ValueError, match="kind"):
        NetConfig("segment")


# ------------------------------------------------------------ preprocessing
def test_normalize_minmax_per_image_and_input_untouched():
    x = torch.stack([torch.linspace(-3, 5, 16).view(1, 4, 4), torch.full((1, 4, 4), 7.0)])
    before = x.clone()
    y = normalize_minmax(x)
    assert torch.equal(x, before)
    assert y[0].min() == 0 and y[0].max() == 1
    assert torch.allclose(y[0].flatten(), (x[0].flatten() + 3) / 8)
    assert torch.equal(y[1], torch.zeros(1, 4, 4))  # constant image
    assert torch.allclose(normalize_minmax(y), y)
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        normalize_minmax(torch.zeros(4, 4))


# -------------------------------------------------------------------- Init
def test_init_decode_isopose_and_scaling():
    raw = np.zeros((3, 6))
    views = np.array([VIEW_LAT_MINUS, VIEW_PA, VIEW_LAT_PLUS])
    np.testing.assert_allclose(decode_init_pose(raw, views), np.stack([isopose(v) for v in views]), atol=1e-9)
    raw = np.array([[0.1, -0.2, 0.05, 0.3, -0.4, 0.5]])
    r, t = params_from_pose(decode_init_pose(raw, np.array([VIEW_LAT_PLUS])))
    np.testing.assert_allclose(r[0], [0.1 + VIEW_ANCHOR_RAD[VIEW_LAT_PLUS], -0.2, 0.05], atol=1e-12)
    np.testing.assert_allclose(t[0], np.asarray(ISO_TRANSLATION_MM) + raw[0, 3:] * INIT_TRANSLATION_SCALE_MM)
    # Training decodes the same way, differentiably.
    raw = np.random.default_rng(0).normal(0, 0.3, (5, 6))
    views = np.array([0, 1, 2, 1, 0])
    np.testing.assert_allclose(init_pose_tensor(torch.as_tensor(raw), torch.as_tensor(views)).numpy(),
                               decode_init_pose(raw, views), atol=1e-12)


def test_init_view_rule_and_view_conditioned_pose():
    torch.manual_seed(0)
    net = small_init()
    with torch.no_grad():
        net.net.fc.view.weight.zero_()
        # logits (LAT-, PA, LAT+): PA highest, then LAT+.
        net.net.fc.view.bias.copy_(torch.tensor([0.0, 5.0, 1.0]))
    init = TorchInit(net)
    image = np.random.default_rng(0).random((2, 1, 64, 64)).astype(np.float32) * 40 + 3  # not normalised
    pose, view, logits = init.predict(image, np.array([False, True]), mirror=False)
    assert view.tolist() == [VIEW_PA, VIEW_LAT_PLUS]
    np.testing.assert_allclose(logits[0], [0.0, 5.0, 1.0], atol=1e-6)
    _, view_free, _ = init.predict(image, None, mirror=False)
    assert view_free.tolist() == [VIEW_PA, VIEW_PA]
    with torch.no_grad():
        net.net.fc.view.bias.copy_(torch.tensor([2.0, 5.0, 1.0]))
    pose, view, _ = init.predict(image, True, mirror=False)
    assert view.tolist() == [VIEW_LAT_MINUS, VIEW_LAT_MINUS]
    # The pose equals the forward pass run with the chosen label's embedding.
    with torch.no_grad():
        raw, _ = net(torch.as_tensor(normalize_minmax(image)), torch.as_tensor(view))
        raw_pa, _ = net(torch.as_tensor(normalize_minmax(image)), torch.full((2,), VIEW_PA))
    np.testing.assert_allclose(pose, decode_init_pose(raw.double().numpy(), view), rtol=1e-6, atol=1e-5)
    assert not torch.allclose(raw, raw_pa)
    with pytest.raises(ValueError, match="view labels"):
        net(torch.as_tensor(image), torch.tensor([0, 3]))
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        init.predict(np.random.rand(2, 3, 64, 64))


def test_mirror_averaged_side_is_antisymmetric_and_cancels_a_side_bias():
    torch.manual_seed(1)
    net = small_init().eval()
    init = TorchInit(net)
    image = np.random.default_rng(1).random((3, 1, 64, 64)).astype(np.float32)
    _, _, logits = init.predict(image, None)
    _, _, mirrored = init.predict(image[..., ::-1], None)
    # LAT+ - LAT- margin flips sign with the image; the PA logit is unchanged.
    margin = logits[:, VIEW_LAT_PLUS] - logits[:, VIEW_LAT_MINUS]
    np.testing.assert_allclose(margin, -(mirrored[:, VIEW_LAT_PLUS] - mirrored[:, VIEW_LAT_MINUS]), atol=1e-5)
    assert np.abs(margin).min() > 1e-4
    np.testing.assert_allclose(logits[:, VIEW_PA], mirrored[:, VIEW_PA], atol=1e-5)
    # It is the mean of the single-image logits and the mirrored image's, re-indexed.
    with torch.no_grad():
        x = torch.as_tensor(normalize_minmax(image))
        _, single = net.forward_all_views(x)
        _, single_flipped = net.forward_all_views(x.flip(-1))
    expected = 0.5 * (single + single_flipped[:, [VIEW_LAT_PLUS, VIEW_PA, VIEW_LAT_MINUS]])
    np.testing.assert_allclose(logits, expected.numpy(), atol=1e-5)
    # A constant preference for LAT- (image-independent logits) cancels out.
    with torch.no_grad():
        net.net.fc.view.weight.zero_()
        net.net.fc.view.bias.copy_(torch.tensor([3.0, 0.0, 1.0]))
    _, _, biased = init.predict(image, None)
    np.testing.assert_allclose(biased[:, VIEW_LAT_PLUS], biased[:, VIEW_LAT_MINUS], atol=1e-6)


# ------------------------------------------------------------------ Refine
def test_refine_residual_scaling_and_identity():
    torch.manual_seed(0)
    net = small_refine()
    refine = TorchRefine(net)
    g = np.random.default_rng(0)
    target, render = g.random((2, 1, 64, 64)), g.random((2, 1, 64, 64))
    with torch.no_grad():
        net.net.head.weight.zero_()
        net.net.head.bias.zero_()
    D = refine.predict_residual(target, render, np.array([VIEW_PA, VIEW_LAT_PLUS]))
    np.testing.assert_allclose(D, np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-6)
    with torch.no_grad():
        net.net.head.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))
    D = refine.predict_residual(target, render, VIEW_PA)
    np.testing.assert_allclose(rotation_angle_rad(D[:, :3, :3]), REFINE_ROTATION_SCALE_RAD[0], atol=1e-6)
    # Translation column is R(w) @ dt with dt = (0, s_y, 0) mm; R(w) is about x.
    a, s = REFINE_ROTATION_SCALE_RAD[0], REFINE_TRANSLATION_SCALE_MM[1]
    np.testing.assert_allclose(D[0, :3, 3], [0.0, s * math.cos(a), s * math.sin(a)], atol=1e-4)
    T = isopose(VIEW_PA)
    np.testing.assert_allclose(D[0] @ (invert(D[0]) @ T), T, atol=1e-9)
    # Training decodes the same residual, differentiably.
    raw = g.normal(0, 1, (4, 6))
    from geopose.nets.decoding import residual_from_raw

    np.testing.assert_allclose(residual_tensor(torch.as_tensor(raw)).numpy(), residual_from_raw(raw), atol=1e-12)
    with pytest.raises(ValueError, match="same shape"):
        refine.predict_residual(target, render[:, :, :32], VIEW_PA)


def test_refine_siamese_encoder_is_shared():
    net = small_refine()
    assert sum(1 for k in net.state_dict() if k.endswith("conv1.weight") and "layer" not in k) == 1
    x = torch.rand(1, 1, 64, 64)
    with torch.no_grad():
        a = net.net.backbone(x)
        net.net.head.weight.zero_()
        net.net.head.bias.zero_()
    assert a.shape == (1, 64)
    assert torch.equal(net(x, x, 1), torch.zeros(1, 6))
    with pytest.raises(ValueError, match="same shape"):
        net(x, torch.rand(1, 1, 32, 32), 1)


# ------------------------------------------------------------- model files
def test_model_file_round_trip(tmp_path):
    net = small_init()
    path = save_model(net, tmp_path / "init.pt", {"trained_on": "unit test"})
    header = read_model_header(path)
    assert header["architecture"]["kind"] == "init" and header["metadata"]["trained_on"] == "unit test"
    loaded = load_model(path)
    x = torch.rand(2, 1, 64, 64)
    assert torch.equal(loaded.forward_all_views(x)[0], net.forward_all_views(x)[0])
    half = load_model(save_model(net, tmp_path / "half.pt", dtype="float16"))
    assert (tmp_path / "half.pt").stat().st_size < 0.6 * path.stat().st_size
    assert torch.allclose(half.forward_all_views(x)[0], net.forward_all_views(x)[0], atol=2e-2)
    # Payload is plain tensors + JSON: loads with weights_only=True.
    payload = torch.load(path, weights_only=True)
    assert set(payload) == {"header", "state_dict"}
    with pytest.raises(ValueError, match="JSON"):
        save_model(net, tmp_path / "bad.pt", {"x": object()})
    with torch.no_grad():
        net.net.fc.pose.bias.fill_(1e6)  # beyond float16 range
    with pytest.raises(ValueError, match="not finite when stored as float16"):
        save_model(net, tmp_path / "overflow.pt", dtype="float16")
    assert not (tmp_path / "overflow.pt").exists()


def test_load_model_rejects_foreign_files(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(os.urandom(300))
    with pytest.raises(ValueError, match="not a GeoPose model file"):
        load_model(junk)
    plain = tmp_path / "plain.pt"
    torch.save({"a": torch.zeros(2)}, plain)
    with pytest.raises(ValueError, match="not a GeoPose model file"):
        load_model(plain)
    with pytest.raises(InputError, match="does not exist"):
        load_model(tmp_path / "missing.pt")


# ------------------------------------------------------- checkpoint import
class Exploit:
    """Pickles as a call to os.system that would create a marker file."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class LightningLikeHparams(dict):
    """A dict subclass with extra state, like Lightning's AttributeDict."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.note = "extra"


def fake_lightning_checkpoint(path: Path, module, marker: Path) -> Path:
    state = collections.OrderedDict(module.state_dict())
    if isinstance(module, RefineNet):
        state["criterion.gncc.sobel.filter.weight"] = torch.randn(2, 1, 3, 3)
    torch.save(
        {
            "epoch": 3,
            "global_step": 12,
            "pytorch-lightning_version": "2.1.0",
            "state_dict": state,
            "callbacks": {"ModelCheckpoint": Exploit(marker)},
            "hyper_parameters": LightningLikeHparams(lr=1e-4, backbone=torch.nn.Linear(2, 2)),
            "optimizer_states": [{"state": {0: {"exp_avg": torch.zeros(3)}}}],
        },
        path,
    )
    return path


@pytest.mark.parametrize("factory", [small_init, small_refine])
def test_import_checkpoint_runs_no_pickled_code(tmp_path, factory):
    module = factory()
    marker = tmp_path / "pwned"
    ckpt = fake_lightning_checkpoint(tmp_path / "my_run.ckpt", module, marker)
    # Sanity: the exploit is real when unpickled normally.
    torch.load(ckpt, weights_only=False)
    assert marker.exists()
    marker.unlink()

    state = read_checkpoint_state_dict(ckpt)
    assert not marker.exists()
    for key, value in module.state_dict().items():
        assert torch.equal(state[key], value), key
    out = import_checkpoint(ckpt, tmp_path / "models")
    assert not marker.exists()
    assert out == tmp_path / "models" / f"{module.config.kind}.pt"
    header = read_model_header(out)
    assert header["architecture"] == module.config.to_dict()
    assert header["metadata"]["source_file"] == "my_run.ckpt" and "published" not in header["metadata"]
    reloaded = load_model(out)
    reloaded.load_state_dict(module.state_dict(), strict=True)  # same layout both ways
    assert all(torch.equal(a, b) for a, b in zip(reloaded.state_dict().values(), module.state_dict().values()))


def test_official_names_are_verified(tmp_path):
    manifest = json.loads(published_manifest_path().read_text())
    ckpt = fake_lightning_checkpoint(tmp_path / "geopose_init.ckpt", small_init(), tmp_path / "m")
    with pytest.raises(ValueError, match=r"named like the published geopose_init\.ckpt .* bytes"):
        import_checkpoint(ckpt, tmp_path / "out.pt")
    assert not (tmp_path / "out.pt").exists()
    # Same size as listed but a different hash -> refused on SHA-256.
    entry = manifest["files"]["geopose_init.ckpt"]
    entry["bytes"] = ckpt.stat().st_size
    fake_manifest = tmp_path / "manifest.json"
    fake_manifest.write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="SHA-256"):
        import_checkpoint(ckpt, tmp_path / "out.pt", manifest_path=fake_manifest)
    # Source file name of the release is official too.
    source = tmp_path / manifest["files"]["geopose_refine.ckpt"]["source_filename"]
    fake_lightning_checkpoint(source, small_refine(), tmp_path / "m")
    with pytest.raises(ValueError, match="geopose_refine.ckpt"):
        import_checkpoint(source, tmp_path / "out.pt")


def test_non_checkpoints_are_refused(tmp_path):
    junk = tmp_path / "random.ckpt"
    junk.write_bytes(os.urandom(4096))
    with pytest.raises(ValueError, match="not a PyTorch checkpoint"):
        import_checkpoint(junk, tmp_path / "o.pt")
    archive = tmp_path / "notes.ckpt"
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("notes/readme.txt", "hello")
    with pytest.raises(ValueError, match="not a PyTorch checkpoint"):
        import_checkpoint(archive, tmp_path / "o.pt")
    other = tmp_path / "other.ckpt"
    torch.save({"state_dict": {"encoder.weight": torch.zeros(3)}}, other)
    with pytest.raises(ValueError, match="neither a GeoPose-Init"):
        import_checkpoint(other, tmp_path / "o.pt")
    with pytest.raises(InputError, match="does not exist"):
        import_checkpoint(tmp_path / "absent.ckpt", tmp_path / "o.pt")
    good = fake_lightning_checkpoint(tmp_path / "run.ckpt", small_init(), tmp_path / "m")
    with pytest.raises(ValueError, match="must be a .pt file"):
        import_checkpoint(good, tmp_path / "model.onnx")


def test_import_checkpoint_command(tmp_path, capsys):
    ckpt = fake_lightning_checkpoint(tmp_path / "run.ckpt", small_init(), tmp_path / "m")
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["import-checkpoint", str(ckpt), "--out", str(tmp_path / "x.pt"), "--dtype", "float16"])
    assert args.func(args) == 0
    assert "x.pt" in capsys.readouterr().out
    assert read_model_header(tmp_path / "x.pt")["storage_dtype"] == "float16"


# ------------------------------------------------------------ ONNX backend
def test_onnx_parity_with_torch(tmp_path):
    torch.manual_seed(0)
    net_init, net_refine = small_init(), small_refine()
    px = 64
    init, refine = TorchInit(net_init), TorchRefine(net_refine)
    init_onnx = OnnxInit(export_onnx(net_init, tmp_path / "init.onnx", image_px=px))
    refine_onnx = OnnxRefine(export_onnx(net_refine, image_px=px))
    g = np.random.default_rng(0)
    image = g.random((3, 1, px, px)).astype(np.float32)
    lateral = np.array([True, False, True])
    pose_t, view_t, logits_t = init.predict(image, lateral)
    pose_o, view_o, logits_o = init_onnx.predict(image, lateral)
    np.testing.assert_array_equal(view_t, view_o)
    np.testing.assert_allclose(logits_t, logits_o, atol=1e-4)
    # Pose parity: rotation 1e-4, translation scaled by 100 mm -> 1e-2 mm.
    np.testing.assert_allclose(pose_t[:, :3, :3], pose_o[:, :3, :3], atol=1e-4)
    np.testing.assert_allclose(pose_t[:, :3, 3], pose_o[:, :3, 3], atol=1e-2)
    target, render = g.random((3, 1, px, px)), g.random((3, 1, px, px))
    view = np.array([0, 1, 2])
    D_t = refine.predict_residual(target, render, view)
    np.testing.assert_allclose(D_t, refine_onnx.predict_residual(target, render, view), atol=1e-4)
    # Half-precision weight storage: about half the file, outputs within fp16 rounding.
    half = export_onnx(net_refine, image_px=px, weights="float16")
    full = export_onnx(net_refine, image_px=px)
    assert len(half) < 0.6 * len(full)
    D_h = OnnxRefine(half).predict_residual(target, render, view)
    np.testing.assert_allclose(D_t, D_h, atol=2e-2)
    assert not np.array_equal(D_h, refine_onnx.predict_residual(target, render, view))
    with pytest.raises(InputError, match="not GeoPose-Refine|GeoPose-Init network"):
        OnnxRefine(tmp_path / "init.onnx")
    with pytest.raises(ValueError, match="32 x 32 px but the network takes 64 x 64"):
        init_onnx.predict(np.random.rand(1, 1, 32, 32))
    with pytest.raises(ValueError, match="pairs"):
        refine_onnx.predict_residual(target, render[:2], view)


def test_stacked_refine_compares_the_pair_as_channels_and_takes_larger_images_block_averaged():
    torch.manual_seed(1)
    stacked = NetConfig("refine", BackboneConfig(depth=18, base_width=8, in_channels=2), pairing="stacked")
    net = _randomise_bn(RefineNet(stacked))
    assert net.net.backbone.conv1.weight.shape[1] == 2
    assert net.net.fusion[0].in_features == stacked.backbone.feature_dim  # one pooled vector, not five
    g = np.random.default_rng(3)
    target, render = g.random((2, 1, 128, 128)), g.random((2, 1, 128, 128))
    halve = lambda a: a.reshape(2, 1, 64, 2, 64, 2).mean(axis=(3, 5))  # noqa: E731
    at_64 = TorchRefine(net, image_px=64).predict_residual(target, render, 1)
    np.testing.assert_allclose(at_64, TorchRefine(net).predict_residual(halve(target), halve(render), 1), atol=1e-6)
    swapped = TorchRefine(net, image_px=64).predict_residual(render, target, 1)
    assert not np.allclose(at_64, swapped, atol=1e-4)  # target and render play different parts
    graph = OnnxRefine(export_onnx(net, image_px=64))
    assert graph.image_px == 64
    np.testing.assert_allclose(graph.predict_residual(target, render, 1), at_64, atol=1e-4)
    with pytest.raises(ValueError, match="whole multiple"):
        graph.predict_residual(target[..., :100, :100], render[..., :100, :100], 1)
    with pytest.raises(ValueError, match="2-channel"):
        NetConfig("refine", SMALL, pairing="stacked")
    with pytest.raises(ValueError, match="Refine only"):
        NetConfig("init", BackboneConfig(depth=18, base_width=8, in_channels=2), pairing="stacked")


def ship_small_models(folder: Path, render_px: int | None = None) -> Path:
    """Small Init + Refine shipped like `geopose train ship` does: .pt, ONNX and the manifest."""
    from geopose.training.manifest import file_entry, model_entry, write_manifest

    entries = {}
    for kind, net in (("init", small_init()), ("refine", small_refine())):
        pt = save_model(net, folder / f"geopose_{kind}.pt")
        onnx = export_onnx(net, folder / f"geopose_{kind}.onnx")
        entry = model_entry(pt, onnx=file_entry(onnx))
        if render_px:
            entry["input"]["render_px"] = render_px
        entries[kind] = entry
    write_manifest(folder, entries)
    return folder


def test_load_models_both_runtimes_agree_and_check_every_file(tmp_path):
    ship_small_models(tmp_path, render_px=96)
    image = np.random.default_rng(2).random((2, 1, 256, 256)).astype(np.float32)
    results = {}
    for runtime in ("torch", "onnxruntime"):
        models = load_models(tmp_path, runtime=runtime)
        assert models.render_px == 96 and models.runtime == runtime
        assert models.files["init"]["format"] == ("pt" if runtime == "torch" else "onnx")
        pose, view, _ = models.init.predict(image, np.array([True, False]))
        results[runtime] = (pose, view, models.refine.predict_residual(image, image[..., ::-1], view))
    np.testing.assert_array_equal(results["torch"][1], results["onnxruntime"][1])
    np.testing.assert_allclose(results["torch"][0][:, :3, :3], results["onnxruntime"][0][:, :3, :3], atol=1e-4)
    np.testing.assert_allclose(results["torch"][2], results["onnxruntime"][2], atol=1e-4)
    with pytest.raises(InputError, match="runtime"):
        load_models(tmp_path, runtime="tensorrt")
    # The ONNX graphs run are the manifest's: a replaced graph is refused by its checksum.
    onnx = tmp_path / "geopose_refine.onnx"
    onnx.write_bytes(onnx.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(ValueError, match="SHA-256"):
        load_models(tmp_path, runtime="onnxruntime")
    load_models(tmp_path, runtime="torch")  # the .pt files are still intact
    (tmp_path / "manifest.json").unlink()
    with pytest.raises(InputError, match="has no manifest.json.*--allow-unverified-models"):
        load_models(tmp_path, runtime="torch")
    # Explicitly unverified: the .pt files found by their headers, on either runtime.
    unverified = load_models(tmp_path, runtime="onnxruntime", allow_unverified=True)
    assert unverified.files["init"]["sha256"].startswith("unverified")
    np.testing.assert_allclose(unverified.init.predict(image, np.array([True, False]))[0][:, :3, :3],
                               results["torch"][0][:, :3, :3], atol=1e-4)
    (tmp_path / "geopose_refine.pt").unlink()
    with pytest.raises(InputError, match="no refine model"):
        verify_models(tmp_path, allow_unverified=True)


def test_the_shipped_models_declare_their_input():
    """The model set takes render size and input clip from each model's manifest entry (the
    shipped CPU models: 96 px, 2-98 clip); an entry that declares no clip gets
    docs/conventions.md 5's 25-75, as published checkpoints do."""
    manifest = json.loads((default_models_dir() / "manifest.json").read_text())["models"]
    declared = manifest["init"]["input"]
    models = load_models(runtime="onnxruntime")
    assert models.render_px == declared["render_px"] == 96
    assert models.clip_percentiles == tuple(declared["clip_percentiles"]) == (2.0, 98.0)
    assert set(models.files) == {"init", "refine"} and all(f["path"].endswith(".onnx") for f in models.files.values())
    assert _model_input({"input": {"render_px": 128}}) == ModelInput(128, (25.0, 75.0), 256)
    assert C.MAP_CLIP_PERCENTILES == (25.0, 75.0)
    assert _model_input({"training": {"config": {"image_px": 128}}}).image_px == 128
    with pytest.raises(InputError, match="block-averaged"):
        _model_input({"input": {"image_px": 100}})


def test_cli_reports_bad_checkpoint_without_traceback(tmp_path, monkeypatch, capsys):
    from geopose import cli

    monkeypatch.setattr(cli, "COMMANDS", [("geopose.nets.checkpoint", "register")])
    junk = tmp_path / "geopose_init.ckpt"
    junk.write_bytes(os.urandom(1000))
    assert cli.main(["import-checkpoint", str(junk), "--out", str(tmp_path / "o.pt")]) == 2
    err = capsys.readouterr().err
    assert "named like the published geopose_init.ckpt" in err and "Traceback" not in err
    assert not (tmp_path / "o.pt").exists()


@pytest.mark.gpu
def test_predictors_on_cuda_match_cpu():
    init, refine = small_init(), small_refine()
    image = np.random.default_rng(3).random((2, 1, 128, 128)).astype(np.float32)
    lateral = np.array([True, False])
    pose_cpu, view_cpu, _ = TorchInit(init).predict(image, lateral)
    D_cpu = TorchRefine(refine).predict_residual(image, image[..., ::-1], view_cpu)
    pose_gpu, view_gpu, _ = TorchInit(init.to("cuda")).predict(image, lateral)
    D_gpu = TorchRefine(refine.to("cuda")).predict_residual(image, image[..., ::-1], view_gpu)
    np.testing.assert_array_equal(view_gpu, view_cpu)
    np.testing.assert_allclose(pose_gpu[:, :3, :3], pose_cpu[:, :3, :3], atol=1e-3)
    np.testing.assert_allclose(D_gpu, D_cpu, atol=1e-3)
