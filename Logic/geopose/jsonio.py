"""Reading small JSON files a user hands in (DSA sidecars, model manifests) with bounded size and nesting."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from . import limits as L
from .errors import InputError
from .inputpaths import read_bounded

__all__ = ["read_json"]


def _depth(value: Any) -> int:
    """Nesting depth of objects/arrays (a scalar is 0), without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, (dict, list)):
            deepest = max(deepest, level)
            stack.extend((v, level + 1) for v in (item.values() if isinstance(item, dict) else item))
    return deepest


def read_json(path: Path, remedy: str) -> Any:
    """The parsed content of ``path``; a file too large, not UTF-8 JSON or nested deeper than
    :data:`~geopose.limits.MAX_JSON_DEPTH` is an :class:`InputError` ending in ``remedy``."""
    data = read_bounded(path, L.MAX_JSON_BYTES, "JSON file", remedy)
    try:
        value = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{path.name} is not UTF-8 text; {remedy}") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path.name} is not valid JSON ({exc}); {remedy}") from None
    except RecursionError:
        raise InputError(f"{path.name} is nested too deeply to be a GeoPose JSON file; {remedy}") from None
    if _depth(value) > L.MAX_JSON_DEPTH:
        raise InputError(f"{path.name} nests objects/arrays {_depth(value)} levels deep (at most {L.MAX_JSON_DEPTH}); {remedy}")
    return value
