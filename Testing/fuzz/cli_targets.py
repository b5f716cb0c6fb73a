"""CLI-level fuzz cases: ``geopose register`` run as a user runs it, on inputs arranged to collide with the
output folder, special files, inputs that cannot belong together, and the CT encodings hospital archives use.

Originals (built once): a small CTA (NIfTI), a signed CT series (DICOM), a PA and a lateral run (DICOM XA)
of one patient and study, and a lateral run as NIfTI + JSON sidecar. Every case copies them into a fresh
folder, arranges one situation drawn from ``rng([seed, index])`` and runs the real entry point
(``geopose.cli.main``) in the forked worker, then checks:

* ``clean error``: exit 2, one ``geopose register: error:`` line naming what the situation is about, every
  input byte-identical (SHA-256 before and after), nothing written into an input's folder;
* anything else (exit 0 or 1, several lines, a missing word, an input changed) is ``accepted, WRONG`` /
  ``other exception``.

``ct_encoding`` cases read a series of a random transfer syntax, BitsStored and padding with the CTA reader
the CLI calls (``load_cta``; a full registration per case would take minutes) and compare it with pydicom's
``pixel_array`` and SimpleITK/GDCM: ``accepted, faithful`` when the voxels inside the scan circle equal both
and the padding reads as air. ``ct_misdeclared`` cases are such a series with PixelRepresentation set to 0
(signed data declared unsigned: the padding reads as e.g. +62,512 HU): through the CLI, refused by the HU or
the BitsStored check, unless the unsigned reading is plausible CT (a 12-bit pattern can be), which must then
equal pydicom's reading of the header as it stands (``accepted, faithful``; the CLI is not run).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import shutil
import socket
import stat
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk
from pydicom.uid import generate_uid

from ct_encodings import ENCODINGS, INTERCEPT, head_hu, write_ct_series

import geopose.cli
from geopose.cta import load_cta, save_volume
from geopose.dsa import DSARun, write_dsa_dicom, write_dsa_nifti
from geopose.errors import InputError
from geopose.geometry import CArmAngles, Detector
from geopose.volume import Volume

__all__ = ["CLI_TARGETS", "build_cli_originals", "run_cli_case", "describe_cli_case"]

CLI_TARGETS = ("out_collision", "special_file", "mismatch", "ct_encoding", "ct_misdeclared")
OUTPUT_NAMES = ("result.json", "overlay_pa.png", "overlay_lat.png", ".geopose.lock", "notes.txt")
PATIENT, STUDY = "FUZZ-PATIENT", generate_uid(entropy_srcs=["cli-fuzz", "study"])


def _run(primary_deg: float, size: int = 64) -> DSARun:
    yy, xx = np.mgrid[:size, :size].astype(float)
    head = np.where(np.hypot(yy - size / 2, xx - size / 2) < 0.4 * size, 600.0, 0.0)
    att = np.stack([head + np.where((np.abs(xx - size / 2) < 2) & (yy < size * (0.3 + 0.1 * t)), 300.0, 0.0) for t in range(3)])
    return DSARun.from_attenuation(att, Detector(size, size, (0.4, 0.4), 1100.0), CArmAngles(primary_deg, 0.0, 1100.0, 750.0), 66.7)


def build_cli_originals(root: Path) -> None:
    root.mkdir(parents=True, exist_ok=True)
    k, j, i = np.mgrid[:24, :40, :40].astype(float)
    r = np.hypot(j - 20, i - 20)
    hu = np.where(r < 16, 40.0, -1000.0) + np.where((r > 13) & (r < 16), 1100.0, 0.0)
    save_volume(Volume(hu.astype(np.float32), np.diag([2.0, 2.0, 2.0, 1.0])), root / "cta.nii.gz")
    series_hu, inside = head_hu((24, 40, 40))
    write_ct_series(root / "ct_series", series_hu, inside, "uncompressed", patient_id=PATIENT, study_uid=generate_uid())
    for name, primary in (("pa", 0.0), ("lat", 90.0)):
        run = _run(primary)
        run.metadata.update(PatientID=PATIENT)
        write_dsa_dicom(run, root / f"{name}.dcm", patient_id=PATIENT, study_instance_uid=STUDY)
    write_dsa_nifti(_run(90.0), root / "lat_nifti" / "run.nii")


def describe_cli_case(seed: int, index: int) -> tuple[str, str]:
    return CLI_TARGETS[index % len(CLI_TARGETS)], ""


# ------------------------------------------------------------------ checks


def _tree(paths: list[Path]) -> dict[str, str]:
    """SHA-256 of every regular file under ``paths`` (special files are named, not read)."""
    out = {}
    for top in paths:
        for f in sorted(top.rglob("*")) if top.is_dir() else [top]:
            mode = os.stat(f, follow_symlinks=False).st_mode if os.path.lexists(f) else 0
            if stat.S_ISREG(mode):
                out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
            elif mode:
                out[str(f)] = f"special {stat.S_IFMT(mode)}"
    return out


def _cli(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = geopose.cli.main(["register", *argv])
    return code, err.getvalue()


def _verdict(code: int, err: str, words: tuple[str, ...], before: dict, after: dict) -> tuple[str, str]:
    if before != after:
        changed = sorted(set(before.items()) ^ set(after.items()))
        return "accepted, WRONG", f"inputs changed: {changed[:3]}"
    if code == 1:
        return "other exception", err
    if code != 2:
        return "accepted, WRONG", f"exit {code}: {err[-300:]}"
    if err.count("\n") != 1 or not err.startswith("geopose register: error: "):
        return "accepted, WRONG", f"not one error line: {err[:300]!r}"
    missing = [w for w in words if not any(alternative in err for alternative in w.split("|"))]
    if missing:
        return "accepted, WRONG", f"the line does not say {missing}: {err.strip()}"
    return "clean error", err.strip()


# ------------------------------------------------------------------ cases


def _inputs(root: Path, case_dir: Path) -> dict[str, Path]:
    folder = case_dir / "in"
    folder.mkdir(parents=True)
    for name in ("cta.nii.gz", "pa.dcm", "lat.dcm"):
        shutil.copy(root / name, folder / name)
    return {"cta": folder / "cta.nii.gz", "pa": folder / "pa.dcm", "lat": folder / "lat.dcm"}


def _argv(inputs: dict[str, Path], out: Path) -> list[str]:
    return ["--cta", str(inputs["cta"]), "--dsa-pa", str(inputs["pa"]), "--dsa-lat", str(inputs["lat"]), "--out", str(out)]


def _out_collision(rng: np.random.Generator, root: Path, case_dir: Path) -> tuple[str, list[str], tuple[str, ...], list[Path]]:
    inputs = _inputs(root, case_dir)
    variant = ("inputs_folder", "ancestor", "input_file", "input_inside_out", "symlink_to_inputs", "root", "series_folder")[int(rng.integers(0, 7))]
    role = ("cta", "pa", "lat")[int(rng.integers(0, 3))]
    out = case_dir / "out"
    if variant == "inputs_folder":
        out = inputs["cta"].parent
    elif variant == "ancestor":
        out = case_dir
    elif variant == "input_file":
        out = inputs[role]
    elif variant == "input_inside_out":
        out.mkdir()
        name = OUTPUT_NAMES[int(rng.integers(0, len(OUTPUT_NAMES)))]
        inputs[role] = inputs[role].rename(out / name)
    elif variant == "symlink_to_inputs":
        out.symlink_to(inputs["cta"].parent, target_is_directory=True)
    elif variant == "root":
        out = Path("/")
    else:
        series = case_dir / "ct"
        shutil.copytree(root / "ct_series", series)
        inputs["cta"] = out = series
    words = ("filesystem root",) if variant == "root" else ("--out", "holds none of the inputs")
    return f"{variant} ({role})", _argv(inputs, out), words, list(inputs.values())


def _special_file(rng: np.random.Generator, root: Path, case_dir: Path) -> tuple[str, list[str], tuple[str, ...], list[Path]]:
    inputs = _inputs(root, case_dir)
    kind = ("dev_zero", "dev_null", "symlink_to_dev_zero", "symlink_chain", "fifo", "socket")[int(rng.integers(0, 6))]
    role = ("cta", "pa", "lat", "series_member", "dsa_member", "sidecar")[int(rng.integers(0, 6))]
    place = {"cta": case_dir / "special.nii.gz", "pa": case_dir / "special.dcm", "lat": case_dir / "special.dcm"}.get(role)
    if role == "series_member":
        shutil.copytree(root / "ct_series", case_dir / "ct")
        inputs["cta"], place = case_dir / "ct", case_dir / "ct" / "slice_500.dcm"
    elif role == "dsa_member":
        (case_dir / "frames").mkdir()
        shutil.copy(root / "lat.dcm", case_dir / "frames" / "lat.dcm")
        inputs["lat"], place = case_dir / "frames", case_dir / "frames" / "frame_2.dcm"
    elif role == "sidecar":
        shutil.copytree(root / "lat_nifti", case_dir / "nifti")
        (case_dir / "nifti" / "run.json").unlink()
        inputs["lat"], place = case_dir / "nifti" / "run.nii", case_dir / "nifti" / "run.json"
    if kind in ("dev_zero", "dev_null") and role in ("cta", "pa", "lat"):
        place = Path(f"/dev/{kind[4:]}")
    elif kind in ("dev_zero", "dev_null", "symlink_to_dev_zero"):
        place.symlink_to("/dev/zero" if kind != "dev_null" else "/dev/null")
    elif kind == "symlink_chain":
        hop = case_dir / "hop"
        hop.symlink_to("/dev/zero")
        place.symlink_to(hop)
    elif kind == "fifo":
        os.mkfifo(place)
    else:
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(place))
    if role in ("cta", "pa", "lat"):
        inputs[role] = place
    word = {"fifo": "is a FIFO", "socket": "is a socket"}.get(kind, "is a character device")
    return f"{kind} as {role}", _argv(inputs, case_dir / "out"), (word,), [p for p in inputs.values() if not str(p).startswith("/dev/")]


def retagged(src: Path, dst: Path, **tags) -> Path:
    ds = pydicom.dcmread(src)
    for key, value in tags.items():
        setattr(ds, key, value)
    ds.save_as(dst, enforce_file_format=True)
    return dst


def _mismatch(rng: np.random.Generator, root: Path, case_dir: Path) -> tuple[str, list[str], tuple[str, ...], list[Path]]:
    inputs = _inputs(root, case_dir)
    variant = ("lat_patient", "pa_patient", "lat_study", "same_path", "same_bytes", "same_instance", "cta_patient")[int(rng.integers(0, 7))]
    other = f"P{int(rng.integers(0, 10**6)):06d}"
    words: tuple[str, ...]
    if variant in ("lat_patient", "pa_patient"):
        role = variant[:-8]
        retagged(inputs[role], inputs[role], PatientID=other)
        words = ("PatientID", other, "--allow-id-mismatch")
    elif variant == "lat_study":
        retagged(inputs["lat"], inputs["lat"], StudyInstanceUID=generate_uid(entropy_srcs=[other]))
        words = ("StudyInstanceUID", "--allow-id-mismatch")
    elif variant == "same_path":
        inputs["lat"] = inputs["pa"]
        words = ("same data", "one each")
    elif variant == "same_bytes":
        shutil.copy(inputs["pa"], inputs["lat"])
        words = ("same data", "one each")
    elif variant == "same_instance":
        retagged(inputs["pa"], inputs["lat"], PatientName=f"Copy^{other}")
        words = ("same DICOM instance", "one each")
    else:
        series = case_dir / "ct"
        shutil.copytree(root / "ct_series", series)
        for f in series.iterdir():
            retagged(f, f, PatientID=other)
        inputs["cta"] = series
        words = ("CTA", other, "--allow-id-mismatch")
    return variant, _argv(inputs, case_dir / "out"), words, list(inputs.values())


def _series(rng: np.random.Generator, folder: Path) -> tuple[str, np.ndarray, np.ndarray, int]:
    encoding = list(ENCODINGS)[int(rng.integers(0, len(ENCODINGS)))]
    bits = (16, 12)[int(rng.integers(0, 2))]
    shape = (int(rng.integers(8, 13)), int(rng.integers(36, 48)), int(rng.integers(36, 48)))
    hu, inside = head_hu(shape, seed=int(rng.integers(0, 1000)))
    top = (1 << (bits - 1)) - 1 + INTERCEPT
    hu = np.minimum(hu, top)
    padding = int(rng.integers(-(1 << (bits - 1)), -1100 - INTERCEPT))
    write_ct_series(folder, hu, inside, encoding, bits_stored=bits, padding_stored=padding, spacing_mm=(2.5, 0.6, 0.6),
                    patient_id=PATIENT)
    return f"{encoding}, BitsStored {bits}, padding {padding}, {shape}", hu, inside, padding


def _ct_encoding(rng: np.random.Generator, case_dir: Path) -> tuple[str, str, str]:
    folder = case_dir / "ct"
    detail, _, inside, _ = _series(rng, folder)
    files = sorted(str(f) for f in folder.iterdir())
    try:
        volume = load_cta(folder)
    except InputError as exc:
        return "other exception", f"{detail}: a valid series was refused: {exc}"
    reference = np.stack([pydicom.dcmread(f).pixel_array.astype(np.float64) + INTERCEPT for f in files])
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    by_gdcm = sitk.GetArrayFromImage(reader.Execute()).astype(np.float64)
    inner = inside[0]
    if not np.array_equal(reference, by_gdcm):
        return "accepted, WRONG", f"{detail}: pydicom and GDCM disagree (test data)"
    if not np.array_equal(volume.array[:, inner], reference[:, inner]) or not np.all(volume.array[:, ~inner] == -1024.0):
        return "accepted, WRONG", f"{detail}: load_cta differs from pydicom/GDCM"
    return "accepted, faithful", detail


def run_cli_case(seed: int, index: int, root: Path, work: Path) -> tuple[str, str, str, str]:
    target, _ = describe_cli_case(seed, index)
    rng = np.random.default_rng([seed, index, 31])
    case_dir = work / "cli"
    if os.path.lexists(case_dir):
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    if target == "ct_encoding":
        outcome, detail = _ct_encoding(rng, case_dir)
        return target, detail.split(":")[0], outcome, detail
    if target == "ct_misdeclared":
        inputs = _inputs(root, case_dir)
        series = case_dir / "ct"
        what, _, _, _ = _series(rng, series)
        for f in series.iterdir():  # signed data declared unsigned: the padding reads as a huge positive HU
            ds = pydicom.dcmread(f)
            ds.PixelRepresentation = 0
            if "PixelPaddingValue" in ds:
                del ds.PixelPaddingValue
            ds.save_as(f, enforce_file_format=True)
        inputs["cta"] = series
        try:  # a 12-bit pattern read unsigned can give plausible HU: then the reading must be the header's, as pydicom's
            volume = load_cta(series)
        except InputError:
            volume = None
        if volume is not None:
            files = sorted(str(f) for f in series.iterdir())
            reference = np.stack([pydicom.dcmread(f).pixel_array.astype(np.float64) + INTERCEPT for f in files])
            outcome = "accepted, faithful" if np.array_equal(volume.array, reference) else "accepted, WRONG"
            return target, what, outcome, f"{what}: read as declared (unsigned), plausible HU"
        situation, argv, words, watched = what, _argv(inputs, case_dir / "out"), ("HU|BitsStored",), list(inputs.values())
    else:
        make = {"out_collision": _out_collision, "special_file": _special_file, "mismatch": _mismatch}[target]
        situation, argv, words, watched = make(rng, root, case_dir)
    before = _tree(watched)
    code, err = _cli(argv)
    outcome, detail = _verdict(code, err, words, before, _tree(watched))
    if outcome == "clean error" and target != "out_collision" and not situation.startswith("root"):
        stray = [p for p in watched if p.is_dir() and any(q.name.startswith(".geopose") for q in p.iterdir())]
        if stray:
            outcome, detail = "accepted, WRONG", f"wrote into the input folder {stray[0]}"
    return target, situation, outcome, detail
