"""DSA input: readers (DICOM XA multi-frame incl. compressed, DICOM folder, NIfTI + sidecar),
geometry overrides and errors, the XA writer, the run contract."""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.pixels.decoders import JPEGBaseline8BitDecoder, JPEGLosslessSV1Decoder
from pydicom.pixels.encoders import JPEG2000LosslessEncoder, JPEGLSLosslessEncoder, RLELosslessEncoder
from pydicom.uid import JPEG2000Lossless, JPEGLSLossless, RLELossless, XRayAngiographicImageStorage

from geopose import contract as C
from geopose.dsa import (
    DSARun,
    geometry_override_args,
    geometry_overrides_from_args,
    read_dsa,
    sidecar_path,
    write_dsa_dicom,
    write_dsa_nifti,
)
from geopose.geometry import CArmAngles, Detector
from geopose.errors import InputError

SAMPLE_OVERRIDES = {"sid_mm": 1100.0, "sod_mm": 750.0, "pixel_spacing_mm": (0.35, 0.35)}


def _run(frames: np.ndarray | None = None, *, offset=(2.5, -1.5), primary=30.0, photometric="MONOCHROME2") -> DSARun:
    rng = np.random.default_rng(3)
    if frames is None:
        frames = rng.integers(0, 4096, size=(5, 48, 64)).astype(np.float32)
    t, h, w = frames.shape
    det = Detector(h, w, (0.3, 0.25), 1100.0, offset)
    angles = CArmAngles(primary, -10.0, 1100.0, 750.0)
    return DSARun(frames, det, angles, 66.5, {"photometric_interpretation": photometric})


def _assert_same_geometry(a: DSARun, b: DSARun) -> None:
    assert b.detector.shape == a.detector.shape
    np.testing.assert_allclose(b.detector.spacing_mm, a.detector.spacing_mm, rtol=1e-9)
    np.testing.assert_allclose(b.detector.principal_offset_mm, a.detector.principal_offset_mm, atol=1e-6)
    assert b.detector.sdd_mm == pytest.approx(a.detector.sdd_mm)
    assert (b.angles.primary_deg, b.angles.secondary_deg) == pytest.approx((a.angles.primary_deg, a.angles.secondary_deg))
    assert (b.angles.sid_mm, b.angles.sod_mm) == pytest.approx((a.angles.sid_mm, a.angles.sod_mm))
    assert b.frame_time_ms == pytest.approx(a.frame_time_ms)


# ------------------------------------------------------------------ real XA sample


@pytest.fixture(scope="module")
def sample(shared_data: Path) -> Path:
    return shared_data / "xa_sample" / "rubo_0002_xa_multiframe.dcm"


def test_sample_without_geometry_names_every_missing_tag(sample: Path):
    with pytest.raises(InputError) as info:
        read_dsa(sample)
    msg = str(info.value)
    assert ("DistanceSourceToDetector (0018,1110) is missing in rubo_0002_xa_multiframe.dcm: pass sid_mm=... "
            "(CLI: --pa-sid-mm / --lat-sid-mm ...)") in msg
    assert "DistanceSourceToPatient (0018,1111)" in msg and "--pa-sod-mm / --lat-sod-mm" in msg
    assert "ImagerPixelSpacing (0018,1164)" in msg and "--pa-pixel-spacing-mm / --lat-pixel-spacing-mm ROW COL" in msg
    assert "PositionerPrimaryAngle" not in msg  # present in the file


