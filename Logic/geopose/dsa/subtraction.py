"""Mask subtraction of a native (unsubtracted) XA run, as its DICOM header prescribes.

Angiography systems often archive a DSA run native: every frame a plain radiograph, skull included, with a Mask
Subtraction Sequence (0028,6100) that tells a viewer how to subtract (Recommended Viewing Mode (0028,1090) "SUB").
GeoPose reads the subtracted run (the MAP of the vessels), so such a run is subtracted here as the header says
(DICOM PS3.3 C.7.6.10, Mask module), supported operation AVG_SUB:

* the frames of Mask Frame Numbers (0028,6110, 1-based) are averaged into the mask; it is moved by Mask Sub-pixel
  Shift (0028,6114, pixels (row, column); a positive row offset moves it towards the last row, a positive column
  offset towards the first column) with linear interpolation (SimpleITK);
* each contrast frame of Applicable Frame Range (0028,6102, pairs of 1-based first and last frames; default: every
  frame that leaves room for the averaging), averaged with the Contrast Frame Averaging (0028,6112) frames from it,
  has the mask subtracted in the logarithm of the X-ray intensity: Pixel Intensity Relationship (0028,1040) LIN
  values are logged first, LOG (and DISP) values are used as stored, Pixel Intensity Relationship Sign (0028,1041)
  -1 turns the difference round;
* the difference (attenuation added by the contrast, positive in the vessels) is put on the scale of an 8-bit DSA
  display, as the runs GeoPose was made for: the 99.9th percentile of its per-pixel maximum at
  :data:`DISPLAY_PEAK` of 255, its zero at :data:`DISPLAY_ZERO`; stored the MONOCHROME2 way (absorbers dark).

Time interval differencing (TID, REV_TID) subtracts neighbouring frames, not a mask: refused with the remedy. A run
with no such sequence is read as stored; where its frames look like radiographs (:func:`unsubtracted_notes`) the
registration says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Mapping

import numpy as np
import pydicom
import SimpleITK as sitk

from ..errors import InputError

if TYPE_CHECKING:
    from .run import DSARun

__all__ = ["MaskSubtraction", "read_mask_subtraction", "mask_subtraction_item", "subtract_mask", "unsubtracted_notes",
           "DISPLAY_PEAK", "DISPLAY_ZERO", "UNSUBTRACTED_RATIO"]

#: Where the subtracted run's brightest contrast (99.9th percentile of its per-pixel maximum) lands on the 0..255
#: display scale, and where no change lands.
DISPLAY_PEAK: Final = 0.75 * 255
DISPLAY_ZERO: Final = 0.06 * 255
#: Pixel Intensity Relationship (0028,1040) values: intensity (logged first), its logarithm, ready for display.
RELATIONSHIPS: Final = ("LIN", "LOG", "DISP")
#: Stored intensities below this are taken as this before the logarithm (a collimated border stores 0).
MIN_INTENSITY: Final = 1.0
#: A run "looks unsubtracted" when its median frame varies across the image more than this many times as much as its
#: pixels vary from frame to frame (the median over the pixels that change at all). Validation phantoms 6010-6015 at
#: 2 mm: stored subtracted 0.6-0.9, native 35-95; a real native coronary run (../shared/data/xa_sample) 11.
UNSUBTRACTED_RATIO: Final = 20.0
_REMEDY: Final = "export the run subtracted from the angiography workstation, or fix the Mask Subtraction Sequence"


@dataclass(frozen=True)
class MaskSubtraction:
    """How one native run is subtracted: 0-based ``mask_frames`` averaged into the mask, moved by ``shift_px``
    (row, column; DICOM's sign), subtracted from each of the 0-based ``contrast_frames`` averaged with the
    ``contrast_averaging`` frames from it; ``relationship`` LIN (intensity, logged first) or LOG / DISP (as stored),
    ``sign`` +1 or -1 (Pixel Intensity Relationship Sign)."""

    mask_frames: tuple[int, ...]
    contrast_frames: tuple[int, ...]
    shift_px: tuple[float, float] = (0.0, 0.0)
    contrast_averaging: int = 1
    relationship: str = "LIN"
    sign: int = 1

    def describe(self) -> str:
        shift = "" if self.shift_px == (0.0, 0.0) else f", mask shifted {self.shift_px[0]:g} / {self.shift_px[1]:g} px (row / column)"
        averaging = "" if self.contrast_averaging == 1 else f", {self.contrast_averaging} contrast frames averaged"
        first, last = self.contrast_frames[0] + 1, self.contrast_frames[-1] + 1
        return (f"native run subtracted as its Mask Subtraction Sequence says (AVG_SUB): mask of frame(s) "
                f"{', '.join(str(k + 1) for k in self.mask_frames)}{shift}{averaging}, {len(self.contrast_frames)} contrast "
                f"frames ({first}..{last}), {'logarithm of the ' if self.relationship == 'LIN' else ''}{self.relationship} "
                "values")


def _listed(value) -> list:
    """A DICOM value as a list: a multi-valued one as its values, a single one as one."""
    return list(value) if isinstance(value, (list, tuple, pydicom.multival.MultiValue)) else [value]


def _parsed(item: pydicom.Dataset) -> pydicom.Dataset:
    """``item`` with every element parsed now (pydicom parses a sequence item's elements when first read)."""
    for element in item:
        _ = element.value
    return item


def _ints(value, name: str, what: str) -> list[int]:
    try:
        return [int(v) for v in _listed(value)]
    except (TypeError, ValueError):
        raise InputError(f"{name}: {what} in its Mask Subtraction Sequence is not a list of frame numbers "
                         f"({str(value)[:60]!r}): {_REMEDY}") from None


def read_mask_subtraction(ds: pydicom.Dataset, n_frames: int, name: str) -> MaskSubtraction | None:
    """The subtraction ``ds`` prescribes for its ``n_frames`` frames; None where it prescribes none (no Mask
    Subtraction Sequence, or only items of Mask Operation NONE). The first other item (where several offer
    alternative views) is applied when it is AVG_SUB, and refused by name otherwise."""
    try:  # the items' elements are parsed when read: a damaged one raises here, not later
        items = [item for item in map(_parsed, ds.get("MaskSubtractionSequence", None) or [])
                 if str(item.get("MaskOperation", "")).strip().upper() != "NONE"]
    except Exception as exc:  # pydicom raises many types for damaged elements
        raise InputError(f"{name} is a damaged DICOM file: its Mask Subtraction Sequence cannot be read "
                         f"(pydicom: {type(exc).__name__}: {str(exc)[:120]}); copy the file again from the archive "
                         "or re-export it") from None
    if not items:
        return None
    item = items[0]
    operation = str(item.get("MaskOperation", "")).strip().upper()
    if operation != "AVG_SUB":
        raise InputError(f"{name} is a native run whose Mask Subtraction Sequence asks for {operation or 'no operation'}; "
                         f"only AVG_SUB (a mask averaged from its frames) makes a DSA run: {_REMEDY}")
    if "MaskFrameNumbers" not in item:
        raise InputError(f"{name}: its Mask Subtraction Sequence (AVG_SUB) names no Mask Frame Numbers: {_REMEDY}")
    masks = _ints(item.MaskFrameNumbers, name, "Mask Frame Numbers")
    averaging = _ints(item.get("ContrastFrameAveraging", 1) or 1, name, "Contrast Frame Averaging")[0]
    if not 1 <= averaging <= n_frames:
        raise InputError(f"{name}: Contrast Frame Averaging {averaging} in its Mask Subtraction Sequence is not within "
                         f"1..{n_frames} frames: {_REMEDY}")
    bounds = _ints(item.ApplicableFrameRange, name, "Applicable Frame Range") if "ApplicableFrameRange" in item \
        else [1, n_frames - averaging + 1]
    if len(bounds) % 2:
        raise InputError(f"{name}: Applicable Frame Range {bounds} in its Mask Subtraction Sequence is not pairs of "
                         f"first and last frames: {_REMEDY}")
    contrast = sorted({k for first, last in zip(bounds[::2], bounds[1::2]) for k in range(first, last + 1)})
    for what, frames, top in (("Mask Frame Numbers", masks, n_frames),
                              ("Applicable Frame Range", contrast, n_frames - averaging + 1)):
        if not frames or min(frames) < 1 or max(frames) > top:
            raise InputError(f"{name}: {what} {frames[:8]} in its Mask Subtraction Sequence lies outside the run's frames "
                             f"1..{top}: {_REMEDY}")
    shift = [float(v) for v in _listed(item.get("MaskSubPixelShift", None) or [0.0, 0.0])]
    if len(shift) != 2 or not all(np.isfinite(shift)) or max(abs(v) for v in shift) > 64:
        raise InputError(f"{name}: Mask Sub-pixel Shift {shift} in its Mask Subtraction Sequence is not a shift of at most "
                         f"64 pixels (row, column): {_REMEDY}")
    relationship = str(ds.get("PixelIntensityRelationship", "LIN") or "LIN").strip().upper()
    if relationship not in RELATIONSHIPS:
        raise InputError(f"{name} is a native run whose Pixel Intensity Relationship is {relationship!r}, not one of "
                         f"{', '.join(RELATIONSHIPS)}: the subtraction cannot tell intensity from its logarithm; {_REMEDY}")
    sign = _ints(ds.get("PixelIntensityRelationshipSign", 1) or 1, name, "Pixel Intensity Relationship Sign")[0]
    return MaskSubtraction(tuple(k - 1 for k in masks), tuple(k - 1 for k in contrast), (shift[0], shift[1]), averaging,
                           relationship, -1 if sign < 0 else 1)


def mask_subtraction_item(plan: MaskSubtraction) -> pydicom.Dataset:
    """``plan`` as one Mask Subtraction Sequence item (1-based frame numbers), for a writer of native runs."""
    item = pydicom.Dataset()
    item.MaskOperation = "AVG_SUB"
    item.MaskFrameNumbers = [k + 1 for k in plan.mask_frames]
    runs, start = [], plan.contrast_frames[0]
    for prev, k in zip(plan.contrast_frames, plan.contrast_frames[1:] + (None,)):
        if k != prev + 1:
            runs += [start + 1, prev + 1]
            start = k
    item.ApplicableFrameRange = runs
    if plan.contrast_averaging != 1:
        item.ContrastFrameAveraging = plan.contrast_averaging
    if plan.shift_px != (0.0, 0.0):
        item.MaskSubPixelShift = list(plan.shift_px)
    return item


def _shifted(mask: np.ndarray, shift_px: tuple[float, float]) -> np.ndarray:
    """``mask`` (H, W) moved ``shift_px`` (row towards the last row, column towards the first column), linear, the
    border continued."""
    image = sitk.GetImageFromArray(mask)
    move = sitk.TranslationTransform(2, (float(shift_px[1]), -float(shift_px[0])))  # output(x) = input(x + offset)
    out = sitk.Resample(image, image, move, sitk.sitkLinear, 0.0, sitk.sitkFloat32, True)
    return sitk.GetArrayFromImage(out)


def subtract_mask(frames: np.ndarray, plan: MaskSubtraction) -> np.ndarray:
    """The subtracted run of native ``frames`` ``(T, H, W)`` float32 (modality LUT applied; overwritten) by ``plan``:
    ``(len(plan.contrast_frames), H, W)`` float32 on the 8-bit display scale, stored the MONOCHROME2 way (255 less the
    display value: vessels dark). Works in place: no second copy of the run."""
    if plan.relationship == "LIN":
        np.log(np.maximum(frames, MIN_INTENSITY, out=frames), out=frames)
    mask = np.zeros(frames.shape[1:], np.float64)
    for k in plan.mask_frames:  # one frame at a time: no copy of the run
        mask += frames[k]
    mask = (mask / len(plan.mask_frames)).astype(np.float32)
    if plan.shift_px != (0.0, 0.0):
        mask = _shifted(mask, plan.shift_px)
    n = plan.contrast_averaging
    for k, i in enumerate(plan.contrast_frames):  # increasing: frame i is read before anything at or after it is written
        live = frames[i] if n == 1 else frames[i:i + n].mean(axis=0)
        frames[k] = (mask - live) * plan.sign  # log intensity falls where contrast absorbs: positive in the vessels
    out = frames[: len(plan.contrast_frames)]
    peak = float(np.percentile(out.max(axis=0), 99.9))
    scale = DISPLAY_PEAK / peak if peak > 0 else 1.0
    out *= -scale
    out += 255.0 - DISPLAY_ZERO
    return out


def unsubtracted_ratio(frames: np.ndarray) -> float:
    """How much a run's median frame varies across the image (sd) against how much its pixels vary from frame to
    frame (the median over the pixels that change at all of their sd over time), on every fourth pixel: about 1 for a
    subtracted run (a flat background, noise), tens for radiographs (the skull in every frame). 0 for one frame."""
    sampled = np.asarray(frames[:, ::4, ::4], dtype=np.float32)
    if len(sampled) < 2:
        return 0.0
    over_time = sampled.std(axis=0)
    changing = over_time > 0
    if not changing.any():
        return 0.0
    return float(np.median(sampled, axis=0)[changing].std() / max(float(np.median(over_time[changing])), 1e-12))


def unsubtracted_notes(runs: Mapping[str, "DSARun"]) -> list[str]:
    """A note per run read as stored (no Mask Subtraction Sequence applied) whose frames look like radiographs
    (:func:`unsubtracted_ratio` above :data:`UNSUBTRACTED_RATIO`): the registration compares subtracted vessels."""
    notes = []
    for key, run in runs.items():
        if "subtraction" in run.metadata:
            continue
        ratio = unsubtracted_ratio(run.frames)
        if ratio > UNSUBTRACTED_RATIO:
            notes.append(f"the {key.upper()} run looks unsubtracted: its median frame varies {ratio:.0f} times as much "
                         "across the image as its pixels vary from frame to frame (a subtracted run: about 1), and it has "
                         "no Mask Subtraction Sequence to subtract it with; GeoPose registers DSA: export the run subtracted "
                         "from the angiography workstation")
    return notes
