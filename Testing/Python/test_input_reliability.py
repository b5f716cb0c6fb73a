"""Issue 31: a user's files are never touched, every CT is read right, inputs that cannot belong together
are refused. Refusals go through the real entry point (``geopose register``): exit 2, one line, before any
work, and every input byte-identical afterwards (checksummed)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import socket
import struct
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.uid import RLELossless, generate_uid

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "Testing" / "fuzz"))

from ct_encodings import ENCODINGS, INTERCEPT, head_hu, write_ct_series  # noqa: E402
from cli_targets import retagged  # noqa: E402
from jpeg_ls import encode_jpeg_ls  # noqa: E402

from geopose.consistency import check_inputs_belong_together  # noqa: E402
from geopose.cta import load_cta, save_volume, validate_cta  # noqa: E402
from geopose.dicomio import decode_frames, read_dataset  # noqa: E402
from geopose.dsa import DSARun, read_dsa, write_dsa_dicom  # noqa: E402
from geopose.errors import InputError  # noqa: E402
from geopose.geometry import CArmAngles, Detector  # noqa: E402
from geopose.register.evaluate import truth_for  # noqa: E402
from geopose.volume import Volume  # noqa: E402

STUDY = generate_uid(entropy_srcs=["issue31", "study"])


def _run(primary_deg: float, size: int = 64, frames: int = 3) -> DSARun:
    yy, xx = np.mgrid[:size, :size].astype(float)
    head = np.where(np.hypot(yy - size / 2, xx - size / 2) < 0.4 * size, 600.0, 0.0)
    att = np.stack([head + np.where((np.abs(xx - size / 2) < 2) & (yy < size * (0.3 + 0.1 * t)), 300.0, 0.0) for t in range(frames)])
    return DSARun.from_attenuation(att, Detector(size, size, (0.4, 0.4), 1100.0), CArmAngles(primary_deg, 0.0, 1100.0, 750.0), 66.7)


def _cta() -> Volume:
    k, j, i = np.mgrid[:24, :40, :40].astype(float)
    r = np.hypot(j - 20, i - 20)
    hu = np.where(r < 16, 40.0, -1000.0) + np.where((r > 13) & (r < 16), 1100.0, 0.0)
    return Volume(hu.astype(np.float32), np.diag([2.0, 2.0, 2.0, 1.0]))


@pytest.fixture()
def case(tmp_path: Path) -> dict[str, Path]:
    """A small CTA (NIfTI) and a PA + lateral pair of one patient and study (DICOM XA)."""
    folder = tmp_path / "case"
    folder.mkdir()
    save_volume(_cta(), folder / "cta.nii.gz")
    write_dsa_dicom(_run(0.0), folder / "dsa_pa.dcm", study_instance_uid=STUDY)
    write_dsa_dicom(_run(90.0), folder / "dsa_lat.dcm", study_instance_uid=STUDY)
    return {"cta": folder / "cta.nii.gz", "pa": folder / "dsa_pa.dcm", "lat": folder / "dsa_lat.dcm", "root": tmp_path}


def _checksums(*paths: Path) -> dict[str, str]:
    files = [f for p in paths for f in (sorted(p.rglob("*")) if p.is_dir() else [p]) if f.is_file()]
    return {str(f): hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


def _register(capsys, cta: Path, pa: Path, lat: Path, out: Path, *extra: str) -> tuple[int, str, float]:
    """``geopose register`` in this process: exit code, stderr, seconds (a hang is stopped after 60 s)."""
    from geopose.cli import main

    def hang(*_):
        raise TimeoutError("geopose register hung")

    capsys.readouterr()
    previous = signal.signal(signal.SIGALRM, hang)
    signal.alarm(60)
    start = time.perf_counter()
    try:
        code = main(["register", "--cta", str(cta), "--dsa-pa", str(pa), "--dsa-lat", str(lat), "--out", str(out), *extra])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    return code, capsys.readouterr().err, time.perf_counter() - start


def _refused(code: int, err: str, seconds: float, *words: str) -> None:
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("geopose register: error: "), err
    assert seconds < 20, f"refused only after {seconds:.1f} s"
    for word in words:
        assert word in err, err


# ----------------------------------------------------------------- 1. the output folder never holds an input


@pytest.mark.parametrize("where", ["inside_out_as_output_names", "out_is_the_inputs_folder", "out_is_a_parent", "out_is_the_root"])
def test_out_folder_holding_an_input_is_refused_and_nothing_is_touched(case, capsys, where: str):
    root = case["root"]
    pa, lat, out = case["pa"], case["lat"], root / "x"
    if where == "inside_out_as_output_names":  # the case: inputs named like the outputs inside --out
        out.mkdir()
        pa, lat = out / "result.json", out / "overlay_lat.png"
        shutil.copy(case["pa"], pa)
        shutil.copy(case["lat"], lat)
    elif where == "out_is_the_inputs_folder":
        out = case["cta"].parent
    elif where == "out_is_a_parent":
        out = root
    else:
        out = Path("/")
    before = _checksums(root)
    code, err, seconds = _register(capsys, case["cta"], pa, lat, out)
    _refused(code, err, seconds, "--out")
    assert ("filesystem root" in err) if where == "out_is_the_root" else ("holds none of the inputs" in err)
    assert _checksums(root) == before
    assert not (out / ".geopose.lock").exists() or where == "out_is_the_root" and not Path("/.geopose.lock").exists()


# ----------------------------------------------------------------- 3. special files


def _special(kind: str, root: Path) -> Path:
    if kind == "dev_zero":
        return Path("/dev/zero")
    if kind == "symlink_to_dev_zero":
        link = root / "run.dcm"
        link.symlink_to("/dev/zero")
        return link
    if kind == "fifo":
        fifo = root / "fifo.dcm"
        os.mkfifo(fifo)
        return fifo
    path = root / "sock.dcm"
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(path))
    return path


@pytest.mark.parametrize("kind, word", [("dev_zero", "character device"), ("symlink_to_dev_zero", "character device"),
                                        ("fifo", "FIFO"), ("socket", "socket")])
@pytest.mark.parametrize("role", ["pa", "cta"])
def test_special_files_are_refused_before_they_are_opened(case, capsys, kind: str, word: str, role: str):
    special = _special(kind, case["root"])
    inputs = {"cta": case["cta"], "pa": case["pa"], "lat": case["lat"], role: special}
    before = _checksums(case["cta"].parent)
    code, err, seconds = _register(capsys, inputs["cta"], inputs["pa"], inputs["lat"], case["root"] / "out")
    _refused(code, err, seconds, word, "regular file")
    assert _checksums(case["cta"].parent) == before


def test_a_fifo_inside_a_series_folder_is_refused(tmp_path: Path):
    hu, inside = head_hu()
    folder = write_ct_series(tmp_path / "ct", hu, inside, "uncompressed")
    os.mkfifo(folder / "slice_999.dcm")
    with pytest.raises(InputError, match="FIFO"):
        load_cta(folder)


def test_json_reads_stop_at_their_bound(tmp_path: Path):
    from geopose.inputpaths import read_bounded

    path = tmp_path / "big.json"
    path.write_bytes(b" " * 101)
    assert read_bounded(path, 101, "JSON file", "r") == b" " * 101
    with pytest.raises(InputError, match="has 101 bytes, more than the 100"):
        read_bounded(path, 100, "JSON file", "r")


# ----------------------------------------------------------------- 2. signed CT read right


@pytest.mark.parametrize("bits_stored", [16, 12])
@pytest.mark.parametrize("encoding", list(ENCODINGS))
def test_signed_ct_series_reads_as_pydicom_and_gdcm_do(tmp_path: Path, encoding: str, bits_stored: int):
    """Signed CT (padding -2000 stored = -3024 HU outside the scan circle) in every accepted transfer syntax:
    the voxels inside the circle equal pydicom's ``pixel_array`` and SimpleITK/GDCM's series read, the padding
    is air."""
    hu, inside = head_hu()
    if bits_stored == 12:
        hu = np.minimum(hu, (1 << 11) - 1 + INTERCEPT)
    folder = write_ct_series(tmp_path / "ct", hu, inside, encoding, bits_stored=bits_stored)
    files = sorted(str(f) for f in folder.iterdir())
    volume = load_cta(folder)
    by_pydicom = np.stack([pydicom.dcmread(f).pixel_array.astype(np.float64) + INTERCEPT for f in files])
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    by_gdcm = sitk.GetArrayFromImage(reader.Execute()).astype(np.float64)
    np.testing.assert_array_equal(by_pydicom, by_gdcm)
    np.testing.assert_array_equal(volume.array[:, inside[0]], by_pydicom[:, inside[0]])
    np.testing.assert_array_equal(by_pydicom[:, ~inside[0]], -3024.0)
    np.testing.assert_array_equal(volume.array[:, ~inside[0]], -1024.0)
    assert volume.metadata["pixel_padding"]["voxels"] == int((~inside).sum())


def test_jpeg_ls_test_encoder_round_trips_through_libjpeg():
    libjpeg = pytest.importorskip("libjpeg")
    rng = np.random.default_rng(3)
    image = rng.integers(0, 1 << 16, (24, 31))
    image[:6] = 63536  # runs
    np.testing.assert_array_equal(np.asarray(libjpeg.decode(encode_jpeg_ls(image, 16))), image)


def test_impossible_hu_distribution_is_refused_naming_the_share():
    """The issue's misread: padding read as +62,512 HU in a fifth of the voxels."""
    hu, inside = head_hu((12, 40, 40))
    misread = np.where(inside, hu, 62512.0).astype(np.float32)
    with pytest.raises(InputError) as exc:
        validate_cta(Volume(misread, np.diag([0.6, 0.6, 2.0, 1.0])))
    share = 100 * (~inside).mean()
    assert f"{share:.1f} % of its voxels lie outside -1100..4000 HU" in str(exc.value)
    assert "re-export" in str(exc.value)
    validate_cta(Volume(np.where(inside, hu, -3024.0).astype(np.float32), np.diag([0.6, 0.6, 2.0, 1.0])))  # padding: fine