def test_sample_imports_with_overrides(sample: Path):
    assert JPEGBaseline8BitDecoder.is_available
    run = read_dsa(sample, **SAMPLE_OVERRIDES)
    assert run.frames.shape == (96, 512, 512) and run.frames.dtype == np.float32
    assert 0 <= run.frames.min() and run.frames.max() <= 255 and run.frames.std() > 10
    assert (run.angles.primary_deg, run.angles.secondary_deg) == (-32.0, 2.0)
    assert run.angles.sid_mm == 1100.0 and run.detector.sdd_mm == 1100.0 and run.angles.sod_mm == 750.0
    assert run.detector.spacing_mm == (0.35, 0.35)
    assert run.frame_time_ms == 33.0
    assert run.view_role == "PA" and run.view_label == C.VIEW_PA
    meta = run.metadata
    assert meta["sha256"] == hashlib.sha256(sample.read_bytes()).hexdigest()
    assert meta["photometric_interpretation"] == "MONOCHROME2"
    assert meta["transfer_syntax"] == pydicom.uid.JPEGBaseline8Bit
    assert meta["SeriesInstanceUID"].startswith("1.3.12.2")
    assert meta["geometry_sources"]["sid_mm"] == "override"
    assert meta["geometry_sources"]["primary_deg"] == "PositionerPrimaryAngle"


def test_overrides_replace_file_values(sample: Path):
    run = read_dsa(sample, primary_deg=-90.0, secondary_deg=None, **SAMPLE_OVERRIDES)
    assert run.angles.primary_deg == -90.0 and run.angles.secondary_deg == 2.0
    assert run.view_role == "LAT" and run.view_label == C.VIEW_LAT_MINUS


def test_bad_overrides(sample: Path):
    with pytest.raises(InputError, match="unknown geometry override"):
        read_dsa(sample, sdd=1000, **SAMPLE_OVERRIDES)
    with pytest.raises(InputError, match="not shorter"):
        read_dsa(sample, sid_mm=700.0, sod_mm=750.0, pixel_spacing_mm=0.3)
    with pytest.raises(InputError, match="one or two numbers"):
        read_dsa(sample, sid_mm=1000.0, sod_mm=750.0, pixel_spacing_mm=(0.3, 0.3, 0.3))


# ------------------------------------------------------------------ view roles


@pytest.mark.parametrize("primary, role, label", [(0.0, "PA", 1), (-44.0, "PA", 1), (-90.0, "LAT", 0), (90.0, "LAT", 2), (60.0, "LAT", 2)])
def test_view_role_from_primary_angle(primary, role, label):
    run = _run(primary=primary)
    assert run.view_role == role and run.view_label == label


# ------------------------------------------------------------------ writer <-> reader


@pytest.mark.parametrize("offset", [(0.0, 0.0), (2.5, -1.5)])
def test_dicom_round_trip_16bit(tmp_path: Path, offset):
    run = _run(offset=offset)
    path = write_dsa_dicom(run, tmp_path / "run.dcm", patient_name="Test^Phantom", series_description="round trip")
    back = read_dsa(path)
    np.testing.assert_array_equal(back.frames, run.frames)
    _assert_same_geometry(run, back)
    ds = pydicom.dcmread(path)
    assert ds.SOPClassUID == XRayAngiographicImageStorage and ds.Modality == "XA"
    assert ds.NumberOfFrames == 5 and ds.FrameIncrementPointer == pydicom.tag.Tag("FrameTime")
    assert ds.PhotometricInterpretation == "MONOCHROME2" and ds.BitsStored == 16
    assert str(ds.PatientName) == "Test^Phantom" and ds.SeriesDescription == "round trip"
    assert ds.BurnedInAnnotation == "NO"
    assert "RescaleSlope" not in ds  # integer frames stored exactly


def test_dicom_is_readable_by_gdcm(tmp_path: Path):
    run = _run()
    path = write_dsa_dicom(run, tmp_path / "run.dcm")
    image = sitk.ReadImage(str(path))
    assert image.GetSize() == (64, 48, 5)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), run.frames)


def test_dicom_8bit_quantises_floats(tmp_path: Path):
    rng = np.random.default_rng(4)
    frames = rng.normal(0.0, 2.0, size=(3, 32, 40)).astype(np.float32)
    run = _run(frames)
    back = read_dsa(write_dsa_dicom(run, tmp_path / "q.dcm", bits=8))
    step = (frames.max() - frames.min()) / 255
    assert np.abs(back.frames - frames).max() <= step / 2 + 1e-5
    assert pydicom.dcmread(tmp_path / "q.dcm").BitsStored == 8


