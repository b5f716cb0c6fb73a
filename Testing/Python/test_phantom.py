"""The phantom world: reproducibility, tissues, labels, frames, DSA and the CLI."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from geopose.dsa import read_dsa, write_dsa_dicom
from geopose.geometry import project_points, view_from_primary_angle
from geopose.phantom import labels as L
from geopose.phantom import make_subject
from geopose.phantom.anatomy import rasterise_head, sample_head
from geopose.phantom.cli import OUTPUT_FILES, register
from geopose.phantom.contrast import ARTERIAL_HU_RANGE, PLAQUE_HU
from geopose.phantom.dsa import (
    DETECTOR_MATRICES_PX,
    SDD_RANGE_MM,
    dsa_renderer,
    injected_arteries,
    sample_acquisition,
    sample_biplane,
    sample_injection,
    simulate_dsa,
)
from geopose.phantom.raster import Grid
from geopose.phantom.veins import PETROUS_Z_MM

SPACING = 2.0


@pytest.fixture(scope="module")
def subject():
    return make_subject(11, spacing_mm=SPACING)


def _native_index(subject, head_pt) -> np.ndarray:
    x = subject.head_to_native @ np.append(head_pt, 1.0)
    return np.rint(np.linalg.inv(subject.cta.ijk_to_centred) @ x)[:3].astype(int)


def _hu_at(subject, head_pt) -> float:
    i, j, k = _native_index(subject, np.asarray(head_pt, float) * subject.params.scale)
    return float(subject.cta.array[k - 1 : k + 2, j - 1 : j + 2, i - 1 : i + 2].mean())


def test_same_seed_same_subject_and_other_seeds_differ(subject):
    again = make_subject(11, spacing_mm=SPACING)
    assert np.array_equal(again.cta.array, subject.cta.array)
    assert np.array_equal(again.labels.array, subject.labels.array)
    assert np.allclose(again.native_to_canonical, subject.native_to_canonical)
    other = make_subject(12, spacing_mm=SPACING)
    assert not np.allclose(other.native_to_canonical, subject.native_to_canonical)
    assert np.mean(other.cta.array != subject.cta.array) > 0.1


#: SHA-256 of subject 11's geometry and poses (:func:`_geometry_sha256`) computed with the code before the
#: CTA realism (commit 77bf0d1): the appearance draws come from their own stream and leave them unchanged.
GEOMETRY_SHA256 = "ed91ce0af8d69b0b864044049e94e4805987aab5603d28a9d5766bdc3dfa2886"


def _geometry_sha256(seed: int) -> str:
    """The native-to-canonical transform, the head scale, every artery's points and radii, and the
    injection and true poses ``write_phantom`` draws for subject ``seed``."""
    digest = hashlib.sha256()
    s = make_subject(seed, spacing_mm=4.0)
    digest.update(np.round(s.native_to_canonical, 9).tobytes())
    digest.update(np.round(s.params.scale, 9).tobytes())
    for a in s.params.arteries:
        digest.update(a["name"].encode())
        digest.update(np.round(a["points"], 6).tobytes())
        digest.update(np.round(a["radii"], 6).tobytes())
    rng = np.random.default_rng([seed, 1])
    digest.update(sample_injection(rng).encode())
    acqs, iso = sample_biplane(rng, s)
    for a in acqs:
        digest.update(np.round(a.pose(iso).matrix[0].numpy(), 6).tobytes())
    return digest.hexdigest()


def test_geometry_and_poses_kept_by_the_appearance_streams():
    assert _geometry_sha256(11) == GEOMETRY_SHA256


def _head_points(subject, kji: np.ndarray) -> np.ndarray:
    """Head-frame points (mm) of native voxel indices ``(N, 3)`` (k, j, i)."""
    ijk = np.c_[kji[:, ::-1], np.ones(len(kji))].T
    return (np.linalg.inv(subject.head_to_native) @ subject.cta.ijk_to_centred @ ijk)[:3].T


def _neighbours(mask: np.ndarray) -> np.ndarray:
    """``mask`` dilated by its 26 neighbours."""
    out = mask.copy()
    for dk in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                out |= np.roll(mask, (dk, dj, di), axis=(0, 1, 2))
    return out


def test_lumen_hu_falls_along_the_tree_and_varies_between_subjects(subject):
    lines = {c["name"]: c for c in subject.centerlines}
    every = np.concatenate([c["lumen_hu"] for c in subject.centerlines])
    assert every.min() >= ARTERIAL_HU_RANGE[0] and every.max() <= ARTERIAL_HU_RANGE[1]
    assert every.max() - every.min() > 40  # not one constant HU
    cca = np.median(np.concatenate([lines[f"cca_{s}"]["lumen_hu"] for s in ("left", "right")]))
    cortical = np.median(np.concatenate([c["lumen_hu"][-5:] for c in subject.centerlines if c["name"].startswith("cortical")]))
    assert cortical < cca - 20  # lower distally
    ica = lines["ica_left"]["lumen_hu"]
    assert np.all(np.abs(np.diff(ica)) < 5)  # smooth along a vessel
    # the CTA shows it: the voxels on the thick ICA's centreline (full coverage) read its lumen HU
    c = lines["ica_left"]
    ijk = np.rint(np.c_[c["points_mm"], np.ones(len(ica))] @ np.linalg.inv(subject.cta.ijk_to_centred).T)[:, :3].astype(int)
    p = subject.params
    read = subject.cta.array[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    assert np.median(np.abs(read - (ica * p.hu_gain + p.hu_offset))) < p.noise_sd_hu + 10
    bolus = [sample_head(np.random.default_rng(seed), seed).hu["vessel"] for seed in range(8)]
    assert max(bolus) - min(bolus) > 100  # per-subject bolus level


def test_sinuses_dura_are_labelled_apart_from_the_arteries(subject):
    lab, hu = subject.labels.array, subject.cta.array
    venous = np.isin(lab, L.label_groups()["venous_sinus"])
    assert (lab == L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET).sum() > 500 and (lab == L.VENOUS_SINUS).sum() > 500  # sinuses, jugulars
    assert not np.any(L.vessel_mask(lab) & (venous | (lab == L.DURA)))
    assert 140 <= np.median(hu[venous]) <= 380 and np.median(hu[venous]) < subject.params.hu["vessel"]
    assert (lab == L.DURA).sum() > 1000 and 35 <= np.median(hu[lab == L.DURA]) <= 110
    # the cranium group is still one solid mask holding the intracranial sinuses and the dura
    cranium = L.cranium_mask(lab)
    filled = sitk.GetArrayFromImage(sitk.BinaryFillhole(sitk.GetImageFromArray(cranium.astype(np.uint8))))
    assert np.array_equal(filled > 0, cranium)
    assert np.all(cranium[np.isin(lab, [L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET, L.DURA])])
    assert not np.any(cranium[lab == L.VENOUS_SINUS])
    # the jugular veins go down the neck; the cavernous sinus wraps the cavernous ICA
    z = _head_points(subject, np.argwhere(lab == L.VENOUS_SINUS))[:, 2] / subject.params.scale[2]
    assert z.min() < -150


def test_ica_runs_through_a_bone_canal_and_the_cavernous_sinus(subject):
    lab, hu = subject.labels.array, subject.cta.array
    ica = np.isin(lab, L.with_intracranial([L.ICA_LEFT, L.ICA_RIGHT]))
    kji = np.argwhere(ica)
    z = _head_points(subject, kji)[:, 2] / subject.params.scale[2]
    canal = np.zeros_like(ica)
    sel = kji[(z > PETROUS_Z_MM[0] + 3) & (z < PETROUS_Z_MM[1] - 3)]
    canal[tuple(sel.T)] = True
    bone = (hu > 700) & ~L.vessel_mask(lab)
    touching = canal & _neighbours(bone)
    assert canal.sum() > 10 and touching.sum() / canal.sum() > 0.7
    venous = np.isin(lab, L.label_groups()["venous_sinus"])
    cav = kji[(z > -45) & (z < -36)]
    assert np.mean(_neighbours(venous)[tuple(cav.T)]) > 0.5


def test_calcified_plaques_are_dense_and_small():
    found = []
    for seed in range(12):
        p = sample_head(np.random.default_rng(seed), seed)
        found += p.enhancement.plaques
    assert 0.1 < len(found) / (12 * 4) < 0.7  # some subjects, some sites
    assert {q["site"] for q in found} == {"bifurcation", "siphon"}
    assert all(PLAQUE_HU[0] <= q["hu"] <= PLAQUE_HU[1] and q["radius_mm"] <= 2.0 for q in found)
    # rasterised: a 0.5 mm grid about one plaque reads its HU at the centre
    seed = next(s for s in range(12) if sample_head(np.random.default_rng(s), s).enhancement.plaques)
    p = sample_head(np.random.default_rng(seed), seed)
    q = p.enhancement.plaques[0]
    m = np.diag([0.5, 0.5, 0.5, 1.0])
    m[:3, 3] = np.asarray(q["centre_mm"]) - 0.5 * 20
    hu, _ = rasterise_head(p, Grid((41, 41, 41), m))
    expected = q["hu"] * p.hu_gain + p.hu_offset
    assert abs(hu[20, 20, 20] - expected) < 4 * p.noise_sd_hu + 5
    without, _ = rasterise_head(dataclasses.replace(p, enhancement=dataclasses.replace(p.enhancement, plaques=[])), Grid((41, 41, 41), m))
    changed_mm3 = np.sum(np.abs(hu - without) > 50) * 0.5**3
    assert 0 < changed_mm3 < 4 / 3 * np.pi * (q["radius_mm"] + 0.5) ** 3  # small: only its ball


def test_noise_is_correlated_and_streaks_are_faint():
    p = sample_head(np.random.default_rng(5), 5)
    m = np.diag([3.0, 3.0, 3.0, 1.0])
    m[:3, 3] = -96.0
    m[2, 3] = -160.0
    grid = Grid((64, 64, 64), m)
    quiet = dataclasses.replace(p, noise_sd_hu=0.0, enhancement=dataclasses.replace(p.enhancement, streaks=[]))
    base, _ = rasterise_head(quiet, grid)
    noisy, _ = rasterise_head(dataclasses.replace(p, enhancement=quiet.enhancement), grid)
    streaked, _ = rasterise_head(dataclasses.replace(quiet, enhancement=p.enhancement), grid)
    inside = (base > -900) & (base < 2000)  # away from the clip at -1024 HU
    noise = (noisy - base)[inside]
    assert abs(noise.std() - p.noise_sd_hu) < 0.15 * p.noise_sd_hu + 1
    d = np.where(inside, noisy - base, 0.0)
    r = np.sum(d[:, :, 1:] * d[:, :, :-1]) / np.sum(d * d)
    assert 0.15 < r < 0.8  # correlated a little
    streak = streaked - base
    assert 5 < np.abs(streak).max() <= 40
    assert np.mean(np.abs(streak) > 2) < 0.05  # faint lines in a few slices


def test_tissue_hu(subject):

    hu = subject.cta.array
    lab = subject.labels.array
    ica = np.isin(lab, L.with_intracranial([L.ICA_LEFT, L.ICA_RIGHT]))
    assert ica.sum() > 50
    assert 300 <= np.median(hu[ica]) <= 600
    assert np.percentile(hu[lab == L.CRANIUM], 99) > 900  # cortical tables
    for pt in [(25, 10, 25), (-25, 10, 25), (20, -30, 30)]:  # deep white matter
        assert 18 <= _hu_at(subject, pt) <= 45, pt
    assert _hu_at(subject, (0, 56, -62) + np.array([30, 0, 0])) < -900  # maxillary sinus air
    assert np.median(hu[:3, :3, :3]) < -950  # air outside the head
    assert hu.min() >= -1024 and hu.max() <= 3071


def test_left_ica_on_patient_left(subject):
    """RAS: +x is the patient's right, so the left ICA has canonical x < 0."""
    lab = subject.labels.array
    for values, sign in ((L.with_intracranial([L.ICA_LEFT]), -1), (L.with_intracranial([L.ICA_RIGHT]), 1)):
        k, j, i = np.nonzero(np.isin(lab, values))
        ijk = np.stack([i, j, k, np.ones_like(i)]).astype(float)
        can = subject.native_to_canonical @ subject.cta.ijk_to_centred @ ijk
        assert sign * can[0].mean() > 10.0
    for c in subject.centerlines:
        if c["name"] in ("ica_left", "ica_right"):
            can = c["points_mm"] @ subject.native_to_canonical[:3, :3].T + subject.native_to_canonical[:3, 3]
            assert np.sign(can[:, 0].mean()) == (-1 if c["name"] == "ica_left" else 1)


