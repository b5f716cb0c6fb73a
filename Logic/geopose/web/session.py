"""What the page works on: the input files, a registration running in a worker thread (progress,
Cancel), and the result it shows, from that registration or from an existing result folder.

No trame here: the page reads a :class:`Session`'s fields and calls its methods.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from ..outputs import RECORD_NAME

if TYPE_CHECKING:  # the registration's modules load when a registration starts
    from ..register.cli import FileEstimate

__all__ = ["CaseFiles", "Review", "Session", "case_files", "error_line", "files_from_fields", "review_from_folder"]

#: File names a case folder is searched for (``geopose phantom`` / ``geopose demo`` write these).
CTA_NAMES = ("cta.nii.gz", "cta.nii", "cta.nrrd", "cta.mha", "cta")
DSA_NAMES = {key: (f"dsa_{key}.dcm", f"dsa_{key}.nii.gz", f"dsa_{key}.nrrd", f"dsa_{key}") for key in ("pa", "lat")}
SEGMENTATION_NAMES = ("vessels.nii.gz", "vessels.nrrd")


@dataclass(frozen=True)
class CaseFiles:
    """The files of one registration (a DSA or CTA may be a DICOM folder)."""

    cta: Path
    dsa_pa: Path
    dsa_lat: Path
    segmentation: Path | None = None


def error_line(exc: BaseException) -> str:
    """What the page shows for an exception: an :class:`InputError`'s one line, or for any other
    error one line naming it and the file its traceback was written to (as the command line does)."""
    from ..cli import one_line, write_traceback

    if isinstance(exc, InputError):
        return one_line(exc)
    return f"internal error: {type(exc).__name__}: {one_line(exc)} (full traceback in {write_traceback(exc)}; please report it)"


def _first(folder: Path, names) -> Path | None:
    return next((folder / n for n in names if (folder / n).exists()), None)


def case_files(folder: str | Path) -> CaseFiles:
    """The CTA, PA and lateral DSA (and vessel label map, when present) of a case folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"case folder {folder} does not exist: give a folder holding cta.nii.gz, dsa_pa.dcm and dsa_lat.dcm")
    found = {"cta": _first(folder, CTA_NAMES), **{k: _first(folder, names) for k, names in DSA_NAMES.items()}}
    missing = [name for name, path in found.items() if path is None]
    if missing:
        raise InputError(f"case folder {folder} has no {', '.join(missing)} file (looked for {CTA_NAMES[0]}, dsa_pa.dcm, "
                         "dsa_lat.dcm): choose the files one by one")
    return CaseFiles(found["cta"], found["pa"], found["lat"], _first(folder, SEGMENTATION_NAMES))


def _existing(text: str, what: str) -> Path:
    path = Path(text.strip()).expanduser()
    if not text.strip():
        raise InputError(f"no {what} given: enter its path (a file or DICOM folder)")
    if not path.exists():
        raise InputError(f"{what} {path} does not exist: check the path")
    return path


def files_from_fields(case: str, cta: str, dsa_pa: str, dsa_lat: str) -> CaseFiles:
    """The case folder when given, else the three paths (each must exist)."""
    if case.strip():
        return case_files(Path(case.strip()).expanduser())
    return CaseFiles(_existing(cta, "CTA"), _existing(dsa_pa, "PA DSA"), _existing(dsa_lat, "lateral DSA"))


@dataclass
class Review:
    """A registration result as the page shows it.

    ``record``: the ``result.json`` contents; ``folder``: where it and the overlays are; ``cta``: the CTA
    ``Volume``; ``maps``: per view key the DSA MAP ``(H, W)`` and ``detectors`` its acquisition ``Detector``.
    """

    record: dict
    folder: Path
    cta: object
    maps: dict[str, np.ndarray]
    detectors: dict


def _input_path(entry: dict, folder: Path) -> Path:
    given = Path(entry["path"])
    for candidate in (given, folder / given, folder.parent / given):
        if candidate.exists():
            return candidate
    raise InputError(f"the input {given} named in {folder / RECORD_NAME} is not there: run the review from the folder the "
                     "registration ran in, or register again")


