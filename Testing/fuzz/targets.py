"""The GeoPose inputs the fuzz suite mutates, and how an accepted mutation is verified.

Originals (built once per run into a folder): a phantom DSA run as DICOM XA (uncompressed,
JPEG Baseline, JPEG Lossless, JPEG 2000 Lossless, RLE; and archived native, with the Mask Subtraction
Sequence that subtracts it), a CT series of 12 DICOM slices, a CTA
as NIfTI (.nii, .nii.gz), NRRD and MetaImage, a DSA run as NIfTI + JSON sidecar, and a models
folder with its manifest. A case mutates one file (bit flips anywhere or in the header,
truncation, or a header field set to a damaging value), reads it with the GeoPose reader and
classifies the outcome:

* ``clean error``: an :class:`~geopose.errors.InputError`;
* ``accepted, identical``: the same image and geometry as the original;
* ``accepted, faithful``: different from the original, but exactly what an independent reader
  (pydicom's own decoders and tags, SimpleITK, ``json``) finds in the mutated file, with the
  mutation inside data the format cannot protect (a pixel value, a digit of an angle);
* ``accepted, WRONG``: anything else that was accepted (a failure);
* ``other exception`` / ``out of memory``: a traceback from the reader (a failure).
"""

from __future__ import annotations

import gzip
import io
import json
import math
import shutil
import struct
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pydicom
import SimpleITK as sitk
from PIL import Image
from pydicom.dataset import FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, JPEG2000Lossless, JPEGBaseline8Bit, JPEGLosslessSV1, RLELossless, generate_uid

from harness import flip_bits, interesting_number, truncate, unlimited_memory
from jpeg_lossless import encode_jpeg_lossless

from geopose.checksums import file_sha256
from geopose.cta import load_cta, save_volume, volume_from_sitk
from geopose.dsa import DSARun, read_dsa, write_dsa_dicom, write_dsa_nifti
from geopose.dsa.readers import sidecar_path
from geopose.dsa.subtraction import MaskSubtraction, subtract_mask
from geopose.errors import InputError
from geopose.geometry import CArmAngles, Detector
from geopose.cta.dicom_series import TILT_OFFSET_MM
from geopose.limits import PRIMARY_DEG, SECONDARY_DEG, SLICE_GAP_TOLERANCE, SLICE_GAP_TOLERANCE_MM, wrap_angle_deg
from geopose.nets.manifest import MANIFEST_NAME, verify_models
from geopose.volume import Volume

__all__ = ["TARGETS", "build_originals", "run_case", "describe_case"]

XA_KINDS = ("xa_uncompressed", "xa_jpeg_baseline", "xa_jpeg_lossless", "xa_jpeg2000", "xa_rle")
CTA_FILES = {"cta_nii": "cta.nii", "cta_nii_gz": "cta.nii.gz", "cta_nrrd": "cta.nrrd", "cta_mha": "cta.mha"}
TARGETS = XA_KINDS + ("xa_native", "ct_series") + tuple(CTA_FILES) + ("dsa_sidecar", "models_manifest")
MUTATIONS = ("flip", "flip_header", "truncate", "field")


# ------------------------------------------------------------------ originals


def _phantom_run(frames: int = 4, size: int = 64) -> DSARun:
    """A head-like attenuation (a disc, a vessel filling over time) as a MONOCHROME2 run."""
    yy, xx = np.mgrid[:size, :size].astype(float)
    head = np.where(np.hypot(yy - size / 2, xx - size / 2) < 0.4 * size, 60.0, 0.0)
    att = np.stack([head + np.where((np.abs(xx - size / 2 - 4) < 2) & (yy < size * (0.3 + 0.15 * t)), 40.0, 0.0)
                    for t in range(frames)])
    det = Detector(size, size, (0.6, 0.6), 1100.0)
    return DSARun.from_attenuation(att * 20, det, CArmAngles(28.0, -6.0, 1100.0, 750.0), 66.7, {})


def _native_run(frames: int = 5, size: int = 64) -> DSARun:
    """The head of :func:`_phantom_run` archived native: X-ray intensities, frame 1 the mask (no contrast)."""
    att = _phantom_run(frames, size).attenuation() / 400.0
    att[0] = att[1:].min(axis=0)
    return DSARun(np.round(4000.0 * np.exp(-att)), Detector(size, size, (0.6, 0.6), 1100.0),
                  CArmAngles(28.0, -6.0, 1100.0, 750.0), 66.7, {})


def _fixed_identity(path: Path, salt: str) -> Path:
    """Replace the writer's fresh UIDs, dates and times by fixed ones, so originals are byte-identical run to run."""
    ds = pydicom.dcmread(path)
    uid = lambda tag: generate_uid(entropy_srcs=[salt, tag])  # noqa: E731
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = uid("sop")
    ds.StudyInstanceUID, ds.SeriesInstanceUID = uid("study"), uid("series")
    for key in ("StudyDate", "SeriesDate", "ContentDate"):
        setattr(ds, key, "20260101")
    for key in ("StudyTime", "SeriesTime", "ContentTime"):
        setattr(ds, key, "120000")
    ds.save_as(path, enforce_file_format=True)
    return path


