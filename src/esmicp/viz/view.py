"""A self-contained interactive HTML viewer: the target and the source placed by a pose, in 3D.

The pose is one the caller holds (a 4x4 ``T_target_source``, or a registration result), drawn
without registering again; or, when none is given, the pose :func:`esmicp.register` finds. On
request (``show_run=True``) a slider steps through the local refinement's iterations, and a second
method can run side by side on the same input.

plotly.js is inlined in the page (no CDN, no server): it opens in any browser, offline. Large
clouds are thinned for display only, evenly over the scene (:func:`display_indices`), and the page
says so. ``figure.layout.meta`` holds the data as JSON: methods, poses, display counts (read by
the tests, handy for scripts).

Frames: every pose maps source coordinates into the target frame (``T_target_source``); the scene
is drawn in the target frame.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Literal

import numpy as np

from ..core.procrustes import apply, axis_bounds
from ..errors import InvalidInputError
from ..io.atomic import atomic_write
from ..metrics import rotation_error_deg, translation_error
from ..result import RegistrationResult
from ..types import as_count, as_points, as_transform
from ._deps import require
from .trace import RegistrationTrace, fixed_trace, start_name, trace_registration

#: Display resolution: the scene's largest extent is cut into this many cells per axis and one
#: point is drawn per occupied cell (:func:`display_indices`), about 2 screen pixels per cell in a
#: page 1,000 pixels wide. A cloud sparser than that is drawn whole.
DISPLAY_CELLS_ACROSS = 500

#: Most points drawn per cloud when the caller sets no limit (the page grows by about 16 bytes per
#: drawn point, on top of plotly.js's 4.7 MB).
DISPLAY_POINTS_CAP = 50_000

#: With ``show_run=True``: most source points drawn over all the slider's steps of one method,
#: when the caller sets no limit. Each step carries its own copy of the aligned source, about 16
#: bytes per point: at most about 6.5 MB of steps per method (KITTI 00 scans 1 -> 0, 31
#: iterations: 12,367 source points drawn, a page of 13 MB).
RUN_POINTS_BUDGET = 400_000

#: ``camera="auto"`` looks from above (an orthographic top view) when the target's extent along
#: ``up`` is at most this fraction of its widest horizontal extent. Chosen between the LiDAR scans
#: of KITTI 00 and Newer College (0.09-0.14, z up) and the 3DMatch fragments and the bunny
#: (0.66-0.99, y down / up); confirmed on small_gicp's LiDAR pair (0.16, 0.21: top) and the 100
#: 7-Scenes depth frames (0.47-0.95: oblique). Flat objects get the top view too (6 of 81
#: ModelNet40 shapes with y up, a keyboard at 0.03).
TOP_VIEW_RATIO = 0.25

#: The top view's box (plotly's ``aspectratio``; its orthographic zoom) fits the scene's area when
#: its side along the screen's height is this size: the box's faces span ``aspectratio / 2`` of
#: the area's height (measured in chromium on a page 1,100 x 760 pixels).
TOP_VIEW_FILL = 1.7
#: The width of a 3D scene's area over its height, as drawn in a window about 1,100 pixels wide
#: (a wider window leaves room on the sides).
SCENE_WIDTH_OVER_HEIGHT = 1.5

#: Colours: target, source as given, aligned source.
TARGET_COLOUR, START_COLOUR, ALIGNED_COLOUR = "#7f7f7f", "#ff9f40", "#1f5fbf"
#: Each cloud is shaded from dark (a surface edge-on to the light) to light (facing it), plotly
#: colour scales: target greys, aligned source blues. Flat colours make a dense cloud one blob.
TARGET_SHADES = [[0.0, "#3c3c3c"], [1.0, "#c8c8c8"]]
ALIGNED_SHADES = [[0.0, "#0b2d66"], [1.0, "#6fa8ff"]]
#: Neighbours of each drawn point (among the drawn points) whose PCA gives its normal for the
#: shading.
SHADING_NEIGHBOURS = 12

#: What ``camera`` and ``up`` accept.
Camera = Literal["auto", "top", "oblique"]
Up = Literal["x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z"]


def display_subset(count: int, limit: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``limit`` of ``count`` points (random, seeded; all if fewer)."""
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=limit, replace=False))