def test_native_to_canonical_is_rigid_and_small(subject):
    m = subject.native_to_canonical
    R = m[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(m[3], [0, 0, 0, 1])
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    assert angle <= 15.0 + 1e-9
    assert json.loads(json.dumps(subject.truth()))["native_to_canonical"] == m.tolist()


def test_native_resampled_matches_canonical(subject):
    can_cta, can_lab = subject.canonical()
    K, J, I = can_lab.array.shape
    k, j, i = np.meshgrid(np.arange(K), np.arange(J), np.arange(I), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel(), np.ones(i.size)])
    native_ijk = np.linalg.inv(subject.cta.ijk_to_centred) @ np.linalg.inv(subject.native_to_canonical) @ can_cta.ijk_to_centred @ ijk
    n = np.rint(native_ijk[:3]).astype(int)
    si, sj, sk = subject.cta.shape_ijk
    ok = (n[0] >= 0) & (n[0] < si) & (n[1] >= 0) & (n[1] < sj) & (n[2] >= 0) & (n[2] < sk)
    resampled = np.zeros(ijk.shape[1], np.uint8)
    resampled[ok] = subject.labels.array[n[2, ok], n[1, ok], n[0, ok]]
    a, b = L.cranium_mask(resampled), L.cranium_mask(can_lab.array.ravel())
    b_in = b & ok  # the native field of view may clip the canonical cube
    dice = 2 * (a & b_in).sum() / (a.sum() + b_in.sum())
    assert dice > 0.95
    va, vb = L.vessel_mask(resampled), L.vessel_mask(can_lab.array.ravel()) & ok
    assert 2 * (va & vb).sum() / (va.sum() + vb.sum()) > 0.5


