"""Loading, validating and saving CT(A) volumes.

SimpleITK describes images in patient LPS: ``lps = origin + D @ diag(spacing) @ ijk``.
A :class:`~geopose.volume.Volume` keeps ``ijk_to_ras``, so the first two rows of
that affine change sign (``RAS = diag(-1, -1, 1) @ LPS``). Arrays stay in
SimpleITK order ``[k, j, i]``. Voxel values are Hounsfield units (HU); DICOM
rescale slope/intercept is applied by the reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .. import limits as L
from ..checksums import file_sha256
from ..errors import InputError
from ..geometry.frames import RAS_TO_LPS
from ..inputpaths import input_kind
from ..imagefiles import IMAGE_EXTENSIONS, check_image_file, image_extension
from ..volume import Volume
from .dicom_series import read_dicom_series

__all__ = [
    "CTA_EXTENSIONS",
    "load_cta",
    "save_volume",
    "validate_cta",
    "volume_from_sitk",
    "sitk_from_volume",
    "sitk_geometry",
    "file_sha256",
]

#: File name endings ``load_cta`` reads (a folder is read as a DICOM series).
CTA_EXTENSIONS = IMAGE_EXTENSIONS
#: Extra spatial tolerance for slightly non-orthonormal directions when saving.
_ORTHONORMAL_TOL = 1e-4


class _ImageVoxels:
    """A SimpleITK image's voxel buffer as numpy sees it (``numpy.asarray`` of this), the image kept alive for as long
    as an array uses the buffer: no copy of the voxels (512 MB for a float32 512^3 CTA)."""

    def __init__(self, image: sitk.Image) -> None:
        self.image = image  # sole owner (GetArrayViewFromImage makes the buffer unique): writable, as a copy would be
        interface = dict(sitk.GetArrayViewFromImage(image).__array_interface__)
        interface["data"] = (interface["data"][0], False)
        self.__array_interface__ = interface


def volume_from_sitk(image: sitk.Image, metadata: dict | None = None) -> Volume:
    """A SimpleITK 3D scalar image -> :class:`Volume` (float32 voxels, ijk->RAS affine). A float32 image's
    voxels are shared with the Volume (the image is the array's base), any other type is converted."""
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    lin_lps = direction @ np.diag(image.GetSpacing())
    ijk_to_lps = np.eye(4)
    ijk_to_lps[:3, :3] = lin_lps
    ijk_to_lps[:3, 3] = image.GetOrigin()
    array = np.asarray(_ImageVoxels(image)).astype(np.float32, copy=False)
    return Volume(array, RAS_TO_LPS @ ijk_to_lps, dict(metadata or {}))


def sitk_geometry(volume: Volume) -> dict:
    """``volume``'s grid as SimpleITK states it (LPS): ``size``, ``outputSpacing``, ``outputDirection`` and
    ``outputOrigin`` (the keywords of ``sitk.Resample``); the affine must be rotation x spacing."""
    ijk_to_lps = RAS_TO_LPS @ volume.ijk_to_ras
    lin = ijk_to_lps[:3, :3]
    spacing = np.linalg.norm(lin, axis=0)
    if np.any(spacing <= 0) or not np.all(np.isfinite(lin)):
        raise InputError(f"the volume affine has a zero or non-finite axis: {volume.ijk_to_ras.tolist()}")
    direction = lin / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=_ORTHONORMAL_TOL):
        raise InputError(
            "the volume affine is sheared (its axes are not orthogonal); NIfTI/NRRD/MHA via SimpleITK store "
            "only rotation x spacing: resample the volume onto an orthogonal grid first"
        )
    return {"size": [int(n) for n in volume.shape_ijk], "outputSpacing": tuple(float(s) for s in spacing),
            "outputDirection": tuple(float(v) for v in direction.ravel()),
            "outputOrigin": tuple(float(v) for v in ijk_to_lps[:3, 3])}


