"""``geopose register``: register a CTA to a PA + lateral DSA pair and write result.json + overlays.

The output folder is checked, locked and cleared before any work (:class:`~geopose.outputs.OutputFolder`);
the overlays are written atomically and ``result.json`` last, listing their checksums.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..consistency import ALLOW_ID_MISMATCH_OPTION, check_inputs_belong_together
from ..cta import load_cta
from ..cta.io import file_sha256
from ..dsa import geometry_override_args, geometry_overrides_from_args, read_dsa
from ..errors import InputError
from ..options import RegistrationOptions, setting_paths
from ..outputs import OutputFolder
from .evaluate import truth_for, truth_metrics
from .engine import resolve_engine
from .pipeline import register_case
from .progress import CancelCheck, ConsoleProgress, Preliminary, ProgressCallback
from .record import build_record
from .report import OVERLAY_NAMES, write_overlays
from .results import CaseRegistration

#: Command-line group titles of the options tree's groups.
OPTION_GROUPS = {"": "registration options", "refine": "greedy Refine options", "search": "similarity search options",
                 "tto": "test-time optimisation options", "objective": "objective options"}


def registration_option_args(p: argparse.ArgumentParser) -> None:
    """Add a flag for every setting of the options tree (:func:`geopose.options.setting_paths`) that the command
    line offers, in one argument group per options group; a flag not given keeps the tree's default."""
    groups: dict[str, argparse._ArgumentGroup] = {}
    for path, s in setting_paths():
        if not s.cli:
            continue
        group = path.rpartition(".")[0]
        if group not in groups:
            groups[group] = p.add_argument_group(OPTION_GROUPS[group])
        default = "" if s.default is None or s.kind == "bool" else f" (default: {_shown(s.default)})"
        kwargs: dict = {"dest": path, "default": None, "help": s.doc + default}
        if s.kind == "bool":
            kwargs["action"] = argparse.BooleanOptionalAction if s.default else "store_true"
        elif s.kind == "percentiles":
            kwargs.update(type=float, nargs=2, metavar=("LO", "HI"))
        elif s.kind == "floats":
            kwargs.update(type=float, nargs="+")
        else:
            kwargs.update(type={"int": int, "float": float}.get(s.kind, str), choices=s.choices)
        if s.kind in ("int", "float", "floats", "device"):
            kwargs["metavar"] = path.rpartition(".")[2].upper()
        groups[group].add_argument(s.flag, **kwargs)


def _shown(value: object) -> str:
    return " ".join(f"{v:g}" for v in value) if isinstance(value, tuple) else str(value)


def options_from_args(args: argparse.Namespace) -> RegistrationOptions:
    """The :class:`RegistrationOptions` the command line gave (validated): the tree's defaults where a flag was
    not given."""
    given = {s.flag: (path, getattr(args, path)) for path, s in setting_paths() if s.cli and getattr(args, path, None) is not None}
    for flag, (path, value) in given.items():  # each flag checked alone, so an error names the flag the user typed
        try:
            RegistrationOptions().replace(**{path: value})
        except InputError as error:
            raise InputError(f"{flag}: {error}") from None
    return RegistrationOptions().replace(**dict(given.values()))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("register", help="register a CTA to a PA + lateral DSA pair")
    p.add_argument("--cta", required=True, help="CTA volume (NIfTI, NRRD, MHA or a DICOM series folder)")
    p.add_argument("--dsa-pa", required=True, help="PA DSA run (DICOM XA, NIfTI/NRRD + JSON sidecar, or DICOM folder)")
    p.add_argument("--dsa-lat", required=True, help="lateral DSA run")
    p.add_argument("--cta-series-uid", help="SeriesInstanceUID of the CTA series, when the --cta folder holds several")
    p.add_argument("--hu-offset", type=float, default=0.0, help="added to the CTA's values to make HU (e.g. -1024)")
    p.add_argument(ALLOW_ID_MISMATCH_OPTION, action="store_true",
                   help="anonymised data: accept runs and CTA whose PatientID or StudyInstanceUID differ (recorded in result.json)")
    p.add_argument("--cranium-mask", help="CTA cranium mask on the CTA grid (default: computed from the CTA)")
    p.add_argument("--segmentation", help="CTA artery label map on the CTA grid (default: a contrast threshold whose arteries a classifier keeps)")
    p.add_argument("--models", help="folder with the Init and Refine model files and their manifest.json (default: the shipped models)")
    p.add_argument("--allow-unverified-models", action="store_true",
                   help="use a --models folder without manifest.json (its files are not checksum-verified)")
    registration_option_args(p)
    p.add_argument("--out", required=True, help="output folder (result.json, overlay PNGs)")
    geometry_override_args(p, prefix="pa-")
    geometry_override_args(p, prefix="lat-")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    record = register_files(
        args.cta, args.dsa_pa, args.dsa_lat, args.out,
        cranium_mask=args.cranium_mask, segmentation=args.segmentation, models=args.models,
        allow_unverified_models=args.allow_unverified_models, hu_offset=args.hu_offset, options=options_from_args(args),
        cta_series_uid=args.cta_series_uid, allow_id_mismatch=args.allow_id_mismatch,
        overrides={k: geometry_overrides_from_args(args, prefix=f"{k}-") for k in ("pa", "lat")},
    )
    print_summary(record, Path(args.out))
    return 0


@dataclass
class FileRegistration:
    """A registration of files and what it read: the record written as ``result.json``, the
    registration, the CTA (its centred frame is the poses' world frame), the DSA runs by view key,
    and the phantom's carotid centreline points (mm, centred frame) when ``truth.json`` was beside the CTA."""

    record: dict
    case: CaseRegistration
    cta: object
    runs: dict
    carotid_mm: np.ndarray | None


