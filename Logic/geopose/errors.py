"""The one error type for user errors.

Anything a user can get wrong (a file, a tag, an option, a Slicer node) raises
:class:`InputError` with one line naming the input, the problem and the remedy.
Every entry point (the ``geopose`` command line, the library's ``register_*``
functions, the Slicer logic) shows that line without a traceback; any other
exception is an internal error.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """A user input that cannot be used; ``str(error)`` names the input, the problem and the remedy."""
