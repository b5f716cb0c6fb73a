"""Issue 16's table of bad inputs, one test (or parameter) per row: each is refused with one
line that names the problem and the remedy, or (valid but unusual inputs) handled correctly."""

from __future__ import annotations

import argparse
import gzip
import json
import re
import struct
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.encaps import generate_frames
from pydicom.uid import JPEG2000Lossless

from geopose.cta import load_cta, save_volume, validate_cta
from geopose.dsa import DSARun, read_dsa, run_from_geometry, write_dsa_dicom, write_dsa_nifti
from geopose.dsa.readers import sidecar_path
from geopose.errors import InputError
from geopose.geometry import CArmAngles, Detector
from geopose.nets.checkpoint import import_checkpoint
from geopose.nets.manifest import MANIFEST_NAME, verify_models
from geopose.options import RefineOptions, RegistrationOptions, TTOSchedule, setting_paths
from geopose.register.cli import options_from_args, registration_option_args
from geopose.volume import Volume

REPO = Path(__file__).resolve().parents[2]
GEOMETRY = {"primary_deg": 0.0, "secondary_deg": 0.0, "sid_mm": 1100.0, "sod_mm": 750.0, "pixel_spacing_mm": (0.4, 0.4)}


def _head_run(frames: int = 4, size: int = 64, photometric: str = "MONOCHROME2") -> DSARun:
    """A head-like disc whose vessel fills over time, stored as MONOCHROME2 (absorbers dark)."""
    yy, xx = np.mgrid[:size, :size].astype(float)
    head = np.where(np.hypot(yy - size / 2, xx - size / 2) < 0.4 * size, 600.0, 0.0)
    att = np.stack([head + np.where((np.abs(xx - size / 2) < 2) & (yy < size * (0.3 + 0.1 * t)), 300.0 + 20 * t, 0.0)
                    for t in range(frames)])
    run = DSARun.from_attenuation(att, Detector(size, size, (0.4, 0.4), 1100.0), CArmAngles(10.0, -5.0, 1100.0, 750.0), 66.7)
    run.metadata["photometric_interpretation"] = photometric
    return run


def _cta(shape=(24, 40, 40), spacing=2.0) -> Volume:
    k, j, i = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(float)
    r = np.hypot(j - shape[1] / 2, i - shape[2] / 2)
    hu = np.where(r < 0.4 * shape[1], 40.0, -1000.0) + np.where((r > 0.33 * shape[1]) & (r < 0.4 * shape[1]), 1100.0, 0.0)
    return Volume(hu.astype(np.float32), np.diag([spacing, spacing, spacing, 1.0]))


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


# ------------------------------------------------------------------ accepted silently


