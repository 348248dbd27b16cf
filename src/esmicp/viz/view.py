"""A self-contained interactive HTML viewer: target, source and aligned source in 3D, a slider
stepping the iterations, optionally a second method side by side on the same input.

plotly.js is inlined in the page (no CDN, no server): it opens in any browser, offline. Large
clouds are subsampled for display only (the registration runs on the full clouds) and the page
says so. ``figure.layout.meta`` holds the data as JSON: methods, poses per iteration, display
counts (read by the tests, handy for scripts).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np

from ..errors import InvalidInputError
from ..io.atomic import atomic_write
from ..metrics import rotation_error_deg
from ..types import as_count
from ._deps import require
from .trace import RegistrationTrace, trace_registration

#: Default cap on the points drawn per cloud.
DEFAULT_DISPLAY_POINTS = 2000

#: Colours: target, source at the start, aligned source.
TARGET_COLOUR, START_COLOUR, ALIGNED_COLOUR = "#7f7f7f", "#ff9f40", "#1f5fbf"


def display_subset(count: int, limit: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``limit`` of ``count`` points (random, seeded; all if fewer)."""
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=limit, replace=False))


def scatter_trace(go, points, name, colour, scene, size=2.0, opacity=0.8, showlegend=True):
    """A plotly ``Scatter3d`` of ``(N, 3)`` points as markers of one colour, in the 3D ``scene``
    named (``"scene"``, ``"scene2"``, ...); ``go`` is ``plotly.graph_objects`` (imported by the
    caller through :func:`esmicp.viz.require`). Legend entries are grouped by ``name``."""
    points = np.asarray(points, dtype=np.float32)
    return go.Scatter3d(
        x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", name=name, scene=scene,
        marker={"size": size, "color": colour, "opacity": opacity}, showlegend=showlegend,
        legendgroup=name,
    )


def _status(trace: RegistrationTrace, k: int, truth) -> str:
    if trace.result is None:  # a pose shown as given
        error = "" if truth is None else f", rotation error {rotation_error_deg(trace.poses[0], truth):.3g} deg"
        return f"{trace.start}{error}"
    shown = min(k, trace.iterations)
    held = " (finished)" if k > trace.iterations else ""
    text = f"{trace.method}: iteration {shown}/{trace.iterations}{held}"
    if shown >= 1:
        step = trace.steps[shown - 1]
        text += f", RMS distance {step.rmse:.3g}"
        if step.sigma is not None:
            text += f", sigma {step.sigma:.3g}"
    if truth is not None:
        text += f", rotation error {rotation_error_deg(trace.poses[shown], truth):.3g} deg"
    return text


