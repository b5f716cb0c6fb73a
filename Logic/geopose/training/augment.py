"""Batched, seeded image augmentations that make training DRRs look like DSA MAPs.

All functions take ``(B, 1, H, W)`` float images in [0, 1] on any device and a
``torch.Generator`` on the same device; each sample draws its own parameters,
so a batch is reproducible from the generator's seed. The output is min-max
normalised to [0, 1] like every network input (docs/conventions.md 4).
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor
from torch.nn import functional as F

from ..images import normalize_minmax
from . import recipe as R


def _uniform(n: int, lo: float, hi: float, gen: torch.Generator, device: torch.device) -> Tensor:
    return lo + (hi - lo) * torch.rand(n, generator=gen, device=device)


def _some(x: Tensor, p: float, gen: torch.Generator, fn: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """``x`` with ``fn(x[chosen], chosen)`` in place of a random share ``p`` of its samples; ``fn``
    sees (and draws parameters for) only those, so an augmentation costs what it is used for."""
    chosen = torch.rand(x.shape[0], generator=gen, device=x.device) < p
    if not bool(chosen.any()):
        return x
    out = x.clone()
    out[chosen] = fn(x[chosen], chosen)
    return out


def box_blur(x: Tensor, size: int = 3) -> Tensor:
    """Mean filter of odd ``size`` px with replicate padding."""
    pad = size // 2
    return F.avg_pool2d(F.pad(x, (pad, pad, pad, pad), mode="replicate"), size, stride=1)


def plasma(n: int, shape: tuple[int, int], roughness: Tensor, gen: torch.Generator) -> Tensor:
    """Fractal ``(n, 1, H, W)`` fields in [0, 1]: octaves of smooth noise, amplitude ``roughness**octave``.

    Low roughness gives smooth fields, high roughness more fine detail.
    """
    H, W = shape
    dev = roughness.device
    field = torch.zeros(n, 1, H, W, device=dev)
    octaves = max(1, int(math.log2(max(H, W))) - 1)
    for o in range(octaves):
        size = 2 ** (o + 1)
        noise = torch.rand(n, 1, size + 1, size + 1, generator=gen, device=dev) - 0.5
        field += F.interpolate(noise, size=(H, W), mode="bilinear", align_corners=True) * roughness.view(n, 1, 1, 1) ** o
    return normalize_minmax(field)


def bilateral(x: Tensor, spatial_sd_px: Tensor, range_sd: Tensor, radius: int = R.BILATERAL_RADIUS_PX) -> Tensor:
    """Edge-preserving bilateral filter, per-sample sigmas (px and intensity), window ``2 radius + 1``."""
    n = x.shape[0]
    padded = F.pad(x, (radius,) * 4, mode="replicate")
    H, W = x.shape[-2:]
    s2 = (2 * spatial_sd_px**2).view(n, 1, 1, 1)
    r2 = (2 * range_sd**2).view(n, 1, 1, 1)
    acc = torch.zeros_like(x)
    norm = torch.zeros_like(x)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            shifted = padded[..., radius + dy : radius + dy + H, radius + dx : radius + dx + W]
            weight = torch.exp(-(dy * dy + dx * dx) / s2 - (shifted - x) ** 2 / r2)
            acc += weight * shifted
            norm += weight
    return acc / norm


def clahe(x: Tensor, clip: Tensor, tiles: int = R.CLAHE_TILES, bins: int = R.CLAHE_BINS) -> Tensor:
    """Contrast-limited adaptive histogram equalisation with per-sample clip limits.

    ``tiles x tiles`` tile histograms of ``bins`` bins are clipped at ``clip x mean
    bin count`` (excess spread uniformly); pixel mappings are bilinearly blended
    between the four nearest tile centres. Needs H and W divisible by ``tiles``.
    """
    n, _, H, W = x.shape
    if H % tiles or W % tiles:
        raise ValueError(f"CLAHE needs an image size divisible by {tiles} tiles, got {H}x{W}")
    th, tw = H // tiles, W // tiles
    idx = (x.clamp(0, 1) * (bins - 1)).round().long()  # (n,1,H,W)
    tile_idx = idx.view(n, tiles, th, tiles, tw).permute(0, 1, 3, 2, 4).reshape(n, tiles * tiles, th * tw)
    hist = torch.zeros(n, tiles * tiles, bins, device=x.device).scatter_add_(2, tile_idx, torch.ones_like(tile_idx, dtype=torch.float32))
    limit = (clip.view(n, 1, 1) * th * tw / bins).clamp_min(1.0)
    excess = (hist - limit).clamp_min(0).sum(-1, keepdim=True)
    hist = hist.clamp(max=limit) + excess / bins
    cdf = hist.cumsum(-1)
    lut = (cdf - cdf[..., :1]) / (cdf[..., -1:] - cdf[..., :1]).clamp_min(1e-6)  # (n, T*T, bins)
    lut = lut.view(n, tiles, tiles, bins)
    # Tile-centre coordinates of each pixel (fractional tile index), clamped at the borders.
    ty = ((torch.arange(H, device=x.device) + 0.5) / th - 0.5).clamp(0, tiles - 1)
    tx = ((torch.arange(W, device=x.device) + 0.5) / tw - 0.5).clamp(0, tiles - 1)
    y0, x0 = ty.floor().long(), tx.floor().long()
    y1, x1 = (y0 + 1).clamp(max=tiles - 1), (x0 + 1).clamp(max=tiles - 1)
    fy, fx = (ty - y0).view(1, H, 1), (tx - x0).view(1, 1, W)
    v = idx[:, 0]  # (n,H,W)
    b = torch.arange(n, device=x.device).view(n, 1, 1)

    def look(yy: Tensor, xx: Tensor) -> Tensor:
        return lut[b, yy.view(1, H, 1), xx.view(1, 1, W), v]

    top = look(y0, x0) * (1 - fx) + look(y0, x1) * fx
    bottom = look(y1, x0) * (1 - fx) + look(y1, x1) * fx
    return (top * (1 - fy) + bottom * fy).unsqueeze(1)


def map_like(x: Tensor, cranium: Tensor, gen: torch.Generator) -> Tensor:
    """Phantom DRR -> DSA-MAP look: a strong skull rim and subtraction noise texture inside the cranium.

    ``cranium`` is the cranium-channel line integral ``(B, 1, H, W)`` (any scale).
    """
    n, dev = x.shape[0], x.device
    silhouette = torch.sigmoid(cranium) * 2.0 - 1.0  # 0 outside, -> 1 through the skull
    rim = (silhouette - box_blur(silhouette, 7)).abs()
    rim = rim / rim.flatten(1).amax(1).clamp_min(1e-6).view(n, 1, 1, 1)
    gain = _uniform(n, *R.SKULL_RIM_GAIN, gen, dev).view(n, 1, 1, 1)
    sd = _uniform(n, *R.SUBTRACTION_NOISE_SD, gen, dev).view(n, 1, 1, 1)
    texture = box_blur(torch.randn(x.shape, generator=gen, device=dev), 3) * sd * silhouette
    return (x + gain * rim + texture).clamp(0, 1)


def _percentile_clip(x: Tensor, mask: Tensor, percentiles: tuple[float, float]) -> Tensor:
    """Per image, clip to ``percentiles`` of the pixels in the columns ``mask`` touches, subtract the
    low end and mask: ``dsa.preprocess.clip_intensities`` + masking, batched."""
    n = x.shape[0]
    columns = mask.amax(dim=-2, keepdim=True).expand_as(mask) > 0
    q = torch.tensor(percentiles, device=x.device, dtype=x.dtype) / 100.0
    out = torch.empty_like(x)
    for i in range(n):
        support = x[i][columns[i]] if bool(columns[i].any()) else x[i].flatten()
        lo, hi = torch.quantile(support, q)
        out[i] = (x[i].clamp(lo, hi) - lo) * mask[i]
    return out


def dsa_map(x: Tensor, vessels: Tensor, gen: torch.Generator, clip: tuple[float, float]) -> Tensor:
    """A DRR ``(B, 1, H, W)`` (min-max total line integral) made into what a DSA MAP looks like
    after the inference chain: the maximum over ``k`` frames (3-26) of subtraction noise whose
    sd grows like ``exp(kappa * line integral)``, mottled (drawn at half resolution), plus the
    vessels (``vessels``: the vessel channel, any scale) at a random gain, saturated like a
    stored 8-10 bit run; then the MAP's preprocessing: light smoothing, the head mask, ``clip``
    percentiles over its columns and masking."""
    n, _, H, W = x.shape
    dev = x.device
    frames = torch.randint(3, 27, (n, 1, 1, 1), generator=gen, device=dev).to(x.dtype)
    u = torch.rand(n, 1, (H + 1) // 2, (W + 1) // 2, generator=gen, device=dev).clamp(1e-6, 1 - 1e-6)
    noise_max = torch.special.ndtri(u ** (1.0 / frames))  # the maximum of `frames` standard normals
    noise_max = F.interpolate(noise_max, size=(H, W), mode="bilinear", align_corners=False)
    kappa = _uniform(n, *R.DSA_NOISE_KAPPA, gen, dev).view(n, 1, 1, 1)
    v = vessels / vessels.flatten(1).amax(1).clamp_min(1e-6).view(n, 1, 1, 1)
    gain = _uniform(n, *R.DSA_VESSEL_GAIN, gen, dev).view(n, 1, 1, 1)
    image = torch.exp(kappa * x) * (1.0 + R.DSA_NOISE_SPREAD * noise_max) + gain * v
    levels = _uniform(n, *R.DSA_SATURATION_QUANTILE, gen, dev)
    top = torch.stack([torch.quantile(image[i].flatten(), levels[i]) for i in range(n)])
    image = torch.minimum(image, top.view(n, 1, 1, 1))
    mask = (x > _uniform(n, *R.DSA_MASK_LEVEL, gen, dev).view(n, 1, 1, 1)).to(x.dtype)
    return normalize_minmax(_percentile_clip(box_blur(image, 3), mask, clip))


def augment(
    x: Tensor, gen: torch.Generator, cranium: Tensor | None = None, *, map_like_p: float = R.MAP_LIKE_P,
    vessels: Tensor | None = None, dsa_p: float = 0.0, clip: tuple[float, float] = (0.0, 100.0),
) -> Tensor:
    """The full training augmentation of a ``(B, 1, H, W)`` batch -> min-max [0, 1], same shape.

    ``cranium`` (the cranium channel) enables the MAP-likeness step; ``vessels`` (the vessel
    channel) and ``dsa_p`` > 0 send that share of the images through :func:`dsa_map` with the
    model's input ``clip`` (what the network will see at inference). Does not alter ``x``.
    """
    if x.ndim != 4 or x.shape[1] != 1:
        raise ValueError(f"augment expects a (B, 1, H, W) batch, got shape {tuple(x.shape)}")
    n, dev = x.shape[0], x.device
    x = normalize_minmax(x)
    p = R.AUG_P

    def per_sample(lo_hi: tuple[float, float], k: int) -> Tensor:
        return _uniform(k, *lo_hi, gen, dev)

    if cranium is not None:
        x = _some(x, map_like_p, gen, lambda xs, c: map_like(xs, cranium[c], gen))
    if vessels is not None and dsa_p > 0:
        x = _some(x, dsa_p, gen, lambda xs, c: dsa_map(xs, vessels[c], gen, clip))
    # Plasma brightness and contrast (p = 1).
    bright = plasma(n, x.shape[-2:], _uniform(n, *R.PLASMA_ROUGHNESS, gen, dev), gen)
    contrast = plasma(n, x.shape[-2:], _uniform(n, *R.PLASMA_ROUGHNESS, gen, dev), gen)
    mean = x.mean(dim=(-2, -1), keepdim=True)
    x = (x - mean) * (1 + R.PLASMA_CONTRAST * (contrast - 0.5)) + mean + R.PLASMA_BRIGHTNESS * (bright - 0.5)
    x = normalize_minmax(x)
    x = _some(x, p, gen, lambda xs, c: clahe(xs, per_sample(R.CLAHE_CLIP, len(xs))))
    x = _some(x, p, gen, lambda xs, c: xs.clamp_min(0) ** per_sample(R.GAMMA_RANGE, len(xs)).view(-1, 1, 1, 1))
    x = _some(x, p, gen, lambda xs, c: bilateral(xs, per_sample(R.BILATERAL_SPATIAL_PX, len(xs)),
                                                 per_sample(R.BILATERAL_RANGE_SD, len(xs))))
    x = _some(x, p, gen, lambda xs, c: box_blur(xs))
    x = _some(x, p, gen, lambda xs, c: (xs + per_sample(R.SHARPNESS_RANGE, len(xs)).view(-1, 1, 1, 1)
                                        * (xs - box_blur(xs))).clamp(0, 1))
    x = _some(x, p, gen, lambda xs, c: (xs + torch.randn(xs.shape, generator=gen, device=dev) * R.NOISE_SD).clamp(0, 1))
    x = _some(x, p, gen, lambda xs, c: xs * (1 - _erase_mask(xs, gen)))
    x = _some(x, p, gen, lambda xs, c: xs * _collimation_mask(xs, gen))
    return normalize_minmax(x)


def _erase_mask(x: Tensor, gen: torch.Generator) -> Tensor:
    """``(B, 1, H, W)`` 1 inside one random rectangle per sample (area fraction ``ERASE_FRACTION``)."""
    n, _, H, W = x.shape
    dev = x.device
    area = _uniform(n, *R.ERASE_FRACTION, gen, dev) * H * W
    aspect = torch.exp(_uniform(n, -1.0, 1.0, gen, dev))
    h = (area * aspect).sqrt().clamp(1, H)
    w = (area / aspect).sqrt().clamp(1, W)
    top = torch.rand(n, generator=gen, device=dev) * (H - h)
    left = torch.rand(n, generator=gen, device=dev) * (W - w)
    rows = torch.arange(H, device=dev).view(1, H, 1)
    cols = torch.arange(W, device=dev).view(1, 1, W)
    inside = (rows >= top.view(n, 1, 1)) & (rows < (top + h).view(n, 1, 1)) & (cols >= left.view(n, 1, 1)) & (cols < (left + w).view(n, 1, 1))
    return inside.unsqueeze(1).to(x.dtype)


def _collimation_mask(x: Tensor, gen: torch.Generator) -> Tensor:
    """``(B, 1, H, W)`` 0 on a random border of up to ``COLLIMATION_MAX_PX`` px per side, else 1."""
    n, _, H, W = x.shape
    dev = x.device
    b = torch.randint(0, R.COLLIMATION_MAX_PX + 1, (n, 4), generator=gen, device=dev)
    rows = torch.arange(H, device=dev).view(1, H, 1)
    cols = torch.arange(W, device=dev).view(1, 1, W)
    keep = (rows >= b[:, 0].view(n, 1, 1)) & (rows < H - b[:, 1].view(n, 1, 1))
    keep = keep & (cols >= b[:, 2].view(n, 1, 1)) & (cols < W - b[:, 3].view(n, 1, 1))
    return keep.unsqueeze(1).to(x.dtype)