@pytest.mark.parametrize("name", ["cta.nii", "cta.nii.gz"])
def test_nifti_cut_at_half_is_refused(tmp_path: Path, name: str):
    path = save_volume(_cta(), tmp_path / name)
    data = path.read_bytes()
    if name.endswith(".gz"):
        raw = gzip.decompress(data)
        path.write_bytes(gzip.compress(raw[: len(raw) // 2]))  # a complete gzip stream of half the file
    else:
        path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as info:
        load_cta(path)
    assert "is truncated" in _one_line(info) and "re-export the image or copy the complete file again" in str(info.value)
    cut = tmp_path / ("cut" + name[3:])
    cut.write_bytes(data[: len(data) // 2])  # the raw bytes cut: the .gz stream itself ends early
    with pytest.raises(InputError, match="truncated"):
        load_cta(cut)


@pytest.mark.parametrize("factor, message", [(0.5, "holds more voxel data than its header declares"), (342, "is truncated")])
def test_nifti_header_dimensions_must_match_the_data(tmp_path: Path, factor: float, message: str):
    path = save_volume(_cta(), tmp_path / "cta.nii")
    data = bytearray(path.read_bytes())
    dims = list(struct.unpack("<8h", data[40:56]))
    dims[2] = int(dims[2] * factor)  # rows halved, or the 16416-row header of the issue
    data[40:56] = struct.pack("<8h", *dims)
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=message):
        load_cta(path)


@pytest.mark.parametrize("name", ["cta.nii", "cta.nii.gz", "cta.mha", "cta.nrrd"])
def test_nan_and_inf_voxels_are_seen_before_simpleitk(tmp_path: Path, name: str):
    vol = _cta()
    vol.array[3, 4, 5], vol.array[6, 7, 8] = np.nan, np.inf
    path = save_volume(vol, tmp_path / name)
    with pytest.raises(InputError) as info:
        load_cta(path)
    assert "has 2 NaN/infinite voxels: replace them" in _one_line(info)


def test_nan_frames_in_a_nifti_dsa_run_are_refused(tmp_path: Path):
    run = _head_run()
    path = write_dsa_nifti(run, tmp_path / "run.nii")
    image = sitk.ReadImage(str(path))
    array = sitk.GetArrayFromImage(image)
    array[1, 5, 5] = np.nan
    out = sitk.GetImageFromArray(array)
    out.CopyInformation(image)
    sitk.WriteImage(out, str(path))
    with pytest.raises(InputError, match="1 NaN/infinite voxels"):
        read_dsa(path)


def _ct_series(folder: Path, positions_mm: list[float], *, tilt_shift_mm: float = 0.0, size: int = 40) -> None:
    """Axial slices at the given z (LPS), each ``tilt_shift_mm * z`` mm further along y (a gantry tilt)."""
    folder.mkdir(parents=True)
    series = pydicom.uid.generate_uid()
    jj, ii = np.mgrid[:size, :size]
    for k, z in enumerate(positions_mm):
        ds = pydicom.Dataset()
        ds.file_meta = pydicom.dataset.FileMetaDataset()
        ds.file_meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
        ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID = pydicom.uid.CTImageStorage
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID = pydicom.uid.generate_uid()
        ds.Modality, ds.SeriesInstanceUID, ds.InstanceNumber = "CT", series, k + 1
        ds.ImagePositionPatient = [-20.0, -20.0 + tilt_shift_mm * z, z]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [1.0, 1.0]
        ds.Rows = ds.Columns = size
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.RescaleIntercept, ds.RescaleSlope = -1024, 1
        hu = np.where(np.hypot(jj - size / 2, ii - size / 2) < size / 3, 1000 + 20 * k, -1000)
        ds.PixelData = (hu + 1024).astype(np.uint16).tobytes()
        ds.save_as(folder / f"{k:03d}.dcm", enforce_file_format=True)


def test_dicom_series_with_a_missing_slice_is_refused(tmp_path: Path):
    z = [2.0 * k for k in range(16) if k != 9]
    _ct_series(tmp_path / "ct", z)
    with pytest.raises(InputError) as info:
        load_cta(tmp_path / "ct")
    assert "1 slice(s) missing from the series: 008.dcm and 009.dcm are 4 mm apart where the series steps 2 mm" in _one_line(info)
    assert "copy the complete series again" in str(info.value)


def test_dicom_series_with_all_slices_at_one_position_is_refused(tmp_path: Path):
    _ct_series(tmp_path / "ct", [0.0] * 12)
    with pytest.raises(InputError, match="all 12 slices of the series sit at the same position.*export the series again"):
        load_cta(tmp_path / "ct")


def test_tiny_cta_is_refused(tmp_path: Path):
    path = save_volume(_cta((4, 4, 4)), tmp_path / "tiny.nii.gz")
    with pytest.raises(InputError, match=r"has size \(4, 4, 4\) \(i, j, k\): a CTA has 8\.\.4096 voxels along each axis"):
        load_cta(path)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"frames": np.zeros((3, 2, 2), np.float32)}, "2 x 2 pixels per frame: a DSA frame has 32..4096"),
        ({"sod_mm": 1.0}, r"sod_mm = 1.0 is outside the plausible range 200..1500"),
        ({"pixel_spacing_mm": (100.0, 100.0)}, r"pixel_spacing_mm = 100.0 is outside the plausible range 0.02..5"),
        ({"primary_deg": float("nan")}, r"primary_deg = nan is outside the plausible range -360..360"),
        ({"primary_deg": 1e9}, r"primary_deg = 1000000000.0 is outside the plausible range -360..360"),
        ({"sid_mm": 1e9}, r"sid_mm = 1000000000.0 is outside the plausible range 500..2000"),
        ({"sid_mm": 1e6}, r"sid_mm = 1000000.0 is outside the plausible range 500..2000"),
        ({"sod_mm": 1200.0, "sid_mm": 1100.0}, "not shorter than the source-to-detector distance"),
        ({"secondary_deg": 120.0}, r"secondary_deg = 120.0 is outside the plausible range -90..90"),
    ],
)
def test_implausible_dsa_geometry_is_refused_by_bound(tmp_path: Path, change: dict, message: str):
    change = dict(change)
    frames = change.pop("frames", _head_run().frames)
    start = time.perf_counter()
    with pytest.raises(InputError) as info:
        run_from_geometry(frames, {**GEOMETRY, **change}, name="node 'DSA PA'", source="Slicer node")
    assert time.perf_counter() - start < 1.0  # refused before any work (SID 1e9 used to allocate 90 GB)
    assert re.search(message, _one_line(info)), str(info.value)
    if change:  # the same check for a file's values (here given as overrides)
        path = write_dsa_dicom(run_from_geometry(frames, GEOMETRY, name="ok", source="test"), tmp_path / "run.dcm")
        with pytest.raises(InputError) as info:
            read_dsa(path, **change)
        assert re.search(message, _one_line(info)) and "CLI: --pa-" in str(info.value)


