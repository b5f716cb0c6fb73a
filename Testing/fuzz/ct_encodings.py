"""Signed CT series as hospital archives store them, for the reader tests and the CLI fuzz cases.

Each slice is a CT Image Storage file with PixelRepresentation 1, RescaleIntercept -1024 and, outside a
scan circle, PixelPaddingValue (default -2000 stored = -3024 HU), in one of the transfer syntaxes
GeoPose accepts: uncompressed, JPEG Lossless SV1 and JPEG-LS (the encoders of this folder; their
streams carry the stored bits' two's complement pattern, as scanners write them), JPEG 2000 Lossless
and RLE (pydicom's encoders). BitsStored may be below BitsAllocated (12 of 16).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom import uid as U

from jpeg_lossless import encode_jpeg_lossless
from jpeg_ls import encode_jpeg_ls

__all__ = ["ENCODINGS", "write_ct_series", "head_hu"]

#: Encoding name -> transfer syntax.
ENCODINGS = {
    "uncompressed": U.ExplicitVRLittleEndian,
    "jpeg_lossless_sv1": U.JPEGLosslessSV1,
    "jpeg_ls": U.JPEGLSLossless,
    "jpeg2000": U.JPEG2000Lossless,
    "rle": U.RLELossless,
}
INTERCEPT = -1024


def head_hu(shape: tuple[int, int, int] = (12, 40, 40), seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A head-like CT in HU ``[k, j, i]`` (air, skull up to 2,200 HU, brain, noise) and the mask of the scan
    circle (True inside; outside is padding)."""
    rng = np.random.default_rng(seed)
    k, j, i = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(float)
    r = np.hypot(j - shape[1] / 2 + 0.5, i - shape[2] / 2 + 0.5) / (shape[1] / 2)
    hu = np.where(r < 0.7, 40.0, -1000.0)
    hu = np.where((r > 0.6) & (r < 0.7), 1800.0 + 400 * np.cos(k + j), hu) + rng.normal(0, 8, shape)
    return np.round(hu), r < 0.95


def write_ct_series(folder: Path, hu: np.ndarray, inside: np.ndarray, encoding: str, *, bits_stored: int = 16,
                    padding_stored: int = -2000, spacing_mm: tuple[float, float, float] = (2.0, 0.6, 0.6),
                    patient_id: str = "FUZZ", study_uid: str | None = None, series_uid: str | None = None) -> Path:
    """Write ``hu`` ``[k, j, i]`` as a signed CT series into ``folder`` (axial, LPS), ``padding_stored`` outside
    ``inside``; returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    study = study_uid or U.generate_uid(entropy_srcs=["ct-study", patient_id])
    series = series_uid or U.generate_uid(entropy_srcs=["ct-series", patient_id, encoding, str(bits_stored)])
    stored = np.where(inside, hu - INTERCEPT, padding_stored).astype(np.int64)
    lo, hi = -(1 << (bits_stored - 1)), (1 << (bits_stored - 1)) - 1
    if stored.min() < lo or stored.max() > hi:
        raise ValueError(f"stored values {stored.min()}..{stored.max()} do not fit {bits_stored} signed bits")
    for k, plane in enumerate(stored):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = U.CTImageStorage
        meta.MediaStorageSOPInstanceUID = U.generate_uid(entropy_srcs=[series, str(k)])
        meta.TransferSyntaxUID = U.ExplicitVRLittleEndian
        ds = pydicom.Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = U.CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.Modality, ds.PatientID, ds.StudyInstanceUID, ds.SeriesInstanceUID = "CT", patient_id, study, series
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [-12.0, -12.0, 30.0 + k * spacing_mm[0]]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [spacing_mm[1], spacing_mm[2]]
        ds.Rows, ds.Columns = plane.shape
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, bits_stored, bits_stored - 1, 1
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = INTERCEPT, 1, "HU"
        ds.PixelPaddingValue = padding_stored
        ds.PixelData = plane.astype("<i2").tobytes()
        syntax = ENCODINGS[encoding]
        if encoding in ("jpeg2000", "rle"):
            ds.compress(syntax, generate_instance_uid=False)
        elif encoding != "uncompressed":
            pattern = plane & ((1 << bits_stored) - 1)  # two's complement of the stored bits
            encode = encode_jpeg_lossless if encoding == "jpeg_lossless_sv1" else encode_jpeg_ls
            ds.PixelData = encapsulate([encode(pattern, bits_stored)])
            ds["PixelData"].VR = "OB"
            ds["PixelData"].is_undefined_length = True
            ds.file_meta.TransferSyntaxUID = syntax
        ds.save_as(folder / f"slice_{k:03d}.dcm", enforce_file_format=True)
    return folder
