"""Strict JSON for result files: what jq and JavaScript parse (no NaN / Infinity constants)."""

from __future__ import annotations

import math


def strict_json(x):
    """``x`` with arrays, tensors and numpy scalars as plain lists and numbers, and NaN/inf floats as None."""
    if hasattr(x, "tolist"):
        x = x.tolist()
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict_json(v) for v in x]
    return x