def test_run_from_geometry_refuses_unknown_keys():
    with pytest.raises(InputError, match=r"unknown geometry key\(s\) \['sdd'\]"):
        run_from_geometry(_head_run().frames, {**GEOMETRY, "sdd": 1000.0}, name="node", source="Slicer node")


def test_monochrome1_on_monochrome2_data_is_refused_unless_confirmed(tmp_path: Path):
    path = write_dsa_dicom(_head_run(), tmp_path / "m2.dcm")
    ds = pydicom.dcmread(path)
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.save_as(path, enforce_file_format=True)
    with pytest.raises(InputError) as info:
        read_dsa(path)
    assert "declares MONOCHROME1 but its frames look like MONOCHROME2" in _one_line(info)
    assert "--pa-photometric" in str(info.value)
    run = read_dsa(path, photometric_interpretation="MONOCHROME2")
    assert run.photometric_interpretation == "MONOCHROME2" and run.metadata["photometric_source"] == "override"
    att = run.attenuation().mean(axis=0)
    assert att[32, 32] > att[2, 2]  # the head comes out bright, as the pipeline needs
    genuine = write_dsa_dicom(DSARun(run.frames.max() - run.frames, run.detector, run.angles, 66.7,
                                     {"photometric_interpretation": "MONOCHROME1"}), tmp_path / "m1.dcm")
    assert read_dsa(genuine).photometric_interpretation == "MONOCHROME1"  # a true MONOCHROME1 run is read


def _j2k_run(tmp_path: Path, frames: int = 15) -> Path:
    path = write_dsa_dicom(_head_run(frames), tmp_path / "raw.dcm")
    ds = pydicom.dcmread(path)
    ds.compress(JPEG2000Lossless)
    ds.save_as(tmp_path / "j2k.dcm", enforce_file_format=True)
    return tmp_path / "j2k.dcm"