def display_indices(points, max_points: int | None = None) -> np.ndarray:
    """Sorted indices of the points of ``points`` to draw: evenly spread over the cloud's extent.

    The cloud's bounding box is cut into cubic cells, :data:`DISPLAY_CELLS_ACROSS` along its
    largest side, and the first point of each occupied cell is kept: the count follows the scene's
    extent against its point spacing (a small object of a few thousand points is drawn whole, a
    LiDAR scan 150 m across keeps about one point per 0.3 m wherever it has points, near the
    sensor as far from it). When more than ``max_points`` (default :data:`DISPLAY_POINTS_CAP`)
    cells are occupied, the cells grow until at most that many are.
    """
    points = as_points(points, "points", min_points=1)
    cap = DISPLAY_POINTS_CAP if max_points is None else as_count(max_points, "max_points")
    low, high = axis_bounds(points)
    extent = float(np.max(high - low))
    if extent == 0.0:
        return np.arange(min(len(points), cap))
    cell = extent / DISPLAY_CELLS_ACROSS
    kept = np.arange(len(points))
    while True:
        cells = np.floor((points[kept] - low) / cell).astype(np.int64)
        sizes = cells.max(axis=0) + 1
        keys = (cells[:, 0] * sizes[1] + cells[:, 1]) * sizes[2] + cells[:, 2]
        _, first = np.unique(keys, return_index=True)
        kept = kept[np.sort(first)]
        if len(kept) <= cap:
            return kept
        # Occupied cells of a surface scale as 1 / cell^2: grow by the square root of the excess,
        # the larger cells drawn from the points kept so far (one per smaller cell).
        cell *= max(math.sqrt(len(kept) / cap), 1.02)


def scatter_trace(go, points, name, colour, scene, size=2.0, opacity=0.8, showlegend=True, visible=True,
                  shades=None):
    """A plotly ``Scatter3d`` of ``(N, 3)`` points as markers of one colour, in the 3D ``scene``
    named (``"scene"``, ``"scene2"``, ...); ``go`` is ``plotly.graph_objects`` (imported by the
    caller through :func:`esmicp.viz.require`). Legend entries are grouped by ``name``;
    ``visible="legendonly"`` draws it only once its legend entry is clicked. ``shades``:
    ``(values in [0, 1], colour scale)`` colours each point along the scale instead."""
    points = np.asarray(points, dtype=np.float32)
    marker = {"size": size, "color": colour, "opacity": opacity}
    if shades is not None:
        values, scale = shades
        marker.update(color=np.asarray(values, dtype=np.float32), colorscale=scale, cmin=0.0, cmax=1.0,
                      showscale=False)
    return go.Scatter3d(
        x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", name=name, scene=scene,
        marker=marker, showlegend=showlegend, legendgroup=name, visible=visible,
    )


def shading(points, light) -> np.ndarray:
    """How much each point's surface faces ``light`` (a direction, 3 numbers), in [0, 1]:
    ``|n . light|`` with ``n`` the PCA normal of its :data:`SHADING_NEIGHBOURS` nearest points of
    ``points`` (unsigned: either side of a surface faces the light alike). All 1 for clouds too
    small to have normals."""
    from ..core.features import estimate_normals

    points = np.asarray(points, dtype=np.float64)
    light = np.asarray(light, dtype=np.float64)
    light = light / np.linalg.norm(light)
    if len(points) < SHADING_NEIGHBOURS:
        return np.ones(len(points))
    normals = estimate_normals(points, k=SHADING_NEIGHBOURS, workers=None)
    return np.abs(normals @ light)


def _up_axis(up) -> tuple[int, float]:
    """``(axis, sign)`` of an ``up`` such as ``"z"`` or ``"-y"``."""
    text = str(up).strip().lower()
    sign = -1.0 if text.startswith("-") else 1.0
    name = text.lstrip("+-")
    if name not in ("x", "y", "z") or len(text) - len(name) > 1:
        raise InvalidInputError(f"up: expected an axis of the target frame (x, y, z, -x, -y or -z), got {up!r}")
    return "xyz".index(name), sign


