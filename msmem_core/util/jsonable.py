"""``jsonable``: numpy scalars and arrays (and tuples) turned into what ``json.dumps`` writes, with
non-finite floats (NaN, ±inf) as ``None``; ``dumps`` writes strict JSON (``null``, never a bare ``NaN``).

Every JSON file msmem writes (run folders, bench episodes and results) goes through ``dumps``, which
passes ``allow_nan=False`` to ``json.dumps``: a non-finite value that escaped ``jsonable`` fails loudly
instead of writing JSON that strict parsers reject. ``nan_from_null`` reads such values back.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def jsonable(x: Any) -> Any:
    """``x`` with dict keys as strings, tuples as lists, numpy scalars as Python numbers, arrays as
    lists and non-finite floats as ``None``."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def dumps(x: Any, **kwargs: Any) -> str:
    """Strict JSON of ``jsonable(x)`` (``allow_nan=False``); ``kwargs`` go to ``json.dumps``."""
    return json.dumps(jsonable(x), allow_nan=False, **kwargs)


def nan_from_null(values: dict[str, Any]) -> dict[str, Any]:
    """A flat dict of metrics read back from JSON: ``None`` (a non-finite value when written) as NaN."""
    return {k: float("nan") if v is None else v for k, v in values.items()}