def review_from_folder(folder: str | Path) -> Review:
    """The :class:`Review` of a finished ``geopose register`` / ``geopose view`` output folder."""
    from ..cta import load_cta
    from ..dsa import read_dsa, temporal_map

    folder = Path(folder).expanduser()
    path = folder / RECORD_NAME
    if not path.is_file():
        raise InputError(f"{folder} holds no {RECORD_NAME}: choose the output folder of a finished registration")
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path} cannot be read as JSON ({exc}): choose the output folder of a finished registration") from None
    if not isinstance(record, dict) or record.get("schema") != "geopose-result":
        raise InputError(f"{path} is not a GeoPose result (schema geopose-result): choose another folder")
    inputs = record["inputs"]
    cta = load_cta(_input_path(inputs["cta"], folder))
    runs = {key: read_dsa(_input_path(inputs[f"dsa_{key}"], folder)) for key in record["views"]}
    return Review(record, folder, cta, {k: temporal_map(r.frames) for k, r in runs.items()},
                  {k: r.detector for k, r in runs.items()})


@dataclass
class Progress:
    """The latest progress report: stage, fraction within it [0, 1], message, seconds since the start."""

    stage: str = ""
    fraction: float = 0.0
    message: str = ""
    elapsed_s: float = 0.0


@dataclass
class Session:
    """One registration at a time, run by :meth:`start` in a worker thread.

    ``status`` is ``idle``, ``running``, ``done``, ``cancelled`` or ``error`` (``error`` holds the
    one-line message); ``estimate`` the networks' estimate of the running (or cancelled) registration once it is
    handed over, before the TTO (a :class:`~geopose.register.cli.FileEstimate`; None before); ``review`` the
    finished result.
    """

    out: Path
    status: str = "idle"
    error: str = ""
    estimate: "FileEstimate | None" = None
    review: Review | None = None
    progress: Progress = field(default_factory=Progress)
    _cancel: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None
    _started: float = 0.0

    def start(self, files: CaseFiles, options) -> None:
        """Register ``files`` with ``options`` (:class:`~geopose.options.RegistrationOptions`) into a new
        numbered folder under ``out``, off the caller's thread."""
        if self.status == "running":
            raise InputError("a registration is running: wait for it or cancel it")
        self._cancel.clear()
        self.status, self.error, self.progress = "running", "", Progress("starting", 0.0, "reading the inputs")
        self.estimate = None
        self._started = time.perf_counter()
        self._thread = threading.Thread(target=self._run, args=(files, options), name="geopose-register", daemon=True)
        self._thread.start()

    def cancel(self) -> None:
        """Ask the running registration to stop at its next step."""
        self._cancel.set()

    def elapsed_s(self) -> float:
        return time.perf_counter() - self._started if self._started else 0.0

    def _report(self, stage: str, fraction: float, message: str) -> None:
        self.progress = Progress(stage, fraction, message, self.elapsed_s())

    def _hand_over(self, estimate: "FileEstimate") -> None:
        self.estimate = estimate

    def next_folder(self) -> Path:
        """``out/run-N`` for the first N not yet used."""
        n = 1
        while (self.out / f"run-{n}").exists():
            n += 1
        return self.out / f"run-{n}"

    def _run(self, files: CaseFiles, options) -> None:
        from ..register.cli import register_and_write
        from ..register.progress import RegistrationCancelled

        folder = self.next_folder()
        try:
            done = register_and_write(files.cta, files.dsa_pa, files.dsa_lat, folder, segmentation=files.segmentation,
                                      options=options, progress=self._report, cancel=self._cancel.is_set,
                                      estimate=self._hand_over)
        except RegistrationCancelled:
            self.status = "cancelled"
            return
        except Exception as exc:
            self.error, self.status = error_line(exc), "error"
            return
        maps = {k: v.prepared.map for k, v in done.case.views.items()}
        detectors = {k: run.detector for k, run in done.runs.items()}
        self.review = Review(done.record, folder, done.cta, maps, detectors)
        self.status = "done"
