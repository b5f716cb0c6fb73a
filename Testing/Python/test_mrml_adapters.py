"""MRML adapters on real Slicer MRML classes (slicer-core wheel): volumes,
segmentations, detector planes, DSA sequences, output nodes and .mrb round trips."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

slicer = pytest.importorskip("slicer", reason="needs the slicer-core wheel (Slicer's MRML in Python)")

from geopose import contract as C  # noqa: E402
from geopose.geometry import CArmAngles, Detector, isopose, pose_from_params, project_points, source_and_detector_points  # noqa: E402
from geopose.volume import Volume  # noqa: E402
from geopose import mrml  # noqa: E402
from geopose.mrml.plane import detector_index_to_camera  # noqa: E402


def _cta() -> tuple[Volume, Volume]:
    """A small oblique CTA (HU) with a vessel tube (label 1) and a blob (label 2)."""
    rng = np.random.default_rng(0)
    k, j, i = 30, 36, 40
    hu = rng.normal(40, 5, (k, j, i)).astype(np.int16)
    lab = np.zeros((k, j, i), np.uint8)
    kk, jj, ii = np.meshgrid(np.arange(k), np.arange(j), np.arange(i), indexing="ij")
    tube = (jj - 18) ** 2 + (kk - 15) ** 2 <= 4
    tube &= (ii > 4) & (ii < 36)
    lab[tube] = 1
    lab[(ii - 10) ** 2 + (jj - 8) ** 2 + (kk - 22) ** 2 <= 9] = 2
    hu[lab > 0] = 400
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    c, s = math.cos(0.2), math.sin(0.2)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ R
    m = np.eye(4)
    m[:3, :3] = R @ np.diag([0.9, 1.1, 1.5])
    m[:3, 3] = (12.0, -30.0, 7.0)
    cta = Volume(hu, m)
    return cta, cta.like(lab)


def _pose(view: int = C.VIEW_PA, dr=(0.05, -0.03, 0.02), dt=(3.0, -5.0, 2.0)) -> np.ndarray:
    return pose_from_params(np.asarray(dr), np.asarray(dt)) @ isopose(view)


DET = Detector(48, 56, (0.6, 0.5), 1000.0, principal_offset_mm=(1.5, -2.0))


@pytest.fixture()
def scene():
    return mrml.new_scene()


def test_volume_round_trip_keeps_array_affine_and_input(scene):
    cta, _ = _cta()
    before = cta.array.copy()
    node = mrml.volume_to_node(scene, cta, "CTA")
    back = mrml.volume_from_node(node)
    np.testing.assert_array_equal(back.array, cta.array)
    assert back.array.dtype == cta.array.dtype
    np.testing.assert_allclose(back.ijk_to_ras, cta.ijk_to_ras, atol=1e-9)
    np.testing.assert_array_equal(cta.array, before)
    back.array[0, 0, 0] = 1234  # a copy, not a view of the node's image
    assert mrml.volume_from_node(node).array[0, 0, 0] != 1234


def test_volume_node_errors_are_clear(scene):
    cta, _ = _cta()
    sheared = Volume(cta.array, cta.ijk_to_ras @ np.array([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    with pytest.raises(ValueError, match="sheared"):
        mrml.volume_to_node(scene, sheared, "bad")
    empty = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "empty")
    with pytest.raises(ValueError, match="no image data"):
        mrml.volume_from_node(empty)
    node = mrml.volume_to_node(scene, cta, "CTA")
    node.SetAndObserveTransformNodeID(scene.AddNewNodeByClass("vtkMRMLLinearTransformNode").GetID())
    with pytest.raises(ValueError, match="harden"):
        mrml.volume_from_node(node)


def test_segmentation_labelmap_round_trip(scene):
    cta, lab = _cta()
    ref = mrml.volume_to_node(scene, cta, "CTA")
    seg = mrml.segmentation_from_labelmap(scene, lab, {1: ("vessel", (1, 0, 0)), 2: ("blob", (0, 1, 0))}, "Vessels")
    n_before = scene.GetNumberOfNodes()
    back, names = mrml.labelmap_from_segmentation(seg, ref)
    assert names == {"vessel": 1, "blob": 2}
    assert scene.GetNumberOfNodes() == n_before  # temporary nodes removed
    np.testing.assert_allclose(back.ijk_to_ras, cta.ijk_to_ras, atol=1e-9)
    np.testing.assert_array_equal(back.array, lab.array)
    assert mrml.segment_colors(seg) == {"vessel": (1.0, 0.0, 0.0), "blob": (0.0, 1.0, 0.0)}
    with pytest.raises(ValueError, match="not in"):
        mrml.labelmap_from_segmentation(seg, ref, ["nope"])


def test_detector_ijk_to_ras_puts_every_pixel_on_its_detector_point():
    cta, _ = _cta()
    pose_c = _pose(C.VIEW_LAT_PLUS)
    pose_ras = cta.centred_to_ras @ pose_c
    m = mrml.detector_ijk_to_ras(DET, pose_ras)
    _, world = source_and_detector_points(pose_c, DET)
    want = world @ cta.centred_to_ras[:3, :3].T + cta.centred_to_ras[:3, 3]  # (H, W, 3) RAS
    jj, ii = np.meshgrid(np.arange(DET.rows), np.arange(DET.cols), indexing="ij")
    ijk = np.stack([ii, jj, np.zeros_like(ii), np.ones_like(ii)], -1).astype(float)
    got = ijk @ m.T
    np.testing.assert_allclose(got[..., :3], want, atol=1e-9)
    # k steps along the beam away from the source, the axes are orthonormal up to spacing.
    spacing = np.linalg.norm(m[:3, :3], axis=0)
    np.testing.assert_allclose(spacing, (DET.spacing_mm[1], DET.spacing_mm[0], mrml.plane.PLANE_THICKNESS_MM))
    assert np.linalg.det(m[:3, :3]) > 0
    src = pose_ras[:3, 3]
    assert np.linalg.norm(m[:3, 2] + m[:3, 3] - src) > np.linalg.norm(m[:3, 3] - src)
    assert np.allclose(detector_index_to_camera(DET)[2, 3], DET.sdd_mm)


def test_dsa_sequence_frames_on_plane_with_browser_and_attributes(scene):
    cta, _ = _cta()
    frames = np.random.default_rng(1).integers(0, 4000, (4, DET.rows, DET.cols)).astype(np.uint16)
    pose_ras = cta.centred_to_ras @ _pose()
    angles = CArmAngles(-2.5, 4.0, DET.sdd_mm, 650.0)
    seq, browser = mrml.dsa_sequence_node(scene, frames, DET, pose_ras, "DSA PA", frame_time_s=0.25, angles=angles)
    assert seq.GetNumberOfDataNodes() == 4
    assert [seq.GetNthIndexValue(n) for n in range(4)] == ["0", "0.25", "0.5", "0.75"]
    np.testing.assert_array_equal(mrml.frames_from_sequence(seq), frames)
    want = mrml.detector_ijk_to_ras(DET, pose_ras)
    for n in range(4):
        got = mrml.volume_from_node(seq.GetNthDataNode(n)).ijk_to_ras
        np.testing.assert_allclose(got, want, atol=1e-9)
    proxy = browser.GetProxyNode(seq)
    assert proxy is not None and proxy.GetScene() is scene
    np.testing.assert_array_equal(mrml.volume_from_node(proxy).array[0], frames[0])
    det, ang, dt = mrml.geometry_from_attributes(seq)
    assert det == DET and ang == angles and dt == 0.25
    with pytest.raises(ValueError, match="does not match"):
        mrml.dsa_sequence_node(scene, frames[:, :10], DET, pose_ras, "bad")


def test_transform_and_camera_nodes_match_pose(scene):
    cta, _ = _cta()
    pose_c = _pose(C.VIEW_LAT_MINUS)
    pose_ras = cta.centred_to_ras @ pose_c
    t = mrml.pose_transform_node(scene, pose_ras, "GeoPose LAT pose")
    got = mrml.transform_matrix(t)
    np.testing.assert_allclose(got, pose_ras, atol=1e-12)
    cam = mrml.camera_node(scene, pose_ras, DET, "GeoPose LAT camera")
    src, world = source_and_detector_points(pose_c, DET)
    to_ras = lambda p: p @ cta.centred_to_ras[:3, :3].T + cta.centred_to_ras[:3, 3]  # noqa: E731
    np.testing.assert_allclose(cam.GetPosition(), to_ras(src), atol=1e-9)
    centre = to_ras(world.reshape(-1, 3).mean(0))
    np.testing.assert_allclose(cam.GetFocalPoint(), centre, atol=1e-6)
    row0_dir = to_ras(world[0].mean(0)) - centre  # towards image row 0
    up = np.asarray(cam.GetViewUp())
    assert np.dot(up, row0_dir / np.linalg.norm(row0_dir)) > 0.999
    fov = 2 * math.degrees(math.atan(DET.rows * DET.spacing_mm[0] / 2 / DET.sdd_mm))
    assert cam.GetViewAngle() == pytest.approx(fov)


def test_projected_segmentation_covers_projected_vessel_voxels(scene):
    cta, lab = _cta()
    pose_c = _pose(C.VIEW_PA)
    det = Detector(64, 64, (0.4, 0.4), 1020.0)
    mrml.volume_to_node(scene, cta, "CTA")
    seg = mrml.projected_segmentation_node(
        scene, lab, {1: ("vessel", (1, 0, 0)), 2: ("blob", (0, 0, 1))}, pose_c, det, "GeoPose PA projected vessels"
    )
    back, names = mrml.labelmap_from_segmentation(
        seg, mrml.plane_volume_node(scene, np.zeros(det.shape), det, cta.centred_to_ras @ pose_c, "MAP"), ["vessel"]
    )
    mask = back.array[0] == names["vessel"]
    # Pixels hit by vessel voxel centres (projected with the geometry module) are covered ...
    kji = np.argwhere(lab.array == 1)
    ijk = np.c_[kji[:, ::-1], np.ones(len(kji))]
    pts = (ijk @ cta.ijk_to_centred.T)[:, :3]
    rc, _ = project_points(pose_c, det, pts)
    rc = np.rint(rc).astype(int)
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < det.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < det.cols)
    assert inside.mean() > 0.9
    hit = np.zeros(det.shape, bool)
    hit[rc[inside, 0], rc[inside, 1]] = True
    assert mask[hit].mean() > 0.99
    # ... and the projection stays close to them (no spill over the whole image).
    # Tolerance: one projected voxel (largest voxel size x magnification at the CTA centre).
    magnification = det.sdd_mm / C.SOURCE_TO_ISOCENTER_MM
    r = int(math.ceil(max(cta.spacing_mm) * magnification / det.spacing_mm[0]))
    near = torch.nn.functional.max_pool2d(torch.as_tensor(hit, dtype=torch.float32)[None], 2 * r + 1, 1, r)[0].numpy() > 0
    assert mask.sum() > 20 and (mask & ~near).sum() == 0
    assert mask.mean() < 0.5


def test_result_table_and_mrb_round_trip(scene, tmp_path):
    cta, lab = _cta()
    mrml.volume_to_node(scene, cta, "CTA")
    pose_ras = cta.centred_to_ras @ _pose()
    frames = np.arange(2 * DET.rows * DET.cols, dtype=np.float32).reshape(2, DET.rows, DET.cols)
    seq, _ = mrml.dsa_sequence_node(scene, frames, DET, pose_ras, "DSA PA", frame_time_s=0.5)
    mrml.pose_transform_node(scene, pose_ras, "GeoPose PA pose")
    mrml.segmentation_from_labelmap(scene, lab, {1: ("vessel", (1, 0, 0))}, "Vessels")
    table = mrml.result_table_node(scene, [{"view": "PA", "ncc": 0.5, "flag": "ok"}, {"view": "LAT", "ncc": 0.25}], "GeoPose results")
    assert table.GetNumberOfRows() == 2 and table.GetCellText(1, 2) == ""
    assert float(table.GetCellText(1, 1)) == 0.25
    path = mrml.save_mrb(scene, tmp_path / "case.mrb")
    s2 = mrml.load_mrb(path)
    cta2 = mrml.volume_from_node(s2.GetFirstNodeByName("CTA"))
    np.testing.assert_array_equal(cta2.array, cta.array)
    np.testing.assert_allclose(cta2.ijk_to_ras, cta.ijk_to_ras, atol=1e-5)
    t2 = s2.GetFirstNodeByName("GeoPose PA pose")
    np.testing.assert_allclose(mrml.transform_matrix(t2), pose_ras, atol=1e-6)
    seq2 = s2.GetFirstNodeByName("DSA PA")
    seq2 = seq2 if seq2.IsA("vtkMRMLSequenceNode") else next(
        s2.GetNthNodeByClass(n, "vtkMRMLSequenceNode") for n in range(s2.GetNumberOfNodesByClass("vtkMRMLSequenceNode"))
    )
    np.testing.assert_array_equal(mrml.frames_from_sequence(seq2), frames)
    np.testing.assert_allclose(
        mrml.volume_from_node(seq2.GetNthDataNode(1)).ijk_to_ras, mrml.detector_ijk_to_ras(DET, pose_ras), atol=1e-5
    )
    assert mrml.geometry_from_attributes(seq2)[0] == DET
    seg2 = s2.GetFirstNodeByName("Vessels")
    back, _ = mrml.labelmap_from_segmentation(seg2, s2.GetFirstNodeByName("CTA"))
    np.testing.assert_array_equal(back.array, (lab.array == 1).astype(back.array.dtype))
    tab2 = s2.GetFirstNodeByName("GeoPose results")
    assert tab2.GetCellText(0, 0) == "PA" and float(tab2.GetCellText(0, 1)) == 0.5
    with pytest.raises(ValueError, match=".mrb"):
        mrml.save_mrb(scene, tmp_path / "case.zip")


def test_detector_image_model_puts_each_pixel_where_its_ray_meets_the_detector(scene):
    from vtk.util import numpy_support

    from geopose.viz import to_uint8

    cta, _ = _cta()
    pose_c = _pose(C.VIEW_LAT_PLUS)
    image = np.random.default_rng(1).normal(size=DET.shape)
    node = mrml.detector_image_model_node(scene, image, DET, cta.centred_to_ras @ pose_c, "GeoPose LAT DSA on detector")
    poly = node.GetPolyData()
    points = numpy_support.vtk_to_numpy(poly.GetPoints().GetData())
    st = numpy_support.vtk_to_numpy(poly.GetPointData().GetTCoords())
    _, world = source_and_detector_points(pose_c, DET)  # (rows, cols, 3), centred frame
    to_ras = lambda p: p @ cta.centred_to_ras[:3, :3].T + cta.centred_to_ras[:3, 3]  # noqa: E731
    for p, (s, t) in zip(points, st):
        row, col = round(t * (DET.rows - 1)), round(s * (DET.cols - 1))
        np.testing.assert_allclose(p, to_ras(world[row, col]), atol=1e-6)
    texture = node.GetDisplayNode().GetTextureImageDataConnection().GetProducer().GetOutputDataObject(0)
    assert texture.GetDimensions() == (DET.cols, DET.rows, 1)
    pixels = numpy_support.vtk_to_numpy(texture.GetPointData().GetScalars()).reshape(DET.rows, DET.cols)
    np.testing.assert_array_equal(pixels, to_uint8(image))  # texture (s, t) = (0, 0) is image row 0, column 0
    with pytest.raises(ValueError, match="does not match"):
        mrml.detector_image_model_node(scene, image[1:], DET, cta.centred_to_ras @ pose_c, "wrong")


# ------------------------------------------------------------------ a registration's nodes (mrml.registration)
RUN_DET = Detector(40, 48, (0.8, 0.8), 1000.0)


def _run(primary: float):
    """A DSA run of 3 frames on RUN_DET at the given primary angle (125 ms frame time)."""
    from geopose.dsa import DSARun

    rng = np.random.default_rng(int(abs(primary)))
    angles = CArmAngles(primary, 3.0, RUN_DET.sdd_mm, 700.0)
    return DSARun(rng.random((3, RUN_DET.rows, RUN_DET.cols), dtype=np.float32) * 100, RUN_DET, angles, 125.0)


def _result(poses: dict) -> SimpleNamespace:
    """A registration result with the fields mrml.result_rows / result_nodes read (each view's Init 5 mm off)."""
    views = {}
    for n, (key, pose) in enumerate(poses.items()):
        shifted = pose.copy()
        shifted[:3, 3] += [3.0, 4.0, 0.0]
        views[key] = SimpleNamespace(
            final_pose=pose, stage_poses={"init": shifted, "final": pose}, final_mncc=0.5 + 0.1 * n,
            silhouette_dice=0.9, quality=SimpleNamespace(flag="ok" if n else "doubtful", reasons=() if n else ("low mNCC",)),
            prepared=SimpleNamespace(map=np.full(RUN_DET.shape, 7.0 + n, np.float32)),
        )
    return SimpleNamespace(views=views, runtimes_s={"init": 0.02, "total": 1.5}, engine={"backend": "torch", "device": "cpu"},
                           registration=SimpleNamespace(mode="biplane-rigid", refine_start="rotation fused, isocentre PA",
                                                        chosen_start="Refine"),
                           notes=["the TTO was skipped", "no cranium mask"])


def test_result_rows_hold_each_views_numbers():
    poses = {"pa": _pose(C.VIEW_PA), "lat": _pose(C.VIEW_LAT_PLUS)}
    rows = mrml.result_rows(_result(poses), {"pa": _run(0.0), "lat": _run(-90.0)})
    assert list(rows[0]) == [
        "view", "mNCC", "silhouette Dice", "quality", "reasons", "registration", "Refine start", "TTO start",
        "pixel axes (registered)", "pixel axes (DICOM angles)", "init to final (mm)", "final to final (mm)",
        "runtime init (s)", "runtime total (s)", "device", "notes"]
    pa, lat = rows
    assert (pa["view"], pa["mNCC"], pa["silhouette Dice"], pa["quality"], pa["reasons"]) == ("PA", 0.5, 0.9, "doubtful", "low mNCC")
    assert (lat["view"], lat["mNCC"], lat["quality"], lat["reasons"]) == ("LAT", pytest.approx(0.6), "ok", "")
    assert pa["init to final (mm)"] == pytest.approx(5.0) and pa["final to final (mm)"] == 0.0  # the 3-4-5 shift
    assert (pa["runtime init (s)"], pa["runtime total (s)"], pa["device"]) == (0.02, 1.5, "torch on cpu")
    assert pa["notes"] == lat["notes"] == "the TTO was skipped; no cranium mask"
    assert (pa["registration"], pa["Refine start"], pa["TTO start"]) == ("biplane-rigid", "rotation fused, isocentre PA", "Refine")
    # The pixel axes of the registered pose and of the run's angles (PA at primary 0: L\F; LAT at -90: A\F).
    assert (pa["pixel axes (registered)"], pa["pixel axes (DICOM angles)"]) == ("L\\F", "L\\F")
    assert lat["pixel axes (DICOM angles)"] == "A\\F"
    assert all(isinstance(v, float) for row in rows for k, v in row.items() if "(mm)" in k or "(s)" in k or k == "mNCC")


def test_result_nodes_place_every_output(scene):
    cta, lab = _cta()
    cta_node = mrml.volume_to_node(scene, cta, "CTA")
    seg = mrml.segmentation_from_labelmap(scene, lab, {1: ("vessel", (1, 0, 0)), 2: ("blob", (0, 1, 0))}, "Vessels")
    before = (mrml.volume_from_node(cta_node).array.copy(), mrml.labelmap_from_segmentation(seg, cta_node)[0].array.copy())
    labels, segments = mrml.segmentation_labels(seg, cta_node)
    assert segments == {1: ("vessel", (1.0, 0.0, 0.0)), 2: ("blob", (0.0, 1.0, 0.0))}
    assert mrml.segmentation_labels(None, cta_node) == (None, {})
    poses = {"pa": _pose(C.VIEW_PA), "lat": _pose(C.VIEW_LAT_PLUS)}
    runs = {"pa": _run(0.0), "lat": _run(-90.0)}
    result = _result(poses)
    out = mrml.result_nodes(scene, mrml.RegistrationInputs(cta, runs, labels, segments), result)
    assert set(out) == {f"{k}{s}" for k in ("pa", "lat") for s in mrml.OUTPUT_KEYS} | {"table"}
    for key, title in (("pa", "PA"), ("lat", "LAT")):
        pose_ras = cta.centred_to_ras @ poses[key]
        assert out[f"{key}Pose"].GetName() == f"GeoPose {title} pose"
        np.testing.assert_allclose(mrml.transform_matrix(out[f"{key}Pose"]), pose_ras, atol=1e-9)
        plane = mrml.detector_ijk_to_ras(RUN_DET, pose_ras)
        np.testing.assert_allclose(mrml.volume_from_node(out[f"{key}MAP"]).ijk_to_ras, plane, atol=1e-9)
        np.testing.assert_array_equal(mrml.volume_from_node(out[f"{key}MAP"]).array[0], result.views[key].prepared.map)
        assert mrml.geometry_from_attributes(out[f"{key}MAP"]) == (RUN_DET, runs[key].angles, 0.125)
        seq = out[f"{key}DSA"]
        np.testing.assert_array_equal(mrml.frames_from_sequence(seq), runs[key].frames)
        np.testing.assert_allclose(mrml.volume_from_node(seq.GetNthDataNode(2)).ijk_to_ras, plane, atol=1e-9)
        assert seq.GetNthIndexValue(1) == "0.125"  # 125 ms frame time, in s
        assert out[f"{key}DSABrowser"].GetProxyNode(seq) is not None
        proj_seg = out[f"{key}Projection"].GetSegmentation()
        assert [proj_seg.GetSegment(s).GetName() for s in proj_seg.GetSegmentIDs()] == ["vessel", "blob"]
        proj, names = mrml.labelmap_from_segmentation(out[f"{key}Projection"], out[f"{key}MAP"], ["vessel"])
        want = mrml.project_labels(labels, [1], poses[key], RUN_DET)[0]
        assert want.sum() > 10
        np.testing.assert_array_equal(proj.array[0] == names["vessel"], want)
        np.testing.assert_allclose(out[f"{key}Camera"].GetPosition(), pose_ras[:3, 3], atol=1e-9)
    # The table node holds the rows of result_rows, numbers as numbers.
    table, rows = out["table"], mrml.result_rows(result, runs)
    cols = [table.GetColumnName(c) for c in range(table.GetNumberOfColumns())]
    assert cols == list(rows[0]) and table.GetNumberOfRows() == 2
    for r, row in enumerate(rows):
        for c, name in enumerate(cols):
            cell = table.GetCellText(r, c)
            assert (float(cell) == pytest.approx(row[name])) if isinstance(row[name], float) else cell == row[name]
    assert mrml.result_summary(table).splitlines() == ["PA: mNCC 0.500, doubtful", "LAT: mNCC 0.600, ok"]
    # Again with these nodes: the same nodes, updated; no node added.
    count = scene.GetNumberOfNodes()
    again = mrml.result_nodes(scene, mrml.RegistrationInputs(cta, runs), result, outputs=out)
    assert scene.GetNumberOfNodes() == count and all(again[k] is out[k] for k in again)
    assert "paProjection" not in again  # no segmentation this time
    # Inputs unchanged.
    np.testing.assert_array_equal(mrml.volume_from_node(cta_node).array, before[0])
    np.testing.assert_array_equal(mrml.labelmap_from_segmentation(seg, cta_node)[0].array, before[1])


def test_a_pose_round_trips_through_its_transform_node(scene):
    """camera-to-centred pose -> the transform node's camera-to-RAS matrix -> the same pose; the RAS pose is
    the result record's (geometry.frames.pose_to_patient) and its LPS twin differs by RAS_TO_LPS."""
    from geopose.geometry.frames import RAS_TO_LPS, pose_from_patient, pose_to_patient

    cta, _ = _cta()
    runs = {"pa": _run(0.0), "lat": _run(-90.0)}
    poses = {"pa": _pose(C.VIEW_PA, dr=(0.1, -0.2, 0.05), dt=(12.0, -7.0, 30.0)), "lat": _pose(C.VIEW_LAT_MINUS)}
    out = mrml.result_nodes(scene, mrml.RegistrationInputs(cta, runs), _result(poses))
    for key, pose in poses.items():
        matrix = mrml.transform_matrix(out[f"{key}Pose"])
        np.testing.assert_allclose(pose_from_patient(matrix, cta.ijk_to_ras, cta.shape_ijk), pose, atol=1e-9)
        np.testing.assert_allclose(matrix, pose_to_patient(pose, cta.ijk_to_ras, cta.shape_ijk), atol=1e-12)
        np.testing.assert_allclose(RAS_TO_LPS @ matrix, pose_to_patient(pose, cta.ijk_to_ras, cta.shape_ijk, "LPS"), atol=1e-12)
        # the translation is the X-ray source: the centred pose's source moved to the CTA's grid centre
        np.testing.assert_allclose(matrix[:3, 3], pose[:3, 3] + cta.centred_to_ras[:3, 3], atol=1e-9)


def test_plane_axes_of_known_planes(scene):
    """The detector plane of the isocentric PA and LAT+ poses about the RAS origin (source 650 mm from the
    isocentre, SDD 1000 mm): the normal points from the source to the detector, the column direction is where
    the image's columns grow (PA: the patient's left, DICOM "L"; LAT+: posterior), the centre is 350 mm past
    the isocentre."""
    det = Detector(4, 6, (0.5, 0.5), 1000.0)
    known = {C.VIEW_PA: ((0, -1, 0), (-1, 0, 0), (0, -350, 0)), C.VIEW_LAT_PLUS: ((1, 0, 0), (0, -1, 0), (350, 0, 0))}
    for view, (normal, column, centre) in known.items():
        pose = isopose(view)
        node = mrml.plane_volume_node(scene, np.zeros(det.shape), det, pose, f"plane {view}")
        got = mrml.plane_axes(node)
        for g, w in zip(got, (normal, column, centre)):
            np.testing.assert_allclose(g, w, atol=1e-9)
        src, world = source_and_detector_points(pose, det)  # the same, from the projection geometry
        beam = world.reshape(-1, 3).mean(0) - src
        np.testing.assert_allclose(got[0], beam / np.linalg.norm(beam), atol=1e-9)
        np.testing.assert_allclose(got[2], world.reshape(-1, 3).mean(0), atol=1e-9)
    # an oblique pose about an oblique CTA: unit axes, the normal along the beam
    cta, _ = _cta()
    pose_c = _pose(C.VIEW_LAT_PLUS)
    node = mrml.plane_volume_node(scene, np.zeros(DET.shape), DET, cta.centred_to_ras @ pose_c, "oblique")
    normal, column, centre = mrml.plane_axes(node)
    assert np.linalg.norm(normal) == pytest.approx(1) and np.linalg.norm(column) == pytest.approx(1)
    assert abs(normal @ column) < 1e-9
    src = (cta.centred_to_ras @ pose_c)[:3, 3]
    assert (centre - src) @ normal == pytest.approx(DET.sdd_mm)  # the plane lies SDD from the source along the normal
    np.testing.assert_allclose(centre, mrml.camera_to_ras_points(cta.centred_to_ras @ pose_c, DET)["centre"], atol=1e-9)


def test_geometry_overrides_keep_the_files_values_for_zero():
    fields = {"primary_deg": 0.0, "secondary_deg": -3.0, "sid_mm": 0.0, "sod_mm": 650.0, "pixel_spacing_mm": 0.0}
    assert mrml.geometry_overrides(fields) == {"primary_deg": 0.0, "secondary_deg": -3.0, "sod_mm": 650.0}
    assert mrml.geometry_overrides({**fields, "sid_mm": 1100.0, "pixel_spacing_mm": 0.3}) == {
        "primary_deg": 0.0, "secondary_deg": -3.0, "sid_mm": 1100.0, "sod_mm": 650.0, "pixel_spacing_mm": (0.3, 0.3)}


def test_run_from_node_uses_attributes_and_overrides_through_the_readers_checks(scene):
    from geopose.errors import InputError

    run = _run(-90.0)
    seq, _ = mrml.dsa_sequence_node(scene, run.frames, run.detector, np.eye(4), "in", 0.125, run.angles)
    back = mrml.run_from_node(seq)
    np.testing.assert_array_equal(back.frames, run.frames)
    assert back.detector == run.detector and back.angles == run.angles and back.frame_time_ms == 125.0
    assert back.view_role == "LAT" and back.metadata["geometry_sources"]["sod_mm"] == "Slicer node in"
    over = mrml.run_from_node(seq, {"primary_deg": 2.0, "sod_mm": 650.0})
    assert over.angles.primary_deg == 2.0 and over.angles.sod_mm == 650.0 and over.view_role == "PA"
    with pytest.raises(InputError, match="not shorter than the source-to-detector"):
        mrml.run_from_node(seq, {"sod_mm": 1200.0})
    bare = scene.AddNewNodeByClass("vtkMRMLSequenceNode", "bare")
    for n in range(2):
        f = slicer.vtkMRMLScalarVolumeNode()
        f.SetAndObserveImageData(mrml.volumes.image_data_from_array(run.frames[n][None]))
        bare.SetDataNodeAtValue(f, str(n))
    with pytest.raises(InputError, match="missing in DSA node 'bare'"):
        mrml.run_from_node(bare)
    geo = {"primary_deg": 0.0, "secondary_deg": 0.0, "sid_mm": 1000.0, "sod_mm": 650.0, "pixel_spacing_mm": (0.8, 0.8)}
    assert mrml.run_from_node(bare, geo).detector == RUN_DET


def test_a_native_run_read_into_slicer_keeps_how_it_was_subtracted(scene, tmp_path):
    """*Import DSA...* of a native run (a Mask Subtraction Sequence) shows the subtracted frames, and the node says how
    they were subtracted, so the run made from it for the registration (and its record) says so too."""
    from geopose.dsa import DSARun, MaskSubtraction, read_dsa, write_dsa_dicom

    intensities = np.round(4000.0 * np.exp(-_run(0.0).frames / 50.0))
    native = DSARun(intensities, RUN_DET, _run(0.0).angles, 125.0)
    path = write_dsa_dicom(native, tmp_path / "pa.dcm", mask_subtraction=MaskSubtraction((0,), (1, 2)))
    seq, _ = mrml.read_dsa_node(scene, path, "DSA PA")
    assert "AVG_SUB" in seq.GetAttribute("GeoPose.subtraction")
    run = mrml.run_from_node(seq)
    assert run.metadata["subtraction"] == read_dsa(path).metadata["subtraction"]
    np.testing.assert_allclose(run.frames, read_dsa(path).frames, rtol=1e-6)
    plain, _ = mrml.read_dsa_node(scene, write_dsa_dicom(native, tmp_path / "plain.dcm"), "DSA plain")
    assert plain.GetAttribute("GeoPose.subtraction") is None and "subtraction" not in mrml.run_from_node(plain).metadata


def test_node_roles_and_read_inputs_checks(scene, tmp_path):
    from geopose.dsa import write_dsa_nifti
    from geopose.errors import InputError

    cta, lab = _cta()
    run = _run(0.0)
    seq, browser = mrml.read_dsa_node(scene, write_dsa_nifti(run, tmp_path / "pa.nii.gz"), "DSA PA")
    proxy = browser.GetProxyNode(seq)
    plane = mrml.plane_volume_node(scene, run.frames[0], run.detector, np.eye(4), "a plane")
    mrml.set_geometry_attributes(plane, run.detector, run.angles)
    assert mrml.first_cta_candidate(scene) is None  # a shown frame and a detector plane are no CTA
    cta_node = mrml.volume_to_node(scene, cta, "CTA")
    mrml.volume_to_node(scene, cta, "second CTA")
    assert mrml.first_cta_candidate(scene) is cta_node
    assert (mrml.is_dsa_image(proxy), mrml.is_dsa_image(plane), mrml.is_dsa_image(cta_node)) == (True, True, False)
    assert sorted(mrml.dsa_image_ids(scene)) == sorted([proxy.GetID(), plane.GetID()])
    seg = mrml.segmentation_from_labelmap(scene, lab, {1: ("vessel", (1, 0, 0))}, "Vessels")
    count = scene.GetNumberOfNodes()
    with pytest.raises(InputError, match="select a CTA volume and a PA and a lateral DSA run"):
        mrml.read_inputs(cta_node, seq, None)
    with pytest.raises(InputError, match="output latMAP is the input node 'DSA PA'"):
        mrml.read_inputs(cta_node, seq, seq, outputs={"latMAP": seq})
    with pytest.raises(InputError, match="is a DSA image"):
        mrml.read_inputs(proxy, seq, seq)
    ticks = []
    inputs = mrml.read_inputs(cta_node, seq, proxy, segmentation=seg, overrides={"lat": {"primary_deg": -90.0}},
                              tick=lambda: ticks.append(1))
    assert len(ticks) == 3 and scene.GetNumberOfNodes() == count
    np.testing.assert_array_equal(inputs.cta.array, cta.array)
    assert inputs.runs["pa"].angles == run.angles and inputs.runs["lat"].angles.primary_deg == -90.0
    np.testing.assert_array_equal(inputs.labels.array, (lab.array == 1).astype(inputs.labels.array.dtype))
    assert inputs.segments == {1: ("vessel", (1.0, 0.0, 0.0))} and inputs.cranium is None


def test_preliminary_nodes_show_the_estimate_and_the_result_moves_them(scene):
    """The networks' estimate in the view nodes (pose, camera, C-arm, run, projection; no MAP, no table), marked
    preliminary; the final result then moves the same nodes and marks them final."""
    from geopose.register.progress import Preliminary

    cta, labels = _cta()
    segments = {1: ("vessel", (1.0, 0.0, 0.0))}
    runs = {"pa": _run(0.0), "lat": _run(-90.0)}
    inputs = mrml.RegistrationInputs(cta, runs, labels, segments)
    estimate = {"pa": _pose(C.VIEW_PA, dt=(9.0, 1.0, -4.0)), "lat": _pose(C.VIEW_LAT_PLUS, dt=(-6.0, 2.0, 5.0))}
    early = mrml.preliminary_nodes(scene, inputs, Preliminary("estimate", estimate, 4.2))
    assert set(early) == {f"{k}{s}" for k in ("pa", "lat") for s in mrml.OUTPUT_KEYS if s != "MAP"}
    for key in ("pa", "lat"):
        np.testing.assert_allclose(mrml.transform_matrix(early[f"{key}Pose"]), cta.centred_to_ras @ estimate[key], atol=1e-9)
        assert early[f"{key}Pose"].GetAttribute(mrml.RESULT_ATTRIBUTE) == mrml.PRELIMINARY_RESULT
        want = mrml.project_labels(labels, [1], estimate[key], RUN_DET)[0]
        got, names = mrml.labelmap_from_segmentation(early[f"{key}Projection"], early[f"{key}DSA"].GetNthDataNode(0), ["vessel"])
        np.testing.assert_array_equal(got.array[0] == names["vessel"], want)
    before = {scene.GetNthNode(n).GetID() for n in range(scene.GetNumberOfNodes())}
    poses = {"pa": _pose(C.VIEW_PA), "lat": _pose(C.VIEW_LAT_PLUS)}
    out = mrml.result_nodes(scene, inputs, _result(poses), outputs=early)
    assert all(out[k] is early[k] for k in early)
    added = {scene.GetNthNode(n) for n in range(scene.GetNumberOfNodes())} - {scene.GetNodeByID(i) for i in before}
    owners = {out["paMAP"], out["latMAP"], out["table"]}
    assert {node.GetID() for node in added} == {node.GetID() for node in owners} | {
        node.GetDisplayNodeID() for node in (out["paMAP"], out["latMAP"])}  # the MAPs (with their display) and the table
    for key in ("pa", "lat"):
        np.testing.assert_allclose(mrml.transform_matrix(out[f"{key}Pose"]), cta.centred_to_ras @ poses[key], atol=1e-9)
        assert out[f"{key}Pose"].GetAttribute(mrml.RESULT_ATTRIBUTE) == mrml.FINAL_RESULT
