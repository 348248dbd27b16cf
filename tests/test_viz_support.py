"""Helpers shared by the visualisation tests (no tests here): the optional libraries (skipped
locally when missing, FAILED in CI where .ci/run installs them) and image checks."""

from __future__ import annotations

import importlib
import os

import numpy as np
import pytest


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_module(name: str, extra: str = "viz"):
    """Import ``name``; skip the test when it is missing locally, fail it in CI."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        message = f"{name} cannot be imported ({exc}): pip install 'esmicp[{extra}]'"
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)


def require_plotting():
    require_module("matplotlib")
    require_module("plotly")
    return require_module("PIL.Image")


def check_image(path, *, min_width: int, min_height: int):
    """Open an image file; check its size and that it is not blank. Returns it as an RGB array."""
    image_module = require_module("PIL.Image")
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