def test_burn_in_text(tmp_path: Path):
    frames = np.full((2, 40, 120), 100.0, np.float32)
    frames[:, 30:, :] = 900.0
    run = _run(frames)
    back = read_dsa(write_dsa_dicom(run, tmp_path / "b.dcm", burn_in_text="PHANTOM"))
    changed = back.frames != run.frames
    assert changed.any() and not changed[:, 25:, :].any()  # text top-left only
    np.testing.assert_array_equal(changed[0], changed[1])  # same on every frame
    assert back.frames[changed].min() == 900.0
    assert pydicom.dcmread(tmp_path / "b.dcm").BurnedInAnnotation == "YES"


def _compressed_copy(src: Path, dst: Path, syntax) -> Path:
    ds = pydicom.dcmread(src)
    ds.compress(syntax)
    ds.save_as(dst, enforce_file_format=True)
    return dst


@pytest.mark.parametrize(
    "syntax, encoder",
    [(RLELossless, RLELosslessEncoder), (JPEG2000Lossless, JPEG2000LosslessEncoder), (JPEGLSLossless, JPEGLSLosslessEncoder)],
)
def test_compressed_transfer_syntaxes_decode(tmp_path: Path, syntax, encoder):
    if not encoder.is_available:
        pytest.skip(f"no {syntax.name} encoder installed ({encoder.missing_dependencies})")
    run = _run()
    src = write_dsa_dicom(run, tmp_path / "raw.dcm")
    path = _compressed_copy(src, tmp_path / "c.dcm", syntax)
    assert pydicom.dcmread(path).file_meta.TransferSyntaxUID == syntax
    back = read_dsa(path)
    np.testing.assert_array_equal(back.frames, run.frames)
    _assert_same_geometry(run, back)


def test_jpeg_lossless_decoder_is_installed():
    """No JPEG Lossless (process 14) encoder is available to make a test file, but the
    decoder the reader relies on (pylibjpeg-libjpeg) must be installed."""
    assert JPEGLosslessSV1Decoder.is_available


def test_monochrome1_kept_and_not_inverted(tmp_path: Path):
    run = _run(photometric="MONOCHROME1")
    back = read_dsa(write_dsa_dicom(run, tmp_path / "m1.dcm"))
    assert back.photometric_interpretation == "MONOCHROME1"
    np.testing.assert_array_equal(back.attenuation(), run.frames)
    m2 = _run()
    np.testing.assert_array_equal(m2.attenuation(), m2.frames.max() - m2.frames)
    np.testing.assert_array_equal(m2.attenuation(invert=False), m2.frames)


def test_from_attenuation_stores_absorbers_dark():
    att = np.zeros((2, 48, 64), np.float32)
    att[:, 20:30, 30:40] = 7.0  # a vessel
    base = _run()
    run = DSARun.from_attenuation(att, base.detector, base.angles, 40.0)
    assert run.photometric_interpretation == "MONOCHROME2"
    assert run.frames[0, 25, 35] < run.frames[0, 0, 0]  # the vessel is dark as stored
    np.testing.assert_array_equal(run.attenuation(), att)


# ------------------------------------------------------------------ NIfTI / NRRD + sidecar


@pytest.mark.parametrize("name", ["run.nii.gz", "run.nrrd"])
def test_nifti_sidecar_round_trip(tmp_path: Path, name: str):
    run = _run()
    path = write_dsa_nifti(run, tmp_path / name)
    side = sidecar_path(path)
    assert side.name == "run.json"
    keys = json.loads(side.read_text())
    assert keys["pixel_spacing_mm"] == [0.3, 0.25] and keys["sid_mm"] == 1100.0
    back = read_dsa(path)
    np.testing.assert_array_equal(back.frames, run.frames)
    _assert_same_geometry(run, back)


