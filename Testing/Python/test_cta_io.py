"""CTA input: loading in HU with a correct ijk->RAS affine, validation errors, saving, masks."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.dataset import FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

from geopose.cta import cranium_mask_from_cta, load_cta, masks, save_volume, vessel_mask_from_cta
from geopose.volume import Volume
from geopose.errors import InputError

HEADSQ_OFFSET_HU = -1024.0  # the headsq MetaImage header stores raw values: HU = value - 1024


def _rotation(ax: float, ay: float, az: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _oblique_volume(dtype=np.float32) -> Volume:
    rng = np.random.default_rng(0)
    array = rng.normal(0, 300, size=(10, 24, 36)).astype(dtype)
    array[0, 0, 0] = -1000
    aff = np.eye(4)
    aff[:3, :3] = _rotation(0.3, -0.2, 0.7) @ np.diag([0.6, 0.9, 2.5])
    aff[:3, 3] = (-12.5, 40.25, 7.0)
    return Volume(array, aff)


# ------------------------------------------------------------------ headsq (real CT)


@pytest.fixture(scope="module")
def headsq(shared_data: Path) -> Volume:
    return load_cta(shared_data / "headsq" / "quarter_sidecar.mhd", hu_offset=HEADSQ_OFFSET_HU)


def _filled_head(volume: Volume) -> np.ndarray:
    """Tissue (> -400 HU) with the air it encloses, filled slice by slice (axial)."""
    head = volume.array > -400
    return np.stack(
        [sitk.GetArrayFromImage(sitk.BinaryFillhole(sitk.GetImageFromArray(s.astype(np.uint8)))) for s in head]
    ).astype(bool)


def test_headsq_without_offset_is_rejected_with_remedy(shared_data: Path):
    with pytest.raises(InputError, match="hu_offset=-1024"):
        load_cta(shared_data / "headsq" / "quarter_sidecar.mhd")


def test_headsq_grid_and_hu(headsq: Volume, shared_data: Path):
    assert headsq.shape_ijk == (64, 64, 93)
    np.testing.assert_allclose(headsq.spacing_mm, (3.2, 3.2, 1.5))
    a = headsq.array
    assert a.min() == pytest.approx(-1024.0)  # air (raw 0)
    assert np.percentile(a, 5) < -900  # plenty of air around the head
    assert (a > 300).mean() > 0.03 and a.max() > 1500  # bone
    soft = a[(a > -200) & (a < 200)]
    assert abs(np.median(soft)) < 80  # soft tissue / brain near 0..60 HU


def test_headsq_metadata_hashes_header_and_slices(headsq: Volume, shared_data: Path):
    folder = shared_data / "headsq"
    files = [folder / "quarter_sidecar.mhd"] + [folder / f"quarter.{n}" for n in range(1, 94)]
    h = hashlib.sha256()
    for f in files:
        h.update(f.read_bytes())
    assert headsq.metadata["sha256"] == h.hexdigest()
    assert headsq.metadata["source_files"] == 94
    assert headsq.metadata["source_path"].endswith("quarter_sidecar.mhd")


def test_headsq_orientation_face_is_anterior(headsq: Volume):
    """The air enclosed by the head outline (nasal cavity, sinuses, pharynx) lies in front of
    the head's centre: its RAS y centroid must be well anterior (+y) of the head's."""
    head = headsq.array > -400
    filled = _filled_head(headsq)
    enclosed_air = filled & ~head

    def centroid_ras(mask: np.ndarray) -> np.ndarray:
        k, j, i = np.nonzero(mask)
        return (headsq.ijk_to_ras @ np.stack([i, j, k, np.ones_like(i)]).astype(float))[:3].mean(axis=1)

    assert enclosed_air.sum() > 1000
    assert centroid_ras(enclosed_air)[1] - centroid_ras(filled)[1] > 20.0  # mm anterior


def test_headsq_header_puts_the_vertex_at_low_z(headsq: Volume):
    """A documented fact of the file: the MetaImage header has no direction (identity in
    LPS), so k grows towards RAS +z, but anatomically k runs from the skull base (slice 1)
    down to the neck. Bone and head cross-section are larger at low k (cranial end)."""
    a = headsq.array
    third = a.shape[0] // 3
    assert headsq.ijk_to_ras[2, 2] > 0
    assert (a[:third] > 300).mean() > 2 * (a[-third:] > 300).mean()


def test_headsq_masks(headsq: Volume):
    cranium = cranium_mask_from_cta(headsq)
    assert cranium.array.dtype == np.uint8 and set(np.unique(cranium.array)) == {0, 1}
    # the brain (soft tissue) in the top slices (cranial end, low k) is inside the mask
    top = headsq.array[:10]
    brain = (top > 0) & (top < 80)
    assert cranium.array[:10][brain].mean() > 0.8
    # hardly anything outside the head outline (a few voxels where the ear canals and
    # mouth open the outline of an axial slice)
    assert cranium.array[~_filled_head(headsq)].sum() < 0.002 * cranium.array.sum()
    vessels = vessel_mask_from_cta(headsq)
    # a CT without contrast: the partial-volume bone in the lumen HU range spans 57 mm at most, no vessel
    # tree, so the mask is empty and says why (the registration then runs without the vessel term)
    assert not vessels.array.any()
    assert vessels.metadata["contrast"] is False
    assert "no contrast-filled vessel tree" in vessels.metadata["method"]


# ------------------------------------------------------------- synthetic skull / vessels


def test_masks_on_synthetic_skull_with_vessel(monkeypatch):
    spacing = 1.0
    n = 96
    z, y, x = np.mgrid[:n, :n, :n].astype(float)
    c = (n - 1) / 2
    r = np.sqrt((z - c) ** 2 + (y - c) ** 2 + (x - c) ** 2)
    a = np.full((n, n, n), -1000.0, np.float32)
    a[r < 40] = 1000  # skull shell 34..40 mm
    a[r < 34] = 35  # brain
    tube = (np.hypot(y - c, x - (c + 10)) < 2.0) & (r < 30)  # a contrast-filled vessel spanning 58 mm
    a[tube] = 400
    a[(r > 33) & (r < 34)] = 500  # partial-volume rim of the skull in the vessel HU range
    vol = Volume(a, np.diag([spacing, spacing, spacing, 1.0]))
    cranium = cranium_mask_from_cta(vol).array.astype(bool)
    inside = r < 40
    iou = (cranium & inside).sum() / (cranium | inside).sum()
    assert iou > 0.95
    with monkeypatch.context() as m:
        m.setattr(masks, "CONTRAST_SPAN_MM", 50.0)  # the synthetic head is smaller than a real one
        vessels = vessel_mask_from_cta(vol, arteries_only=False).array.astype(bool)  # the threshold rule's geometry
    assert (vessels & tube).sum() / tube.sum() > 0.8  # most of the vessel found
    assert vessels[(r > 33) & (r < 34)].sum() == 0  # skull rim excluded
    assert (vessels & ~tube).sum() < 0.05 * tube.sum()


def test_vessel_mask_of_a_fine_grid_is_found_on_the_working_grid(monkeypatch):
    """At 0.5 mm the vessel mask is computed on 1 mm blocks and mapped back: contrast voxels closer to
    dense bone than BONE_MARGIN_MM less one working voxel are dropped, those farther than it plus
    one are kept, and the record says which grid."""
    spacing = 0.5
    a = np.full((24, 48, 80), 300.0, np.float32)  # contrast everywhere ...
    a[:, :, :20] = 1000.0  # ... beside a bone slab (x < 10 mm)
    vol = Volume(a, np.diag([spacing, spacing, spacing, 1.0]))
    monkeypatch.setattr(masks, "CONTRAST_SPAN_MM", 10.0)  # the block is 12 mm tall
    result = vessel_mask_from_cta(vol, arteries_only=False)
    assert result.metadata["method"].endswith("on a 1 mm working grid")
    vessels = result.array
    distance_mm = (np.arange(80) - 19) * spacing  # from the slab's last voxel, along x
    tolerance = masks.VESSEL_WORK_SPACING_MM
    assert not vessels[:, :, distance_mm <= masks.BONE_MARGIN_MM - tolerance].any()
    assert vessels[:, :, distance_mm > masks.BONE_MARGIN_MM + tolerance].all()


def test_vessel_mask_leaves_out_the_marrow_dense_bone_rings():
    """A vertical bone tube (cortex 1200 HU, marrow core of lumen HU 500, radius 6 mm) beside a contrast-filled
    tube (300 HU, radius 3 mm) in soft tissue, 1 mm voxels, 120 mm tall: the core is bone, the lumen is vessel."""
    n_k, n = 120, 64
    k, j, i = np.mgrid[:n_k, :n, :n].astype(float)
    a = np.full((n_k, n, n), 40.0, np.float32)
    r_bone = np.hypot(j - 32, i - 20)
    a[r_bone <= 8.0] = 1200.0
    core = r_bone <= 6.0
    a[core] = 500.0
    lumen = np.hypot(j - 32, i - 46) <= 3.0
    a[lumen] = 300.0
    result = vessel_mask_from_cta(Volume(a, np.eye(4)), arteries_only=False)
    vessels = result.array > 0
    assert result.metadata["contrast"] is True
    assert not (vessels & core).any()
    assert (vessels & lumen).sum() / lumen.sum() > 0.95


def test_a_clear_canal_tube_is_bridged_to_the_tree_across_its_mouth_and_a_faint_piece_is_not():
    """1 mm voxels: a tree (a vertical vessel stub) ends 4 mm (CANAL_BRIDGE_MM) below a bent canal tube (2 x 2 voxels,
    21 mm up then 15 mm across, an L like the petrous ICA; tube measure 0.2) and 3 mm beside a faint piece of the
    measure (a 6 x 8 x 8 mm blob at 0.04, like lumen-HU marrow), both reached across near-bone lumen: only the clear tube
    is joined, with its whole mouth, of which only the voxels within 3 mm (CANAL_MOUTH_MM) of both stay lumen; without
    the near-bone lumen at its mouth nothing is joined."""
    assert (masks.CANAL_MOUTH_MM, masks.CANAL_BRIDGE_MM) == (3.0, 4.0)  # the geometry below is drawn for these
    shape = (48, 64, 64)
    tree, canal, lumen = (np.zeros(shape, bool) for _ in range(3))
    tubes = np.zeros(shape, np.float32)
    tree[2:10, 30:32, 30:32] = True
    canal[14:35, 30:32, 30:32] = True  # up ...
    canal[33:35, 30:32, 32:47] = True  # ... then across
    tubes[canal] = 0.2
    canal[2:8, 30:38, 35:43] = True  # the faint piece beside the stub
    tubes[2:8, 30:38, 35:43] = 0.04
    lumen[10:14, 30:32, 30:32] = True  # the canal's mouth, 4 mm
    lumen[2:6, 30:32, 32:35] = True  # near-bone lumen between the stub and the faint piece
    bridged, mouths = masks._canal_mouths(tree, canal, tubes, lumen | canal, (1.0, 1.0, 1.0))
    assert bridged[14:35, 30:32, 30:32].all() and bridged[33:35, 30:32, 32:47].all() and bridged[10:14, 30:32, 30:32].all()
    assert not bridged[2:8, 30:38, 35:43].any() and not bridged[2:6, 30:32, 32:35].any()
    assert mouths[11:13, 30:32, 30:32].all() and mouths.sum() == mouths[11:13].sum() == 8  # 2 and 3 mm from both ends
    without = masks._canal_mouths(tree, canal, tubes, canal, (1.0, 1.0, 1.0))
    assert not without[0][10:14].any() and not without[1].any()


def test_cranium_mask_needs_bone():
    vol = Volume(np.full((8, 8, 8), 20.0, np.float32), np.eye(4))
    with pytest.raises(ValueError, match="no voxel above"):
        cranium_mask_from_cta(vol)


# ------------------------------------------------------------------ affine conventions


def test_lps_header_becomes_ras_affine(tmp_path: Path):
    image = sitk.GetImageFromArray(np.linspace(-1000, 1000, 12 * 30 * 44, dtype=np.float32).reshape(12, 30, 44))
    image.SetSpacing((0.5, 0.8, 2.0))
    image.SetOrigin((10.0, -20.0, 30.0))
    image.SetDirection(tuple(_rotation(0.1, 0.4, -0.3).ravel()))
    path = tmp_path / "ct.mha"
    sitk.WriteImage(image, str(path))
    vol = load_cta(path)
    for ijk in [(0, 0, 0), (5, 0, 0), (2, 3, 1), (39, 29, 11)]:
        lps = np.array(image.TransformIndexToPhysicalPoint(ijk))
        ras = (vol.ijk_to_ras @ np.append(ijk, 1.0))[:3]
        np.testing.assert_allclose(ras, lps * (-1, -1, 1), atol=1e-9)
    # voxel (i, j, k) is array[k, j, i]
    assert vol.array[1, 3, 2] == pytest.approx(sitk.GetArrayViewFromImage(image)[1, 3, 2])
    assert image.GetPixel(2, 3, 1) == pytest.approx(vol.array[1, 3, 2])


def test_a_float32_file_is_loaded_without_copying_its_voxels(tmp_path: Path):
    """A float32 CTA's voxels stay in SimpleITK's buffer (no 512 MB copy at 512^3): the array's base keeps the image
    alive after everything else is gone, the values are SimpleITK's, and it is writable as a copy would be. Another
    voxel type is converted to float32."""
    import gc

    values = np.linspace(-1000, 1000, 12 * 30 * 44, dtype=np.float32).reshape(12, 30, 44)
    image = sitk.GetImageFromArray(values)
    image.SetSpacing((2.0, 2.0, 2.0))
    sitk.WriteImage(image, str(tmp_path / "f.nii.gz"))
    sitk.WriteImage(sitk.Cast(image, sitk.sitkInt16), str(tmp_path / "i.nii.gz"))
    array = load_cta(tmp_path / "f.nii.gz").array
    assert array.base is not None and isinstance(getattr(array.base, "image", None), sitk.Image)
    del image
    gc.collect()
    np.testing.assert_array_equal(array, values)
    array[0, 0, 0] = 7.0
    assert array[0, 0, 0] == 7.0
    converted = load_cta(tmp_path / "i.nii.gz").array
    assert converted.dtype == np.float32 and converted.base is None
    np.testing.assert_array_equal(converted, values.astype(np.int16).astype(np.float32))


@pytest.mark.parametrize("name", ["v.nii.gz", "v.nii", "v.nrrd", "v.mha"])
def test_save_load_round_trip_oblique_anisotropic(tmp_path: Path, name: str):
    vol = _oblique_volume()
    out = save_volume(vol, tmp_path / name)
    back = load_cta(out)
    np.testing.assert_array_equal(back.array, vol.array)
    atol = 1e-4 if name.startswith("v.nii") else 1e-9  # NIfTI stores the affine in float32
    np.testing.assert_allclose(back.ijk_to_ras, vol.ijk_to_ras, atol=atol)


def test_save_keeps_label_type(tmp_path: Path):
    vol = _oblique_volume()
    labels = vol.like((vol.array > 0).astype(np.uint8))
    save_volume(labels, tmp_path / "l.nrrd")
    image = sitk.ReadImage(str(tmp_path / "l.nrrd"))
    assert image.GetPixelID() == sitk.sitkUInt8
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), labels.array)


def test_save_rejects_shear_and_unknown_format(tmp_path: Path):
    vol = _oblique_volume()
    sheared = Volume(vol.array, vol.ijk_to_ras @ np.array([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    with pytest.raises(InputError, match="sheared"):
        save_volume(sheared, tmp_path / "s.nii.gz")
    with pytest.raises(InputError, match=r"\.nrrd"):
        save_volume(vol, tmp_path / "s.png")


# ------------------------------------------------------------------ DICOM series


def _write_ct_series(folder: Path, hu: np.ndarray, spacing=(0.7, 0.6, 2.0), origin=(-90.0, -100.0, 50.0), series_uid=None):
    folder.mkdir(parents=True, exist_ok=True)
    series_uid = series_uid or generate_uid()
    study_uid = generate_uid()
    for k, plane in enumerate(hu):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = pydicom.Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.Modality, ds.PatientName, ds.PatientID = "CT", "Phantom^Test", "P1"
        ds.StudyInstanceUID, ds.SeriesInstanceUID = study_uid, series_uid
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [origin[0], origin[1], origin[2] + k * spacing[2]]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [spacing[1], spacing[0]]  # row spacing, column spacing
        ds.SliceThickness = spacing[2]
        ds.Rows, ds.Columns = plane.shape
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.RescaleIntercept, ds.RescaleSlope = -1024, 1
        ds.PixelData = (plane + 1024).astype(np.uint16).tobytes()
        ds.save_as(folder / f"slice_{k:03d}.dcm", enforce_file_format=True)


def test_dicom_series_in_hu_with_lps_geometry(tmp_path: Path):
    rng = np.random.default_rng(1)
    hu = rng.integers(-1024, 2000, size=(12, 40, 36)).astype(np.int16)
    _write_ct_series(tmp_path / "ct", hu)
    vol = load_cta(tmp_path / "ct")
    np.testing.assert_array_equal(vol.array, hu.astype(np.float32))
    np.testing.assert_allclose(vol.spacing_mm, (0.7, 0.6, 2.0), atol=1e-6)  # PixelSpacing = [row 0.6, col 0.7]
    # DICOM ImagePositionPatient is LPS: the first voxel sits at RAS (90, 100, 50)
    np.testing.assert_allclose(vol.ijk_to_ras[:3, 3], (90.0, 100.0, 50.0), atol=1e-6)
    np.testing.assert_allclose(vol.ijk_to_ras[:3, :3], np.diag((-0.7, -0.6, 2.0)), atol=1e-6)
    assert vol.metadata["source_files"] == 12
    assert vol.metadata["slice_geometry"]["resampled"] is False


def test_dicom_folder_with_two_series_needs_a_choice(tmp_path: Path):
    hu = np.full((12, 36, 36), -1000, np.int16)
    hu[1, 1, 1] = 500
    uid = generate_uid()
    _write_ct_series(tmp_path / "mixed", hu, series_uid=uid)
    _write_ct_series(tmp_path / "mixed2", hu)
    for f in (tmp_path / "mixed2").iterdir():
        f.rename(tmp_path / "mixed" / ("b_" + f.name))
    with pytest.raises(InputError, match="series_uid"):
        load_cta(tmp_path / "mixed")
    assert load_cta(tmp_path / "mixed", series_uid=uid).array.shape == (12, 36, 36)


# ------------------------------------------------------------------ bad input


def _write(tmp_path: Path, array: np.ndarray, spacing=None, name="x.nii.gz", vector=False) -> Path:
    image = sitk.GetImageFromArray(array, isVector=vector)
    image.SetSpacing(spacing if spacing is not None else (2.0,) * image.GetDimension())
    path = tmp_path / name
    sitk.WriteImage(image, str(path))
    return path


def _write_mhd(tmp_path: Path, spacing: str) -> Path:
    """A MetaImage header with a hand-written ElementSpacing (SimpleITK refuses to write a zero spacing)."""
    a = _ct()
    (tmp_path / "z.mhd").write_text(
        f"ObjectType = Image\nNDims = 3\nDimSize = {a.shape[2]} {a.shape[1]} {a.shape[0]}\n"
        f"ElementSpacing = {spacing}\nElementType = MET_FLOAT\nElementDataFile = z.raw\n"
    )
    a.tofile(tmp_path / "z.raw")
    return tmp_path / "z.mhd"


def _ct(shape=(12, 24, 28)) -> np.ndarray:
    a = np.zeros(shape, np.float32)
    a[0] = -1000
    a[-1] = 1200
    return a


@pytest.mark.parametrize(
    "make, pattern",
    [
        (lambda p: _write(p, _ct()[0]), "2D image"),
        (lambda p: _write(p, np.stack([_ct(), _ct()])), "4D"),
        (lambda p: _write(p, np.stack([_ct()] * 3, axis=-1), vector=True, name="x.mha"), "components per voxel"),
        (lambda p: _write(p, _ct()[:1]), "voxels along each axis"),
        (lambda p: _write(p, _ct((4, 4, 4))), "voxels along each axis"),
        (lambda p: _write(p, np.where(_ct() > 1000, np.nan, _ct()).astype(np.float32), name="x.mha"), "NaN"),
        (lambda p: _write(p, np.full((12, 24, 28), -1000, np.float32)), "constant"),
        (lambda p: _write(p, _ct(), spacing=(2.0, 2.0, 12.0)), "voxel size"),
        (lambda p: _write_mhd(p, "1 0 1"), "voxel size"),
        (lambda p: _write(p, np.linspace(0, 1, 12 * 24 * 28, dtype=np.float32).reshape(12, 24, 28)), "normalised"),
        (lambda p: _write(p, _ct() + 1024), "hu_offset=-1024"),
        (lambda p: _write(p, _ct() * 0.05), "air"),
    ],
)
def test_invalid_images_raise_clear_errors(tmp_path: Path, make, pattern):
    with pytest.raises(InputError, match=pattern):
        load_cta(make(tmp_path))


def test_missing_unknown_and_corrupt_files(tmp_path: Path):
    with pytest.raises(InputError, match="not found"):
        load_cta(tmp_path / "nope.nii.gz")
    (tmp_path / "ct.png").write_bytes(b"\x89PNG")
    with pytest.raises(InputError, match="unknown CTA format"):
        load_cta(tmp_path / "ct.png")
    (tmp_path / "bad.nii.gz").write_bytes(b"this is not a NIfTI file at all" * 10)
    with pytest.raises(InputError, match="cannot read"):
        load_cta(tmp_path / "bad.nii.gz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no DICOM series"):
        load_cta(tmp_path / "empty")


def test_load_does_not_alter_the_file(tmp_path: Path):
    path = save_volume(_oblique_volume(), tmp_path / "v.nrrd")
    before = path.read_bytes()
    load_cta(path, hu_offset=-5.0)
    assert path.read_bytes() == before
