"""The ``geopose`` command line. Each sub-command lives beside the code it drives;
this file only lists them (``module:register`` adds a sub-parser whose
``func(args)`` runs it)."""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__

#: (module, register-function) for every sub-command.
COMMANDS: list[tuple[str, str]] = [
    ("geopose.demo", "register"),
    ("geopose.nets.checkpoint", "register"),
    ("geopose.training.cli", "register"),
    ("geopose.register.cli", "register"),
    ("geopose.bench.cli", "register"),
    ("geopose.phantom.cli", "register"),
    ("geopose.phantom.gallery", "register"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="geopose", description="GeoPose CTA-to-DSA C-arm pose estimation")
    parser.add_argument("--version", action="version", version=f"geopose {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for module, fn in COMMANDS:
        getattr(importlib.import_module(module), fn)(sub)
    return parser


class UserError(Exception):
    """An error caused by the user's input; printed without a traceback."""


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, FileNotFoundError, ValueError) as exc:
        print(f"geopose {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