def test_jpeg2000_with_flipped_bytes_is_refused_or_identical(tmp_path: Path):
    path = _j2k_run(tmp_path)
    original = read_dsa(path)
    assert "re-encoded and compared" in original.metadata["pixel_integrity"]
    data = path.read_bytes()
    ds = pydicom.dcmread(path)
    streams = list(generate_frames(ds.PixelData, number_of_frames=15))
    rng = np.random.default_rng(16)
    refused = 0
    for k in range(0, 15, 2):  # damage 8 of 15 frames, in their entropy-coded data
        stream = streams[k]
        body = stream.find(b"\xff\x93") + 2
        pos = data.find(stream) + int(rng.integers(body, len(stream) - 2))
        bad = bytearray(data)
        bad[pos] ^= 0x10
        (tmp_path / "bad.dcm").write_bytes(bytes(bad))
        try:
            again = read_dsa(tmp_path / "bad.dcm")
        except InputError as exc:
            assert f"frame {k + 1} of 15" in str(exc) and "is damaged" in str(exc)
            refused += 1
            continue
        np.testing.assert_array_equal(again.frames, original.frames)  # accepted only if identical
    assert refused >= 6


def test_angles_are_wrapped_on_read(tmp_path: Path):
    run = _head_run()
    path = write_dsa_dicom(run, tmp_path / "run.dcm")
    ds = pydicom.dcmread(path)
    ds.PositionerPrimaryAngle = "346.6"
    ds.save_as(path, enforce_file_format=True)
    back = read_dsa(path)
    assert back.angles.primary_deg == pytest.approx(-13.4) and back.view_role == "PA"


@pytest.mark.parametrize("argv, message", [
    (["--iterations", "-1"], "--iterations: tto.iterations = -1 is outside the plausible range 0..2000"),
    (["--refine-steps", "-3"], "--refine-steps: refine.steps = -3 is outside the plausible range 0..20"),
    (["--tto-px", "1"], "--tto-px: tto.px = 1 is outside the plausible range 32..1024"),
])
def test_register_options_are_checked_before_any_file_is_read(tmp_path: Path, capsys, argv: list[str], message: str):
    code, err = _cli(capsys, ["register", "--cta", "nowhere.nii", "--dsa-pa", "a.dcm", "--dsa-lat", "b.dcm", "--out", str(tmp_path / "o"), *argv])
    assert code == 2 and err.count("\n") == 1 and message in err
    assert not (tmp_path / "o").exists()


def test_fractional_iterations_are_refused():
    with pytest.raises(InputError, match="tto.iterations must be a whole number, got 2.7"):
        TTOSchedule(iterations=2.7)


def test_command_line_switches_reach_the_options():
    parser = argparse.ArgumentParser()
    registration_option_args(parser)
    assert options_from_args(parser.parse_args([])) == RegistrationOptions()
    options = options_from_args(parser.parse_args(["--no-search", "--independent-views", "--iterations", "7",
                                                   "--objective-silhouette", "clipped"]))
    assert options.search.enabled is False and options.independent_views is True and options.biplanar is False
    assert options.tto.iterations == 7 and options.objective.silhouette == "clipped"
    assert options.refine == RefineOptions() and options.tto.px is None  # flags not given keep the tree's defaults


@pytest.mark.parametrize("path", ["independent_views", "search.enabled", "biplanar", "objective.read_opacified"])
def test_switches_take_only_true_or_false(path: str):
    with pytest.raises(InputError, match=f"{path} must be True or False, got 'no'"):
        RegistrationOptions().replace(**{path: "no"})


def test_every_setting_has_one_flag_and_unknown_paths_are_refused():
    """The command line is generated from the options tree: one flag per offered setting, none twice."""
    flags = [s.flag for _, s in setting_paths() if s.cli]
    assert len(flags) == len(set(flags)) and {"--iterations", "--refine-steps", "--tto-px", "--search"} <= set(flags)
    with pytest.raises(InputError, match="unknown registration option"):
        RegistrationOptions().replace(**{"tto.steps": 3})
    with pytest.raises(InputError, match="tto.iterations must be given"):
        TTOSchedule(iterations=None)  # None only where the data decide (tto.px, render_px, ...)
    assert RegistrationOptions().replace(**{"tto.px": None, "device": "cuda:1"}).device == "cuda:1"


