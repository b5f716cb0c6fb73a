"""Label values of the phantom label map (uint8), defined once.

``CRANIUM`` is a solid mask of the skull and everything inside it. Arteries carry
a territory label; an artery voxel inside the cranium stores its label plus
``INTRACRANIAL_OFFSET`` so the cranium group can still be a solid mask
(``label_groups()["cranium"]``) while each vessel group stays complete. Left and
right are the *patient's*: in RAS, +x points to the patient's right, so the left
ICA lies at x < 0 in the canonical frame.

Besides the arteries the map holds what a CTA shows enhanced but a vessel mask
must leave out: the venous sinuses (with the cavernous sinuses and the internal
jugular veins they drain into; ``INTRACRANIAL_OFFSET`` added inside the cranium
like the arteries), the dura under the inner table and, in a subject drawn with
an arteriovenous malformation, its nidus and early draining vein. The last two
lie inside the cranium only. None of them is in ``ARTERY_LABELS`` or
``vessel_mask``; all of them inside the cranium are in the cranium group.
"""

from __future__ import annotations

from typing import Final

import numpy as np

BACKGROUND: Final = 0
CRANIUM: Final = 1
ICA_LEFT: Final = 2
ICA_RIGHT: Final = 3
ANTERIOR_LEFT: Final = 4  # left ACA and MCA trees, left PComm
ANTERIOR_RIGHT: Final = 5
POSTERIOR: Final = 6  # vertebral, basilar, PCA, cerebellar arteries
EXTERNAL_LEFT: Final = 7  # left common carotid and external carotid branches
EXTERNAL_RIGHT: Final = 8
VENOUS_SINUS: Final = 9  # dural venous and cavernous sinuses, internal jugular veins
#: Added to an artery (or venous) label when the voxel lies inside the cranium.
INTRACRANIAL_OFFSET: Final = 10
DURA: Final = 20  # the enhancing dura under the inner table and the falx (intracranial only)
NIDUS: Final = 21  # an arteriovenous malformation: nidus and early draining vein (intracranial only)

ARTERY_LABELS: Final = (ICA_LEFT, ICA_RIGHT, ANTERIOR_LEFT, ANTERIOR_RIGHT, POSTERIOR, EXTERNAL_LEFT, EXTERNAL_RIGHT)
LABEL_NAMES: Final = {
    BACKGROUND: "background",
    CRANIUM: "cranium",
    ICA_LEFT: "ica_left",
    ICA_RIGHT: "ica_right",
    ANTERIOR_LEFT: "anterior_left",
    ANTERIOR_RIGHT: "anterior_right",
    POSTERIOR: "posterior",
    EXTERNAL_LEFT: "external_left",
    EXTERNAL_RIGHT: "external_right",
    VENOUS_SINUS: "venous_sinus",
    DURA: "dura",
    NIDUS: "nidus",
}


def with_intracranial(labels: tuple[int, ...] | list[int]) -> list[int]:
    """Artery labels together with their intracranial variants."""
    return [int(v) for v in labels] + [int(v) + INTRACRANIAL_OFFSET for v in labels]


def label_groups() -> dict[str, list[int]]:
    """Name -> label values, the ``label_groups`` argument of ``DRR.from_volume``."""
    groups = {
        "cranium": [CRANIUM] + [v + INTRACRANIAL_OFFSET for v in (*ARTERY_LABELS, VENOUS_SINUS)] + [DURA, NIDUS],
        "vessels": with_intracranial(ARTERY_LABELS),
        "venous_sinus": with_intracranial([VENOUS_SINUS]),
        "dura": [DURA],
        "nidus": [NIDUS],
    }
    for v in ARTERY_LABELS:
        groups[LABEL_NAMES[v]] = with_intracranial([v])
    return groups


def cranium_mask(labels: np.ndarray) -> np.ndarray:
    """Boolean solid cranium (skull and contents, vessels inside it included)."""
    return np.isin(labels, label_groups()["cranium"])


def vessel_mask(labels: np.ndarray) -> np.ndarray:
    """Boolean arteries (intracranial parts included; no veins, dura or nidus)."""
    return np.isin(labels, label_groups()["vessels"])
