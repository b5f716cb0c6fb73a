"""Are the CTA and the runs of one patient? The precision of the vessel fit at the result.

One patient's CTA, registered, lays its vessels on the runs' to within the registration's error (about 0.5 mm on
validation phantoms). Another patient's CTA fits only roughly: its best rigid pose leaves each branch millimetres off
the branch it stands for, and the flag's other numbers do not show it (validation 6010-6029 at 1 mm, one subject's
CTA with the next subject's runs: 14 of 20 "ok" in both views, their mirror test mostly undecided, since neither the
CTA nor its mirror image fits; ``experiments/wrong_pairing/wrong_pairing.md``). A blur forgives offsets of its own
size, so the vessel NCC gains far more from blurring a loose fit than a tight one. Per view, at the result, on the
vessels the result was judged by (``opacified.selection_judge``), on the TTO's detector: the NCC of the run's vessel
image with the CTA's projected vessels, both blurred by :data:`BLUR_SIGMA_PX`, over the same unblurred. The case's
gain is the mean of its views'; above :data:`GAIN_FAILED` the result fails, above :data:`GAIN_OK` it is doubtful. Needs
the TTO's result (the networks' estimate alone lies millimetres off even for the right patient) and a vessel mask of
mostly arteries: the one computed with the artery classifier (a CTA no coarser than 1.5 mm), or a given segmentation.
A given segmentation may hold veins, and they loosen a right pairing's fit too (validation 6010-6029 at 1 mm, the
computed mask without the classifier given as the segmentation: right pairings x1.12-1.26, wrong x1.22-1.50), so there
a loose fit is doubtful, never failed; with the phantom's arteries given (an upper bound), right x1.03-1.15 against
wrong x1.18-1.43. On 2 mm validation CTAs, whose computed mask keeps veins and bone rims, right and wrong pairings
overlapped (gains 1.17-1.23 against 1.21-1.39): there it does not run (the record's ``registration.pairing`` is null,
and :data:`NOT_RUN_NOTE` says so).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Mapping

import numpy as np

from ..dsa import PreparedDSA
from ..images import gaussian_blur
from ..metrics.similarity import ncc
from ..render.renderer import Renderer

__all__ = ["BLUR_SIGMA_PX", "GAIN_OK", "GAIN_FAILED", "NOT_RUN_NOTE", "PairingTest", "pairing_test"]

#: The blur (Gaussian sd, pixels of the TTO's detector, about 2.3 mm at the detector) of both vessel images.
BLUR_SIGMA_PX: Final = 2.0
#: Blurring raises the vessel NCC of a right pairing by at most this factor (mean of the views), else the result is
#: doubtful; by more than :data:`GAIN_FAILED` it fails. Set on validation phantoms 6010-6049 at 1 mm, the user's path
#: (``experiments/wrong_pairing/wrong_pairing.md``): right pairings 1.04-1.155, one subject's CTA with the next
#: one's runs 1.172-1.46 (37 of 40 above 1.20). Phantom 13 at 1.5 mm, right: 1.174; the fit of a right pairing is
#: looser where the registration is less precise, so the band between the two bars says doubtful, not failed.
GAIN_OK: Final = 1.16
GAIN_FAILED: Final = 1.20
#: Said (record, console, Slicer) where the CTA's computed vessel mask is too coarse for the test.
NOT_RUN_NOTE: Final = ("the test for another patient's CTA (how tightly its vessels fit the runs') did not run: the CTA's "
                       "voxels are coarser than 1.5 mm; make sure the CTA is this patient's (its identifiers are compared "
                       "only where it is DICOM)")


@dataclass(frozen=True)
class PairingTest:
    """Per view, the vessel NCC at the result (``ncc``) and the same with both images blurred (``blurred_ncc``);
    ``given_segmentation``: the vessels are the user's segmentation (a loose fit is then doubtful, never failed)."""

    ncc: Mapping[str, float]
    blurred_ncc: Mapping[str, float]
    given_segmentation: bool = False

    @property
    def gains(self) -> dict[str, float]:
        """Per view, blurred over unblurred NCC (views whose NCC is not positive left out)."""
        return {k: self.blurred_ncc[k] / v for k, v in self.ncc.items() if v > 0}

    @property
    def gain(self) -> float | None:
        """The mean of the views' gains (None: no view has a positive NCC)."""
        gains = list(self.gains.values())
        return float(np.mean(gains)) if gains else None

    @property
    def verdict(self) -> str:
        """``failed`` above :data:`GAIN_FAILED` (not on a given segmentation), ``doubtful`` above :data:`GAIN_OK`, else
        ``ok`` (also without a gain)."""
        if self.gain is None or self.gain <= GAIN_OK:
            return "ok"
        return "failed" if self.gain > GAIN_FAILED and not self.given_segmentation else "doubtful"

    @property
    def loose(self) -> bool:
        """The CTA's vessels fit the runs' only loosely: the result fails."""
        return self.verdict == "failed"

    @property
    def reason(self) -> str | None:
        """Why the result fails or is doubtful (None where it is neither)."""
        if self.verdict == "ok":
            return None
        bar = GAIN_FAILED if self.gain > GAIN_FAILED else GAIN_OK
        fit = "only loosely" if self.gain > GAIN_FAILED else "more loosely than one patient's usually do"
        segmentation = ", that the segmentation holds arteries only (veins loosen the fit too)" if self.given_segmentation else ""
        return (f"the CTA's vessels fit the runs' {fit} (their NCC gains x{self.gain:.2f} from a {BLUR_SIGMA_PX:g}-pixel "
                f"blur, above x{bar:g}: offsets of millimetres remain at the best pose): are the CTA and the runs of one "
                f"patient? Check the CTA's patient{segmentation}, or the registration missed its fit")

    def as_dict(self) -> dict:
        return {"ncc": dict(self.ncc), "blurred_ncc": dict(self.blurred_ncc), "gains": self.gains, "gain": self.gain,
                "verdict": self.verdict, "loose": self.loose, "given_segmentation": self.given_segmentation,
                "blur_sigma_px": BLUR_SIGMA_PX, "gain_ok": GAIN_OK, "gain_failed": GAIN_FAILED}


def pairing_test(judge: Renderer, poses: Mapping[str, np.ndarray], views: Mapping[str, PreparedDSA],
                 given_segmentation: bool = False) -> PairingTest:
    """The test at the result's ``poses`` (``(4, 4)`` per view), ``judge`` rendering the vessels the result was judged
    by, ``views`` the prepared runs (their vessel images on the TTO's detector); ``given_segmentation``: the vessels
    are the user's."""
    plain, blurred = {}, {}
    sigma = (BLUR_SIGMA_PX, BLUR_SIGMA_PX)
    for key, view in views.items():
        drr = np.asarray(judge.render(poses[key], view.tto_detector, ("vessels",))[0], np.float64)
        run = np.asarray(view.tto_vessels, np.float64)
        plain[key] = float(ncc(run, drr))
        blurred[key] = float(ncc(gaussian_blur(run, sigma), gaussian_blur(drr, sigma)))
    return PairingTest(plain, blurred, given_segmentation)