# ----------------------------------------------------------------- 4. bounded allocations


def _bomb_series(folder: Path) -> Path:
    """The issue's 9 KB memory bomb: ten 8 x 8 slices at 0.05 mm, in-plane offsets, one uneven gap."""
    folder.mkdir()
    for k, z in enumerate((0, 1, 2, 3, 4, 5, 6, 7, 8, 9.5)):
        meta = pydicom.dataset.FileMetaDataset()
        meta.MediaStorageSOPClassUID = pydicom.uid.CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
        ds = pydicom.Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality, ds.SeriesInstanceUID = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID, "CT", "1.2.3"
        ds.ImageOrientationPatient, ds.PixelSpacing = [1, 0, 0, 0, 1, 0], [0.05, 0.05]
        ds.ImagePositionPatient = [8.0 * (k % 2) * k, 8.0 * k, 0.05 * z]
        ds.Rows = ds.Columns = 8
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.PixelData = np.full((8, 8), -1000, "<i2").tobytes()
        ds.save_as(folder / f"s{k}.dcm", enforce_file_format=True)
    return folder


def test_series_memory_bomb_is_refused_before_allocating(tmp_path: Path):
    folder = _bomb_series(tmp_path / "bomb")
    tracemalloc.start()
    start = time.perf_counter()
    with pytest.raises(InputError, match="times as many"):
        load_cta(folder)
    seconds, (_, peak) = time.perf_counter() - start, tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert seconds < 10 and peak < 50e6, (seconds, peak)


