"""Whether the inputs of one registration can belong together, checked before any work.

The two runs must be two different acquisitions (not one file or one DICOM instance given twice)
of one patient in one study (PatientID, StudyInstanceUID), and a DICOM CTA must be of that patient.
A CTA is usually its own study (acquired before the angiography), so its StudyInstanceUID is
recorded, not compared. Anonymised data may carry different or fresh identifiers in each file:
``allow_id_mismatch`` (CLI ``--allow-id-mismatch``) accepts differing identifiers and the record
says so. Identifiers a file does not carry (NIfTI inputs, stripped tags) cannot be compared; the
record names them.
"""

from __future__ import annotations

from typing import Any

from .dsa import DSARun
from .errors import InputError
from .volume import Volume

__all__ = ["check_inputs_belong_together", "ALLOW_ID_MISMATCH_OPTION"]

#: The command-line option that accepts differing identifiers.
ALLOW_ID_MISMATCH_OPTION = "--allow-id-mismatch"


def _ids(metadata: dict) -> dict[str, str]:
    source = metadata.get("dicom_ids", metadata)
    return {k: str(source[k]).strip() for k in ("PatientID", "StudyInstanceUID", "SOPInstanceUID") if str(source.get(k, "")).strip()}


def check_inputs_belong_together(cta: Volume, runs: dict[str, DSARun], *, allow_id_mismatch: bool = False) -> dict[str, Any]:
    """Refuse (:class:`InputError`) one run given for both views, and runs or a CTA of another patient or runs of
    another study unless ``allow_id_mismatch``; returns the record entry: the identifiers compared, the
    mismatches accepted, and what could not be compared."""
    pa, lat = runs["pa"].metadata, runs["lat"].metadata
    ids = {"cta": _ids(cta.metadata), "pa": _ids(pa), "lat": _ids(lat)}
    same_file = pa.get("sha256") and pa.get("sha256") == lat.get("sha256")
    same_instance = ids["pa"].get("SOPInstanceUID") and ids["pa"].get("SOPInstanceUID") == ids["lat"].get("SOPInstanceUID")
    if same_file or same_instance:
        why = "the same data" if same_file else f"the same DICOM instance (SOPInstanceUID {ids['pa']['SOPInstanceUID']})"
        raise InputError(f"--dsa-pa {pa.get('source_path')} and --dsa-lat {lat.get('source_path')} are {why}: give the PA run "
                         "and the lateral run of the biplane acquisition, one each")
    mismatches, unchecked = [], []
    pairs = [("PatientID", "pa", "lat"), ("StudyInstanceUID", "pa", "lat"), ("PatientID", "cta", "pa"), ("PatientID", "cta", "lat")]
    for key, a, b in pairs:
        va, vb = ids[a].get(key), ids[b].get(key)
        if va is None or vb is None:
            unchecked.append(f"{key} {a}/{b}")
        elif va != vb:
            mismatches.append(f"the {'CTA' if a == 'cta' else a.upper() + ' run'} has {key} {va!r}, the {b.upper()} run {vb!r}")
    if mismatches and not allow_id_mismatch:
        raise InputError(f"the inputs are not of one patient and study: {'; '.join(mismatches)}. Give the runs and the CTA of "
                         f"one patient; for anonymised data whose identifiers differ, confirm with {ALLOW_ID_MISMATCH_OPTION}")
    if ids["cta"].get("StudyInstanceUID") and ids["cta"].get("StudyInstanceUID") != ids["pa"].get("StudyInstanceUID"):
        unchecked.append("StudyInstanceUID cta/runs (a CTA is usually a study of its own)")
    return {
        "identifiers": {k: {key: v for key, v in d.items() if key != "SOPInstanceUID"} for k, d in ids.items()},
        "allow_id_mismatch": bool(allow_id_mismatch),
        "mismatches_accepted": mismatches,
        "not_compared": unchecked,
    }
