"""Shared pieces of the renderer validation and benchmark: test volumes, poses,
image metrics and an adapter that renders the same volume, pose and detector
with DiffDRR 0.6.x (when it is importable).

Needs only numpy and torch (plus our ``geopose`` package, found in ``Logic/`` of
this checkout if it is not installed); DiffDRR and SimpleITK are optional.
"""

from __future__ import annotations

from collections.abc import Callable
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
try:
    import geopose  # noqa: F401
except ImportError:  # a bare GPU machine: use the checkout's sources
    sys.path.insert(0, str(REPO / "Logic"))

from geopose import contract as C  # noqa: E402
from geopose.geometry import Detector, RigidTransform  # noqa: E402
from geopose.volume import Volume  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

HEADSQ_HEADER = REPO.parent / "shared" / "data" / "headsq" / "quarter_sidecar.mhd"

#: Pose sampling spread around the isoposes (docs/conventions.md section 6): rad per Euler angle, mm.
ROTATION_SD_RAD = 0.2
TRANSLATION_SD_MM = (25.0, 75.0, 25.0)

#: HU values of the synthetic head.
HU_AIR, HU_SOFT, HU_BRAIN, HU_CSF, HU_BONE, HU_VESSEL, HU_BEAD = -1000.0, 40.0, 35.0, 8.0, 1100.0, 450.0, 2500.0


def diffdrr_version() -> str | None:
    """DiffDRR's version string, or None when it (or one of its imports) is missing."""
    try:
        import diffdrr
        from diffdrr.drr import DRR  # noqa: F401
    except Exception:  # ImportError, or a dependency that fails to load
        return None
    return diffdrr.__version__


def lps_like_affine(shape_ijk: tuple[int, int, int], spacing_mm: float, origin_mm=(12.0, -7.0, 30.0)) -> np.ndarray:
    """A DICOM-like index-to-RAS affine (i -> left, j -> posterior, k -> superior) with an
    off-centre origin, so that axis flips and centring errors show up in comparisons."""
    m = np.diag([-spacing_mm, -spacing_mm, spacing_mm, 1.0])
    m[:3, 3] = origin_mm
    return m


def _grid_mm(shape_ijk: tuple[int, int, int], affine: np.ndarray, device=None) -> tuple[torch.Tensor, ...]:
    """Centred-frame coordinates (mm) x, y, z of every voxel, each ``[k, j, i]``."""
    grid = Volume(np.broadcast_to(np.uint8(0), shape_ijk[::-1]), affine)
    m = torch.as_tensor(grid.ijk_to_centred, dtype=torch.float32)
    i, j, k = (torch.arange(n, dtype=torch.float32, device=device) for n in shape_ijk)
    kk, jj, ii = torch.meshgrid(k, j, i, indexing="ij")
    return tuple(m[a, 0] * ii + m[a, 1] * jj + m[a, 2] * kk + m[a, 3] for a in range(3))


def head_phantom(n: int = 256, spacing_mm: float = 0.9, seed: int = 0) -> Volume:
    """Synthetic head CTA in HU on an ``n^3`` grid: skin, skull shell, brain with texture,
    ventricles, an air sinus, contrast-filled vessels and a few asymmetric bright beads."""
    g = torch.Generator().manual_seed(seed)
    affine = lps_like_affine((n, n, n), spacing_mm)
    x, y, z = _grid_mm((n, n, n), affine)
    scale = spacing_mm * n / 230.0  # the head fills the grid whatever the voxel size

    def ellipsoid(cx, cy, cz, ax, ay, az):
        return ((x - cx * scale) / (ax * scale)) ** 2 + ((y - cy * scale) / (ay * scale)) ** 2 + (
            (z - cz * scale) / (az * scale)
        ) ** 2

    hu = torch.full_like(x, HU_AIR)
    head = ellipsoid(0, 5, 0, 78, 98, 92)
    hu[head <= 1] = HU_SOFT
    skull_outer = ellipsoid(0, 5, 5, 72, 92, 84)
    skull_inner = ellipsoid(0, 5, 7, 65, 85, 76)
    bone = (skull_outer <= 1) & (skull_inner > 1)
    hu[bone] = (HU_BONE + 300.0 * torch.sin(0.09 * x / scale) * torch.cos(0.07 * y / scale))[bone]
    brain = skull_inner <= 1
    # Low-frequency texture: a sum of random plane waves (gyri-like contrast).
    tex = torch.zeros_like(x)
    for _ in range(6):
        k = torch.randn(3, generator=g) * 0.08 / scale
        tex += torch.cos(k[0] * x + k[1] * y + k[2] * z + 6.28 * torch.rand(1, generator=g))
    hu[brain] = HU_BRAIN + 6.0 * tex[brain]
    for side in (-1, 1):
        hu[(ellipsoid(side * 12, 5, 12, 8, 28, 12) <= 1) & brain] = HU_CSF
    hu[ellipsoid(0, 80, -55, 22, 12, 14) <= 1] = HU_AIR * 0.9  # frontal sinus
    hu[(ellipsoid(0, 45, -75, 40, 35, 12) <= 1) & (head <= 1)] = HU_BONE  # skull base, anterior
    # Vessels: tubes along parametrised curves (radius 1.5-3 mm).
    t = torch.linspace(0.0, 1.0, 400)
    curves = [
        (20 * torch.sin(3 * t) + 15, 60 * t - 20, 70 * t - 50, 2.5),
        (-25 * torch.cos(2 * t) - 5, 40 - 70 * t, 30 * torch.sin(4 * t) + 10, 2.0),
        (50 * t - 25, 10 * torch.sin(5 * t), 45 - 20 * t, 1.5),
    ]
    for cx, cy, cz, r in curves:
        pts = torch.stack((cx, cy, cz), -1) * scale
        _paint_tube(hu, x, y, z, pts, r * scale, HU_VESSEL)
    for bx, by, bz in ((30.0, 40.0, 50.0), (-45.0, -30.0, 20.0), (10.0, -60.0, -40.0)):
        hu[ellipsoid(bx, by, bz, 2.0, 2.0, 2.0) <= 1] = HU_BEAD
    return Volume(hu.numpy(), affine, {"name": f"head_phantom_{n}"})