@dataclass(frozen=True)
class FileEstimate:
    """The networks' estimate of a registration of files, handed over before the TTO (``preliminary``: the poses per view
    in the CTA's centred frame, seconds since the start) with what was read: the CTA and the DSA runs by view key."""

    preliminary: Preliminary
    cta: object
    runs: dict


def register_files(cta_path: str | Path, dsa_pa: str | Path, dsa_lat: str | Path, out: str | Path, **kwargs) -> dict:
    """Read the files, register, and write the overlays and then ``result.json`` into ``out``; returns the record
    (:func:`register_and_write` takes the same arguments)."""
    return register_and_write(cta_path, dsa_pa, dsa_lat, out, **kwargs).record


def register_and_write(
    cta_path: str | Path,
    dsa_pa: str | Path,
    dsa_lat: str | Path,
    out: str | Path,
    *,
    cranium_mask: str | Path | None = None,
    segmentation: str | Path | None = None,
    models: str | Path | None = None,
    allow_unverified_models: bool = False,
    options: RegistrationOptions | None = None,
    overrides: dict[str, dict] | None = None,
    hu_offset: float = 0.0,
    cta_series_uid: str | None = None,
    allow_id_mismatch: bool = False,
    progress: ProgressCallback | None = None,
    cancel: CancelCheck | None = None,
    estimate: Callable[[FileEstimate], None] | None = None,
) -> FileRegistration:
    """Read the files, register, and write the overlays and then ``result.json`` into ``out``.

    ``out`` is checked (it must hold none of the inputs), locked and cleared first
    (:class:`~geopose.outputs.OutputFolder`); a run that fails, is cancelled (``cancel()`` returned True)
    or is killed leaves no ``result.json``. Before any work the inputs are read and checked to belong
    together (:func:`~geopose.consistency.check_inputs_belong_together`). A ``truth.json`` next to the
    CTA (a ``geopose phantom`` case) adds accuracy metrics; one that is not that CTA's is ignored with a
    note. ``overrides[view]`` are ``read_dsa`` keywords. Without ``progress`` a console bar is drawn. ``estimate``
    receives the networks' estimate with the CTA and runs read (:class:`FileEstimate`), on the registration's thread,
    while the TTO has still to run.
    """
    options = options or RegistrationOptions()
    overrides = overrides or {}
    given = {"--cta": cta_path, "--dsa-pa": dsa_pa, "--dsa-lat": dsa_lat, "--cranium-mask": cranium_mask,
             "--segmentation": segmentation, "--models": models}
    with OutputFolder(out, OVERLAY_NAMES, inputs=given) as folder:
        cta = load_cta(cta_path, hu_offset=hu_offset, series_uid=cta_series_uid)
        runs = {
            "pa": read_dsa(dsa_pa, **overrides.get("pa", {})),
            "lat": read_dsa(dsa_lat, **overrides.get("lat", {})),
        }
        consistency = check_inputs_belong_together(cta, runs, allow_id_mismatch=allow_id_mismatch)
        cranium = load_cta(cranium_mask, check_hu=False) if cranium_mask else None
        seg = load_cta(segmentation, check_hu=False) if segmentation else None
        truth, truth_note = truth_for(cta_path, cta)
        _, _, model_set = resolve_engine(options, models, allow_unverified=allow_unverified_models)
        bar = ConsoleProgress() if progress is None else None
        try:
            handed = None if estimate is None else (lambda p: estimate(FileEstimate(p, cta, runs)))
            case = register_case(cta, runs, models=model_set, options=options, cranium_mask=cranium, segmentation=seg,
                                 progress=progress or bar, cancel=cancel, preliminary=handed)
        finally:
            if bar is not None:
                bar.finish()
        inputs = {"cta": {"path": str(cta_path), "sha256": cta.metadata.get("sha256")}, "consistency": consistency}
        for key, path in (("pa", dsa_pa), ("lat", dsa_lat)):
            inputs[f"dsa_{key}"] = {"path": str(path), "sha256": runs[key].metadata.get("sha256")}
        for name, path in (("cranium_mask", cranium_mask), ("segmentation", segmentation)):
            if path:
                inputs[name] = {"path": str(path), "sha256": file_sha256([Path(path)])}
        record = build_record(case, runs, inputs=inputs, truth_metrics=truth_metrics(case, runs, truth) if truth else None)
        record["notes"] += [note for note in (truth_note, cta.metadata.get("orientation_note")) if note]
        carotid_mm = truth.carotid_points_mm if truth else None
        write_overlays(case, folder, carotid_mm)
        folder.commit(record)
    return FileRegistration(record, case, cta, runs, carotid_mm)


def print_summary(record: dict, out: Path) -> None:
    """Per view the flag and why it is not "ok", the record's notes not said there, the runtimes and the files written."""
    said = set()
    for key, v in record["views"].items():
        line = f"{key.upper():>3}: view {v['view_name']:<4} mNCC {v['final_mncc']:.3f}  silhouette Dice {v['silhouette_dice']:.3f}  quality {v['quality']['flag']}"
        if "truth" in v:
            line += f"  mPCD final {v['truth']['final']['mpcd_mm']:.2f} mm"
        print(line)
        for reason in v["quality"]["reasons"]:
            print(f"     - {reason}")
        said.update(v["quality"]["reasons"])
    for note in record["notes"]:
        if note not in said:
            print(f"note: {note}")
    print("runtimes (s): " + json.dumps({k: round(t, 3) for k, t in record["runtimes_s"].items()}))
    print(f"wrote {out / 'result.json'}, {out / 'overlay_pa.png'} and {out / 'overlay_lat.png'}")
