"""TEST-ONLY stand-in for ``slicer.parameterNodeWrapper`` (no serialisation, no GUI); see ../README.md."""

from __future__ import annotations

import typing

__all__ = ["parameterNodeWrapper", "WithinRange", "Choice"]


class WithinRange:
    def __init__(self, minimum, maximum):
        self.minimum, self.maximum = minimum, maximum


class Choice:
    def __init__(self, choices):
        self.choices = list(choices)


def parameterNodeWrapper(cls):
    """Class with a ``(parameterNode)`` constructor and the annotated defaults as attributes."""
    hints = typing.get_type_hints(cls, include_extras=True)
    defaults = {name: getattr(cls, name, None) for name in hints}

    def __init__(self, parameterNode=None):
        self.parameterNode = parameterNode
        for name, value in defaults.items():
            setattr(self, name, value)

    return type(cls.__name__, (), {"__init__": __init__, "__doc__": cls.__doc__})
