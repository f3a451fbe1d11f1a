"""JSON that every parser reads: NaN and infinities become ``null``.

Python's ``json`` writes ``NaN`` and ``Infinity`` by default, which strict parsers (jq,
JavaScript's ``JSON.parse``, most non-Python tools) reject. The project's results use NaN
for "never happened" (e.g. a threshold never reached); ``to_json`` writes those as
``null``. NumPy scalars and arrays and paths are converted too.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def plain(value: Any) -> Any:
    """``value`` with NumPy scalars/arrays as Python numbers/lists, paths as strings, and
    every non-finite float as None (recursively through dicts, lists and tuples)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def to_json(value: Any, indent: int | None = 1) -> str:
    """Strict JSON text of ``value`` (see ``plain``); raises TypeError for other objects."""
    return json.dumps(plain(value), indent=indent, allow_nan=False)


def write_json(path: str | Path, value: Any, indent: int | None = 1) -> Path:
    """Write ``to_json(value)`` to ``path`` (UTF-8, trailing newline); returns the path."""
    path = Path(path)
    path.write_text(to_json(value, indent) + "\n", encoding="utf-8")
    return path