def test_compressed_run_decodes_into_one_float32_copy(tmp_path: Path):
    """Decoding allocates the float32 frames once (no int64 copies of the run)."""
    run = _run(0.0, size=256, frames=24)
    path = write_dsa_dicom(run, tmp_path / "raw.dcm")
    ds = pydicom.dcmread(path)
    ds.compress(RLELossless, generate_instance_uid=False)
    ds.save_as(tmp_path / "rle.dcm", enforce_file_format=True)
    dataset = read_dataset(tmp_path / "rle.dcm")
    tracemalloc.start()
    frames, _ = decode_frames(dataset, "rle.dcm", lambda shape: None)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert frames.dtype == np.float32
    assert peak < frames.nbytes + 3 * len(dataset.PixelData) + 4e6, (peak, frames.nbytes)


# ----------------------------------------------------------------- 5. inputs that cannot belong together


@pytest.mark.parametrize("tags, word", [({"PatientID": "SOMEONE-ELSE"}, "PatientID"),
                                        ({"StudyInstanceUID": generate_uid()}, "StudyInstanceUID")])
def test_lateral_of_another_patient_or_study_is_refused(case, capsys, tags: dict, word: str):
    lat = retagged(case["lat"], case["root"] / "lat_other.dcm", **tags)
    before = _checksums(case["cta"].parent, lat)
    code, err, seconds = _register(capsys, case["cta"], case["pa"], lat, case["root"] / "out")
    _refused(code, err, seconds, word, "--allow-id-mismatch")
    assert _checksums(case["cta"].parent, lat) == before
    assert not (case["root"] / "out" / "result.json").exists()


