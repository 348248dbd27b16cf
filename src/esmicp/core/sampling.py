"""Even subsets of a cloud's points, the same for the same input (no random draw)."""

from __future__ import annotations

import numpy as np


def evenly_strided(length: int, at_most: int) -> np.ndarray:
    """At most ``at_most`` indices into ``range(length)``, evenly strided from the first to the last
    (all of them when ``length <= at_most``), in increasing order without repeats."""
    return np.linspace(0, length - 1, min(at_most, length)).astype(np.intp)
