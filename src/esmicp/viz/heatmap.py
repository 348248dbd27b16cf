"""The evolution of the similarity matrix M over the iterations, as a grid of heat maps (the
ESM-ICP paper's Fig. 3): one row per method, one column per shown iteration."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import InvalidInputError
from ..metrics import rotation_error_deg
from ..types import as_count
from ._deps import new_figure
from .inputs import PicturePair, builtin_pair
from .similarity import similarity_matrix
from .trace import RegistrationTrace, trace_registration

#: Methods drawn by default: the paper's formulation and ours.
DEFAULT_METHODS = ("esm-paper", "esm")

#: Default number of iterations shown per method.
DEFAULT_COLUMNS = 6


def shown_iterations(iterations: int, columns: int) -> list[int]:
    """Up to ``columns`` iteration numbers spread over ``1 .. iterations``, first and last included."""
    if iterations < 1:
        return []
    return sorted({int(round(k)) for k in np.linspace(1, iterations, min(columns, iterations))})


def heatmap_figure(
    traces: Sequence[RegistrationTrace], *, columns: int = DEFAULT_COLUMNS, title: str | None = None, truth=None
):
    """A matplotlib Figure: row r shows M of ``traces[r]`` at :func:`shown_iterations`.

    Colour = weight (0 to 1, same scale everywhere). Rows are source points; columns are source
    points too for ``esm-paper`` (its N x N matrix) and target points for the other methods.
    ``truth`` (4x4 ``T_target_source``), when known, adds each method's final rotation error.
    """
    columns = as_count(columns, "columns")
    if not traces:
        raise InvalidInputError("traces: need at least one registration to draw")
    columns = max(1, max(len(shown_iterations(trace.iterations, columns)) for trace in traces))
    figure = new_figure(2.3 * columns + 1.2, 2.5 * len(traces) + 0.3 * len(traces) + 0.7)
    figure.set_layout_engine("constrained")
    grid = figure.add_gridspec(len(traces), columns)
    image = None
    for row, trace in enumerate(traces):
        shown = shown_iterations(trace.iterations, columns)
        for col in range(columns):
            axes = figure.add_subplot(grid[row, col])
            if col >= len(shown):
                axes.set_axis_off()
                continue
            step = trace.steps[shown[col] - 1]
            matrix = similarity_matrix(trace.method, step.indices, step.weights, len(trace.source), len(trace.target))
            image = axes.imshow(matrix, vmin=0.0, vmax=1.0, cmap="viridis", interpolation="nearest")
            sigma = "" if step.sigma is None else f", sigma {step.sigma:.3g}"
            axes.set_title(f"iteration {step.iteration}{sigma}", fontsize=8)
            axes.tick_params(labelsize=6)
            axes.xaxis.get_major_locator().set_params(integer=True)
            axes.yaxis.get_major_locator().set_params(integer=True)
            if col == 0:
                axes.set_ylabel(f"{trace.method}\nsource point i", fontsize=8)
            if row == len(traces) - 1 or col == 0:
                axes.set_xlabel("source point" if trace.method == "esm-paper" else "target point", fontsize=7)
    if image is not None:
        colorbar = figure.colorbar(image, ax=figure.axes, shrink=0.8, pad=0.02)
        colorbar.set_label("M entry (weight w_i)", fontsize=8)
    starts = ", ".join(sorted({trace.start for trace in traces}))
    summary = "\n".join(_summary(trace, truth) for trace in traces)
    heading = "Similarity matrix M per iteration" + (f": {title}" if title else "")
    figure.suptitle(f"{heading}; start: {starts}\n{summary}", fontsize=9)
    return figure


def _summary(trace: RegistrationTrace, truth) -> str:
    if truth is None:
        return trace.label
    return f"{trace.label}, final rotation error {rotation_error_deg(trace.poses[-1], truth):.3g} deg"


def heatmap(
    source=None,
    target=None,
    *,
    methods: Sequence[str] = DEFAULT_METHODS,
    init="identity",
    sigma: float | None = None,
    max_iterations: int = 30,
    columns: int = DEFAULT_COLUMNS,
    title: str | None = None,
    truth=None,
):
    """Heat maps of M over the iterations of each method in ``methods``; returns the Figure.

    With no clouds, the built-in shape at 21 well-spread points, the source a copy rotated 30
    degrees (the paper's protocol; see :func:`esmicp.viz.inputs.builtin_pair`). The clouds are
    used as given: downsample them first (:func:`esmicp.viz.inputs.downsample`) so that M is
    readable. ``init`` is ``"identity"`` or a 4x4 ``T_target_source``; ``truth`` (the true 4x4
    ``T_target_source``, when known) adds the final rotation errors to the title.
    """
    if (source is None) != (target is None):
        raise InvalidInputError("source, target: give both clouds, or neither (the built-in shape)")
    if source is None:
        pair: PicturePair = builtin_pair(points=21)
        source, target, title = pair.source, pair.target, title or pair.description
        truth = pair.T_target_source
    if isinstance(methods, str):
        methods = [methods]
    traces = [
        trace_registration(source, target, method=method, init=init, sigma=sigma, max_iterations=max_iterations)
        for method in methods
    ]
    return heatmap_figure(traces, columns=columns, title=title, truth=truth)