@pytest.mark.parametrize("array, message", [
    (np.where(_cta().array > 1000, np.nan, _cta().array), "NaN/infinite voxels"),
    (np.clip(_cta().array, 0, None) * 3.0, "has no negative values"),  # an MR-like volume
])
def test_validate_cta_is_the_check_for_volumes_from_no_file(array: np.ndarray, message: str):
    with pytest.raises(InputError, match=message):
        validate_cta(Volume(array.astype(np.float32), np.diag([2.0, 2.0, 2.0, 1.0])), name="CTA node")


def _models(tmp_path: Path) -> Path:
    folder = tmp_path / "models"
    folder.mkdir()
    entries = {}
    for kind in ("init", "refine"):
        f = folder / f"{kind}.pt"
        f.write_bytes(kind.encode() * 100)
        entries[kind] = {"file": f.name, "bytes": f.stat().st_size, "sha256": __import__("hashlib").sha256(f.read_bytes()).hexdigest()}
    (folder / MANIFEST_NAME).write_text(json.dumps({"schema_version": 1, "models": entries}))
    return folder


def test_models_without_manifest_are_refused_unless_allowed(tmp_path: Path):
    folder = _models(tmp_path)
    assert set(verify_models(folder)) == {"init", "refine"}
    (folder / MANIFEST_NAME).unlink()
    with pytest.raises(InputError) as info:
        verify_models(folder)
    assert "has no manifest.json, so its model files cannot be verified" in _one_line(info)
    assert "--allow-unverified-models" in str(info.value)


@pytest.mark.parametrize("edit, message", [
    (lambda e: e.update(file="../x.pt"), "names '../x.pt', which is not a file in the models folder"),
    (lambda e: e.update(file="/etc/hosts"), "names '/etc/hosts', which is not a file in the models folder"),
    (lambda e: e.pop("bytes"), "needs a 'file' name and a whole-number 'bytes'"),
    (lambda e: e.update(sha256="0" * 64), "does not match its size/SHA-256"),
])
def test_manifest_entries_are_validated_and_confined(tmp_path: Path, edit, message: str):
    folder = _models(tmp_path)
    (tmp_path / "x.pt").write_bytes(b"outside")
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    edit(manifest["models"]["init"])
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(InputError) as info:
        verify_models(folder)
    assert message in _one_line(info)


def test_manifest_entry_as_a_list_is_one_line(tmp_path: Path):
    folder = _models(tmp_path)
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    manifest["models"]["refine"] = list(manifest["models"]["refine"].values())
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="the refine model entry must be an object with 'file', 'bytes' and 'sha256', got list"):
        verify_models(folder)


# ------------------------------------------------------------------ real files read wrongly


