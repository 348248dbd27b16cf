"""One colour per scan, for merged clouds and their views."""

from __future__ import annotations

import colorsys

import numpy as np

from ..types import as_count

__all__ = ["FIRST_COLOURS", "scan_palette"]

#: The first ten scans' colours (matplotlib's and plotly's "tab10" / "D3" qualitative palette).
FIRST_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
                 "#7f7f7f", "#bcbd22", "#17becf")
#: Steps of the later scans' hue, saturation and value (fractions of each range): a low-discrepancy
#: sequence (the powers of 1 / 1.2207..., the plastic number's analogue in three dimensions), so that
#: any run of consecutive scans is spread over the colour space, near colours far apart in index.
_STEPS = (0.8191725133961645, 0.6710436067037893, 0.5497004779019703)
#: Saturation and value ranges of the later scans (no greys, no near-black, no near-white).
_SATURATION, _VALUE = (0.45, 1.0), (0.55, 0.95)


def scan_palette(count: int) -> np.ndarray:
    """``(count, 3)`` uint8 red / green / blue, one colour per scan, all different.

    The first ten are :data:`FIRST_COLOURS`; the next spread around the colour wheel. Indexed by a
    scan index (``scan_palette(n)[scan_index]``), it colours a merged cloud by scan.
    """
    count = as_count(count, "count", minimum=0)
    colours: list[tuple[int, int, int]] = [
        tuple(int(code[i:i + 2], 16) for i in (1, 3, 5)) for code in FIRST_COLOURS[:count]  # type: ignore[misc]
    ]
    taken = set(colours)
    step = 0
    while len(colours) < count:
        hue, s, v = ((0.5 + step * a) % 1.0 for a in _STEPS)
        saturation = _SATURATION[0] + s * (_SATURATION[1] - _SATURATION[0])
        value = _VALUE[0] + v * (_VALUE[1] - _VALUE[0])
        red, green, blue = colorsys.hsv_to_rgb(hue, saturation, value)
        colour = (round(255 * red), round(255 * green), round(255 * blue))
        step += 1
        if colour not in taken:
            taken.add(colour)
            colours.append(colour)
    return np.array(colours, dtype=np.uint8).reshape(count, 3)