def _encapsulated_copy(src: Path, dst: Path, syntax: pydicom.uid.UID, encode: Callable[[np.ndarray], bytes], bits: int) -> None:
    ds = pydicom.dcmread(src)
    stored = ds.pixel_array.reshape(int(ds.NumberOfFrames), ds.Rows, ds.Columns)
    ds.PixelData = encapsulate([encode(frame) for frame in stored])
    ds["PixelData"].VR = "OB"
    ds["PixelData"].is_undefined_length = True
    ds.BitsStored = bits
    ds.HighBit = bits - 1
    ds.file_meta.TransferSyntaxUID = syntax
    ds.save_as(dst, enforce_file_format=True)


def _jpeg_baseline(frame: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(frame.astype(np.uint8)).save(buf, format="JPEG", quality=92)
    return buf.getvalue()


def _ct_volume() -> Volume:
    rng = np.random.default_rng(7)
    k, j, i = np.mgrid[:12, :40, :40].astype(float)
    hu = np.where(np.hypot(j - 20, i - 20) < 16, 40.0, -1000.0)
    hu = np.where((np.hypot(j - 20, i - 20) > 13) & (hu > 0), 1200.0, hu) + rng.normal(0, 5, hu.shape)
    aff = np.diag([0.6, 0.6, 2.0, 1.0])
    aff[:3, 3] = (-12.0, -12.0, 30.0)
    return Volume(np.round(hu).astype(np.float32), aff)


def _write_ct_series(folder: Path, volume: Volume) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    series, study = generate_uid(entropy_srcs=["ct", "series"]), generate_uid(entropy_srcs=["ct", "study"])
    spacing = volume.spacing_mm
    origin_lps = volume.ijk_to_ras[:3, 3] * (-1, -1, 1)
    for k, plane in enumerate(volume.array):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = CTImageStorage, generate_uid(entropy_srcs=["ct", str(k)])
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = pydicom.Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.Modality, ds.PatientID, ds.StudyInstanceUID, ds.SeriesInstanceUID = "CT", "FUZZ", study, series
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [f"{origin_lps[0]:.4f}", f"{origin_lps[1]:.4f}", f"{origin_lps[2] + k * spacing[2]:.4f}"]
        ds.ImageOrientationPatient = [-1, 0, 0, 0, -1, 0]
        ds.PixelSpacing = [spacing[1], spacing[0]]
        ds.Rows, ds.Columns = plane.shape
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
        ds.RescaleIntercept, ds.RescaleSlope = -1024, 1
        ds.PixelData = (plane + 1024).astype(np.uint16).tobytes()
        ds.save_as(folder / f"slice_{k:02d}.dcm", enforce_file_format=True)


def build_originals(root: Path) -> dict[str, Any]:
    """Write every original under ``root``; returns what the verification needs."""
    root.mkdir(parents=True, exist_ok=True)
    run = _phantom_run()
    raw = _fixed_identity(write_dsa_dicom(run, root / "xa_uncompressed.dcm"), "xa16")
    raw8 = _fixed_identity(write_dsa_dicom(run, root / "xa8.dcm", bits=8), "xa8")
    _fixed_identity(write_dsa_dicom(_native_run(), root / "xa_native.dcm",
                                    mask_subtraction=MaskSubtraction((0,), (1, 2, 3, 4), shift_px=(0.5, -1.0))), "native")
    _encapsulated_copy(raw8, root / "xa_jpeg_baseline.dcm", JPEGBaseline8Bit, _jpeg_baseline, 8)
    _encapsulated_copy(raw, root / "xa_jpeg_lossless.dcm", JPEGLosslessSV1, lambda f: encode_jpeg_lossless(f, 16), 16)
    for name, syntax in (("xa_jpeg2000", JPEG2000Lossless), ("xa_rle", RLELossless)):
        ds = pydicom.dcmread(raw)
        ds.compress(syntax, generate_instance_uid=False)
        ds.save_as(root / f"{name}.dcm", enforce_file_format=True)
    volume = _ct_volume()
    _write_ct_series(root / "ct_series", volume)
    save_volume(volume.like(volume.array.astype(np.int16)), root / CTA_FILES["cta_nii"])
    save_volume(volume.like(volume.array.astype(np.int16)), root / CTA_FILES["cta_nii_gz"])
    save_volume(volume, root / CTA_FILES["cta_mha"])
    _write_nrrd_raw(root / CTA_FILES["cta_nrrd"], volume)
    write_dsa_nifti(run, root / "dsa_sidecar" / "run.nii")
    models = root / "models"
    models.mkdir()
    rng = np.random.default_rng(11)
    entries = {}
    for kind in ("init", "refine"):
        f = models / f"geopose_{kind}.pt"
        f.write_bytes(rng.bytes(2048))
        entries[kind] = {"file": f.name, "bytes": f.stat().st_size, "sha256": file_sha256(f)}
    (models / MANIFEST_NAME).write_text(json.dumps({"schema_version": 1, "models": entries}, indent=1))
    originals: dict[str, Any] = {}
    for kind in XA_KINDS + ("xa_native",):
        originals[kind] = _dsa_summary(read_dsa(root / f"{kind}.dcm"))
    originals["ct_series"] = _volume_summary(load_cta(root / "ct_series"))
    for kind, name in CTA_FILES.items():
        originals[kind] = _volume_summary(load_cta(root / name))
    originals["dsa_sidecar"] = _dsa_summary(read_dsa(root / "dsa_sidecar" / "run.nii"))
    originals["models_manifest"] = {k: str(v) for k, v in verify_models(models).items()}
    return originals


def _write_nrrd_raw(path: Path, volume: Volume) -> None:
    """A raw (uncompressed) attached NRRD, written by hand so byte flips hit voxels (SimpleITK writes gzip)."""
    k, j, i = volume.array.shape
    lin = (volume.ijk_to_ras[:3, :3] * np.array([[-1], [-1], [1]])).T
    header = (
        "NRRD0004\n# written by the fuzz suite\ntype: float\ndimension: 3\nspace: left-posterior-superior\n"
        f"sizes: {i} {j} {k}\nspace directions: " + " ".join(f"({v[0]:g},{v[1]:g},{v[2]:g})" for v in lin) + "\n"
        "kinds: domain domain domain\nendian: little\nencoding: raw\n"
        f"space origin: ({-volume.ijk_to_ras[0, 3]:g},{-volume.ijk_to_ras[1, 3]:g},{volume.ijk_to_ras[2, 3]:g})\n\n"
    )
    path.write_bytes(header.encode() + volume.array.astype("<f4").tobytes())


def _dsa_summary(run: DSARun) -> dict:
    return {
        "frames": run.frames,
        "geometry": (run.detector.shape, tuple(run.detector.spacing_mm), tuple(run.detector.principal_offset_mm), run.detector.sdd_mm,
                     run.angles.primary_deg, run.angles.secondary_deg, run.angles.sid_mm, run.angles.sod_mm, run.frame_time_ms,
                     run.photometric_interpretation),
    }


def _volume_summary(volume: Volume) -> dict:
    return {"array": volume.array, "affine": volume.ijk_to_ras}


def _same_dsa(a: dict, b: dict) -> bool:
    return a["frames"].shape == b["frames"].shape and np.array_equal(a["frames"], b["frames"]) and _same_tuple(a["geometry"], b["geometry"])


def _same_tuple(a: Any, b: Any) -> bool:
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same_tuple(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9 * max(1.0, abs(a))
    return a == b


def _same_volume(a: dict, b: dict) -> bool:
    return a["array"].shape == b["array"].shape and np.array_equal(a["array"], b["array"]) and np.allclose(a["affine"], b["affine"], atol=1e-6)


# ------------------------------------------------------------------- mutations

#: (keyword, kind) of DICOM XA header fields the "field" mutation damages.
XA_FIELDS = (
    ("Rows", "int"), ("Columns", "int"), ("NumberOfFrames", "int"), ("BitsAllocated", "int"), ("BitsStored", "int"),
    ("HighBit", "int"), ("PixelRepresentation", "int"), ("SamplesPerPixel", "int"), ("PhotometricInterpretation", "text"),
    ("PositionerPrimaryAngle", "num"), ("PositionerSecondaryAngle", "num"), ("DistanceSourceToDetector", "num"),
    ("DistanceSourceToPatient", "num"), ("ImagerPixelSpacing", "num2"), ("FrameTime", "num"), ("RescaleSlope", "num"),
    ("RescaleIntercept", "num"), ("TransferSyntaxUID", "uid"), ("length", "length"), ("delete", "delete"),
)
#: (keyword, kind) of the Mask Subtraction Sequence's first item and the tags that say how to subtract.
NATIVE_FIELDS = XA_FIELDS + (
    ("MaskOperation", "mask_text"), ("MaskFrameNumbers", "mask_frames"), ("ApplicableFrameRange", "mask_frames"),
    ("MaskSubPixelShift", "mask_num2"), ("ContrastFrameAveraging", "mask_int"), ("PixelIntensityRelationship", "relationship"),
    ("PixelIntensityRelationshipSign", "sign"), ("RecommendedViewingMode", "viewing"), ("MaskSubtractionSequence", "delete_item"),
)
CT_FIELDS = (
    ("Rows", "int"), ("Columns", "int"), ("BitsStored", "int"), ("ImagePositionPatient", "num3"),
    ("ImageOrientationPatient", "num6"), ("PixelSpacing", "num2"), ("RescaleSlope", "num"), ("RescaleIntercept", "num"),
    ("SeriesInstanceUID", "uid"), ("length", "length"), ("delete", "delete"),
)


def _value(rng: np.random.Generator, kind: str, original: Any) -> Any:
    if kind == "int":
        return int(rng.choice([0, 1, 2, 3, 7, 8, 12, 15, 16, 17, 24, 31, 32, 33, 255, 65535, int(original or 1) * 2, max(0, int(original or 1) - 1), int(original or 1) + 1]))
    if kind == "text":
        return str(rng.choice(["MONOCHROME1", "MONOCHROME2", "RGB", "PALETTE COLOR", "", "MONO"]))
    if kind == "uid":
        return str(rng.choice([str(pydicom.uid.ImplicitVRLittleEndian), str(pydicom.uid.ExplicitVRBigEndian), str(JPEG2000Lossless),
                               str(RLELossless), str(JPEGBaseline8Bit), "1.2.3.4", str(generate_uid())]))
    n = {"num": 1, "num2": 2, "num3": 3, "num6": 6}[kind]
    orig = list(original) if isinstance(original, (list, tuple, pydicom.multival.MultiValue)) else ([] if original is None else [original])
    out = [float(v) for v in orig[:n]] + [1.0] * (n - len(orig[:n]))
    k = int(rng.integers(0, n))
    base = float(orig[k]) if k < len(orig) and orig[k] not in (None, "") else None
    out[k] = interesting_number(rng, base)
    return [f"{v:.6g}" if math.isfinite(v) else str(v) for v in out] if n > 1 else (f"{out[0]:.6g}" if math.isfinite(out[0]) else str(out[0]))


def _dicom_field(data: bytes, rng: np.random.Generator, fields: tuple) -> tuple[bytes, str]:
    keyword, kind = fields[int(rng.integers(0, len(fields)))]
    if kind == "length":  # damage the length field of a random element (explicit VR little endian)
        ds = pydicom.dcmread(io.BytesIO(data))
        tags = [e.tag for e in ds if e.tag != 0x7FE00010] + [pydicom.tag.Tag(0x7FE00010)]
        tag = tags[int(rng.integers(0, len(tags)))]
        needle = struct.pack("<HH", tag.group, tag.elem)
        pos = data.find(needle, 132)
        if pos < 0:
            return data, "length: tag not found"
        vr = data[pos + 4:pos + 6]
        long_vr = vr in (b"OB", b"OW", b"OF", b"SQ", b"UT", b"UN", b"OD", b"OL", b"OV", b"UC", b"UR")
        at, width = (pos + 8, 4) if long_vr else (pos + 6, 2)
        value = int(rng.choice([0, 1, 2**(8 * width) - 1, 2**(8 * width) - 16, int(rng.integers(0, 2**(8 * width)))]))
        return data[:at] + value.to_bytes(width, "little") + data[at + width:], f"length of {tag} = {value}"
    ds = pydicom.dcmread(io.BytesIO(data))
    if kind.startswith("mask_") or kind in ("relationship", "sign", "viewing", "delete_item"):
        value, detail = _subtraction_field(ds, rng, keyword, kind)
    elif kind == "delete":
        candidates = [e.keyword for e in ds if e.keyword and e.keyword != "PixelData"] + ["PixelData"]
        keyword = candidates[int(rng.integers(0, len(candidates)))]
        del ds[keyword]
        detail = f"delete {keyword}"
    elif kind == "uid":
        value = _value(rng, kind, None)
        if keyword == "TransferSyntaxUID":
            ds.file_meta.TransferSyntaxUID = value
        else:
            setattr(ds, keyword, value)
        detail = f"{keyword} = {value}"
    else:
        value = _value(rng, kind, ds.get(keyword))
        setattr(ds, keyword, value)
        detail = f"{keyword} = {value}"
    buf = io.BytesIO()
    try:
        ds.save_as(buf, enforce_file_format=False)
    except Exception as exc:  # pydicom cannot write the damaged value: keep the file as it was
        return data, f"{detail} (unwritable: {type(exc).__name__})"
    return buf.getvalue(), detail


def _subtraction_field(ds: pydicom.Dataset, rng: np.random.Generator, keyword: str, kind: str) -> tuple[Any, str]:
    """Set one tag of the mask subtraction (in the sequence's first item for ``mask_*`` kinds) to a damaging value."""
    item = ds.MaskSubtractionSequence[0]
    if kind == "delete_item":
        del ds.MaskSubtractionSequence
        return None, "delete MaskSubtractionSequence"
    value: Any = {
        "mask_text": lambda: str(rng.choice(["TID", "REV_TID", "NONE", "", "avg_sub", "AVG_SUB", "SUB"])),
        "mask_frames": lambda: [int(v) for v in rng.choice([0, 1, 2, 3, 4, 5, 6, 65535], size=int(rng.integers(1, 5)))],
        "mask_num2": lambda: [interesting_number(rng, 0.5), interesting_number(rng, -1.0)][: int(rng.integers(1, 3))],
        "mask_int": lambda: int(rng.choice([0, 1, 2, 4, 5, 6, 65535])),
        "relationship": lambda: str(rng.choice(["LIN", "LOG", "DISP", "", "OTHER"])),
        "sign": lambda: int(rng.choice([-1, 1, 0, 32767])),
        "viewing": lambda: str(rng.choice(["SUB", "NAT", ""])),
    }[kind]()
    setattr(item if kind.startswith("mask_") else ds, keyword, value)
    return value, f"{keyword} = {value}"


def _pixel_offset(data: bytes) -> int:
    """Where the Pixel Data element starts (the header ends)."""
    pos = data.rfind(b"\xe0\x7f\x10\x00")
    return pos if pos > 0 else len(data)


def _mutate_file(path: Path, rng: np.random.Generator, mutation: str,
                      field: Callable[[str, np.random.Generator], tuple[str, str]]) -> str:
    """Mutate a file in place: for mutation ``field`` one JSON value set by ``field``, otherwise its
    bytes (any file, e.g. a model); returns what was done."""
    data = path.read_bytes()
    if mutation == "field":
        new, detail = field(data.decode(), rng)
        path.write_text(new)
    else:
        mutated, detail = _mutate_bytes(data, rng, mutation, len(data))
        path.write_bytes(mutated)
    return detail


def _mutate_bytes(data: bytes, rng: np.random.Generator, mutation: str, header_end: int) -> tuple[bytes, str]:
    if mutation == "flip":
        out, positions = flip_bits(data, rng)
        return out, f"flip at {positions}"
    if mutation == "flip_header":
        out, positions = flip_bits(data, rng, 0, max(1, header_end))
        return out, f"header flip at {positions}"
    out, cut = truncate(data, rng)
    return out, f"cut at {cut} of {len(data)}"


# ---------------------------------------------------------------- verification


def _classify(
    read: Callable[[], Any], summarise: Callable[[Any], dict], same: Callable[[dict, dict], bool], original: dict,
    oracle: Callable[[], dict], wrong: Callable[[dict, dict], str],
    resampled: Callable[[Any, dict], bool] = lambda result, expected: False,
) -> tuple[str, str]:
    """Outcome of one damaged file: a clean error, accepted identical to the undamaged original, accepted and
    faithful to what an independent reader makes of the damaged file, or accepted and WRONG."""
    try:
        result = read()
    except InputError as exc:
        return "clean error", str(exc)[:300]
    except MemoryError:
        return "out of memory", "MemoryError"
    except Exception:
        return "other exception", traceback.format_exc()[-1500:]
    got = summarise(result)
    if same(got, original):
        return "accepted, identical", ""
    try:
        with unlimited_memory():
            expected = oracle()
    except Exception as exc:
        return "accepted, WRONG", f"accepted, but the independent reader fails: {type(exc).__name__}: {exc}"[:500]
    if resampled(result, expected):
        return "accepted, faithful", "slice positions changed: resampled"
    if same(got, expected):
        return "accepted, faithful", ""
    return "accepted, WRONG", wrong(got, expected)


def _classify_dsa(read: Callable[[], DSARun], original: dict, oracle: Callable[[], dict]) -> tuple[str, str]:
    def wrong(got: dict, expected: dict) -> str:
        frames_equal = got["frames"].shape == expected["frames"].shape and np.array_equal(got["frames"], expected["frames"])
        return f"geometry {got['geometry']} vs independent {expected['geometry']}; frames equal: {frames_equal}"

    return _classify(read, _dsa_summary, _same_dsa, original, oracle, wrong)


def _classify_volume(read: Callable[[], Volume], original: dict, oracle: Callable[[], dict]) -> tuple[str, str]:
    def same(got: dict, expected: dict) -> bool:
        return "array" in expected and _same_volume(got, expected)

    def wrong(got: dict, expected: dict) -> str:
        return f"shape {got['array'].shape} vs {original['array'].shape}, affine equal to the original: " \
            f"{np.allclose(got['affine'], original['affine'], atol=1e-6)}"

    def resampled(volume: Volume, expected: dict) -> bool:
        return bool(expected.get("resampled_ok") and volume.metadata.get("slice_geometry", {}).get("resampled"))

    return _classify(read, _volume_summary, same, original, oracle, wrong, resampled)


def _pydicom_dsa(path: Path) -> dict:
    """The run as plain pydicom reads it: pixel_array with the modality LUT, angles wrapped like GeoPose wraps them."""
    ds = pydicom.dcmread(path)
    frames = ds.pixel_array.astype(np.float32)
    frames = frames.reshape(int(ds.get("NumberOfFrames", 1) or 1), ds.Rows, ds.Columns)
    if "RescaleSlope" in ds or "RescaleIntercept" in ds:
        frames = frames * np.float32(float(ds.get("RescaleSlope", 1))) + np.float32(float(ds.get("RescaleIntercept", 0)))
    spacing = tuple(float(v) for v in ds.ImagerPixelSpacing)
    frame_time = float(ds.FrameTime) if ds.get("FrameTime") not in (None, "") and float(ds.FrameTime) else None
    sid = float(ds.DistanceSourceToDetector)
    plan = _pydicom_subtraction(ds, len(frames))
    if plan is not None:
        frames = subtract_mask(frames, plan)
    photometric = "MONOCHROME2" if plan is not None else str(ds.PhotometricInterpretation)
    return {"frames": frames, "geometry": (
        (int(ds.Rows), int(ds.Columns)), spacing, (0.0, 0.0), sid,
        wrap_angle_deg("primary", float(ds.PositionerPrimaryAngle), PRIMARY_DEG),
        wrap_angle_deg("secondary", float(ds.PositionerSecondaryAngle), SECONDARY_DEG),
        sid, float(ds.DistanceSourceToPatient), frame_time, photometric)}


def _pydicom_subtraction(ds: pydicom.Dataset, n_frames: int) -> MaskSubtraction | None:
    """The AVG_SUB the first working item of the Mask Subtraction Sequence asks for, read with plain pydicom
    (PS3.3 C.7.6.10: 1-based frames, the default frame range leaves room for the contrast averaging)."""
    items = [i for i in ds.get("MaskSubtractionSequence") or [] if str(i.get("MaskOperation", "")).strip().upper() != "NONE"]
    if not items:
        return None
    item = items[0]
    as_list = lambda v: list(v) if isinstance(v, (list, pydicom.multival.MultiValue)) else [v]  # noqa: E731
    averaging = int(item.get("ContrastFrameAveraging") or 1)
    bounds = as_list(item.ApplicableFrameRange) if "ApplicableFrameRange" in item else [1, n_frames - averaging + 1]
    contrast = sorted({k - 1 for a, b in zip(bounds[::2], bounds[1::2]) for k in range(int(a), int(b) + 1)})
    relationship = str(ds.get("PixelIntensityRelationship") or "LIN").strip().upper()
    return MaskSubtraction(tuple(int(v) - 1 for v in as_list(item.MaskFrameNumbers)), tuple(contrast),
                           tuple(float(v) for v in item.get("MaskSubPixelShift") or (0.0, 0.0)), averaging,
                           relationship, -1 if int(ds.get("PixelIntensityRelationshipSign") or 1) < 0 else 1)


def _sidecar_oracle(image: Path, original: dict) -> dict:
    keys = json.loads(sidecar_path(image).read_text())
    spacing = keys["pixel_spacing_mm"]
    spacing = tuple(float(v) for v in (spacing if isinstance(spacing, list) else [spacing, spacing]))
    offset = tuple(float(v) for v in keys.get("principal_offset_mm", (0.0, 0.0)))
    sid = float(keys["sid_mm"])
    return {"frames": original["frames"], "geometry": (
        original["geometry"][0], spacing, offset, sid,
        wrap_angle_deg("p", float(keys["primary_deg"]), PRIMARY_DEG), wrap_angle_deg("s", float(keys["secondary_deg"]), SECONDARY_DEG),
        sid, float(keys["sod_mm"]), float(keys["frame_time_ms"]) if keys.get("frame_time_ms") is not None else None,
        str(keys.get("photometric_interpretation", "MONOCHROME2")))}




def _sitk_volume(path: Path) -> dict:
    volume = volume_from_sitk(sitk.ReadImage(str(path)))
    return _volume_summary(volume)


def _ct_oracle(folder: Path, mutated: Path, original_root: Path, original: dict) -> dict:
    """The series as the original with the mutated slice's pixels as pydicom reads them. When the mutation moved
    the slice (position, orientation, spacing) beyond the reader's tolerances, resampling is the right answer."""
    ds = pydicom.dcmread(mutated)
    before = pydicom.dcmread(original_root / "ct_series" / mutated.name)
    expected: dict[str, Any] = {}
    moved = [np.asarray([float(v) for v in ds.get(key, [])]) - np.asarray([float(v) for v in before.get(key, [])])
             if len(ds.get(key, [])) == len(before.get(key, [])) else None
             for key in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing")]
    if any(m is None or np.any(m) for m in moved):
        expected["resampled_ok"] = True
        position, orientation, spacing = moved
        gap_tol = max(SLICE_GAP_TOLERANCE_MM, SLICE_GAP_TOLERANCE * abs(original["affine"][2, 2]))  # of the 2 mm gaps
        within = (position is not None and orientation is not None and spacing is not None and not np.any(orientation)
                  and not np.any(spacing) and np.abs(position[:2]).max() <= TILT_OFFSET_MM and abs(position[2]) <= gap_tol)
        if not within:
            return expected
    k = int(mutated.stem.split("_")[1])
    array = original["array"].copy()
    plane = ds.pixel_array.astype(np.float32) * np.float32(float(ds.get("RescaleSlope", 1))) + np.float32(float(ds.get("RescaleIntercept", 0)))
    array[k] = plane
    return {**expected, "array": array, "affine": original["affine"]}


# ------------------------------------------------------------------------ cases


def describe_case(seed: int, index: int) -> tuple[str, str]:
    rng = np.random.default_rng([seed, index])
    return TARGETS[index % len(TARGETS)], MUTATIONS[int(rng.integers(0, len(MUTATIONS)))]


def _nifti_field(data: bytes, rng: np.random.Generator, gz: bool) -> tuple[bytes, str]:
    raw = gzip.decompress(data) if gz else data
    fields = [("dim", 40, "8h"), ("datatype", 70, "h"), ("bitpix", 72, "h"), ("pixdim", 76, "8f"), ("vox_offset", 108, "f"),
              ("scl_slope", 112, "f"), ("scl_inter", 116, "f"), ("qform_code", 252, "h"), ("sform_code", 254, "h"),
              ("quatern", 256, "6f"), ("srow", 280, "12f"), ("magic", 344, "4s")]
    name, offset, fmt = fields[int(rng.integers(0, len(fields)))]
    values = list(struct.unpack("<" + fmt, raw[offset:offset + struct.calcsize(fmt)]))
    k = int(rng.integers(0, len(values)))
    if fmt == "4s":
        values[0] = bytes(rng.choice([b"n+1\x00", b"ni1\x00", b"n+2\x00", b"\x00\x00\x00\x00"]))
    elif fmt.endswith("h"):
        v = values[k]
        values[k] = int(rng.choice([0, 1, -1, 2, 3, 4, 7, 8, 16, 32767, -32768, v + 1, v - 1, min(32767, v * 2), v // 2]))
    else:
        values[k] = interesting_number(rng, float(values[k]))
    try:
        packed = struct.pack("<" + fmt, *values)
    except (struct.error, OverflowError):
        return data, f"{name}[{k}]: unpackable"
    raw = raw[:offset] + packed + raw[offset + len(packed):]
    return (gzip.compress(raw) if gz else raw), f"{name}[{k}] = {values[k]!r}"


def _text_field(data: bytes, rng: np.random.Generator, keys: tuple[str, ...], sep: str, extra: tuple[str, ...] = ()) -> tuple[bytes, str]:
    """Damage one field of a NRRD/MetaImage text header (or, one time in five, add one of ``extra`` with a value)."""
    head_end = data.find(b"\n\n") if sep == ":" else data.find(b"\n", data.find(b"ElementDataFile"))
    head = data[: head_end if head_end > 0 else 400].decode("latin-1")
    lines = head.split("\n")
    if extra and rng.random() < 0.2:
        field = str(rng.choice(list(extra))) + str(rng.choice(["-1", "0", "1", "5", "1000000", "abc", "LIST", "x.raw", ""]))
        lines.insert(max(1, len(lines) - 2), field)
        return "\n".join(lines).encode("latin-1") + data[len(head):], f"add {field!r}"
    candidates = [i for i, line in enumerate(lines) if any(line.lower().startswith(k.lower()) for k in keys)]
    if not candidates:
        return data, "no field"
    i = candidates[int(rng.integers(0, len(candidates)))]
    key, _, value = lines[i].partition(sep)
    numbers = value.replace("(", " ").replace(")", " ").replace(",", " ").split()
    choice = int(rng.integers(0, 4))
    if choice == 0 and numbers:
        k = int(rng.integers(0, len(numbers)))
        try:
            numbers[k] = f"{interesting_number(rng, float(numbers[k])):g}"
        except ValueError:
            numbers[k] = "x"
        new = f"{key}{sep} " + " ".join(numbers)
    elif choice == 1:
        new = f"{key}{sep} " + str(rng.choice(["", "abc", "-1", "0", "1e30", "nan", "double", "gzip", "big", "LOCAL", "MET_DOUBLE"]))
    elif choice == 2:
        new = ""
    else:
        new = lines[i] + " 7"
    lines[i] = new
    return "\n".join(lines).encode("latin-1") + data[len(head):], f"{key.strip()} -> {new.strip()!r}"


def _json_field(text: str, rng: np.random.Generator) -> tuple[str, str]:
    try:
        doc = json.loads(text)
    except ValueError:
        return text, "unparsable original"
    choice = int(rng.integers(0, 6))
    if choice == 0:
        depth = int(rng.choice([40, 2000, 100000]))
        return "[" * depth + "]" * depth, f"nested {depth}"
    if choice == 1:
        return json.dumps(["not", "an", "object"]), "a list"
    keys = list(doc) if isinstance(doc, dict) else []
    if not keys:
        return text, "no keys"
    key = keys[int(rng.integers(0, len(keys)))]
    if choice == 2:
        del doc[key]
        return json.dumps(doc), f"delete {key}"
    value = [interesting_number(rng), {"a": 1}, "abc", None, True, [], [1, 2, 3], "1100", -5, [float("nan"), 1.0]][int(rng.integers(0, 10))]
    doc[key] = value
    return json.dumps(doc), f"{key} = {value!r}"


def _manifest_field(text: str, rng: np.random.Generator) -> tuple[str, str]:
    doc = json.loads(text)
    kind = str(rng.choice(["init", "refine"]))
    choice = int(rng.integers(0, 7))
    entry = doc["models"][kind]
    if choice == 0:
        doc["models"][kind] = [entry["file"], entry["bytes"], entry["sha256"]]
    elif choice == 1:
        del entry[str(rng.choice(["file", "bytes", "sha256"]))]
    elif choice == 2:
        entry["file"] = str(rng.choice(["../x.pt", "/etc/passwd", "", "sub/geopose_init.pt", "geopose_refine.pt"]))
    elif choice == 3:
        entry["bytes"] = [interesting_number(rng, float(entry["bytes"])), "2048", None, True][int(rng.integers(0, 4))]
    elif choice == 4:
        entry["sha256"] = str(rng.choice(["", "0" * 64, entry["sha256"].upper(), entry["sha256"][:-1]]))
    elif choice == 5:
        doc["schema_version"] = [2, "1", None, 1.0][int(rng.integers(0, 4))]
    else:
        doc["models"] = {kind: entry}
    return json.dumps(doc), f"manifest {kind}: change {choice}"


def run_case(seed: int, index: int, root: Path, originals: dict, work: Path) -> tuple[str, str, str, str]:
    """Mutate one input of target ``index % len(TARGETS)`` (drawn from ``rng([seed, index])``), read it, classify."""
    target, mutation = describe_case(seed, index)
    rng = np.random.default_rng([seed, index])
    rng.integers(0, len(MUTATIONS))  # the draw describe_case made
    case_dir = work / "case"
    if case_dir.exists():
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    original = originals[target]
    if target in XA_KINDS + ("xa_native",):
        src = root / f"{target}.dcm"
        data = src.read_bytes()
        fields = NATIVE_FIELDS if target == "xa_native" else XA_FIELDS
        data, detail = _dicom_field(data, rng, fields) if mutation == "field" else _mutate_bytes(data, rng, mutation, _pixel_offset(data))
        path = case_dir / src.name
        path.write_bytes(data)
        outcome, why = _classify_dsa(lambda: read_dsa(path), original, lambda: _pydicom_dsa(path))
    elif target == "ct_series":
        folder = case_dir / "ct"
        shutil.copytree(root / "ct_series", folder)
        victim = sorted(folder.iterdir())[int(rng.integers(0, 12))]
        data = victim.read_bytes()
        data, detail = _dicom_field(data, rng, CT_FIELDS) if mutation == "field" else _mutate_bytes(data, rng, mutation, _pixel_offset(data))
        victim.write_bytes(data)
        detail = f"{victim.name}: {detail}"
        outcome, why = _classify_volume(lambda: load_cta(folder), original, lambda: _ct_oracle(folder, victim, root, original))
    elif target in CTA_FILES:
        src = root / CTA_FILES[target]
        data = src.read_bytes()
        path = case_dir / src.name
        if mutation == "field":
            if target in ("cta_nii", "cta_nii_gz"):
                data, detail = _nifti_field(data, rng, target == "cta_nii_gz")
            elif target == "cta_nrrd":
                data, detail = _text_field(data, rng, ("type", "dimension", "sizes", "space directions", "endian", "encoding", "space origin",
                                                       "kinds", "space"), ":", extra=("byte skip: ", "line skip: ", "data file: "))
            else:
                data, detail = _text_field(data, rng, ("NDims", "DimSize", "ElementSpacing", "ElementType", "Offset", "TransformMatrix",
                                                       "CompressedData", "CompressedDataSize", "BinaryDataByteOrderMSB", "HeaderSize",
                                                       "ElementNumberOfChannels", "ElementDataFile"), " =",
                                           extra=("HeaderSize = ", "ElementNumberOfChannels = "))
        else:
            header_end = {"cta_nii": 352, "cta_nii_gz": len(data), "cta_nrrd": data.find(b"\n\n") + 2,
                          "cta_mha": data.find(b"ElementDataFile")}[target]
            data, detail = _mutate_bytes(data, rng, mutation, header_end)
        path.write_bytes(data)
        outcome, why = _classify_volume(lambda: load_cta(path), original, lambda: _sitk_volume(path))
    elif target == "dsa_sidecar":
        shutil.copytree(root / "dsa_sidecar", case_dir / "dsa")
        image = case_dir / "dsa" / "run.nii"
        detail = _mutate_file(sidecar_path(image), rng, mutation, _json_field)
        outcome, why = _classify_dsa(lambda: read_dsa(image), original, lambda: _sidecar_oracle(image, original))
    else:
        models = case_dir / "models"
        shutil.copytree(root / "models", models)
        victim = models / MANIFEST_NAME if mutation != "flip" or rng.random() < 0.5 else models / str(rng.choice(["geopose_init.pt", "geopose_refine.pt"]))
        detail = _mutate_file(victim, rng, mutation, _manifest_field)
        if mutation != "field":
            detail = f"{victim.name}: {detail}"
        outcome, why = _classify_models(models, root / "models", original)
    return target, f"{mutation}: {detail}"[:300], outcome, why


def _classify_models(models: Path, original_models: Path, original: dict) -> tuple[str, str]:
    try:
        found = verify_models(models)
    except InputError as exc:
        return "clean error", str(exc)[:300]
    except MemoryError:
        return "out of memory", "MemoryError"
    except Exception:
        return "other exception", traceback.format_exc()[-1500:]
    names = {k: v.name for k, v in found.items()}
    if names != {k: Path(v).name for k, v in original.items()}:
        return "accepted, WRONG", f"verified {names} instead of {original}"
    if any(v.read_bytes() != (original_models / v.name).read_bytes() for v in found.values()):
        return "accepted, WRONG", "a changed model file passed the check"
    return "accepted, identical", ""