def _paint_tube(hu, x, y, z, pts: torch.Tensor, radius: float, value: float) -> None:
    """Set voxels within ``radius`` mm of the polyline ``pts (P, 3)`` to ``value`` (in place)."""
    lo, hi = pts.min(0).values - radius, pts.max(0).values + radius
    box = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])
    idx = box.nonzero(as_tuple=True)
    p = torch.stack((x[idx], y[idx], z[idx]), -1)
    near = torch.zeros(len(p), dtype=torch.bool)
    for chunk in range(0, len(pts), 50):
        d = torch.cdist(p, pts[chunk : chunk + 50]).amin(1)
        near |= d <= radius
    hu[tuple(a[near] for a in idx)] = value


def smooth_blobs(n: int = 32, spacing_mm: float = 4.0, seed: int = 0) -> Volume:
    """A smooth volume for gradient checks: Gaussian blobs times a smooth window that
    vanishes at the grid border. Values lie in [0, 5], inside the soft-tissue HU range,
    so ``hu_to_density`` only min-max rescales them."""
    g = torch.Generator().manual_seed(seed)
    affine = lps_like_affine((n, n, n), spacing_mm, origin_mm=(3.0, -2.0, 5.0))
    x, y, z = _grid_mm((n, n, n), affine)
    half = spacing_mm * (n - 1) / 2
    vol = torch.zeros_like(x)
    for _ in range(5):
        c = (torch.rand(3, generator=g) - 0.5) * half
        s = (0.12 + 0.1 * torch.rand(1, generator=g)) * half
        vol += torch.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * s**2))
    for a in (x, y, z):
        vol *= (1 - (a / half) ** 2).clamp_min(0) ** 2
    return Volume(vol.numpy(), affine, {"name": "smooth_blobs"})


def bead_volume(n: int = 96, spacing_mm: float = 1.0, centre_mm=(17.3, -11.6, 23.9), sigma_mm: float = 1.5) -> Volume:
    """HU volume of air holding one Gaussian bead (peak 3000 HU) at ``centre_mm`` in the centred frame."""
    affine = lps_like_affine((n, n, n), spacing_mm)
    x, y, z = _grid_mm((n, n, n), affine)
    r2 = (x - centre_mm[0]) ** 2 + (y - centre_mm[1]) ** 2 + (z - centre_mm[2]) ** 2
    hu = HU_AIR + (3000.0 - HU_AIR) * torch.exp(-r2 / (2 * sigma_mm**2))
    return Volume(hu.numpy(), affine, {"name": "bead", "centre_mm": centre_mm})