def test_nifti_without_sidecar_needs_overrides(tmp_path: Path):
    run = _run()
    path = write_dsa_nifti(run, tmp_path / "run.nii.gz")
    sidecar_path(path).unlink()
    with pytest.raises(InputError, match=r"'sid_mm' \(sidecar run.json\) is missing in run.nii.gz: pass sid_mm=\.\.\."):
        read_dsa(path)
    back = read_dsa(path, primary_deg=0, secondary_deg=0, sid_mm=1000, sod_mm=700, pixel_spacing_mm=0.2)
    assert back.detector.spacing_mm == (0.2, 0.2) and back.frame_time_ms is None


def test_bad_sidecars(tmp_path: Path):
    path = write_dsa_nifti(_run(), tmp_path / "run.nii.gz")
    side = sidecar_path(path)
    keys = json.loads(side.read_text())
    side.write_text(json.dumps({**keys, "sdd": 1000}))
    with pytest.raises(InputError, match="unknown key"):
        read_dsa(path)
    side.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_dsa(path)


# ------------------------------------------------------------------ folder of single frames


def _single_frames(tmp_path: Path, run: DSARun, order: list[int]) -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for t in order:
        single = DSARun(run.frames[t : t + 1], run.detector, run.angles, run.frame_time_ms, dict(run.metadata))
        p = write_dsa_dicom(single, tmp_path / f"tmp_{t}.dcm")
        ds = pydicom.dcmread(p)
        ds.InstanceNumber = t + 1
        ds.SeriesInstanceUID = "1.2.3.4.5"
        del ds.FrameTime
        ds.ContentTime = f"1200{10 + t // 10:02d}.{(t % 10) * 100000:06d}"  # 100 ms apart
        ds.save_as(folder / f"img_{len(order) - t:02d}.dcm", enforce_file_format=True)
        p.unlink()
    return folder


def test_folder_of_single_frames_sorted_by_instance_number(tmp_path: Path):
    run = _run()
    folder = _single_frames(tmp_path, run, [3, 0, 4, 2, 1])
    (folder / "notes.txt").write_text("not DICOM")
    back = read_dsa(folder)
    np.testing.assert_array_equal(back.frames, run.frames)
    assert back.frame_time_ms == pytest.approx(100.0)
    assert back.metadata["source_files"] == 5


def test_folder_with_changing_angle_is_rejected(tmp_path: Path):
    run = _run()
    folder = _single_frames(tmp_path, run, [0, 1, 2])
    f = sorted(folder.iterdir())[0]
    ds = pydicom.dcmread(f)
    ds.PositionerPrimaryAngle = 45
    ds.save_as(f, enforce_file_format=True)
    with pytest.raises(InputError, match="not one fixed-angle run"):
        read_dsa(folder)


# ------------------------------------------------------------------ DICOM geometry mapping


def test_pixel_spacing_and_principal_offset_from_tags(tmp_path: Path):
    run = _run(np.ones((1, 100, 100), np.float32), offset=(0.0, 0.0))
    path = write_dsa_dicom(run, tmp_path / "g.dcm")
    ds = pydicom.dcmread(path)
    del ds.ImagerPixelSpacing
    ds.PixelSpacing = [0.2, 0.2]
    ds.EstimatedRadiographicMagnificationFactor = 1.5
    ds.PhysicalDetectorSize = [400.0, 400.0]
    ds.DetectorActiveDimensions = [300.0, 300.0]
    ds.DetectorActiveOrigin = [60.0, 40.0]  # image centre 10 mm below and 10 mm left of the detector centre
    ds.save_as(path, enforce_file_format=True)
    back = read_dsa(path)
    assert back.detector.spacing_mm == pytest.approx((0.3, 0.3))
    assert back.detector.principal_offset_mm == pytest.approx((10.0, -10.0))
    assert "Magnification" in back.metadata["geometry_sources"]["pixel_spacing_mm"]


def test_missing_and_non_dicom_inputs(tmp_path: Path):
    with pytest.raises(InputError, match="not found"):
        read_dsa(tmp_path / "none.dcm")
    (tmp_path / "x.dcm").write_bytes(b"garbage" * 50)
    with pytest.raises(InputError, match="not a DICOM file"):
        read_dsa(tmp_path / "x.dcm")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no DICOM images"):
        read_dsa(tmp_path / "empty")