def scene_camera(target, *, camera: Camera = "auto", up: Up = "z") -> tuple[dict, str]:
    """The plotly scene camera for a scene in ``target``'s frame, and the view chosen (``"top"`` or
    ``"oblique"``).

    ``up`` is the target frame's axis that points up (``"z"`` for LiDAR and for plotly's default
    view, ``"-y"`` for a depth camera's frame): the caller declares it, the data cannot tell.
    ``"top"`` looks down ``up`` with an orthographic projection (a map of a street or a campus);
    ``"oblique"`` looks from above one side, in perspective; ``"auto"`` takes the top view when the
    target's extent along ``up`` is at most :data:`TOP_VIEW_RATIO` of its widest horizontal extent.
    """
    axis, sign = _up_axis(up)
    if camera not in ("auto", "top", "oblique"):
        raise InvalidInputError(f"camera: expected 'auto', 'top' or 'oblique', got {camera!r}")
    if camera == "auto":
        low, high = axis_bounds(as_points(target, "target", min_points=1))
        extents = high - low
        width = max(extents[(axis + 1) % 3], extents[(axis + 2) % 3])
        camera = "top" if width > 0 and extents[axis] <= TOP_VIEW_RATIO * width else "oblique"
    vertical = np.zeros(3)
    vertical[axis] = sign
    right, forward = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
    if camera == "top":
        # From above (z up: x to the right, y up the screen, as a map).
        eye, screen_up, projection = 2.0 * vertical, forward, "orthographic"
    else:
        eye, screen_up, projection = 1.25 * (right + forward + vertical), vertical, "perspective"
    view = {
        "eye": dict(zip("xyz", eye.tolist())), "up": dict(zip("xyz", screen_up.tolist())),
        "center": {"x": 0.0, "y": 0.0, "z": 0.0}, "projection": {"type": projection},
    }
    return view, camera


def _errors(pose, truth) -> str:
    if truth is None:
        return ""
    return (f"rotation error {rotation_error_deg(pose, truth):.3g} deg, "
            f"translation error {translation_error(pose, truth):.3g}")


def _status(trace: RegistrationTrace, k: int, truth) -> str:
    if not trace.steps:  # one pose, drawn as it is
        errors = _errors(trace.poses[-1], truth)
        return f"{trace.method or 'pose'}: {errors}" if errors else ""
    shown = min(k, trace.iterations)
    held = " (finished)" if k > trace.iterations else ""
    text = f"{trace.method}: iteration {shown}/{trace.iterations}{held}"
    if shown >= 1:
        step = trace.steps[shown - 1]
        text += f", RMS distance {step.rmse:.3g}"
        if step.sigma is not None:
            text += f", sigma {step.sigma:.3g}"
    if truth is not None:
        text += ", " + _errors(trace.poses[shown], truth)
    return text