def headsq_volume(n: int = 256) -> Volume:
    """The VTK head CT (shared data) resampled to ``n^3`` isotropic voxels covering its extent (HU).
    Needs SimpleITK and ../shared/data/headsq."""
    import SimpleITK as sitk

    if not HEADSQ_HEADER.is_file():
        raise FileNotFoundError(f"{HEADSQ_HEADER} not found: the real-CT comparison needs the shared data folder")
    img = sitk.ReadImage(str(HEADSQ_HEADER))
    extent = max(s * d for s, d in zip(img.GetSpacing(), img.GetSize()))
    spacing = extent / n
    centre = img.TransformContinuousIndexToPhysicalPoint([(s - 1) / 2 for s in img.GetSize()])
    origin = [c - spacing * (n - 1) / 2 for c in centre]
    res = sitk.Resample(
        img, [n, n, n], sitk.Transform(), sitk.sitkLinear, origin, [spacing] * 3, img.GetDirection(), 0, sitk.sitkFloat32
    )
    hu = sitk.GetArrayFromImage(res) - 1024.0
    hu[hu < -1024.0] = -1024.0
    lps = np.eye(4)
    lps[:3, :3] = np.asarray(res.GetDirection()).reshape(3, 3) * spacing
    lps[:3, 3] = res.GetOrigin()
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps
    return Volume(hu.astype(np.float32), ras, {"name": f"headsq_{n}"})


def validation_poses(n_random: int = 5, seed: int = 0, dtype=torch.float64) -> tuple[list[str], RigidTransform]:
    """The three isoposes plus ``n_random`` perturbed ones (Gaussian, docs/conventions.md section 6)."""
    g = torch.Generator().manual_seed(seed)
    names = ["LAT- iso", "PA iso", "LAT+ iso"]
    views = [C.VIEW_LAT_MINUS, C.VIEW_PA, C.VIEW_LAT_PLUS]
    r = torch.zeros(3 + n_random, 3, dtype=dtype)
    t = torch.zeros(3 + n_random, 3, dtype=dtype)
    r[:3, 0] = torch.tensor([C.VIEW_ANCHOR_RAD[v] for v in views], dtype=dtype)
    t[:3] = torch.tensor(C.ISO_TRANSLATION_MM, dtype=dtype)
    for b in range(3, 3 + n_random):
        v = views[b % 3]
        r[b] = torch.randn(3, generator=g, dtype=dtype) * ROTATION_SD_RAD
        r[b, 0] += C.VIEW_ANCHOR_RAD[v]
        t[b] = torch.tensor(C.ISO_TRANSLATION_MM, dtype=dtype) + torch.randn(3, generator=g, dtype=dtype) * torch.tensor(
            TRANSLATION_SD_MM, dtype=dtype
        )
        names.append(f"{C.VIEW_NAMES[v]} random {b - 2}")
    return names, RigidTransform.from_euler_zyx(r, t)


def ncc(a: torch.Tensor, b: torch.Tensor) -> float:
    """Global normalised cross-correlation of two images (any shape)."""
    a = a.double().flatten()
    b = b.double().flatten()
    a = (a - a.mean()) / a.std(correction=0)
    b = (b - b.mean()) / b.std(correction=0)
    return float((a * b).mean())


def patch_ncc(a: torch.Tensor, b: torch.Tensor) -> float:
    """Mean NCC over all ``MNCC_PATCH_PX`` square patches (stride 1) of two ``(H, W)`` images,
    counting only patches with texture in both (std > 1e-3 x the image std): the local
    half of the paper's multiscale NCC, without the flat air patches that score 0 even
    for identical images."""
    x = a.double()[None, None]
    y = b.double()[None, None]
    k = C.MNCC_PATCH_PX
    pool = torch.nn.functional.avg_pool2d
    mx, my = pool(x, k, 1), pool(y, k, 1)
    sx = (pool(x * x, k, 1) - mx**2).clamp_min(0).sqrt()
    sy = (pool(y * y, k, 1) - my**2).clamp_min(0).sqrt()
    cov = pool(x * y, k, 1) - mx * my
    textured = (sx > 1e-3 * x.std()) & (sy > 1e-3 * y.std())
    return float((cov / (sx * sy).clamp_min(1e-30))[textured].mean())


def intensity_centroid(img: torch.Tensor) -> tuple[float, float]:
    """Intensity-weighted centroid (row, col) in px of an ``(H, W)`` image."""
    img = img.double()
    rows = torch.arange(img.shape[0], dtype=torch.float64)
    cols = torch.arange(img.shape[1], dtype=torch.float64)
    total = img.sum()
    return float((img.sum(1) * rows).sum() / total), float((img.sum(0) * cols).sum() / total)


