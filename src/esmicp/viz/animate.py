"""The alignment as an animation (matplotlib, rendered headlessly on the Agg canvas): frame k
shows the target and the source after k iterations, so a run of n iterations has n + 1 frames."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..io.atomic import atomic_write
from ..metrics import rotation_error_deg
from ..types import as_count, as_positive
from ._deps import new_figure, require
from .trace import RegistrationTrace, trace_registration
from .view import TARGET_COLOUR, display_subset

#: Default cap on the points drawn per cloud (keeps GIFs small).
DEFAULT_DISPLAY_POINTS = 1500

#: Output formats :func:`write_animation` knows, by extension.
ANIMATION_EXTENSIONS = (".gif", ".mp4")


def animation_figure(
    trace: RegistrationTrace,
    *,
    max_display_points: int = DEFAULT_DISPLAY_POINTS,
    title: str | None = None,
    truth=None,
    fps: float = 4.0,
):
    """A ``matplotlib.animation.FuncAnimation`` of ``trace``: ``trace.iterations + 1`` frames.

    The aligned source is coloured by the weight its pair had in the next iteration (the current
    one for the last frame; 1 everywhere for ``icp``). ``truth`` adds the rotation error.
    """
    animation = require("matplotlib.animation")
    max_display_points = as_count(max_display_points, "max_display_points")
    fps = as_positive(fps, "fps")
    source_shown = display_subset(len(trace.source), max_display_points, seed=1)
    target_shown = display_subset(len(trace.target), max_display_points, seed=2)
    figure = new_figure(4.8, 4.6, dpi=80)
    axes = figure.add_subplot(projection="3d")
    every = [trace.target, trace.source] + [trace.aligned(k) for k in range(trace.iterations + 1)]
    low = np.min([p.min(axis=0) for p in every], axis=0)
    high = np.max([p.max(axis=0) for p in every], axis=0)
    centre, half = (low + high) / 2, max(float(np.max(high - low)) / 2, 1e-12)
    target = trace.target[target_shown]
    axes.scatter(*target.T, s=2, c=TARGET_COLOUR, alpha=0.5, depthshade=False, label="target")
    start = trace.aligned(0)[source_shown]
    moving = axes.scatter(*start.T, s=3, c=np.ones(len(start)), cmap="viridis", vmin=0, vmax=1,
                          depthshade=False, label="source")
    for setter, c in zip((axes.set_xlim, axes.set_ylim, axes.set_zlim), centre):
        setter(c - half, c + half)
    axes.set_box_aspect((1, 1, 1))
    axes.tick_params(labelsize=6)
    axes.legend(loc="lower left", fontsize=7)
    colorbar = figure.colorbar(moving, ax=axes, shrink=0.6, pad=0.08)
    colorbar.set_label("weight of the source point's pair", fontsize=7)
    colorbar.ax.tick_params(labelsize=6)
    heading = figure.suptitle("", fontsize=8)
    shown = "" if len(source_shown) == len(trace.source) else f" ({len(source_shown)} of {len(trace.source)} source points shown)"

    def draw(k: int):
        points = trace.aligned(k)[source_shown]
        moving._offsets3d = tuple(points.T)
        step = trace.steps[min(k, trace.iterations - 1)] if trace.iterations else None
        if step is not None:
            moving.set_array(step.weights[source_shown])
        text = f"{title or 'esmicp'}{shown}\n{trace.method} from {trace.start}: iteration {k}/{trace.iterations}"
        if k >= 1:
            sigma = "" if trace.steps[k - 1].sigma is None else f", sigma {trace.steps[k - 1].sigma:.3g}"
            text += f"\nRMS distance {trace.steps[k - 1].rmse:.3g}{sigma}"
        if truth is not None:
            text += f", rotation error {rotation_error_deg(trace.poses[k], truth):.3g} deg"
        heading.set_text(text)
        return moving, heading

    return animation.FuncAnimation(
        figure, draw, frames=trace.iterations + 1, interval=1000.0 / fps, blit=False, repeat=True
    )


def animate(
    source,
    target,
    *,
    method: str = "esm",
    init="identity",
    sigma: float | None = None,
    max_iterations: int = 100,
    max_display_points: int = DEFAULT_DISPLAY_POINTS,
    title: str | None = None,
    truth=None,
    fps: float = 4.0,
):
    """Register with ``method`` from ``init`` and return the animation (:func:`animation_figure`);
    in a notebook show it with ``IPython.display.HTML(animation.to_jshtml())``, save it with
    :func:`write_animation`."""
    trace = trace_registration(source, target, method=method, init=init, sigma=sigma, max_iterations=max_iterations)
    return animation_figure(trace, max_display_points=max_display_points, title=title, truth=truth, fps=fps)


def write_animation(animation, path, *, overwrite: bool = False, fps: float = 4.0) -> None:
    """Save ``animation`` as a GIF (Pillow) or, where an ffmpeg writer exists, an MP4; atomically.

    Raises :class:`~esmicp.errors.InvalidInputError` for another extension, or for ``.mp4``
    without ffmpeg.
    """
    matplotlib_animation = require("matplotlib.animation")
    path = Path(path)
    extension = path.suffix.lower()
    if extension not in ANIMATION_EXTENSIONS:
        raise InvalidInputError(f"{path}: unsupported animation extension {extension!r}; use .gif or .mp4")
    fps = as_positive(fps, "fps")
    if extension == ".gif":
        writer = matplotlib_animation.PillowWriter(fps=fps)
    elif matplotlib_animation.writers.is_available("ffmpeg"):
        writer = matplotlib_animation.FFMpegWriter(fps=fps)
    else:
        raise InvalidInputError(f"{path}: writing .mp4 needs ffmpeg on the PATH (not found); write a .gif instead")
    with atomic_write(path, overwrite) as handle, tempfile.TemporaryDirectory(prefix="esmicp-anim-") as scratch:
        rendered = os.path.join(scratch, f"animation{extension}")
        animation.save(rendered, writer=writer)
        with open(rendered, "rb") as finished:
            handle.write(finished.read())
