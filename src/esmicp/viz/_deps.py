"""Lazy imports of the optional plotting libraries (the ``viz`` extra), with an install hint."""

from __future__ import annotations

import importlib

from ..errors import MissingDependencyError

#: What to tell a user whose plotting library is missing.
VIZ_INSTALL_HINT = "pip install 'esmicp[viz]' (matplotlib and plotly)"


def require(module: str):
    """Import an optional plotting module (``"plotly.graph_objects"``, ``"matplotlib"``) now and
    return it, or raise :class:`~esmicp.errors.MissingDependencyError` with the install hint of the
    ``viz`` extra. Public as :func:`esmicp.viz.require` (call it before long work, so a missing
    plotting library fails first)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        package = module.split(".")[0]
        raise MissingDependencyError(
            f"{package} is needed for this picture but cannot be imported ({exc}); install it with: "
            f"{VIZ_INSTALL_HINT}"
        ) from exc


def new_figure(width_in: float, height_in: float, dpi: int = 100):
    """A matplotlib Figure on the Agg canvas (headless; no pyplot, no global state)."""
    figure_module = require("matplotlib.figure")
    agg = require("matplotlib.backends.backend_agg")
    figure = figure_module.Figure(figsize=(width_in, height_in), dpi=dpi)
    agg.FigureCanvasAgg(figure)
    return figure