def test_folder_with_one_multiframe_file(tmp_path: Path, sample: Path):
    (tmp_path / "one").mkdir()
    shutil.copy(sample, tmp_path / "one" / "run.dcm")
    assert read_dsa(tmp_path / "one", **SAMPLE_OVERRIDES).frames.shape == (96, 512, 512)


# ------------------------------------------------------------------ CLI options


def test_geometry_override_args(sample: Path):
    parser = argparse.ArgumentParser()
    geometry_override_args(parser)
    args = parser.parse_args(["--sid-mm", "1100", "--sod-mm", "750", "--pixel-spacing-mm", "0.35", "--primary-deg", "-85"])
    overrides = geometry_overrides_from_args(args)
    assert overrides == {"primary_deg": -85.0, "sid_mm": 1100.0, "sod_mm": 750.0, "pixel_spacing_mm": (0.35,)}
    run = read_dsa(sample, **overrides)
    assert run.detector.spacing_mm == (0.35, 0.35) and run.view_role == "LAT"
    args = parser.parse_args(["--pixel-spacing-mm", "0.3", "0.4", "0.5"])
    with pytest.raises(ValueError, match="one or two values"):
        geometry_overrides_from_args(args)


@pytest.mark.parametrize("prefix", ["lat", "lat-"])
def test_geometry_override_args_with_prefix(prefix):
    parser = argparse.ArgumentParser()
    geometry_override_args(parser, prefix="pa-")
    geometry_override_args(parser, prefix=prefix)
    args = parser.parse_args(["--lat-sid-mm", "1200", "--pa-sid-mm", "1000"])
    assert geometry_overrides_from_args(args, prefix=prefix) == {"sid_mm": 1200.0}
    assert geometry_overrides_from_args(args, prefix="pa-") == {"sid_mm": 1000.0}


def test_run_contract_errors():
    det = Detector(40, 40, (0.3, 0.3), 1000.0)
    angles = CArmAngles(0.0, 0.0, 1000.0, 700.0)
    with pytest.raises(InputError, match="detector"):
        DSARun(np.zeros((2, 40, 48)), det, angles)
    with pytest.raises(InputError, match="NaN"):
        DSARun(np.full((2, 40, 40), np.nan), det, angles)
    with pytest.raises(InputError, match="SID"):
        DSARun(np.zeros((2, 40, 40)), det, CArmAngles(0.0, 0.0, 1100.0, 700.0))


# ------------------------------------------------------------------ native runs (mask subtraction)


def _native_run(t: int = 6, shift_px: tuple[int, int] = (0, 0), relationship: str = "LIN") -> tuple[DSARun, np.ndarray, np.ndarray]:
    """A native run of ``t`` frames: frames 0-1 the head alone (a smooth skull-like attenuation), frames 2.. the head
    moved by ``shift_px`` (rows down, columns left) with a vessel whose contrast rises; X-ray intensities (LIN) or
    their logarithm (LOG). Returns the run, the skull and the vessel's added attenuation per frame ``(t, H, W)``."""
    h, w = 64, 80
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    skull = 2.5 * np.exp(-(((y - 30) / 22) ** 2 + ((x - 40) / 28) ** 2)) + 0.4 * np.sin(x / 5.0) * np.cos(y / 7.0) + 0.5
    vessel = np.exp(-((x - 0.5 * y - 20) / 1.5) ** 2) * ((y > 10) & (y < 55))
    added = np.zeros((t, h, w))
    moved = np.roll(skull, (shift_px[0], -shift_px[1]), axis=(0, 1))
    log_intensity = np.empty((t, h, w))
    for k in range(t):
        added[k] = 0.0 if k < 2 else 0.3 * (k - 1) * vessel
        log_intensity[k] = np.log(4000.0) - (skull if k < 2 else moved) - added[k]
    frames = np.round(np.exp(log_intensity)) if relationship == "LIN" else np.round(1000.0 * log_intensity)
    return _run(frames.astype(np.float32), offset=(0.0, 0.0)), skull, added