class DiffDRRAdapter:
    """DiffDRR 0.6.x rendering of one of our ``Volume``s (HU) on one of our ``Detector``s.

    The volume goes through DiffDRR's own ``read()`` (RAS affine, its HU-to-density
    transform with bone multiplier ``contract.BONE_FACTOR``, ``orientation="AP"``,
    ``center_volume=True``), so our density conversion is compared too. Poses are our
    camera-to-world 4x4s, which DiffDRR takes as they are.
    """

    #: DiffDRR's perspective_projection puts pixel centres at half-integers; ours at integers.
    PIXEL_CENTRE_OFFSET = 0.5

    def __init__(self, volume: Volume, detector: Detector, renderer: str = "trilinear", device=None, **kwargs):
        from diffdrr.data import read
        from diffdrr.drr import DRR as DiffDRR
        from torchio import ScalarImage

        if detector.principal_offset_mm != (0.0, 0.0):
            raise ValueError("the DiffDRR adapter supports only a zero principal offset")
        hu_ijk = torch.as_tensor(np.ascontiguousarray(volume.array, dtype=np.float32)).permute(2, 1, 0)[None]
        subject = read(
            ScalarImage(tensor=hu_ijk, affine=volume.ijk_to_ras),
            orientation="AP",
            bone_attenuation_multiplier=C.BONE_FACTOR,
            center_volume=True,
        )
        dely, delx = detector.spacing_mm
        self.drr = DiffDRR(
            subject,
            sdd=detector.sdd_mm,
            height=detector.rows,
            delx=delx,
            width=detector.cols,
            dely=dely,
            renderer=renderer,
            reverse_x_axis=True,
            **kwargs,
        ).to(device)
        self.device = device

    def density_kji(self) -> torch.Tensor:
        """DiffDRR's density volume, reordered to our ``[k, j, i]``."""
        return self.drr.density.permute(2, 1, 0)

    def __call__(self, poses: RigidTransform, **kwargs) -> torch.Tensor:
        """``(B, 1, H, W)`` line integrals (density x mm) at camera-to-world ``poses``."""
        from diffdrr.pose import RigidTransform as DRigid

        return self.drr(DRigid(poses.matrix.to(device=self.device, dtype=torch.float32)), **kwargs)

    def render_params(self, r: torch.Tensor, t: torch.Tensor, **kwargs) -> torch.Tensor:
        """Render from Euler ZYX rotation ``r`` (rad) and rotated-frame translation ``t`` (mm):
        DiffDRR's ``convert(..., "euler_angles", "ZYX")`` builds the same matrix as
        ``RigidTransform.from_euler_zyx``."""
        return self.drr(r, t, parameterization="euler_angles", convention="ZYX", **kwargs)

    def project(self, poses: RigidTransform, points_mm: torch.Tensor) -> torch.Tensor:
        """World points ``(B, N, 3)`` -> pixels ``(B, N, 2)`` as (row, col) in our pixel-centre convention."""
        from diffdrr.pose import RigidTransform as DRigid

        pose = DRigid(poses.matrix.to(device=self.device, dtype=torch.float32))
        xy = self.drr.perspective_projection(pose, points_mm.to(device=self.device, dtype=torch.float32))
        return torch.stack((xy[..., 1], xy[..., 0]), -1) - self.PIXEL_CENTRE_OFFSET


def default_trilinear_samples() -> int:
    """DiffDRR Trilinear's default ``n_points`` (read from its signature)."""
    import inspect

    from diffdrr.renderers import Trilinear

    return int(inspect.signature(Trilinear.forward).parameters["n_points"].default)


def model_detector(rows: int) -> Detector:
    """The model detector (field of view, SDD) sampled on ``rows x rows`` pixels."""
    return Detector.model().resized(rows)


def relative_l1(a: torch.Tensor, b: torch.Tensor) -> float:
    """``sum|a - b| / sum|b|``."""
    return float((a.double() - b.double()).abs().sum() / b.double().abs().sum().clamp_min(1e-30))


def autograd_and_fd_gradients(
    render: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    loss: Callable[[torch.Tensor], torch.Tensor],
    r: torch.Tensor,
    t: torch.Tensor,
    h_rad: float,
    h_mm: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """d loss(render(r, t)) / d (r, t) as ``(6,)`` vectors: by autograd, and by central
    finite differences with steps ``h_rad`` (rotations, rad) and ``h_mm`` (translations, mm)."""
    r = r.detach().reshape(1, 3)
    t = t.detach().reshape(1, 3)
    rg, tg = r.clone().requires_grad_(True), t.clone().requires_grad_(True)
    loss(render(rg, tg)).backward()
    auto = torch.cat((rg.grad[0], tg.grad[0])).double()
    fd = torch.zeros(6, dtype=torch.float64)
    with torch.no_grad():
        for p in range(6):
            h = h_rad if p < 3 else h_mm
            e = torch.zeros(6, dtype=r.dtype)
            e[p] = h
            plus = loss(render(r + e[:3], t + e[3:])).double()
            minus = loss(render(r - e[:3], t - e[3:])).double()
            fd[p] = (plus - minus) / (2 * h)
    return auto, fd
