"""Loading, validating and saving CT(A) volumes.

SimpleITK describes images in patient LPS: ``lps = origin + D @ diag(spacing) @ ijk``.
A :class:`~geopose.volume.Volume` keeps ``ijk_to_ras``, so the first two rows of
that affine change sign (``RAS = diag(-1, -1, 1) @ LPS``). Arrays stay in
SimpleITK order ``[k, j, i]``. Voxel values are Hounsfield units (HU); DICOM
rescale slope/intercept is applied by the reader.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ..geometry.frames import RAS_TO_LPS
from ..checksums import file_sha256
from ..volume import Volume

__all__ = [
    "CTAInputError",
    "CTA_EXTENSIONS",
    "load_cta",
    "save_volume",
    "validate_cta",
    "volume_from_sitk",
    "sitk_from_volume",
    "file_sha256",
]

#: File name endings ``load_cta`` reads (a folder is read as a DICOM series).
CTA_EXTENSIONS = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")
#: Largest voxel size (mm) accepted as a CT of a head.
MAX_SPACING_MM = 10.0
#: A CT of a head in HU contains air: its minimum lies below this value.
HU_AIR_UPPER = -200.0
#: A value span this small suggests a normalised (e.g. 0..1) image, not HU.
NORMALISED_SPAN = 2.0
#: Extra spatial tolerance for slightly non-orthonormal directions when saving.
_ORTHONORMAL_TOL = 1e-4


class CTAInputError(ValueError):
    """A CT(A) input that cannot be used; the message names the problem and the remedy."""


def _ext(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _detached_data_files(header: Path) -> list[Path]:
    """Data files named by a MetaImage (.mhd) or detached NRRD (.nhdr) header, in order."""
    text = header.read_text(errors="replace")
    key = r"ElementDataFile\s*=\s*(.+)" if _ext(header) == ".mhd" else r"data ?file\s*:\s*(.+)"
    m = re.search(key, text, flags=re.IGNORECASE)
    if not m:
        return []
    spec = m.group(1).strip()
    if spec.upper().startswith("LIST"):
        tail = text[m.end():].split()
        return [header.parent / t for t in tail]
    if spec.upper() == "LOCAL":
        return []
    parts = spec.split()
    if "%" in parts[0] and len(parts) >= 3:
        start, stop = int(parts[1]), int(parts[2])
        step = int(parts[3]) if len(parts) > 3 else 1
        return [header.parent / (parts[0] % n) for n in range(start, stop + 1, step)]
    return [header.parent / spec]


def volume_from_sitk(image: sitk.Image, metadata: dict | None = None) -> Volume:
    """A SimpleITK 3D scalar image -> :class:`Volume` (float32 voxels, ijk->RAS affine)."""
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    lin_lps = direction @ np.diag(image.GetSpacing())
    ijk_to_lps = np.eye(4)
    ijk_to_lps[:3, :3] = lin_lps
    ijk_to_lps[:3, 3] = image.GetOrigin()
    array = sitk.GetArrayFromImage(image).astype(np.float32, copy=False)
    return Volume(array, RAS_TO_LPS @ ijk_to_lps, dict(metadata or {}))


def sitk_from_volume(volume: Volume) -> sitk.Image:
    """A :class:`Volume` -> SimpleITK image in LPS; the affine must be rotation x spacing."""
    ijk_to_lps = RAS_TO_LPS @ volume.ijk_to_ras
    lin = ijk_to_lps[:3, :3]
    spacing = np.linalg.norm(lin, axis=0)
    if np.any(spacing <= 0) or not np.all(np.isfinite(lin)):
        raise CTAInputError(f"the volume affine has a zero or non-finite axis: {volume.ijk_to_ras.tolist()}")
    direction = lin / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=_ORTHONORMAL_TOL):
        raise CTAInputError(
            "the volume affine is sheared (its axes are not orthogonal); NIfTI/NRRD/MHA via SimpleITK store "
            "only rotation x spacing: resample the volume onto an orthogonal grid first"
        )
    array = volume.array
    if array.dtype == bool:
        array = array.astype(np.uint8)
    image = sitk.GetImageFromArray(np.ascontiguousarray(array))
    image.SetSpacing(tuple(float(s) for s in spacing))
    image.SetDirection(tuple(float(v) for v in direction.ravel()))
    image.SetOrigin(tuple(float(v) for v in ijk_to_lps[:3, 3]))
    return image


def save_volume(volume: Volume, path: str | Path) -> Path:
    """Write a volume (image or label map, voxel type kept) to NIfTI, NRRD or MHA (RAS -> LPS)."""
    path = Path(path)
    if _ext(path) not in (".nii", ".nii.gz", ".nrrd", ".mha"):
        raise CTAInputError(f"cannot write {path.name}: use a .nii, .nii.gz, .nrrd or .mha file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(sitk_from_volume(volume), str(path), useCompression=_ext(path) != ".nii")
    return path


def _read_dicom_series(folder: Path, series_uid: str | None) -> tuple[sitk.Image, list[Path]]:
    reader = sitk.ImageSeriesReader()
    ids = list(reader.GetGDCMSeriesIDs(str(folder)))
    if not ids:
        raise CTAInputError(f"{folder} holds no DICOM series: point to a folder of CT slices or to a NIfTI/NRRD/MHA file")
    if series_uid is None:
        if len(ids) > 1:
            raise CTAInputError(
                f"{folder} holds {len(ids)} DICOM series ({', '.join(ids)}): choose one with series_uid=... "
                "or put the CTA series in a folder of its own"
            )
        series_uid = ids[0]
    elif series_uid not in ids:
        raise CTAInputError(f"series {series_uid} is not in {folder}; it holds {', '.join(ids)}")
    files = list(reader.GetGDCMSeriesFileNames(str(folder), series_uid))
    reader.SetFileNames(files)
    return reader.Execute(), [Path(f) for f in files]


def load_cta(path: str | Path, *, hu_offset: float = 0.0, series_uid: str | None = None, check_hu: bool = True) -> Volume:
    """Read a CT(A) volume in HU from NIfTI, NRRD (.nrrd/.nhdr), MetaImage (.mha/.mhd)
    or a folder holding a DICOM series, and validate it (:func:`validate_cta`).

    ``hu_offset`` (HU) is added to every voxel after reading, for files that store
    raw CT numbers without the rescale intercept (e.g. ``hu_offset=-1024``).
    Metadata: ``source_path``, ``source_files`` (count), ``sha256`` (of the header and
    data files, or the DICOM files in series order, concatenated), ``hu_offset``.
    """
    path = Path(path)
    if not path.exists():
        raise CTAInputError(f"CTA not found: {path} (check the path; a DICOM series is given as its folder)")
    if path.is_dir():
        image, files = _read_dicom_series(path, series_uid)
    else:
        ext = _ext(path)
        if ext not in CTA_EXTENSIONS:
            raise CTAInputError(
                f"unknown CTA format {path.name!r}: give a NIfTI (.nii/.nii.gz), NRRD (.nrrd/.nhdr), "
                "MetaImage (.mha/.mhd) file or a folder with a DICOM series"
            )
        files = [path]
        if ext in (".mhd", ".nhdr"):
            data = _detached_data_files(path)
            missing = [str(d) for d in data if not d.exists()]
            if missing:
                raise CTAInputError(f"{path.name} names data files that do not exist: {missing[:3]}; keep them next to the header")
            files += data
        try:
            image = sitk.ReadImage(str(path))
        except RuntimeError as exc:
            detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no detail"
            if "spacing" in detail.lower():
                raise CTAInputError(
                    f"{path.name} has an invalid voxel size ({detail}): fix the spacing in the file header (positive mm)"
                ) from None
            raise CTAInputError(
                f"cannot read {path} as an image ({detail}): check that the file is complete and in the format its name says"
            ) from None
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise CTAInputError(
            f"{path.name} has {image.GetNumberOfComponentsPerPixel()} components per voxel (colour or vector image): "
            "a CTA is a scalar image in HU; export the CT itself"
        )
    if image.GetDimension() != 3:
        raise CTAInputError(
            f"{path.name} is a {image.GetDimension()}D image of size {image.GetSize()}: a CTA must be one 3D volume "
            "(split a 4D/time series and pick one phase, or give the full slice stack for a 2D file)"
        )
    meta = {
        "source_path": str(path.resolve()),
        "source_files": len(files),
        "sha256": file_sha256(files),
        "hu_offset": float(hu_offset),
    }
    volume = volume_from_sitk(image, meta)
    if hu_offset:
        volume.array = volume.array + np.float32(hu_offset)
    validate_cta(volume, name=path.name, check_hu=check_hu)
    return volume


def validate_cta(volume: Volume, *, name: str = "the CTA", check_hu: bool = True) -> None:
    """Raise :class:`CTAInputError` unless ``volume`` looks like a 3D CT in HU.

    Checks: at least 2 voxels along each axis, voxel size in (0, 10] mm, finite voxels,
    not constant, and (``check_hu``) HU-like values: a span wider than a normalised image
    and a minimum below -200 HU (air).
    """
    if min(volume.shape_ijk) < 2:
        raise CTAInputError(f"{name} has size {volume.shape_ijk} (i, j, k): a CTA needs a 3D stack with at least 2 voxels along each axis")
    spacing = np.asarray(volume.spacing_mm)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0) or np.any(spacing > MAX_SPACING_MM):
        raise CTAInputError(
            f"{name} has voxel size {tuple(round(float(s), 4) for s in spacing)} mm: expected finite values in (0, {MAX_SPACING_MM:g}] mm; "
            "fix the spacing in the file header (or re-export the series)"
        )
    a = volume.array
    finite = np.isfinite(a)
    if not finite.all():
        raise CTAInputError(f"{name} has {int((~finite).sum())} NaN/infinite voxels: replace them (e.g. with -1024 HU) before loading")
    lo, hi = float(a.min()), float(a.max())
    if lo == hi:
        raise CTAInputError(f"{name} is constant ({lo:g} everywhere): the file holds no image; check the export")
    if not check_hu:
        return
    if hi - lo <= NORMALISED_SPAN:
        raise CTAInputError(
            f"{name} has values in [{lo:g}, {hi:g}]: this looks like a normalised image, not Hounsfield units; "
            "use the original CT in HU"
        )
    if lo >= 0:
        raise CTAInputError(
            f"{name} has no negative values (range [{lo:g}, {hi:g}]): a CT in HU has air near -1000. It probably "
            "stores raw CT numbers without the -1024 offset: load it with hu_offset=-1024 (CLI: --hu-offset -1024) "
            "or fix the rescale intercept; if it is not a CT (e.g. MR), it cannot be used"
        )
    if lo > HU_AIR_UPPER:
        raise CTAInputError(
            f"{name} has minimum {lo:g}: a head CT in HU contains air (about -1000 HU) around the head; "
            "check the rescale (hu_offset) or use an uncropped CT"
        )