def _write_native(run: DSARun, path: Path, plan, relationship: str = "LIN", sign: int | None = None) -> Path:
    from geopose.dsa.subtraction import MaskSubtraction

    write_dsa_dicom(run, path, mask_subtraction=MaskSubtraction(**plan, relationship=relationship))
    if sign is not None or relationship != "LIN":
        ds = pydicom.dcmread(path)
        if relationship == "LOG":
            ds.RescaleSlope, ds.RescaleIntercept = "0.001", "0"  # the stored logarithm, x 1000
        if sign is not None:
            ds.PixelIntensityRelationshipSign = sign
        ds.save_as(path)
    return path


def test_a_native_run_is_read_subtracted_as_its_mask_subtraction_sequence_says(tmp_path: Path):
    """A native run's frames are radiographs (the skull in each); its Mask Subtraction Sequence (AVG_SUB of frames 1-2)
    is applied in the logarithm of the intensity: the contrast frames come out with the skull gone and the vessel's
    added attenuation left, on the 8-bit display scale, MONOCHROME2."""
    run, skull, added = _native_run()
    path = _write_native(run, tmp_path / "native.dcm", {"mask_frames": (0, 1), "contrast_frames": (2, 3, 4, 5)})
    ds = pydicom.dcmread(path, stop_before_pixels=True)
    assert ds.RecommendedViewingMode == "SUB" and ds.MaskSubtractionSequence[0].MaskOperation == "AVG_SUB"
    assert list(ds.MaskSubtractionSequence[0].MaskFrameNumbers) == [1, 2]
    assert list(ds.MaskSubtractionSequence[0].ApplicableFrameRange) == [3, 6]
    read = read_dsa(path)
    assert read.frames.shape == (4, 64, 80)
    assert "AVG_SUB" in read.metadata["subtraction"] and "frame(s) 1, 2" in read.metadata["subtraction"]
    assert read.photometric_interpretation == "MONOCHROME2" and read.metadata["bits_stored"] == 8
    attenuation = read.attenuation()
    assert np.corrcoef(attenuation.ravel(), added[2:].ravel())[0, 1] > 0.999
    peak = np.percentile(attenuation.max(axis=0), 99.9) - attenuation.min()
    assert peak == pytest.approx(0.75 * 255, rel=0.02)
    background = added[-1] < 1e-3
    assert attenuation[:, background].std() < 0.01 * peak  # the skull has gone: flat beside the vessel
    # the same frames read natively (no sequence) keep the skull: what GeoPose read before
    plain = read_dsa(write_dsa_dicom(run, tmp_path / "plain.dcm"))
    assert "subtraction" not in plain.metadata and plain.frames.shape == (6, 64, 80)
    skull_left = plain.attenuation()[2:, background]
    assert skull_left.std() > 0.1 * np.ptp(plain.attenuation())


def test_the_mask_sub_pixel_shift_moves_the_mask_as_dicom_says(tmp_path: Path):
    """The live frames see the head 2 rows down and 3 columns left of the mask: Mask Sub-pixel Shift (2, 3) (positive
    row: towards the last row; positive column: towards the first column) takes the skull out; no shift or the
    opposite one leaves it as residue."""
    run, skull, added = _native_run(shift_px=(2, 3))
    base = {"mask_frames": (0, 1), "contrast_frames": (2, 3, 4, 5)}
    residue = {}
    for name, shift in (("right", (2.0, 3.0)), ("none", (0.0, 0.0)), ("opposite", (-2.0, -3.0))):
        read = read_dsa(_write_native(run, tmp_path / f"{name}.dcm", base | {"shift_px": shift}))
        inner = (slice(6, -6), slice(6, -6))
        a = read.attenuation()[:, inner[0], inner[1]]
        residue[name] = 1.0 - np.corrcoef(a.ravel(), added[2:, inner[0], inner[1]].ravel())[0, 1]
    assert residue["right"] < 0.001
    assert residue["none"] > 20 * residue["right"] and residue["opposite"] > 20 * residue["right"]