def test_the_same_run_for_both_views_says_so(case, capsys):
    code, err, seconds = _register(capsys, case["cta"], case["pa"], case["pa"], case["root"] / "out")
    _refused(code, err, seconds, "are the same data", "one each")
    assert "swap" not in err
    copy = retagged(case["pa"], case["root"] / "copy.dcm", PatientName="Copy^Same")  # the same instance, rewritten
    code, err, seconds = _register(capsys, case["cta"], case["pa"], copy, case["root"] / "out")
    _refused(code, err, seconds, "the same DICOM instance")


def test_cta_series_of_another_patient_is_refused(case, capsys):
    hu, inside = head_hu((24, 40, 40))
    cta = write_ct_series(case["root"] / "ct", hu, inside, "uncompressed", patient_id="SOMEONE-ELSE")
    code, err, seconds = _register(capsys, cta, case["pa"], case["lat"], case["root"] / "out")
    _refused(code, err, seconds, "the CTA has PatientID 'SOMEONE-ELSE', the PA run 'GEOPOSE-PHANTOM'", "--allow-id-mismatch")


def test_override_accepts_differing_ids_and_records_it(case):
    runs = {"pa": read_dsa(case["pa"]), "lat": read_dsa(retagged(case["lat"], case["root"] / "l.dcm", PatientID="ANON-2"))}
    with pytest.raises(InputError, match="PatientID"):
        check_inputs_belong_together(load_cta(case["cta"]), runs)
    entry = check_inputs_belong_together(load_cta(case["cta"]), runs, allow_id_mismatch=True)
    assert entry["allow_id_mismatch"] is True
    assert entry["mismatches_accepted"] == ["the PA run has PatientID 'GEOPOSE-PHANTOM', the LAT run 'ANON-2'"]
    assert "PatientID cta/pa" in entry["not_compared"]  # a NIfTI CTA carries no PatientID
    json.dumps(entry)


def test_shipped_case_belongs_together():
    """The phantom case the Slicer self-test and the README ship passes the gate a user's case goes through
    (its two runs carried different StudyInstanceUIDs until session 30: `geopose register` refused it)."""
    shipped = Path(__file__).resolve().parents[2] / "Resources" / "Testing" / "phantom_seed0_2mm"
    runs = {key: read_dsa(shipped / f"dsa_{key}.dcm") for key in ("pa", "lat")}
    entry = check_inputs_belong_together(load_cta(shipped / "cta.nii.gz"), runs)
    assert entry["mismatches_accepted"] == []


# ----------------------------------------------------------------- 6., 7. truth.json, remedies, sform/qform


