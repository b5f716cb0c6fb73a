"""One definition of the geometry-override command-line options (register command)."""

from __future__ import annotations

import argparse
from typing import Any

from ..errors import InputError
from .run import GEOMETRY_SOURCES, PHOTOMETRIC, cli_option

__all__ = ["geometry_override_args", "geometry_overrides_from_args"]

_HELP = {
    "primary_deg": "C-arm primary angle in deg, LAO positive",
    "secondary_deg": "C-arm secondary angle in deg, cranial positive",
    "sid_mm": "source-to-detector distance (SID/SDD) in mm",
    "sod_mm": "source-to-isocentre distance in mm",
    "pixel_spacing_mm": "detector-plane pixel spacing in mm: ROW COL, or one value for square pixels",
    "principal_offset_mm": "camera offset (x0, y0) in mm of the image centre from the central ray",
}


def _clean(prefix: str) -> str:
    return prefix.strip("-_")


def geometry_override_args(parser: argparse.ArgumentParser, *, prefix: str = "") -> None:
    """Add ``--primary-deg --secondary-deg --sid-mm --sod-mm --pixel-spacing-mm
    --principal-offset-mm --photometric`` (with ``prefix="pa"`` or ``"pa-"``: ``--pa-sid-mm`` ... for one
    view of several) to ``parser``; each replaces the value read from the DSA file."""
    prefix = _clean(prefix)
    group = parser.add_argument_group(f"{prefix.upper() + ' ' if prefix else ''}DSA geometry overrides")
    for key, text in _HELP.items():
        option = cli_option(key) if not prefix else f"--{prefix}-" + cli_option(key)[2:]
        kwargs: dict[str, Any] = {"type": float, "default": None, "dest": f"{prefix + '_' if prefix else ''}{key}"}
        if key == "pixel_spacing_mm":
            kwargs.update(nargs="+", metavar=("ROW", "COL"))
        elif key == "principal_offset_mm":
            kwargs.update(nargs=2, metavar=("X0", "Y0"))
        group.add_argument(option, help=f"{text} (replaces {GEOMETRY_SOURCES[key]})", **kwargs)
    group.add_argument(
        f"--{prefix + '-' if prefix else ''}photometric", choices=PHOTOMETRIC, default=None,
        dest=f"{prefix + '_' if prefix else ''}photometric_interpretation",
        help="how the stored frames are to be read (replaces PhotometricInterpretation (0028,0004) or the sidecar's)",
    )


def geometry_overrides_from_args(args: argparse.Namespace, *, prefix: str = "") -> dict[str, Any]:
    """The overrides given on the command line as keyword arguments for ``read_dsa``."""
    prefix = _clean(prefix)
    out = {}
    for key in (*_HELP, "photometric_interpretation"):
        value = getattr(args, f"{prefix + '_' if prefix else ''}{key}", None)
        if value is not None:
            if key == "pixel_spacing_mm" and len(value) > 2:
                raise InputError(f"--pixel-spacing-mm takes one or two values (ROW COL), got {len(value)}")
            out[key] = tuple(value) if isinstance(value, list) else value
    return out