def test_log_runs_and_the_intensity_relationship_sign(tmp_path: Path):
    """LOG values are subtracted as stored; a Pixel Intensity Relationship Sign of -1 (values fall with intensity)
    turns the difference round, so the vessel comes out bright either way."""
    run, _, added = _native_run(relationship="LOG")
    plan = {"mask_frames": (0, 1), "contrast_frames": (2, 3, 4, 5)}
    read = read_dsa(_write_native(run, tmp_path / "log.dcm", plan, relationship="LOG"))
    assert "LOG values" in read.metadata["subtraction"]
    assert np.corrcoef(read.attenuation().ravel(), added[2:].ravel())[0, 1] > 0.999
    flipped = _run(-run.frames, offset=(0.0, 0.0))
    read = read_dsa(_write_native(flipped, tmp_path / "log_minus.dcm", plan, relationship="LOG", sign=-1))
    assert np.corrcoef(read.attenuation().ravel(), added[2:].ravel())[0, 1] > 0.999


@pytest.mark.parametrize("change, message", [
    (lambda item: setattr(item, "MaskOperation", "TID"), "asks for TID"),
    (lambda item: setattr(item, "MaskFrameNumbers", [1, 9]), r"Mask Frame Numbers \[1, 9\] .* outside the run.s frames 1..6"),
    (lambda item: setattr(item, "ApplicableFrameRange", [3, 7]), "Applicable Frame Range"),
    (lambda item: setattr(item, "ApplicableFrameRange", [3, 4, 5]), "is not pairs"),
    (lambda item: delattr(item, "MaskFrameNumbers"), "names no Mask Frame Numbers"),
    (lambda item: setattr(item, "MaskSubPixelShift", [0.5, 300.0]), "Mask Sub-pixel Shift"),
])
def test_a_mask_subtraction_that_cannot_be_followed_is_refused_by_name(tmp_path: Path, change, message):
    run, _, _ = _native_run()
    path = _write_native(run, tmp_path / "native.dcm", {"mask_frames": (0, 1), "contrast_frames": (2, 3, 4, 5)})
    ds = pydicom.dcmread(path)
    change(ds.MaskSubtractionSequence[0])
    ds.save_as(path)
    with pytest.raises(InputError, match=message) as err:
        read_dsa(path)
    assert "export the run subtracted" in str(err.value) and "\n" not in str(err.value)


def test_contrast_frame_averaging_and_the_default_frame_range(tmp_path: Path):
    """Contrast Frame Averaging 2 averages each contrast frame with the next before the mask is subtracted; without an
    Applicable Frame Range every frame that leaves room for the averaging is a contrast frame (1..T-1 here)."""
    run, _, added = _native_run()
    path = _write_native(run, tmp_path / "avg.dcm", {"mask_frames": (0,), "contrast_frames": (2, 3, 4), "contrast_averaging": 2})
    read = read_dsa(path)
    expected = (added[2:5] + added[3:6]) / 2
    assert read.frames.shape == (3, 64, 80) and "2 contrast frames averaged" in read.metadata["subtraction"]
    assert np.corrcoef(read.attenuation().ravel(), expected.ravel())[0, 1] > 0.999
    ds = pydicom.dcmread(path)
    del ds.MaskSubtractionSequence[0].ApplicableFrameRange
    ds.save_as(path)
    assert read_dsa(path).frames.shape == (5, 64, 80)  # frames 1..5 of 6, each averaged with the next


def test_a_native_run_of_unknown_intensity_relationship_is_refused(tmp_path: Path):
    """Whether to take the logarithm first depends on Pixel Intensity Relationship: a value outside LIN, LOG and DISP is
    refused by name rather than guessed."""
    run, _, _ = _native_run()
    path = _write_native(run, tmp_path / "native.dcm", {"mask_frames": (0, 1), "contrast_frames": (2, 3, 4, 5)})
    ds = pydicom.dcmread(path)
    ds.PixelIntensityRelationship = "OTHER"
    ds.save_as(path)
    with pytest.raises(InputError, match="Pixel Intensity Relationship is 'OTHER', not one of LIN, LOG, DISP"):
        read_dsa(path)