def _truth_files(folder: Path, volume: Volume, *, shape=None) -> None:
    pose = np.eye(4).tolist()
    truth = {"views": {"pa": {"pose_camera_to_world": pose}, "lat": {"pose_camera_to_world": pose}},
             "labels": {"ica_left": 2}, "shape_ijk": list(shape or volume.shape_ijk), "ijk_to_ras": volume.ijk_to_ras.tolist()}
    (folder / "truth.json").write_text(json.dumps(truth))
    (folder / "centerlines.json").write_text(json.dumps({"centerlines": [{"label": 2, "points_mm": [[0, 0, 0], [1, 1, 1]]}]}))


def test_truth_json_is_checked_before_the_work(case):
    cta = load_cta(case["cta"])
    folder = case["cta"].parent
    _truth_files(folder, cta)
    truth, note = truth_for(case["cta"], cta)
    assert truth is not None and note is None
    _truth_files(folder, cta, shape=(9, 9, 9))
    truth, note = truth_for(case["cta"], cta)
    assert truth is None and "belongs to another case" in note
    (folder / "truth.json").write_text(json.dumps({"something": "else"}))  # the KeyError after the work
    truth, note = truth_for(case["cta"], cta)
    assert truth is None and note.startswith("ground truth ignored") and "not a geopose phantom's" in note


def test_two_series_remedy_names_an_option_the_cli_has(tmp_path: Path, capsys):
    from geopose.cli import build_parser

    hu, inside = head_hu((24, 40, 40))
    folder = write_ct_series(tmp_path / "ct", hu, inside, "uncompressed", series_uid="1.2.826.0.1.1")
    write_ct_series(tmp_path / "other", hu, inside, "uncompressed", series_uid="1.2.826.0.1.2")
    for f in (tmp_path / "other").iterdir():
        f.rename(folder / f"b_{f.name}")
    with pytest.raises(InputError, match="--cta-series-uid UID"):
        load_cta(folder)
    args = build_parser().parse_args(["register", "--cta", str(folder), "--dsa-pa", "a", "--dsa-lat", "b", "--out", "o",
                                      "--cta-series-uid", "1.2.826.0.1.2"])
    assert args.cta_series_uid == "1.2.826.0.1.2"
    assert load_cta(folder, series_uid=args.cta_series_uid).metadata["dicom_ids"]["SeriesInstanceUID"] == "1.2.826.0.1.2"


def test_contradicting_sform_and_qform_get_a_note(tmp_path: Path):
    path = tmp_path / "cta.nii"
    save_volume(_cta(), path)
    assert "orientation_note" not in load_cta(path).metadata
    data = bytearray(path.read_bytes())
    srow = list(struct.unpack("<12f", data[280:328]))
    srow[0], srow[3] = -srow[0], -srow[3] + 80.0  # mirror the sform left-right
    data[280:328] = struct.pack("<12f", *srow)
    path.write_bytes(bytes(data))
    note = load_cta(path).metadata["orientation_note"]
    assert "sform and qform disagree" in note and "mirrored" in note


def test_jpeg_ls_run_decodes_like_the_uncompressed_one(tmp_path: Path):
    """A DSA run in JPEG-LS (the test encoder of Testing/fuzz; no pydicom encoder is installed) reads frame for frame
    as its uncompressed original."""
    run = _run(0.0)
    src = write_dsa_dicom(run, tmp_path / "raw.dcm")
    ds = pydicom.dcmread(src)
    stored = ds.pixel_array.reshape(int(ds.NumberOfFrames), ds.Rows, ds.Columns)
    ds.PixelData = pydicom.encaps.encapsulate([encode_jpeg_ls(frame, int(ds.BitsStored)) for frame in stored])
    ds["PixelData"].VR = "OB"
    ds["PixelData"].is_undefined_length = True
    ds.file_meta.TransferSyntaxUID = pydicom.uid.JPEGLSLossless
    ds.save_as(tmp_path / "jls.dcm", enforce_file_format=True)
    np.testing.assert_array_equal(read_dsa(tmp_path / "jls.dcm").frames, read_dsa(src).frames)