def test_acquisition_distribution():
    rng = np.random.default_rng(0)
    pa = [sample_acquisition(rng, "PA") for _ in range(150)]
    lat = [sample_acquisition(rng, "LAT") for _ in range(150)]
    assert all(view_from_primary_angle(a.angles.primary_deg) == 1 for a in pa)
    assert all(view_from_primary_angle(a.angles.primary_deg) != 1 for a in lat)
    assert all(-115.5 <= a.angles.primary_deg <= 84.0 for a in pa + lat)
    sdd = np.array([a.detector.sdd_mm for a in pa + lat])
    assert sdd.min() >= SDD_RANGE_MM[0] and sdd.max() <= SDD_RANGE_MM[1] and 1050 < np.median(sdd) < 1120
    frames = np.array([a.n_frames for a in pa + lat])
    assert frames.min() >= 3 and frames.max() <= 26 and 11 <= np.median(frames) <= 17
    assert {a.detector.rows for a in pa + lat} <= set(DETECTOR_MATRICES_PX)
    with pytest.raises(ValueError, match="view_role"):
        sample_acquisition(rng, "AP")


def test_bad_grid_is_refused():
    with pytest.raises(ValueError, match="spacing_mm"):
        make_subject(0, spacing_mm=0.2)
    with pytest.raises(ValueError, match="shape"):
        make_subject(0, spacing_mm=2.0, shape=(4, 4, 4))