def view_figure(
    traces: Sequence[RegistrationTrace],
    *,
    max_display_points: int | None = None,
    title: str | None = None,
    subtitle: str | None = None,
    truth=None,
    shown_iteration: int = 0,
    camera: Camera = "auto",
    up: Up = "z",
):
    """A plotly Figure: one 3D scene per trace (same clouds), side by side.

    Each scene draws the target (grey), the source placed by the trace's pose (blue) and, once its
    legend entry is clicked, the source as given (orange). When some trace holds iterations, a
    slider steps through them: step k shows every method after k iterations (a method that
    stopped earlier keeps its last pose, and its caption says so), and the page opens at step
    ``shown_iteration`` (clipped to the last). Traces of no iteration (:func:`fixed_trace`) are
    drawn at their one pose, with no slider.

    ``max_display_points``: most points drawn per cloud (default: :func:`display_indices`'s
    choice, at most :data:`DISPLAY_POINTS_CAP`, and with a slider :data:`RUN_POINTS_BUDGET` over
    its steps). ``truth`` (4x4 ``T_target_source``), when known, adds the pose errors to the
    captions. ``camera`` and ``up``: :func:`scene_camera`. ``subtitle`` replaces the line under
    the title.
    """
    go = require("plotly.graph_objects")
    subplots = require("plotly.subplots")
    if not traces:
        raise InvalidInputError("traces: need at least one registration to show")
    first = traces[0]
    for trace in traces[1:]:
        if not (np.array_equal(trace.source, first.source) and np.array_equal(trace.target, first.target)):
            raise InvalidInputError("traces: the methods shown side by side must have run on the same clouds")
    steps = max(trace.iterations for trace in traces)
    opened = min(as_count(shown_iteration, "shown_iteration", minimum=0), steps)
    source_cap = target_cap = max_display_points
    if max_display_points is None and steps > 0:
        source_cap = max(1, min(DISPLAY_POINTS_CAP, RUN_POINTS_BUDGET // (steps + 1)))
    source_shown = display_indices(first.source, source_cap)
    target_shown = display_indices(first.target, target_cap)
    source, target = first.source[source_shown], first.target[target_shown]
    view, chosen_view = scene_camera(first.target, camera=camera, up=up)
    eye = np.array([view["eye"][name] for name in "xyz"])
    # Lit from above, toward the first view's eye: in a top view walls darker than the ground.
    light = eye / np.linalg.norm(eye) + 2.0 * np.array([view["up"][name] for name in "xyz"]) * (chosen_view != "top")
    target_shades = shading(target, light)

    figure = subplots.make_subplots(
        rows=1, cols=len(traces), specs=[[{"type": "scene"}] * len(traces)],
        # Side by side, each verdict on a line of its own under its method (one line would overlap).
        subplot_titles=[trace.label if len(traces) == 1 else trace.label.replace("; ", "<br>", 1) for trace in traces],
        horizontal_spacing=0.02,
    )
    placed = [[apply(pose, source) for pose in trace.poses] for trace in traces]
    every = [target, source] + [points for poses in placed for points in poses]
    low = np.min([points.min(axis=0) for points in every], axis=0)
    high = np.max([points.max(axis=0) for points in every], axis=0)
    pad = 0.02 * max(float(np.max(high - low)), 1e-12)
    low, high = low - pad, high + pad
    aspect = (high - low) / np.max(high - low)
    axes = {f"{name}axis": {"range": [lo, hi], "title": name} for name, lo, hi in zip("xyz", low, high)}
    if chosen_view == "top":
        # An orthographic view's zoom is its box's size: fit the box's horizontal face to the
        # scene's area, then drop the vertical axis's labels, which would all print at one spot.
        vertical = _up_axis(up)[0]
        across, along = aspect[(vertical + 1) % 3], aspect[(vertical + 2) % 3]
        aspect = aspect * TOP_VIEW_FILL * min(1.0 / along, SCENE_WIDTH_OVER_HEIGHT / across)
        axes["xyz"[vertical] + "axis"].update(showticklabels=False, title="")
    aligned_index = []
    for column, (trace, poses) in enumerate(zip(traces, placed), start=1):
        scene = "scene" if column == 1 else f"scene{column}"
        legend = column == 1
        # The source's normals turn with it: shaded as placed at the trace's last pose.
        source_shades = shading(poses[-1], light)
        figure.add_trace(scatter_trace(go, target, "target", TARGET_COLOUR, scene, showlegend=legend,
                                       shades=(target_shades, TARGET_SHADES)), 1, column)
        figure.add_trace(scatter_trace(go, source, "source (as given)", START_COLOUR, scene, 1.5, 0.35, legend,
                                       visible="legendonly"), 1, column)
        figure.add_trace(scatter_trace(go, poses[min(opened, trace.iterations)], "source (aligned)",
                                       ALIGNED_COLOUR, scene, showlegend=legend,
                                       shades=(source_shades, ALIGNED_SHADES)), 1, column)
        aligned_index.append(len(figure.data) - 1)
        # Fixed ranges at one scale on every axis: the clouds do not jump as the slider moves, and
        # are not distorted.
        figure.layout[scene].update(
            aspectmode="manual", aspectratio=dict(zip("xyz", aspect.tolist())), camera=view, **axes,
        )

    titles = list(figure.layout.annotations)
    thinned = len(target_shown) < len(first.target) or len(source_shown) < len(first.source)
    shown_note = (
        f"drawn: {len(target_shown):,} of {len(first.target):,} target points, {len(source_shown):,} of "
        f"{len(first.source):,} source points" + (" (thinned evenly for display)" if thinned else "")
        + "; click 'source (as given)' to show the source unmoved"
    )

    def annotations(k):
        status = "<br>".join(text for text in (_status(trace, k, truth) for trace in traces) if text)
        return titles + [
            go.layout.Annotation(
                text=f"{status}<br>{shown_note}" if status else shown_note, x=0.0, y=-0.02, xref="paper",
                yref="paper", xanchor="left", yanchor="top", showarrow=False, align="left", font={"size": 12},
            )
        ]

    layout = {}
    if steps > 0:
        frames = []
        for k in range(steps + 1):
            data = [go.Scatter3d(**dict(zip("xyz", poses[min(k, trace.iterations)].astype(np.float32).T)))
                    for trace, poses in zip(traces, placed)]
            frames.append(go.Frame(name=str(k), data=data, traces=aligned_index,
                                   layout={"annotations": annotations(k)}))
        figure.frames = frames
        slider_steps = [
            {
                "label": str(k), "method": "animate",
                "args": [[str(k)], {"mode": "immediate", "frame": {"duration": 0, "redraw": True},
                                    "transition": {"duration": 0}}],
            }
            for k in range(steps + 1)
        ]
        layout["sliders"] = [{"active": opened, "steps": slider_steps, "currentvalue": {"prefix": "iteration "},
                              "y": -0.12, "pad": {"t": 40}}]
        if subtitle is None:
            subtitle = f"start: {', '.join(sorted({t.start for t in traces}))}; slider: iterations (0 = start)"
    meta = {
        "esmicp_view": 1,
        "methods": [trace.method for trace in traces],
        "start": [trace.start for trace in traces],
        "iterations": [trace.iterations for trace in traces],
        "poses": [[pose.tolist() for pose in trace.poses] for trace in traces],
        "verdicts": [trace.label for trace in traces],
        "points_source": len(first.source), "points_target": len(first.target),
        "shown_source": len(source_shown), "shown_target": len(target_shown),
        "camera": chosen_view,
    }
    heading = title or "esmicp registration"
    figure.update_layout(
        title={"text": heading + (f"<br><sup>{subtitle}</sup>" if subtitle else ""), "y": 0.975, "yanchor": "top"},
        annotations=annotations(opened),
        margin={"l": 10, "r": 10, "t": 80 if len(traces) == 1 else 105, "b": 190 if steps > 0 else 90},
        height=720, meta=meta, legend={"itemsizing": "constant"}, **layout,
    )
    return figure


def given_pose(transformation) -> tuple[np.ndarray, RegistrationResult | None, str]:
    """``(T_target_source, result, label)`` of what a caller holds: a 4x4 array-like, an
    :class:`esmicp.RegistrationResult` (its verdict then captions the view), or another library's
    result holding its pose in ``transformation`` (Open3D) or ``T_target_source`` (small_gicp)."""
    if isinstance(transformation, RegistrationResult):
        return as_transform(transformation.transformation, "transformation"), transformation, ""
    for attribute in ("transformation", "T_target_source"):
        if not isinstance(transformation, (np.ndarray, list, tuple)) and hasattr(transformation, attribute):
            pose = as_transform(np.asarray(getattr(transformation, attribute)), f"transformation.{attribute}")
            facts = [f"{name.replace('_', ' ')} {getattr(transformation, name):.3g}"
                     for name in ("fitness", "inlier_rmse") if isinstance(getattr(transformation, name, None), float)]
            kind = type(transformation).__name__
            return pose, None, f"given {kind}" + (f" ({', '.join(facts)})" if facts else "")
    return as_transform(transformation, "transformation"), None, "given pose"


def view_html(
    source,
    target,
    transformation=None,
    *,
    show_run: bool = False,
    method: str = "esm",
    compare: str | None = None,
    init=None,
    sigma: float | None = None,
    max_iterations: int = 100,
    max_display_points: int | None = None,
    title: str | None = None,
    truth=None,
    shown_iteration: int | None = None,
    camera: Camera = "auto",
    up: Up = "z",
):
    """The viewer of a pose as a plotly Figure (:func:`write_view` saves it as one HTML page).

    Parameters
    ----------
    source, target : (N, 3) / (M, 3) array-like, or cloud objects with ``points``
        The clouds as given (an ``open3d.geometry.PointCloud`` works). The scene is the target's
        frame.
    transformation : optional
        The pose to draw, not registered again: a 4x4 ``T_target_source`` (it maps source
        coordinates into the target frame), an :class:`esmicp.RegistrationResult` (its method,
        iterations and confidence verdict caption the view), or another library's result with the
        pose in ``transformation`` (Open3D's) or ``T_target_source`` (small_gicp's). None (the
        default): register with ``method`` as :func:`esmicp.register` does (``init``, ``sigma``,
        ``max_iterations`` as there; ``init=None`` runs the global search) and draw its pose.
    show_run : bool
        Only when registering: draw the local refinement's iterations too, with a slider (after a
        global search, from the search's pose); the page opens at step ``shown_iteration``
        (default 0, the start; a large value: the last).
    compare : str, optional
        Only when registering: a second method, registered on the same clouds and drawn side by
        side.
    max_display_points : int, optional
        Most points drawn per cloud; default :func:`display_indices`'s choice (more for a large
        scene, at most :data:`DISPLAY_POINTS_CAP`). Registration always runs on every point.
    title : str, optional
    truth : (4, 4) array-like, optional
        The true ``T_target_source``, when known: the captions add the pose errors.
    camera, up
        The first view (:func:`scene_camera`): ``"auto"`` looks from above at a scene much wider
        than tall along ``up`` (a LiDAR scan), obliquely at others; ``up`` is the target frame's
        upward axis (``"z"``, or ``"-y"`` for a depth camera's frame).

    Returns
    -------
    plotly.graph_objects.Figure
        Its ``layout.meta`` holds the data (:func:`view_figure`) and ``registered``: whether a
        registration ran here.

    Raises
    ------
    InvalidInputError
        ``show_run``, ``compare`` or ``shown_iteration`` with a given ``transformation`` (a pose
        holds no run; register to draw one), ``shown_iteration`` without ``show_run``, or bad
        clouds, pose, ``camera`` or ``up``.
    """
    source_points, target_points = as_points(source, "source"), as_points(target, "target")
    scene_camera(target_points, camera=camera, up=up)  # bad camera / up: refused before any work
    if shown_iteration is not None and not show_run:
        raise InvalidInputError("shown_iteration: a step of the registration run; pass show_run=True to draw the run")
    if transformation is not None:
        for name, value in (("show_run", show_run), ("compare", compare), ("shown_iteration", shown_iteration)):
            if value:
                raise InvalidInputError(f"{name}: a given transformation holds no registration run to draw; "
                                        "call view_html(source, target, show_run=True) to register and draw one")
        pose, result, label = given_pose(transformation)
        trace = fixed_trace(source_points, target_points, pose, label, result)
        figure = view_figure(
            [trace], max_display_points=max_display_points, title=title, truth=truth, camera=camera, up=up,
            subtitle=f"the source placed by the {'pose' if result is None else 'result'} given (not registered here)",
        )
        figure.layout.meta = {**figure.layout.meta, "registered": False}
        return figure
    methods = [method] if compare is None else [method, compare]
    if show_run:
        traces = [
            trace_registration(source_points, target_points, method=name, init=init, sigma=sigma,
                               max_iterations=max_iterations, per_point=False)
            for name in methods
        ]
    else:
        from ..api import register

        traces = []
        for name in methods:
            result = register(source_points, target_points, method=name, init=init, sigma=sigma,
                              max_iterations=max_iterations)
            traces.append(RegistrationTrace(name, start_name(result), source_points, target_points,
                                            (result.transformation,), (), result))
    figure = view_figure(
        traces, max_display_points=max_display_points, title=title, truth=truth,
        shown_iteration=shown_iteration or 0, camera=camera, up=up,
        subtitle=None if show_run else "the source placed by esmicp.register's pose",
    )
    figure.layout.meta = {**figure.layout.meta, "registered": True}
    return figure


def view(source, target, transformation=None, *, renderer: str | None = None, **options):
    """Show :func:`view_html`'s figure (same arguments) where plotly shows figures: inline in a
    notebook, else in the default web browser (plotly's ``renderer`` to choose another); return
    the figure. Like Open3D's ``draw_geometries``, for a session; :func:`write_view` keeps a page."""
    figure = view_html(source, target, transformation, **options)
    figure.show(renderer=renderer)
    return figure


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
