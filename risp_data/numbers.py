"""What counts as a number in a JSON file the user gave (sidecars, truth files, cell files, manifests)."""

from __future__ import annotations

import math


def is_finite_number(value) -> bool:
    """A JSON number that is finite as a float: not a bool (``True`` is an int in Python), not a string, not NaN/inf,
    not an integer beyond float's range (``float(10**400)`` raises OverflowError)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False
