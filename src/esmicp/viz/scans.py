"""The merged model of many scans, coloured by scan, as an interactive 3D view.

A few scans get one legend entry each (click to hide one); many scans would bury the model under
a legend of that many lines, so they are drawn as one cloud coloured by scan index along a colour
scale, with a colour bar, and each point's hover text names its scan.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from ..io.palette import scan_palette
from ..types import as_count
from ._deps import require
from .view import display_indices

#: Up to this many scans, one legend entry (and one palette colour, as in the merged cloud's file)
#: per scan; beyond, one cloud on a colour scale by scan index.
LEGEND_SCANS = 12
#: Points drawn per scan at most, and in all (the page stays a few MB and turns smoothly in a
#: browser): each scan gets ``min(VIEW_POINTS_PER_SCAN, VIEW_POINTS_TOTAL // scans)``, at least
#: ``VIEW_POINTS_MIN_PER_SCAN``.
VIEW_POINTS_PER_SCAN, VIEW_POINTS_TOTAL, VIEW_POINTS_MIN_PER_SCAN = 3000, 100_000, 300
#: The colour scale of many scans (plotly's name): perceptually ordered, so neighbouring indices
#: (consecutive frames of a walk) read as neighbours.
COLOUR_SCALE = "Turbo"


def _hex(colour) -> str:
    return "#{:02x}{:02x}{:02x}".format(*(int(c) for c in colour))


def merged_scans_figure(points, scan_index, names, *, title: str | None = None,
                        legend_scans: int = LEGEND_SCANS):
    """A plotly Figure of a merged cloud coloured by scan.

    Parameters
    ----------
    points : (N, 3) array_like
        The merged cloud, in the world frame.
    scan_index : (N,) array_like of int
        The scan of each point (``MultiRegistrationResult.merged``'s labels).
    names : sequence of str
        Every scan's name, indexed by scan index (shown in the legend or the hover text).
    title : str, optional
    legend_scans : int
        Up to this many scans in the cloud: one trace and legend entry per scan, in the colours of
        :func:`esmicp.io.scan_palette` (those of the merged cloud ``esmicp merge`` writes). More:
        one trace on the colour scale :data:`COLOUR_SCALE` by scan index, a colour bar, no legend.

    Returns
    -------
    plotly.graph_objects.Figure
        Its ``layout.meta``: ``scans`` (the scan indices drawn), ``shown`` (points drawn per scan),
        ``legend`` (whether each scan has its entry).
    """
    go = require("plotly.graph_objects")
    points = np.asarray(points, dtype=np.float64)
    labels = np.asarray(scan_index)
    if points.ndim != 2 or points.shape[1] != 3 or labels.shape != (len(points),):
        raise InvalidInputError(f"points, scan_index: expected (N, 3) points and (N,) scan indices, got "
                                f"{points.shape} and {labels.shape}")
    legend_scans = as_count(legend_scans, "legend_scans", minimum=0)
    names = [str(name) for name in names]
    scans = sorted(set(labels.tolist()))
    if scans and not 0 <= scans[0] <= scans[-1] < len(names):
        raise InvalidInputError(f"scan_index: expected indices into names (0..{len(names) - 1}), got "
                                f"{scans[0]}..{scans[-1]}")
    per_scan = max(VIEW_POINTS_MIN_PER_SCAN, min(VIEW_POINTS_PER_SCAN, VIEW_POINTS_TOTAL // max(len(scans), 1)))
    shown = {}
    for k in scans:
        mine = np.flatnonzero(labels == k)
        shown[k] = mine[display_indices(points[mine], per_scan)]
    figure = go.Figure()
    legend = len(scans) <= legend_scans
    if legend:
        colours = scan_palette(len(names))
        for k in scans:
            mine = points[shown[k]].astype(np.float32)
            figure.add_trace(go.Scatter3d(
                x=mine[:, 0], y=mine[:, 1], z=mine[:, 2], mode="markers", name=f"{k}: {names[k]}",
                marker={"size": 2.0, "color": _hex(colours[k]), "opacity": 0.8},
            ))
    elif scans:
        order = np.concatenate([shown[k] for k in scans])
        drawn = points[order].astype(np.float32)
        index = labels[order]
        figure.add_trace(go.Scatter3d(
            x=drawn[:, 0], y=drawn[:, 1], z=drawn[:, 2], mode="markers", name="scans", showlegend=False,
            customdata=index, hovertext=[f"{k}: {names[k]}" for k in index.tolist()],
            hovertemplate="scan %{hovertext}<br>x %{x:.4g}, y %{y:.4g}, z %{z:.4g}<extra></extra>",
            marker={"size": 2.0, "color": index, "colorscale": COLOUR_SCALE, "cmin": 0,
                    "cmax": max(len(names) - 1, 1), "opacity": 0.8,
                    "colorbar": {"title": {"text": "scan"}, "thickness": 15}},
        ))
    heading = title or "esmicp merge: merged model coloured by scan"
    subtitle = (f"{len(scans)} scans; click a legend entry to hide its scan" if legend else
                f"{len(scans)} scans, coloured by scan index; hover a point for its scan")
    figure.update_layout(
        title={"text": f"{heading}<br><sup>{subtitle} (subsampled for display)</sup>"},
        scene={"aspectmode": "data"}, showlegend=legend, legend={"itemsizing": "constant"},
        meta={"scans": scans, "shown": [len(shown[k]) for k in scans], "legend": legend},
    )
    return figure