def view_figure(
    traces: Sequence[RegistrationTrace],
    *,
    max_display_points: int = DEFAULT_DISPLAY_POINTS,
    title: str | None = None,
    truth=None,
    shown_iteration: int = 0,
):
    """A plotly Figure: one 3D scene per trace (same input), a slider over the iterations.

    Slider step k shows every method after k iterations (a method that stopped earlier keeps
    its last pose, and its caption says so). ``truth`` (4x4 ``T_target_source``), when known,
    adds the rotation error to the captions. The page opens at step ``shown_iteration``
    (clipped to the last step).
    """
    go = require("plotly.graph_objects")
    subplots = require("plotly.subplots")
    if not traces:
        raise InvalidInputError("traces: need at least one registration to show")
    max_display_points = as_count(max_display_points, "max_display_points")
    first = traces[0]
    for trace in traces[1:]:
        if not (np.array_equal(trace.source, first.source) and np.array_equal(trace.target, first.target)):
            raise InvalidInputError("traces: the methods shown side by side must have run on the same clouds")
    source_shown = display_subset(len(first.source), max_display_points, seed=1)
    target_shown = display_subset(len(first.target), max_display_points, seed=2)
    steps = max(trace.iterations for trace in traces)
    opened = min(as_count(shown_iteration, "shown_iteration", minimum=0), steps)

    figure = subplots.make_subplots(
        rows=1, cols=len(traces), specs=[[{"type": "scene"}] * len(traces)],
        subplot_titles=[trace.label for trace in traces], horizontal_spacing=0.02,
    )
    every = [first.target, first.source] + [trace.aligned(k) for trace in traces for k in range(trace.iterations + 1)]
    low = np.min([points.min(axis=0) for points in every], axis=0)
    high = np.max([points.max(axis=0) for points in every], axis=0)
    centre, half = (low + high) / 2, max(float(np.max(high - low)) / 2 * 1.05, 1e-12)
    aligned_index = []
    for column, trace in enumerate(traces, start=1):
        scene = "scene" if column == 1 else f"scene{column}"
        legend = column == 1
        figure.add_trace(scatter_trace(go, first.target[target_shown], "target", TARGET_COLOUR, scene, showlegend=legend), 1, column)
        figure.add_trace(
            scatter_trace(go, first.source[source_shown], "source (as given)", START_COLOUR, scene, 1.5, 0.35, legend), 1, column
        )
        figure.add_trace(
            scatter_trace(go, trace.aligned(min(opened, trace.iterations))[source_shown], "source (aligned)",
                     ALIGNED_COLOUR, scene, showlegend=legend),
            1, column,
        )
        aligned_index.append(len(figure.data) - 1)
        # Fixed, equal ranges: the clouds do not jump as the slider moves, and stay undistorted.
        figure.layout[scene].update(
            aspectmode="cube",
            **{f"{name}axis": {"range": [c - half, c + half], "title": name} for name, c in zip("xyz", centre)},
        )

    titles = list(figure.layout.annotations)
    shown_note = (
        f"shown: {len(target_shown)} of {len(first.target)} target points, {len(source_shown)} of "
        f"{len(first.source)} source points"
        + (" (subsampled for display; registered on all points)"
           if len(target_shown) < len(first.target) or len(source_shown) < len(first.source) else "")
    )

    def annotations(k):
        status = "<br>".join(_status(trace, k, truth) for trace in traces)
        return titles + [
            go.layout.Annotation(
                text=f"{status}<br>{shown_note}", x=0.0, y=-0.02, xref="paper", yref="paper",
                xanchor="left", yanchor="top", showarrow=False, align="left", font={"size": 12},
            )
        ]

    frames = []
    for k in range(steps + 1):
        data = [
            go.Scatter3d(
                **dict(zip("xyz", trace.aligned(min(k, trace.iterations))[source_shown].astype(np.float32).T))
            )
            for trace in traces
        ]
        frames.append(go.Frame(name=str(k), data=data, traces=aligned_index, layout={"annotations": annotations(k)}))
    figure.frames = frames
    slider_steps = [
        {
            "label": str(k), "method": "animate",
            "args": [[str(k)], {"mode": "immediate", "frame": {"duration": 0, "redraw": True}, "transition": {"duration": 0}}],
        }
        for k in range(steps + 1)
    ]
    meta = {
        "esmicp_view": 1,
        "methods": [trace.method for trace in traces],
        "start": [trace.start for trace in traces],
        "iterations": [trace.iterations for trace in traces],
        "poses": [[pose.tolist() for pose in trace.poses] for trace in traces],
        "verdicts": [trace.label for trace in traces],
        "points_source": len(first.source), "points_target": len(first.target),
        "shown_source": len(source_shown), "shown_target": len(target_shown),
    }
    heading = title or "esmicp registration"
    figure.update_layout(
        title={"text": f"{heading}<br><sup>start: {', '.join(sorted({t.start for t in traces}))}; "
               "slider: iterations (0 = start)</sup>"},
        annotations=annotations(opened),
        sliders=[{"active": opened, "steps": slider_steps, "currentvalue": {"prefix": "iteration "}, "y": -0.12, "pad": {"t": 40}}],
        margin={"l": 10, "r": 10, "t": 80, "b": 190},
        height=720, meta=meta, legend={"itemsizing": "constant"},
    )
    return figure


def view_html(
    source,
    target,
    *,
    method: str = "esm",
    compare: str | None = None,
    init=None,
    sigma: float | None = None,
    max_iterations: int = 100,
    max_display_points: int = DEFAULT_DISPLAY_POINTS,
    title: str | None = None,
    truth=None,
    shown_iteration: int = 0,
):
    """Register with ``method`` (and ``compare``, side by side) as :func:`esmicp.register` does
    (``init`` as there: None, the default, runs the global search) and return the viewer's plotly
    Figure (:func:`view_figure`), its slider over the local refinement's iterations (after a
    global search, from the search's pose); :func:`write_view` saves it as one HTML file. To show
    a pose as given, pass :func:`~esmicp.viz.trace.fixed_trace` to :func:`view_figure`."""
    methods = [method] if compare is None else [method, compare]
    traces = [
        trace_registration(source, target, method=name, init=init, sigma=sigma, max_iterations=max_iterations,
                           per_point=False)
        for name in methods
    ]
    return view_figure(
        traces, max_display_points=max_display_points, title=title, truth=truth, shown_iteration=shown_iteration
    )


#: id of the plot's element in the page, and of the JSON block holding the data.
PLOT_ID, DATA_ID = "esmicp-view", "esmicp-data"


def view_page(figure) -> str:
    """The viewer as one self-contained HTML page (plotly.js inlined). The page also carries
    ``figure.layout.meta`` (methods, poses per iteration, counts) as a JSON block with id
    :data:`DATA_ID`, for scripts."""
    html = figure.to_html(include_plotlyjs=True, full_html=True, div_id=PLOT_ID, auto_play=False)
    meta = figure.layout.meta
    if meta is not None:
        data = json.dumps(meta).replace("</", "<\\/")
        html = html.replace("</body>", f'<script type="application/json" id="{DATA_ID}">{data}</script>\n</body>', 1)
    return html


def write_view(figure, path, *, overwrite: bool = False) -> None:
    """Write :func:`view_page` to ``path`` atomically (refused if it exists, unless ``overwrite``)."""
    html = view_page(figure)
    with atomic_write(path, overwrite, mode="w") as handle:
        handle.write(html)
