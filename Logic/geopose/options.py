"""Every setting of a registration, in one tree: :class:`RegistrationOptions`.

The engine's settings at the top, each stage's in its own group: ``refine`` (:class:`RefineOptions`),
``search`` (:class:`SearchOptions`), ``tto`` (:class:`TTOSchedule`) and ``objective``
(:class:`Objective`). Each setting is declared once, with its default, unit, bound and help
(:func:`setting`); the ``geopose`` command line's flags (:func:`setting_paths`), the Slicer parameter
node's defaults and the result record's ``options`` are generated from this tree. Built by keyword,
validated once on construction, frozen, so no caller's options change behind its back;
``replace(**{"tto.iterations": 10})`` changes a setting by its path (:meth:`RegistrationOptions.replace`).
Imports nothing beyond the standard library (the Slicer module reads its defaults before the
dependencies are installed).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Iterator

from . import contract as C
from . import limits as L
from .errors import InputError

__all__ = ["BACKENDS", "DEVICES", "SILHOUETTE_MODELS", "TTO_PX_CUDA", "TTO_PX_CPU", "RefineOptions", "SearchOptions",
           "TTOSchedule", "Objective", "RegistrationOptions", "Setting", "setting", "setting_paths",
           "check_clip_percentiles"]

#: ``torch``: torch renderer and networks; ``onnxruntime``: numpy renderer and the shipped
#: ONNX graphs (no PyTorch needed); ``auto``: torch when it imports, else onnxruntime.
BACKENDS = ("auto", "torch", "onnxruntime")
#: Where torch computes: ``auto`` takes CUDA when present.
DEVICES = ("auto", "cpu", "cuda")
#: How the DRR's total channel is compared with the silhouette target: ``raw`` (the paper), ``clipped``
#: like the target or ``fitted`` to it (``register/objective.py``).
SILHOUETTE_MODELS = ("raw", "clipped", "fitted")
#: Default TTO image size (pixels along the detector's longer side): the GPU affords the model
#: resolution; on a CPU half of it.
TTO_PX_CUDA = 256
TTO_PX_CPU = 128


def check_clip_percentiles(percentiles: Any, name: str = "clip percentiles") -> tuple[float, float]:
    """``(lo, hi)`` with ``0 <= lo < hi <= 100`` as floats, or an :class:`InputError` naming the rule."""
    try:
        lo, hi = (float(p) for p in percentiles)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be two numbers (lo, hi), got {percentiles!r}") from None
    if not L.CLIP_PERCENTILE[0] <= lo < hi <= L.CLIP_PERCENTILE[1]:
        raise InputError(f"{name} ({lo:g}, {hi:g}) must satisfy 0 <= lo < hi <= 100, e.g. (2, 98) or "
                         f"docs/conventions.md 5's {C.MAP_CLIP_PERCENTILES}")
    return lo, hi


def setting(default: Any, doc: str, *, kind: str | None = None, bounds: tuple | None = None,
            choices: tuple | None = None, flag: str | None = None, cli: bool = True, remedy: str = "") -> Any:
    """A field of the options tree: its ``default``, help (``doc``, with the unit), ``kind`` (``int``,
    ``float``, ``bool``, ``str``, ``percentiles``, ``floats``; default: the default's type), the
    plausible ``bounds`` or ``choices``, the command-line ``flag`` (default: the dotted path with
    hyphens), whether the command line offers it (``cli``) and the ``remedy`` a bad value's error names."""
    if kind is None:
        kind = {bool: "bool", int: "int", float: "float", str: "str"}.get(type(default), "")
    if not kind:
        raise TypeError(f"setting({default!r}) needs a kind")
    meta = {"doc": doc, "kind": kind, "bounds": bounds, "choices": choices, "flag": flag, "cli": cli, "remedy": remedy}
    return field(default=default, metadata=meta)


def _checked(name: str, value: Any, meta: dict) -> Any:
    """``value`` of the setting ``name`` checked against its ``meta`` (:func:`setting`) and normalised."""
    kind, remedy = meta["kind"], meta["remedy"]
    if kind == "device":
        device = str(value)
        if device not in DEVICES and not (device.startswith("cuda:") and device[5:].isdigit()):
            raise InputError(f"{name} must be auto, cpu, cuda or cuda:N, got {value!r}")
        return device
    if kind == "bool":
        if not isinstance(value, bool):
            raise InputError(f"{name} must be True or False, got {value!r}")
        return value
    if kind == "int":
        return L.check_int(name, value, meta["bounds"], remedy)
    if kind == "float":
        return L.check_range(name, value, meta["bounds"], remedy)
    if kind == "percentiles":
        return check_clip_percentiles(value, name)
    if kind == "floats":
        return tuple(L.check_range(name, v, meta["bounds"], remedy) for v in value)
    if meta["choices"] is not None and value not in meta["choices"]:
        raise InputError(f"{name} must be one of {', '.join(meta['choices'])}, got {value!r}")
    return value


class _Group:
    """A group of settings: validates its fields on construction (:func:`setting`)."""

    #: The group's name in the tree (``tto``, ``objective``...).
    group: ClassVar[str] = ""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if "kind" in f.metadata:
                path = f"{self.group}.{f.name}" if self.group else f.name
                value = getattr(self, f.name)
                if value is None and f.default is not None:
                    raise InputError(f"{path} must be given (its default is {f.default!r}), got None")
                if value is not None:
                    object.__setattr__(self, f.name, _checked(path, value, f.metadata))


@dataclass(frozen=True)
class RefineOptions(_Group):
    """Similarity-gated greedy Refine (paper section 2.3.2; ``register/refine.py``)."""

    group: ClassVar[str] = "refine"
    steps: int = setting(5, "greedy Refine proposals per start (paper: 5)", bounds=L.REFINE_STEPS,
                         flag="--refine-steps", remedy="the paper uses 5")
    retry_fraction: float = setting(0.5, "a rejected move of one patient pose is tried once more at this share of its size",
                                    bounds=(0.0, 1.0))


@dataclass(frozen=True)
class SearchOptions(_Group):
    """The similarity search of one patient pose after greedy Refine (ours; ``register/search.py``)."""

    group: ClassVar[str] = "search"
    enabled: bool = setting(True, "search the patient pose's shift and in-plane turns by the views' mNCC after "
                            "biplane greedy Refine (ignored with independent views)", flag="--search")
    #: Coarse to fine: (step in mm of isocentre shift and deg of turn about a view's central ray, pixels per
    #: side of the images scored; None: the models' render size).
    schedule: tuple = setting(((4.0, 64), (2.0, 64), (1.0, None)), "(step mm/deg, image px) coarse to fine",
                              kind="schedule", cli=False)


@dataclass(frozen=True)
class TTOSchedule(_Group):
    """The test-time optimisation (paper section 2.3.3; ``register/tto.py``): steps, image size, the
    share of steps at half size and the peak learning rates of the OneCycle (of a patient pose's
    rotation, rad, and isocentre shift, mm); ``paper``: the published per-view schedule instead
    (max ``paper_lr`` on Euler angles and translation / 200, all steps at full size). The common-axis
    search (``register/axis_search.py``) runs after ``axis_search_at`` of the steps; the tournament of
    starts (``register/tournament.py``) takes ``finalists`` on after the coarse steps."""

    group: ClassVar[str] = "tto"
    iterations: int = setting(25, "test-time optimisation steps (paper: 25; 0 skips it)", bounds=L.ITERATIONS,
                              flag="--iterations", remedy="the paper uses 25; 0 skips the test-time optimisation")
    px: int | None = setting(None, f"TTO image size, pixels along the detector's longer side (default: {TTO_PX_CUDA} on "
                             f"CUDA, {TTO_PX_CPU} on a CPU)", kind="int", bounds=L.TTO_PX, flag="--tto-px",
                             remedy=f"leave it unset for {TTO_PX_CUDA} on CUDA, {TTO_PX_CPU} on a CPU")
    coarse_fraction: float = setting(0.6, "share of the steps rendered at half size", bounds=(0.0, 1.0))
    rotation_lr_rad: float = setting(0.02, "peak learning rate of a patient pose's rotation (rad)", bounds=(0.0, 1.0))
    translation_lr_mm: float = setting(4.0, "peak learning rate of a patient pose's isocentre shift (mm)",
                                       bounds=(0.0, 100.0))
    #: After 60 and 80 % of the steps (was 60, 70, 80, 90 %): on validation phantoms 6010-6029 (2 mm, two
    #: starts) carotid mPCD 2.20 -> 2.17 mm, rotation 4.39 -> 4.37 deg, TTO 10.7 -> 9.4 s
    #: (docs/pipeline_benchmark.md, 2026-12-04).
    axis_search_at: tuple = setting((0.6, 0.8), "shares of the steps after which the common-axis search runs",
                                    kind="floats", bounds=(0.0, 1.0))
    axis_search_step_deg: float = setting(4.0, "turn (deg) the common-axis search tries either side", bounds=(0.0, 45.0))
    #: Weight (per rad^2) of a prior holding a patient pose's rotation about the axis both image
    #: planes contain (``register/biplane.common_axis``) near its start (or where the last common-axis
    #: search put it): that rotation is out of plane in both views, its gradient is weak, and
    #: without the prior NAdam's normalised steps wander along it. The other two rotations are
    #: in-plane in one view and free: a prior on all three held the start's rotation error
    #: (`git show 5fa7719:docs/benchmark/bench.md`, its reading: 3.05 mm with it). The prior also
    #: holds the start's error about the common axis, which the objective does see over a few
    #: degrees; the common-axis search
    #: (``axis_search_at``) corrects it (experiments/tto_schedule/tto_schedule.md).
    rotation_prior_per_rad2: float = setting(10.0, "weight (per rad^2) of the prior holding the turn about the common "
                                             "axis", bounds=(0.0, 1e6))
    #: On validation phantoms 6010-6029 (2 mm, default path) the tournament's winner was the DICOM angles'
    #: start or the best other by its objective in 19 of 20; trying those two instead of all five distinct
    #: starts: TTO 14.3 -> 10.6 s, carotid mPCD 2.33 -> 2.20 mm (docs/pipeline_benchmark.md, 2026-12-04).
    #: The networks' estimate runs too when it is not among them (``tournament.tried_starts``): on validation phantoms
    #: 6077 and 6088, where a raw Init start scored better, 38.2 / 5.7 -> 1.3 / 2.9 mm and 2.6 / 2.4 -> 1.5 / 2.1 mm.
    starts: int = setting(2, "candidate starts that run the coarse steps: the DICOM angles' and the best others by "
                          "their objective (and the networks' estimate)", bounds=(1, 100))
    finalists: int = setting(2, "starts that run on after the coarse steps", bounds=(1, 100))
    #: On validation phantoms 6010-6029 (2 mm, default path) the gap between the two finalists after the coarse steps,
    #: judged by one objective, closed by at most 0.1 over the remaining steps (final gaps 0.1-0.92, one pair converged
    #: together); a finalist 0.2 behind never came back (experiments/tto_schedule/tournament_stop.md).
    stop_behind: float = setting(0.2, "a finalist whose best pose after the coarse steps is behind the leader's by more "
                                 "than this (objective, both views summed) stops there; 0 never stops one",
                                 bounds=(0.0, 100.0))
    final_lr_fraction: float = setting(0.1, "learning rate the OneCycle anneals to, as a share of the peak",
                                       bounds=(1e-9, 1.0))
    warmup_fraction: float = setting(0.3, "share of the steps the OneCycle warms up over", bounds=(0.0, 1.0))
    div_factor: float = setting(25.0, "the OneCycle's start learning rate is the peak over this", bounds=(1.0, 1e6))
    paper: bool = setting(False, "the published per-view schedule (independent views)", cli=False)
    paper_lr: float = setting(1e-2, "peak learning rate of the published per-view schedule", bounds=(0.0, 1.0), cli=False)

    def coarse_steps(self) -> int:
        return int(round(self.iterations * self.coarse_fraction))

    def axis_search_iterations(self) -> set[int]:
        """The steps (strictly inside the run) before which the common-axis search runs."""
        steps = {int(round(self.iterations * f)) for f in self.axis_search_at}
        return {i for i in steps if 0 < i < self.iterations}


@dataclass(frozen=True)
class Objective(_Group):
    """The objective's weights (``register/objective.py``): ``vessel_weight`` on the vessel term (-NCC of the
    MAP's vessels and the DRR's vessel channel; 0 where the CTA has no vessel channel), the rest on the
    GeoReg silhouette terms, of which ``ncc_weight`` on -mNCC and the rest on the Dice loss.
    ``silhouette``: the DRR the silhouette target is compared with (:data:`SILHOUETTE_MODELS`); the fitted
    model's optimum lies nearest the truth, but it adapts its intensities to any pose, so far from the
    truth it also rewards wrong ones; the clipped DRR's fixed mapping draws a start 10 deg off in, so the
    coarse steps use it (``coarse_silhouette``). ``read_opacified``: the TTO reads which vessels the runs
    show opacified at the networks' estimate and compares those alone (``register/opacified.py``)."""

    group: ClassVar[str] = "objective"
    ncc_weight: float = setting(0.5, "share of the silhouette terms on -mNCC (the rest on the Dice loss)",
                                bounds=(0.0, 1.0))
    silhouette: str = setting("fitted", "the DRR compared with the silhouette target", choices=SILHOUETTE_MODELS)
    coarse_silhouette: str = setting("clipped", "the same at the TTO's half-size steps", choices=SILHOUETTE_MODELS)
    clip_percentiles: tuple = setting(C.MAP_CLIP_PERCENTILES, "percentiles a clipped DRR is clipped to",
                                      kind="percentiles", cli=False)
    vessel_weight: float = setting(0.75, "weight of the vessel term against the silhouette terms", bounds=(0.0, 1.0))
    read_opacified: bool = setting(True, "compare only the vessels the runs show opacified at the networks' estimate")


@dataclass(frozen=True)
class RegistrationOptions(_Group):
    """Every setting of one registration. ``None`` means "decided by the data": the models' manifest
    (``render_px``, ``model_clip_percentiles``), the device (``tto.px``) or the CTA and the TTO size (``work_spacing_mm``);
    the result record says what was used."""

    backend: str = setting("auto", "torch (torch renderer and networks), onnxruntime (numpy renderer, shipped ONNX "
                           "graphs), auto", choices=BACKENDS)
    device: str = setting("auto", "auto, cpu, cuda or cuda:N (torch backend)", kind="device")
    render_px: int | None = setting(None, "network-input DRR size (default: the models' training size)", kind="int",
                                    bounds=L.RENDER_PX, remedy="leave it unset for the models' training size")
    model_clip_percentiles: tuple | None = setting(
        None, "percentiles the networks' MAP is clipped to (default: the models' manifest, else "
        f"{' '.join(f'{p:g}' for p in C.MAP_CLIP_PERCENTILES)}); the TTO target keeps "
        f"{' '.join(f'{p:g}' for p in C.MAP_CLIP_PERCENTILES)}", kind="percentiles")
    #: At 3 the result before the TTO takes 1.0-1.4 s less, but it costs accuracy: on 1 mm validation phantoms
    #: 6010-6034 the mean carotid mPCD goes 0.790 -> 0.859 mm (experiments/speed_targets/speed_targets.md; on 2 mm
    #: phantoms earlier, the benchmark lost a little: experiments/refine_starts/refine_starts.md), so the default
    #: stays the renderers' own.
    estimate_voxel_per_pixel: float = setting(1.5, "greedy Refine and the similarity search render the coarsest CTA level "
                                              "whose voxels are at most this many pixel footprints (3: about 1 s faster, "
                                              "less accurate; see experiments/speed_targets)", bounds=L.VOXEL_PER_PIXEL)
    work_spacing_mm: float | None = setting(None, "the finest CTA level the renderers sample is the coarsest with voxels of at "
                                            f"most this (mm) (default: 2 mm for the CPU's {TTO_PX_CPU} px TTO images, 1 mm for "
                                            f"CUDA's {TTO_PX_CUDA})",
                                            kind="float", bounds=L.WORK_SPACING_MM)
    independent_views: bool = setting(False, "register each view on its own (the published pipeline) instead of one "
                                      "patient pose seen by both arms")
    biplanar: bool = setting(False, "independent views: add the orthogonality term to the TTO")
    refine: RefineOptions = field(default_factory=RefineOptions)
    search: SearchOptions = field(default_factory=SearchOptions)
    tto: TTOSchedule = field(default_factory=TTOSchedule)
    objective: Objective = field(default_factory=Objective)

    def __post_init__(self) -> None:
        super().__post_init__()
        for f in dataclasses.fields(self):
            if "kind" not in f.metadata and not isinstance(getattr(self, f.name), type(f.default_factory())):
                raise InputError(f"{f.name} must be a {type(f.default_factory()).__name__}, got {getattr(self, f.name)!r}")

    def replace(self, **changes: Any) -> "RegistrationOptions":
        """A copy with ``changes`` by dotted path (``**{"tto.iterations": 10}``) or top-level name
        (validated like a new one)."""
        known = dict(setting_paths())
        unknown = sorted(set(changes) - set(known) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise InputError(f"unknown registration option(s) {', '.join(unknown)}; known: {', '.join(known)}")
        groups: dict[str, dict[str, Any]] = {}
        top = {}
        for path, value in changes.items():
            group, _, name = path.rpartition(".")
            if group:
                groups.setdefault(group, {})[name] = value
            else:
                top[path] = value
        for group, values in groups.items():
            top[group] = dataclasses.replace(getattr(self, group), **values)
        return dataclasses.replace(self, **top)

    def as_dict(self) -> dict[str, Any]:
        """The tree as nested plain values (the result record's ``options``)."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Setting:
    """One leaf of the options tree: its dotted ``path``, default and :func:`setting` metadata."""

    path: str
    default: Any
    doc: str
    kind: str
    bounds: tuple | None
    choices: tuple | None
    flag: str
    cli: bool


def _leaves(cls: type, prefix: str = "") -> Iterator[Setting]:
    for f in dataclasses.fields(cls):
        if "kind" in f.metadata:
            path = prefix + f.name
            m = f.metadata
            yield Setting(path, f.default, m["doc"], m["kind"], m["bounds"], m["choices"],
                          m["flag"] or "--" + path.replace(".", "-").replace("_", "-"), m["cli"])
        elif dataclasses.is_dataclass(f.default_factory):
            yield from _leaves(f.default_factory, prefix + f.name + ".")


def setting_paths() -> list[tuple[str, Setting]]:
    """Every setting of :class:`RegistrationOptions` as ``(dotted path, Setting)``, in declaration order."""
    return [(s.path, s) for s in _leaves(RegistrationOptions)]