def test_tilted_real_head_ct_is_resampled_where_its_slices_are(shared_data: Path):
    folder = shared_data / "ge_head_ct_tilt"
    vol = load_cta(folder)
    geo = vol.metadata["slice_geometry"]
    assert geo["resampled"] and geo["reason"] == "gantry tilt, uneven slice positions"
    assert geo["gantry_tilt_deg"] == pytest.approx(18.5, abs=0.05)
    assert min(geo["slice_gaps_mm"]) == pytest.approx(1.08, abs=0.01) and max(geo["slice_gaps_mm"]) == pytest.approx(6.99, abs=0.01)
    lps_to_ijk = np.linalg.inv(np.diag([-1.0, -1.0, 1.0, 1.0]) @ vol.ijk_to_ras)
    raw, resampled = [], []
    rng = np.random.default_rng(0)
    for f in sorted(folder.glob("*.dcm"))[::3]:
        ds = pydicom.dcmread(f)
        hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        ipp = np.array(ds.ImagePositionPatient, float)
        row, col = np.array(ds.ImageOrientationPatient[:3], float), np.array(ds.ImageOrientationPatient[3:], float)
        dr, dc = (float(v) for v in ds.PixelSpacing)
        jj, ii = np.nonzero(hu > 1000)  # bone
        for n in rng.choice(len(jj), min(40, len(jj)), replace=False):
            lps = ipp + ii[n] * dc * row + jj[n] * dr * col  # where the raw slice geometry puts this pixel
            i, j, k = np.rint((lps_to_ijk @ np.append(lps, 1.0))[:3]).astype(int)
            raw.append(hu[jj[n], ii[n]])
            resampled.append(vol.array[k, j, i])
    resampled = np.asarray(resampled)
    assert (resampled > 700).mean() > 0.9  # bone lands on bone
    assert np.corrcoef(raw, resampled)[0, 1] > 0.8
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(f) for f in sorted(folder.glob("*.dcm"))])
    naive = reader.Execute()  # the plain regular-grid read the issue describes
    naive_hu = sitk.GetArrayFromImage(naive)
    hits = []
    for f in sorted(folder.glob("*.dcm"))[::3]:
        ds = pydicom.dcmread(f)
        hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        ipp = np.array(ds.ImagePositionPatient, float)
        row, col = np.array(ds.ImageOrientationPatient[:3], float), np.array(ds.ImageOrientationPatient[3:], float)
        jj, ii = np.nonzero(hu > 1000)
        for n in rng.choice(len(jj), min(40, len(jj)), replace=False):
            lps = ipp + ii[n] * 0.48828 * row + jj[n] * 0.48828 * col
            i, j, k = np.rint(naive.TransformPhysicalPointToContinuousIndex(tuple(lps))).astype(int)
            if 0 <= k < naive_hu.shape[0]:
                hits.append(naive_hu[k, j, i] > 700)
    assert np.mean(hits) < 0.6  # ... which puts much of the skull elsewhere


def test_pixel_spacing_from_field_of_view_or_intensifier(tmp_path: Path):
    run = _head_run(size=512, frames=1)
    path = write_dsa_dicom(run, tmp_path / "ge.dcm")
    ds = pydicom.dcmread(path)
    del ds.ImagerPixelSpacing
    ds.FieldOfViewDimensions = [200]
    ds.IntensifierSize = "300"
    ds.save_as(path, enforce_file_format=True)
    back = read_dsa(path)
    assert back.detector.spacing_mm == (0.390625, 0.390625)
    assert back.metadata["geometry_sources"]["pixel_spacing_mm"] == "FieldOfViewDimensions (200 mm) / matrix (512 x 512)"
    del ds.FieldOfViewDimensions
    ds.save_as(path, enforce_file_format=True)
    back = read_dsa(path)
    assert back.detector.spacing_mm == (300 / 512, 300 / 512)
    assert back.metadata["geometry_sources"]["pixel_spacing_mm"].startswith("IntensifierSize (300 mm)")


# ------------------------------------------------------------------ tracebacks or hangs


def _cli(capsys, argv: list[str]) -> tuple[int, str]:
    """``geopose ARGV`` in this process (the entry point's own error handling): exit code and stderr."""
    from geopose.cli import main

    capsys.readouterr()
    code = main(argv)
    return code, capsys.readouterr().err


@pytest.mark.parametrize("kind", ["file", "dev_full", "under_a_file"])
def test_bad_out_is_refused_before_the_work(tmp_path: Path, capsys, kind: str):
    out = {"file": tmp_path / "result.txt", "dev_full": Path("/dev/full"), "under_a_file": tmp_path / "result.txt" / "sub"}[kind]
    (tmp_path / "result.txt").write_text("keep me")
    if kind == "dev_full" and not out.exists():
        pytest.skip("no /dev/full here")
    code, err = _cli(capsys, ["register", "--cta", str(tmp_path / "absent.nii.gz"), "--dsa-pa", "a.dcm", "--dsa-lat", "b.dcm",
                              "--out", str(out)])
    assert code == 2 and err.count("\n") == 1, err
    assert ("exists and is not a folder" in err) or ("cannot create the output folder" in err)
    assert "CTA not found" not in err  # --out is checked first
    assert (tmp_path / "result.txt").read_text() == "keep me"