@pytest.fixture(scope="module")
def dsa_pair(subject):
    rng = np.random.default_rng(3)
    acqs, iso = sample_biplane(rng, subject)
    drr = dsa_renderer(subject, "ica_left", render_px=160)
    sims = [simulate_dsa(subject, a, a.pose(iso), rng, injection="ica_left", drr=drr, render_px=160, max_matrix_px=320) for a in acqs]
    return acqs, iso, sims


def test_pose_centres_isocentre(dsa_pair):
    acqs, iso, sims = dsa_pair
    for acq, sim in zip(acqs, sims):
        det = sim.run.detector
        px, depth = project_points(acq.pose(iso).matrix[0].numpy(), det, np.asarray(iso)[None])
        assert np.allclose(px[0], [(det.rows - 1) / 2, (det.cols - 1) / 2], atol=1e-6)
        assert np.isclose(float(depth[0]), acq.angles.sod_mm)


def test_projected_carotid_lands_on_opacified_vessel(dsa_pair):
    _, _, sims = dsa_pair
    for sim in sims:
        m = sim.map
        H, W = m.shape

        def sample(px):
            r, c = np.rint(px).astype(int).T
            ok = (r >= 0) & (r < H) & (c >= 0) & (c < W)
            return m[r[ok], c[ok]]

        left = sample(sim.carotids["ica_left"])
        assert left.size > 20
        background = np.percentile(m[sim.cranium_mask], 75)
        assert np.median(left) > background  # the injected left ICA is bright
        assert sim.map.shape == sim.run.frames.shape[1:] and sim.cranium_mask.mean() > 0.1