def sitk_from_volume(volume: Volume) -> sitk.Image:
    """A :class:`Volume` -> SimpleITK image in LPS (:func:`sitk_geometry`)."""
    geometry = sitk_geometry(volume)
    array = volume.array
    if array.dtype == bool:
        array = array.astype(np.uint8)
    image = sitk.GetImageFromArray(np.ascontiguousarray(array))
    image.SetSpacing(geometry["outputSpacing"])
    image.SetDirection(geometry["outputDirection"])
    image.SetOrigin(geometry["outputOrigin"])
    return image


def save_volume(volume: Volume, path: str | Path) -> Path:
    """Write a volume (image or label map, voxel type kept) to NIfTI, NRRD or MHA (RAS -> LPS)."""
    path = Path(path)
    if image_extension(path) not in (".nii", ".nii.gz", ".nrrd", ".mha"):
        raise InputError(f"cannot write {path.name}: use a .nii, .nii.gz, .nrrd or .mha file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(sitk_from_volume(volume), str(path), useCompression=image_extension(path) != ".nii")
    return path


def _read_image_file(path: Path) -> tuple[sitk.Image, list[Path], dict]:
    """A NIfTI/NRRD/MetaImage file read by SimpleITK after :func:`~geopose.imagefiles.check_image_file`
    has checked its header against its voxel data; the files it consists of; notes."""
    declared = check_image_file(path, L.CTA_MAX_VOXELS)
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no detail"
        if "spacing" in detail.lower():
            raise InputError(
                f"{path.name} has an invalid voxel size ({detail}): fix the spacing in the file header (positive mm)"
            ) from None
        raise InputError(
            f"cannot read {path} as an image ({detail}): check that the file is complete and in the format its name says"
        ) from None
    if image.GetNumberOfComponentsPerPixel() == 1 and image.GetNumberOfPixels() != int(np.prod(declared.shape)):
        raise InputError(f"{path.name}: SimpleITK read {image.GetSize()} voxels but the header declares {declared.shape}: "
                         "the header is damaged; re-export the image")
    notes = {"voxel_data_checks": declared.checks}
    if len(declared.xforms) == 2 and image.GetDimension() == 3:
        note = _xform_disagreement(declared.xforms, volume_from_sitk(image[:1, :1, :1]).ijk_to_ras, path.name, image.GetSize())
        if note:
            notes["orientation_note"] = note
    return image, declared.files, notes


#: sform and qform of one NIfTI header count as contradicting when a grid corner lands this far apart (mm).
XFORM_DISAGREEMENT_MM = 0.5


def _xform_disagreement(xforms: dict[str, np.ndarray], used: np.ndarray, name: str, size: tuple[int, ...]) -> str | None:
    """A note when a NIfTI header's sform and qform place the grid's corners more than
    :data:`XFORM_DISAGREEMENT_MM` apart (which one SimpleITK used, whether one of them is mirrored)."""
    corners = np.array([[i, j, k, 1.0] for i in (0, size[0] - 1) for j in (0, size[1] - 1) for k in (0, size[2] - 1)]).T
    q, s = xforms["qform"] @ corners, xforms["sform"] @ corners
    apart = float(np.linalg.norm(q - s, axis=0).max())
    if apart <= XFORM_DISAGREEMENT_MM:
        return None
    chose = min(xforms, key=lambda k: float(np.abs(xforms[k][:3] - used[:3]).max()))
    mirrored = np.sign(np.linalg.det(xforms["qform"][:3, :3])) != np.sign(np.linalg.det(xforms["sform"][:3, :3]))
    return (f"{name}: the NIfTI sform and qform disagree (grid corners up to {apart:.1f} mm apart"
            f"{'; one of them is mirrored' if mirrored else ''}); the {chose} was used. Check the CTA's orientation "
            "(left-right!) in a viewer and re-export it with one consistent transform")


def load_cta(path: str | Path, *, hu_offset: float = 0.0, series_uid: str | None = None, check_hu: bool = True) -> Volume:
    """Read a CT(A) volume in HU from NIfTI, NRRD (.nrrd/.nhdr), MetaImage (.mha/.mhd)
    or a folder holding a DICOM series, and validate it (:func:`validate_cta`).

    Files are checked against their headers first (:mod:`geopose.imagefiles`: truncated or
    surplus voxel data, NaN/Inf voxels); a DICOM series is placed by its slices' geometry
    and resampled when tilted or unevenly spaced (:mod:`geopose.cta.dicom_series`).
    ``hu_offset`` (HU) is added to every voxel after reading, for files that store
    raw CT numbers without the rescale intercept (e.g. ``hu_offset=-1024``).
    Metadata: ``source_path``, ``source_files`` (count), ``sha256`` (of the header and
    data files, or the DICOM files in series order, concatenated), ``hu_offset``, and
    ``slice_geometry`` (DICOM) or ``voxel_data_checks``.
    """
    path = Path(path)
    hu_offset = L.check_range("hu_offset", hu_offset, L.HU_OFFSET, "use -1024 for raw CT numbers, else 0")
    if input_kind(path, "CTA") == "folder":
        array, ijk_to_lps, files, notes = read_dicom_series(path, series_uid)
        meta = {"source_path": str(path.resolve()), "source_files": len(files), "sha256": file_sha256(files),
                "hu_offset": float(hu_offset), **notes}
        volume = Volume(array, RAS_TO_LPS @ ijk_to_lps, meta)
    else:
        ext = image_extension(path)
        if ext not in CTA_EXTENSIONS:
            raise InputError(
                f"unknown CTA format {path.name!r}: give a NIfTI (.nii/.nii.gz), NRRD (.nrrd/.nhdr), "
                "MetaImage (.mha/.mhd) file or a folder with a DICOM series"
            )
        image, files, notes = _read_image_file(path)
        if image.GetNumberOfComponentsPerPixel() != 1:
            raise InputError(
                f"{path.name} has {image.GetNumberOfComponentsPerPixel()} components per voxel (colour or vector image): "
                "a CTA is a scalar image in HU; export the CT itself"
            )
        if image.GetDimension() != 3:
            raise InputError(
                f"{path.name} is a {image.GetDimension()}D image of size {image.GetSize()}: a CTA must be one 3D volume "
                "(split a 4D/time series and pick one phase, or give the full slice stack for a 2D file)"
            )
        meta = {
            "source_path": str(path.resolve()),
            "source_files": len(files),
            "sha256": file_sha256(files),
            "hu_offset": float(hu_offset),
            **notes,
        }
        volume = volume_from_sitk(image, meta)
    if hu_offset:
        volume.array = volume.array + np.float32(hu_offset)
    validate_cta(volume, name=path.name, check_hu=check_hu)
    return volume


def validate_cta(volume: Volume, *, name: str = "the CTA", check_hu: bool = True) -> None:
    """Raise :class:`InputError` unless ``volume`` looks like a 3D CT in HU.

    Checks (bounds of :mod:`geopose.limits`): voxels per axis (``CTA_VOXELS_PER_AXIS``), a finite,
    non-degenerate affine, voxel
    size (``CTA_VOXEL_SIZE_MM``), extent (``CTA_EXTENT_MM``), finite voxels, not constant, and
    (``check_hu``) HU-like values: a span wider than a normalised image and a minimum below
    -200 HU (air).
    """
    lo, hi = L.CTA_VOXELS_PER_AXIS
    if not all(lo <= n <= hi for n in volume.shape_ijk):
        raise InputError(f"{name} has size {volume.shape_ijk} (i, j, k): a CTA has {lo}..{hi} voxels along each axis; "
                         "give the whole 3D stack (or check the header's dimensions)")
    if not np.all(np.isfinite(volume.ijk_to_ras)) or abs(np.linalg.det(volume.ijk_to_ras[:3, :3])) < 1e-12:
        raise InputError(f"{name} has a non-finite or degenerate position/orientation in its header "
                         f"({np.round(volume.ijk_to_ras[:3], 4).tolist()}): fix the header's origin and direction (or re-export it)")
    spacing = np.asarray(volume.spacing_mm)
    vlo, vhi = L.CTA_VOXEL_SIZE_MM
    if not np.all(np.isfinite(spacing)) or np.any(spacing < vlo) or np.any(spacing > vhi):
        raise InputError(
            f"{name} has voxel size {tuple(round(float(s), 4) for s in spacing)} mm: expected finite values in {vlo:g}..{vhi:g} mm; "
            "fix the spacing in the file header (or re-export the series)"
        )
    extent = np.asarray(volume.extent_mm)
    elo, ehi = L.CTA_EXTENT_MM
    if np.any(extent < elo) or np.any(extent > ehi):
        raise InputError(
            f"{name} covers {' x '.join(f'{e:.4g}' for e in extent)} mm: a CTA of a head covers {elo:g}..{ehi:g} mm along each "
            "axis; check the header's dimensions and spacing (or give the complete volume)"
        )
    a = volume.array
    lo, hi = float(a.min()), float(a.max())  # NaN or infinite when any voxel is: no full-size temporary otherwise
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = sum(int(np.count_nonzero(~np.isfinite(slab))) for slab in _slabs(a))
        raise InputError(f"{name} has {bad} NaN/infinite voxels: replace them (e.g. with -1024 HU) before loading")
    if lo == hi:
        if not check_hu and lo == 0:
            raise InputError(f"{name} is empty (0 everywhere): give a mask with the structure labelled, or leave it out")
        raise InputError(f"{name} is constant ({lo:g} everywhere): the file holds no image; check the export")
    if not check_hu:
        return
    if hi - lo <= L.CTA_MIN_SPAN_HU:
        raise InputError(
            f"{name} has values in [{lo:g}, {hi:g}]: this looks like a normalised image, not Hounsfield units; "
            "use the original CT in HU"
        )
    if lo >= 0:
        raise InputError(
            f"{name} has no negative values (range [{lo:g}, {hi:g}]): a CT in HU has air near -1000. It probably "
            "stores raw CT numbers without the -1024 offset: load it with hu_offset=-1024 (CLI: --hu-offset -1024) "
            "or fix the rescale intercept; if it is not a CT (e.g. MR), it cannot be used"
        )
    if lo > L.CTA_AIR_MAX_HU:
        raise InputError(
            f"{name} has minimum {lo:g}: a head CT in HU contains air (about -1000 HU) around the head; "
            "check the rescale (hu_offset) or use an uncropped CT"
        )
    _check_hu_distribution(a, lo, name)


def _slabs(a: np.ndarray, slices: int = 32):
    """``a`` in slabs of ``slices`` along its first axis (counts over them need no full-size temporaries)."""
    return (a[k:k + slices] for k in range(0, a.shape[0], slices))


def _check_hu_distribution(a: np.ndarray, lo: float, name: str) -> None:
    """Refuse a volume whose voxels lie outside :data:`~geopose.limits.CTA_PLAUSIBLE_HU` in more than
    :data:`~geopose.limits.CTA_MAX_IMPLAUSIBLE_SHARE` of the volume. Voxels at the minimum below that range, when
    they are at least 1 % of the volume, are padding (outside the scan circle, e.g. -3024 HU) and not counted."""
    plo, phi = L.CTA_PLAUSIBLE_HU
    at_lo = below = above = 0
    for slab in _slabs(a):
        at_lo += int(np.count_nonzero(slab == lo)) if lo < plo else 0
        below += int(np.count_nonzero(slab < plo))
        above += int(np.count_nonzero(slab > phi))
    padding = at_lo if at_lo >= 0.01 * a.size else 0
    below -= padding
    counted = a.size - padding
    share = (below + above) / max(counted, 1)
    if share > L.CTA_MAX_IMPLAUSIBLE_SHARE:
        pad = f" (the {padding} padding voxels at {lo:g} HU not counted)" if padding else ""
        raise InputError(
            f"{name}: {100 * share:.1f} % of its voxels lie outside {plo:g}..{phi:g} HU{pad} ({100 * below / counted:.1f} % below, "
            f"{100 * above / counted:.1f} % above), which no CT in HU has: its pixel data or rescale are read wrong (e.g. signed "
            "values as unsigned, a wrong RescaleSlope/Intercept or --hu-offset); re-export the series uncompressed "
            "(gdcmconv --raw) or as NIfTI (dcm2niix), check its HU in a viewer and load that"
        )