@pytest.mark.parametrize("value, message", [
    ({"row": 0.3}, r"'pixel_spacing_mm' \(sidecar run.json\) in run.nii must be a number, got \{'row': 0.3\}"),
    ("abc", r"'pixel_spacing_mm' \(sidecar run.json\) in run.nii must be a number, got 'abc'"),
])
def test_sidecar_values_of_the_wrong_type_name_the_key(tmp_path: Path, value, message: str):
    path = write_dsa_nifti(_head_run(), tmp_path / "run.nii")
    keys = json.loads(sidecar_path(path).read_text())
    keys["pixel_spacing_mm"] = value
    sidecar_path(path).write_text(json.dumps(keys))
    with pytest.raises(InputError, match=message):
        read_dsa(path)


def test_deeply_nested_sidecar_is_one_line(tmp_path: Path):
    path = write_dsa_nifti(_head_run(), tmp_path / "run.nii")
    sidecar_path(path).write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(InputError) as info:
        read_dsa(path)
    assert "run.json is nested too deeply" in _one_line(info)


def _xa(tmp_path: Path) -> bytes:
    return write_dsa_dicom(_head_run(), tmp_path / "xa.dcm").read_bytes()


def test_corrupted_meta_group_length_and_element_lengths_are_one_line(tmp_path: Path):
    data = _xa(tmp_path)
    original = read_dsa(tmp_path / "xa.dcm")
    assert data[132:136] == b"\x02\x00\x00\x00"  # (0002,0000) group length, its value at 140
    for value in (0, 1, 7, 50, 199, 2**31, 2**32 - 1):
        bad = bytearray(data)
        bad[140:144] = struct.pack("<I", value)
        (tmp_path / "bad.dcm").write_bytes(bytes(bad))
        try:
            run = read_dsa(tmp_path / "bad.dcm")
        except InputError as exc:
            assert "bad.dcm" in str(exc) and "\n" not in str(exc)
            continue
        np.testing.assert_array_equal(run.frames, original.frames)  # pydicom 3 parses past it: the same image
    rows = data.find(b"\x28\x00\x10\x00US")  # Rows, a 2-byte value: length 3 misaligns the parse
    bad = bytearray(data)
    bad[rows + 6:rows + 8] = struct.pack("<H", 3)
    (tmp_path / "bad.dcm").write_bytes(bytes(bad))
    with pytest.raises(InputError) as info:
        read_dsa(tmp_path / "bad.dcm")
    assert "bad.dcm is a damaged DICOM file (pydicom: BytesLengthException:" in _one_line(info)


def test_corrupted_element_length_does_not_allocate(tmp_path: Path):
    """The Pixel Data length set to 0xFFFFFFF0 (pydicom reading the file path allocates 4 GiB for it): read
    in a worker limited to 512 MiB beyond its start, the same frames or a clean refusal, never MemoryError."""
    data = bytearray(_xa(tmp_path))
    original = read_dsa(tmp_path / "xa.dcm").frames
    at = data.rfind(b"\xe0\x7f\x10\x00") + 8
    data[at:at + 4] = struct.pack("<I", 0xFFFFFFF0)
    path = tmp_path / "bad.dcm"
    path.write_bytes(bytes(data))
    sys.path.insert(0, str(REPO / "Testing" / "fuzz"))
    import harness

    def case(index: int):
        if index == 1:  # the pixel data now ends 100 bytes early
            path.write_bytes(bytes(data[:-100]))
        try:
            run = read_dsa(path)
        except InputError as exc:
            return "xa", "length", "clean error", str(exc)
        return "xa", "length", "accepted, identical" if np.array_equal(run.frames, original) else "accepted, WRONG", ""

    report = harness.run_cases(case, [0, 1], describe=lambda i: ("xa", "length"), workers=1, timeout_s=60, memory_bytes=512 << 20)
    assert [r.outcome for r in report.results] == ["accepted, identical", "clean error"], report.results
    assert "the pixel data is truncated" in report.results[1].detail