def test_map_is_textured_cranium_silhouette(dsa_pair):
    _, _, sims = dsa_pair
    for sim in sims:
        inside = sim.map[sim.cranium_mask]
        outside = sim.map[~sim.cranium_mask & (sim.map > 0)]
        assert np.median(inside) > np.median(outside) + 5  # grainy bright head on a dark field
        assert inside.std() > 3


def test_dicom_carries_geometry(dsa_pair, tmp_path):
    acqs, _, sims = dsa_pair
    path = write_dsa_dicom(sims[1].run, tmp_path / "lat.dcm", bits=8)
    ds = pydicom.dcmread(path)
    a = acqs[1].angles
    assert ds.Modality == "XA" and int(ds.NumberOfFrames) == acqs[1].n_frames
    assert np.isclose(float(ds.PositionerPrimaryAngle), a.primary_deg, atol=0.01)
    assert np.isclose(float(ds.PositionerSecondaryAngle), a.secondary_deg, atol=0.01)
    assert np.isclose(float(ds.DistanceSourceToDetector), a.sid_mm, atol=0.01)
    assert np.isclose(float(ds.DistanceSourceToPatient), a.sod_mm, atol=0.01)
    assert np.allclose([float(v) for v in ds.ImagerPixelSpacing], sims[1].run.detector.spacing_mm, rtol=1e-4)
    assert np.isclose(float(ds.FrameTime), acqs[1].frame_time_ms, atol=0.01)
    back = read_dsa(path)
    assert np.allclose(back.attenuation(), sims[1].run.attenuation(), atol=1.0)


def test_cli_writes_a_dense_avm_run(tmp_path):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["phantom", "--seed", "4", "--out", str(tmp_path), "--spacing-mm", "4", "--max-matrix-px", "128",
                              "--injection", "avm"])
    assert args.func(args) == 0
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["injection"] == "avm" and truth["pathology"] == "avm" and truth["avm"]["radius_mm"] > 5
    assert L.NIDUS in truth["opacified_labels"]["early"] and L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET in truth["opacified_labels"]["venous"]
    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "labels.nii.gz")))
    assert np.any(labels == L.NIDUS)


def test_cli_writes_the_six_files(tmp_path):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["phantom", "--seed", "4", "--out", str(tmp_path), "--spacing-mm", "2", "--max-matrix-px", "256"])
    assert args.func(args) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(OUTPUT_FILES)
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert np.asarray(truth["native_to_canonical"]).shape == (4, 4)
    for view in ("pa", "lat"):
        pose = np.asarray(truth["views"][view]["pose_camera_to_world"])
        assert np.allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
    img = sitk.ReadImage(str(tmp_path / "cta.nii.gz"))
    ijk_to_ras = np.asarray(truth["ijk_to_ras"])
    ras = ijk_to_ras @ np.array([3.0, 5.0, 7.0, 1.0])
    lps = np.asarray(img.TransformContinuousIndexToPhysicalPoint((3.0, 5.0, 7.0)))
    assert np.allclose(ras[:3] * [-1, -1, 1], lps, atol=1e-3)
    lines = json.loads((tmp_path / "centerlines.json").read_text())["centerlines"]
    assert {"ica_left", "ica_right", "basilar"} <= {c["name"] for c in lines}


@pytest.fixture(scope="module")
def avm_subject():
    return make_subject(11, spacing_mm=SPACING, pathology="avm")


