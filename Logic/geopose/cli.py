"""The ``geopose`` command line. Each sub-command lives beside the code it drives;
this file only lists them (``module:register`` adds a sub-parser whose
``func(args)`` runs it).

Errors: an :class:`~geopose.errors.InputError` prints its one line and exits with 2;
any other exception prints one line naming it and the file the full traceback was
written to, and exits with 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import traceback

from . import __version__
from .errors import InputError

#: The module of each sub-command; a command line naming one imports only that module (so e.g.
#: ``geopose view`` and ``geopose register`` start without importing PyTorch).
COMMAND_MODULES: dict[str, str] = {
    "demo": "geopose.demo",
    "import-checkpoint": "geopose.nets.checkpoint",
    "train": "geopose.training.cli",
    "register": "geopose.register.cli",
    "bench": "geopose.bench.cli",
    "phantom": "geopose.phantom.cli",
    "phantom-gallery": "geopose.phantom.gallery",
    "view": "geopose.web.cli",
}
#: (module, register-function) for every sub-command.
COMMANDS: list[tuple[str, str]] = [(module, "register") for module in COMMAND_MODULES.values()]


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of every sub-command, or only of the one ``argv`` starts with."""
    parser = argparse.ArgumentParser(prog="geopose", description="GeoPose CTA-to-DSA C-arm pose estimation")
    parser.add_argument("--version", action="version", version=f"geopose {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    named = COMMAND_MODULES.get(argv[0]) if argv else None
    for module, fn in [c for c in COMMANDS if c[0] == named] or COMMANDS:
        getattr(importlib.import_module(module), fn)(sub)
    return parser


def one_line(text) -> str:
    """``text`` (or an exception's message) on one line."""
    return " ".join(str(text).split())


def write_traceback(exc: BaseException) -> str:
    """Write ``exc``'s full traceback to a new temporary file; its path (or why none could be written)."""
    try:
        with tempfile.NamedTemporaryFile("w", prefix="geopose-traceback-", suffix=".txt", delete=False) as handle:
            traceback.print_exception(type(exc), exc, exc.__traceback__, file=handle)
            return handle.name
    except OSError as error:
        return f"<not written: {error.strerror or error}>"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"geopose {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # an internal error: one line here, the traceback in a file
        where = write_traceback(exc)
        print(f"geopose {args.command}: internal error: {type(exc).__name__}: {one_line(exc)} "
              f"(full traceback in {where}; please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