def test_checkpoint_storage_size_is_bounded_before_reading(tmp_path: Path):
    """A storage whose zip entry declares 4 GiB (the issue's was a 6 GiB deflated storage in 28 MB) is
    refused from the zip directory, before anything is decompressed."""
    path = tmp_path / "geopose_like.ckpt"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", b"\x80\x02}q\x00.")
        z.writestr("archive/data/0", b"\x00" * 16)
    data = bytearray(path.read_bytes())
    central = data.rfind(b"PK\x01\x02")
    name_at = data.find(b"archive/data/0", central)
    entry = data.rfind(b"PK\x01\x02", 0, name_at)
    data[entry + 24:entry + 28] = struct.pack("<I", 0xFFFFFFF0)  # uncompressed size in the central directory
    path.write_bytes(bytes(data))
    start = time.perf_counter()
    with pytest.raises(InputError, match="declares .* bytes|more than the"):
        import_checkpoint(path, tmp_path / "out.pt")
    assert time.perf_counter() - start < 5.0


# ------------------------------------------------------------------ wrong messages


def test_missing_tag_message_names_the_register_options(shared_data: Path):
    with pytest.raises(InputError) as info:
        read_dsa(shared_data / "xa_sample" / "rubo_0002_xa_multiframe.dcm")
    text = _one_line(info)
    assert "(CLI: --pa-sid-mm / --lat-sid-mm ...)" in text
    assert "(CLI: --pa-pixel-spacing-mm / --lat-pixel-spacing-mm ROW COL)" in text
    assert "--sid-mm " not in text.replace("-pa-sid-mm", "").replace("-lat-sid-mm", "")


def test_truncated_uncompressed_dicom_is_called_truncated(tmp_path: Path):
    data = _xa(tmp_path)
    (tmp_path / "cut.dcm").write_bytes(data[: len(data) - 1000])
    with pytest.raises(InputError) as info:
        read_dsa(tmp_path / "cut.dcm")
    assert "the pixel data is truncated" in _one_line(info) and "pylibjpeg" not in str(info.value)
    (tmp_path / "cut600.dcm").write_bytes(data[:600])
    with pytest.raises(InputError) as info:
        read_dsa(tmp_path / "cut600.dcm")
    assert "declares an image but holds no pixel data: the file is truncated or damaged" in _one_line(info)
    assert "report or structure" not in str(info.value)


def test_all_zero_mask_is_called_empty(tmp_path: Path):
    path = save_volume(_cta().like(np.zeros((24, 40, 40), np.uint8)), tmp_path / "mask.nii.gz")
    with pytest.raises(InputError) as info:
        load_cta(path, check_hu=False)
    assert "mask.nii.gz is empty (0 everywhere)" in _one_line(info)


def test_internal_errors_print_one_line_and_a_traceback_file(tmp_path: Path, capsys, monkeypatch):
    (tmp_path / "x.ckpt").write_bytes(b"PK\x03\x04" + b"\x00" * 100)
    code, err = _cli(capsys, ["import-checkpoint", str(tmp_path / "x.ckpt"), "--out", str(tmp_path / "o.pt")])
    assert code == 2 and err.count("\n") == 1 and "not a PyTorch checkpoint" in err
    import geopose.nets.checkpoint as checkpoint

    monkeypatch.setattr(checkpoint, "import_checkpoint", lambda *a, **k: 1 / 0)  # an injected internal fault
    code, err = _cli(capsys, ["import-checkpoint", str(tmp_path / "x.ckpt"), "--out", str(tmp_path / "o.pt")])
    assert code == 1 and err.count("\n") == 1, err
    assert "internal error: ZeroDivisionError: division by zero (full traceback in " in err
    trace = Path(err.split("full traceback in ")[1].split(";")[0])
    assert "Traceback (most recent call last)" in trace.read_text() and "ZeroDivisionError" in trace.read_text()
    trace.unlink()