def test_avm_adds_a_nidus_and_changes_nothing_else(subject, avm_subject):
    lab, hu = avm_subject.labels.array, avm_subject.cta.array
    nidus = lab == L.NIDUS
    assert nidus.sum() > 100 and np.all(L.cranium_mask(lab)[nidus]) and not np.any(L.vessel_mask(lab) & nidus)
    assert np.median(hu[nidus]) > 120
    centre = avm_subject.truth()["avm"]["centre_native_mm"]
    kji = np.argwhere(nidus)
    ijk = np.c_[kji[:, ::-1], np.ones(len(kji))] @ avm_subject.cta.ijk_to_centred.T
    assert np.median(np.linalg.norm(ijk[:, :3] - centre, axis=1)) < avm_subject.params.avm["radius_mm"] + 5
    # its draining vein reaches the sagittal sinus; its feeder is an artery
    drain = avm_subject.params.avm["drain"]["points"]
    sss = next(v["points"] for v in avm_subject.params.veins if v["name"] == "superior_sagittal_sinus")
    assert np.linalg.norm(sss - drain[-1], axis=1).min() < 1.0
    assert any(c["name"].startswith("avm_feeder") for c in avm_subject.centerlines)
    # away from the AVM the subject is the one without it
    far = ~_neighbours(_neighbours(nidus | (lab != subject.labels.array)))
    assert np.array_equal(avm_subject.native_to_canonical, subject.native_to_canonical)
    assert np.mean(far) > 0.97 and np.array_equal(hu[far], subject.cta.array[far])
    with pytest.raises(ValueError, match="pathology"):
        make_subject(11, spacing_mm=4.0, pathology="tumour")


@pytest.mark.parametrize("injection", ["all_territories", "avm", "late_venous"])
def test_dense_runs_opacify_their_labels(subject, avm_subject, injection):
    s = avm_subject if injection == "avm" else subject
    filled = injected_arteries(s.labels.array, injection)
    arteries = L.vessel_mask(s.labels.array)
    assert np.array_equal(filled & arteries, arteries)  # every artery, both sides
    venous = np.isin(s.labels.array, L.label_groups()["venous_sinus"])
    assert np.any(filled & venous) == (injection != "all_territories")
    assert np.any(filled & (s.labels.array == L.NIDUS)) == (injection == "avm")
    routine = injected_arteries(s.labels.array, "ica_left")
    assert not np.any(routine & (venous | (s.labels.array == L.NIDUS)))  # an arterial phase shows no veins
    rng = np.random.default_rng(3)
    acqs, iso = sample_biplane(rng, s)
    sims = {}
    for run in ("arch", injection):
        drr = dsa_renderer(s, run, render_px=128)
        sims[run] = simulate_dsa(s, acqs[0], acqs[0].pose(iso), np.random.default_rng(5), injection=run, drr=drr, render_px=128,
                                 max_matrix_px=256)
    # the MAP shows it: a blush over the whole cranium, or the sinuses bright over it
    def blush(sim):
        m = sim.map.astype(float)
        outside = m[~sim.cranium_mask & (m > 0)]
        return (np.median(m[sim.cranium_mask]) - np.median(outside)) / np.percentile(m[sim.cranium_mask], 99.5)

    def sinuses(sim):
        pts = np.concatenate([v["points"] for v in s.params.veins if not v["name"].startswith("cavernous")])
        px, _ = project_points(sim.pose, sim.run.detector, pts @ s.head_to_native[:3, :3].T + s.head_to_native[:3, 3])
        r, c = np.rint(px).astype(int).T
        ok = (r >= 0) & (r < sim.map.shape[0]) & (c >= 0) & (c < sim.map.shape[1])
        return np.median(sim.map[r[ok], c[ok]]) / np.median(sim.map[sim.cranium_mask])

    measure = blush if injection == "all_territories" else sinuses
    dense, routine = measure(sims[injection]), measure(sims["arch"])
    assert dense > 1.3 * routine, (dense, routine)


def test_avm_run_needs_an_avm_subject(subject):
    with pytest.raises(ValueError, match="pathology='avm'"):
        dsa_renderer(subject, "avm", render_px=64)
