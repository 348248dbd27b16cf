"""Helpers shared by the visualisation tests (no tests here): the optional libraries (skipped
locally when missing, FAILED in CI where .ci/run installs them) and image checks."""

from __future__ import annotations


import numpy as np
import pytest
from conftest import require_module


def require_plotting():
    require_module("matplotlib", "viz")
    require_module("plotly", "viz")
    return require_module("PIL.Image", "viz")


def check_image(path, *, min_width: int, min_height: int):
    """Open an image file; check its size and that it is not blank. Returns it as an RGB array."""
    image_module = require_module("PIL.Image", "viz")
    with image_module.open(path) as image:
        width, height = image.size
        pixels = np.asarray(image.convert("RGB"), dtype=np.int16)
    assert width >= min_width and height >= min_height, (width, height)
    # Not blank: many pixels differ from the background (the most common colour), in several colours.
    background = np.median(pixels.reshape(-1, 3), axis=0)
    drawn = np.any(np.abs(pixels - background) > 40, axis=2)
    assert drawn.mean() > 0.01, f"{path}: only {100 * drawn.mean():.2f}% of the pixels are drawn"
    assert len(np.unique(pixels.reshape(-1, 3)[drawn.reshape(-1)], axis=0)) > 10
    return pixels
