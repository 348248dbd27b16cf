"""The pictures the results pages open on, drawn from a benchmark's own records.

Each function takes plain records (dicts, arrays) as a benchmark script stores them and returns a
matplotlib Figure (Agg canvas, no pyplot state); :func:`write_picture` saves one as a PNG about
:data:`PICTURE_WIDTH_PX` pixels wide. matplotlib is imported only when a figure is drawn (the
``viz`` or ``bench`` extra).

- :func:`confidence_error_figure`: the rotation error of each registration (degrees, log axis)
  against its confidence, right and wrong results in two colours, trusted ones filled, the trust
  bar as a vertical line;
- :func:`success_bars_figure`: success rates of several methods, grouped by data kind or protocol;
- :func:`success_grid_figure`: the same as a grid (methods down, protocols across), for tables
  too wide for bars;
- :func:`merged_scans_figure`: scans placed by their poses, one colour per scan, in two views;
- :func:`trajectory_figure`: estimated scan positions against the true ones, seen from above.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from esmicp.errors import InvalidInputError
from esmicp.io.atomic import atomic_write
from esmicp.viz._deps import new_figure
from esmicp.viz.files import check_extension

#: Width of a results page's picture (pixels): a page's text column, drawn at :data:`PICTURE_DPI`.
PICTURE_WIDTH_PX = 900
#: Resolution the pictures are drawn at (dots per inch); the figure widths are in inches.
PICTURE_DPI = 100
#: Rotation errors below this (degrees) are drawn at it on the log axis (exact recoveries reach 1e-12).
ROTATION_FLOOR_DEG = 1e-3
#: Points drawn per scan in :func:`merged_scans_figure` (a seeded subset; enough to see a surface).
POINTS_PER_SCAN = 3000

RIGHT_COLOUR, WRONG_COLOUR, BAR_COLOUR = "#2a9d4b", "#d62728", "#333333"
#: Markers of the groups in :func:`confidence_error_figure`, in the order the groups first appear.
GROUP_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">")


def _records(records: Iterable[Mapping], keys: Sequence[str], what: str) -> list[Mapping]:
    checked = []
    for number, record in enumerate(records):
        missing = [key for key in keys if key not in record]
        if missing:
            raise InvalidInputError(f"{what}[{number}]: missing key(s) {', '.join(missing)}")
        checked.append(record)
    if not checked:
        raise InvalidInputError(f"{what}: nothing to draw")
    return checked


def confidence_error_figure(records: Iterable[Mapping], *, trust_bar: float, title: str, group=None):
    """Rotation error (degrees, log axis) against confidence, one point per registration.

    ``records``: dicts with ``confidence`` (0-1), ``rotation_error_deg``, ``success`` (right by the
    record's own criterion) and ``trusted`` (``result.trusted``: the confidence reaches the bar and
    nothing else casts doubt on the pose); ``group``: a function of a record giving its marker's
    label (None: one marker). Right results are green, wrong ones red; trusted ones filled, the
    others hollow; the vertical line is ``trust_bar``, the confidence below which no pose is
    trusted. The legend counts the results right, wrong, and trusted and wrong."""
    records = _records(records, ("confidence", "rotation_error_deg", "success", "trusted"), "records")
    figure = new_figure(PICTURE_WIDTH_PX / PICTURE_DPI, 4.2, PICTURE_DPI)
    axes = figure.subplots()
    labels = list(dict.fromkeys(group(r) for r in records)) if group else [None]
    markers = dict(zip(labels, GROUP_MARKERS * (len(labels) // len(GROUP_MARKERS) + 1)))
    for label in labels:
        for right in (True, False):
            for trusted in (True, False):
                chosen = [r for r in records if bool(r["success"]) == right and bool(r["trusted"]) == trusted
                          and (group is None or group(r) == label)]
                if not chosen:
                    continue
                x = np.array([float(r["confidence"]) for r in chosen])
                y = np.maximum(np.array([float(r["rotation_error_deg"]) for r in chosen]), ROTATION_FLOOR_DEG)
                colour = RIGHT_COLOUR if right else WRONG_COLOUR
                axes.scatter(x, y, s=24, marker=markers[label], facecolor=colour if trusted else "none",
                             edgecolor=colour, linewidth=0.9, alpha=0.85, zorder=3)
    axes.axvline(trust_bar, color=BAR_COLOUR, lw=1.2, ls="--", zorder=2)
    axes.set_yscale("log")
    axes.set_xlim(-0.03, 1.03)
    axes.set_xlabel("confidence (result.confidence)")
    axes.set_ylabel("rotation error (deg)")
    axes.grid(alpha=0.3, which="major", lw=0.4)
    axes.set_title(title, fontsize=10)
    right = sum(bool(r["success"]) for r in records)
    wrong_trusted = sum(not r["success"] and bool(r["trusted"]) for r in records)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=RIGHT_COLOUR, label=f"right ({right})"),
               Line2D([], [], ls="", marker="o", color=WRONG_COLOUR, label=f"wrong ({len(records) - right})"),
               Line2D([], [], ls="", marker="o", color="#777777", label="filled: trusted"),
               Line2D([], [], ls="", marker="o", markerfacecolor="none", color="#777777", label="hollow: not trusted"),
               Line2D([], [], color=BAR_COLOUR, ls="--", label=f"trust bar (confidence {trust_bar:g})"),
               Line2D([], [], ls="", label=f"trusted and wrong: {wrong_trusted}")]
    if group is not None and len(labels) > 1:
        handles += [Line2D([], [], ls="", marker=markers[label], color="#777777", markerfacecolor="none",
                           label=str(label)) for label in labels]
    axes.legend(handles=handles, fontsize=7.5, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    figure.tight_layout()
    return figure


def success_bars_figure(rates: Iterable[Mapping], *, title: str, ylabel: str = "success rate (%)"):
    """Grouped bars: one group per data kind or protocol (``group``), one bar per ``method`` in
    each, its height ``100 * successes / trials`` (written on it when there are at most 40 bars; a
    method that solved none has a mark on the axis). ``rates``: dicts with ``group``, ``method``,
    ``successes`` and ``trials`` (> 0)."""
    rates = _records(rates, ("group", "method", "successes", "trials"), "rates")
    for number, rate in enumerate(rates):
        if not 0 <= rate["successes"] <= rate["trials"] or rate["trials"] <= 0:
            raise InvalidInputError(f"rates[{number}]: successes {rate['successes']} of {rate['trials']} trials")
    groups = list(dict.fromkeys(r["group"] for r in rates))
    methods = list(dict.fromkeys(r["method"] for r in rates))
    figure = new_figure(PICTURE_WIDTH_PX / PICTURE_DPI, 4.0, PICTURE_DPI)
    axes = figure.subplots()
    found = {(r["group"], r["method"]): r for r in rates}
    present = {group: [m for m in methods if (group, m) in found] for group in groups}
    width = 0.84 / max(len(shown) for shown in present.values())
    palette = "tab10" if len(methods) <= 10 else "tab20"
    colours = [_palette_colour(palette, k) for k in range(len(methods))]
    labelled = len(found) <= 40
    for position, group in enumerate(groups):
        shown = present[group]
        for slot, method in enumerate(shown):
            index = methods.index(method)
            rate = found[group, method]
            x = position + (slot - (len(shown) - 1) / 2) * width
            height = 100.0 * rate["successes"] / rate["trials"]
            axes.bar(x, height, width * 0.92, color=colours[index], zorder=3)
            if height == 0:  # ran and solved none: a mark on the axis, so it is not taken for "not run"
                axes.plot([x], [0.8], marker="^", ms=3.5, color=colours[index], zorder=4, clip_on=False)
            if labelled:
                axes.text(x, height + 1.0, f"{height:.3g}%", ha="center", va="bottom", fontsize=6.5,
                          rotation=90 if width < 0.2 else 0)
    axes.set_xticks(range(len(groups)))
    axes.set_xticklabels(groups, fontsize=8, rotation=15 if len(groups) > 5 else 0)
    axes.set_ylim(0, 118)
    axes.set_yticks(range(0, 101, 20))
    axes.set_ylabel(ylabel)
    axes.grid(alpha=0.3, axis="y", zorder=0)
    axes.set_title(title, fontsize=10)
    from matplotlib.patches import Patch

    axes.legend([Patch(color=c) for c in colours], methods, fontsize=7, loc="upper left",
                bbox_to_anchor=(1.01, 1.0), frameon=False)
    figure.tight_layout()
    return figure


#: Colour map of :func:`success_grid_figure` (0% to 100%), and the grey of a cell not run.
GRID_COLOURS, NOT_RUN_COLOUR = "YlGn", "#e6e6e6"


def success_grid_figure(rates: Iterable[Mapping], *, title: str, legend: str = "success rate (%)"):
    """Success rates as a grid: one row per ``method`` (in the order they first appear), one column
    per ``group``, each cell coloured by its rate and labelled with it in percent; a pair not in
    ``rates``, or whose ``percent`` is None (not run, unavailable), is a grey cell with a dash.
    ``rates``: dicts with ``group``, ``method`` and ``percent`` (0-100 or None)."""
    rates = _records(rates, ("group", "method", "percent"), "rates")
    for number, rate in enumerate(rates):
        if rate["percent"] is not None and not 0.0 <= float(rate["percent"]) <= 100.0:
            raise InvalidInputError(f"rates[{number}]: percent {rate['percent']} outside 0-100")
    groups = list(dict.fromkeys(r["group"] for r in rates))
    methods = list(dict.fromkeys(r["method"] for r in rates))
    grid = np.full((len(methods), len(groups)), np.nan)
    for rate in rates:
        if rate["percent"] is not None:
            grid[methods.index(rate["method"]), groups.index(rate["group"])] = float(rate["percent"])
    height = 1.3 + 0.24 * len(methods)
    figure = new_figure(PICTURE_WIDTH_PX / PICTURE_DPI, height, PICTURE_DPI)
    axes = figure.subplots()
    from matplotlib import colormaps

    colours = colormaps[GRID_COLOURS].with_extremes(bad=NOT_RUN_COLOUR)
    image = axes.imshow(np.ma.masked_invalid(grid), cmap=colours, vmin=0.0, vmax=100.0, aspect="auto")
    for row, column in np.ndindex(grid.shape):
        value = grid[row, column]
        text = "-" if np.isnan(value) else f"{value:.0f}"
        dark = not np.isnan(value) and value > 60.0
        axes.text(column, row, text, ha="center", va="center", fontsize=7,
                  color="white" if dark else "black")
    axes.set_xticks(range(len(groups)))
    axes.set_xticklabels(groups, fontsize=8)
    axes.xaxis.tick_top()
    axes.set_yticks(range(len(methods)))
    axes.set_yticklabels(methods, fontsize=7.5)
    axes.tick_params(length=0)
    axes.set_title(title, fontsize=10, pad=24)
    bar = figure.colorbar(image, ax=axes, fraction=0.03, pad=0.02)
    bar.set_label(legend, fontsize=8)
    bar.ax.tick_params(labelsize=7)
    figure.tight_layout()
    return figure


def _palette_colour(name: str, index: int):
    from matplotlib import colormaps

    return colormaps[name](index % colormaps[name].N)


def _placed(cloud, pose) -> np.ndarray:
    cloud = np.asarray(cloud, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    return cloud @ pose[:3, :3].T + pose[:3, 3]


def merged_scans_figure(clouds: Sequence, poses: Sequence, names: Sequence[str], *, views, title: str,
                        points_per_scan: int = POINTS_PER_SCAN, seed: int = 0):
    """Scans placed by their poses (``poses[k]`` maps scan ``k``'s coordinates into the model's
    frame), one colour per scan, in one panel per view. ``views``: ``(title, horizontal axis,
    vertical axis)`` with axes 0, 1, 2 for the model frame's x, y, z; a scan whose pose is not
    finite (unplaced) is left out and named under the picture. Each scan is drawn as a seeded
    subset of ``points_per_scan`` points."""
    if not (len(clouds) == len(poses) == len(names)) or not len(clouds):
        raise InvalidInputError(f"clouds, poses, names: {len(clouds)}, {len(poses)}, {len(names)} (expected the same "
                                "number, at least one)")
    rng = np.random.default_rng(seed)
    figure = new_figure(PICTURE_WIDTH_PX / PICTURE_DPI, 4.4, PICTURE_DPI)
    panels = figure.subplots(1, len(views), squeeze=False)[0]
    placed, left_out = [], []
    for cloud, pose, name in zip(clouds, poses, names):
        if not np.isfinite(np.asarray(pose, dtype=np.float64)).all():
            left_out.append(str(name))
            continue
        cloud = np.asarray(cloud, dtype=np.float64)
        subset = cloud[rng.choice(len(cloud), min(points_per_scan, len(cloud)), replace=False)]
        placed.append((str(name), _placed(subset, pose)))
    colours = [f"C{k % 10}" for k in range(len(placed))]
    for axes, (view, horizontal, vertical) in zip(panels, views):
        for (name, points), colour in zip(placed, colours):
            axes.scatter(points[:, horizontal], points[:, vertical], s=0.3, color=colour, linewidths=0,
                         rasterized=True)
        axes.set_aspect("equal")
        axes.set_xticks([])
        axes.set_yticks([])
        axes.set_title(view, fontsize=9)
    from matplotlib.patches import Patch

    panels[-1].legend([Patch(color=c) for c in colours], [name for name, _ in placed], fontsize=7,
                      loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    figure.suptitle(title, fontsize=10)
    if left_out:
        figure.text(0.01, 0.01, "not placed: " + ", ".join(left_out), fontsize=7, color="#444444")
    figure.tight_layout()
    return figure


def top_view_axes(positions: np.ndarray) -> np.ndarray:
    """The two directions (rows of a 2x3 array) along which ``positions`` spread most: the plane
    a walk on a floor lies in, whatever the frame's up axis."""
    positions = np.asarray(positions, dtype=np.float64)
    centred = positions - positions.mean(axis=0)
    _, _, directions = np.linalg.svd(centred, full_matrices=False)
    return directions[:2]


def trajectory_figure(truth, estimates: Mapping[str, np.ndarray], *, title: str, unit: str = "m"):
    """Scan positions along a walk seen from above: the true positions (``truth``, N x 3) as a
    black line, each estimate of ``estimates`` (label: N x 3, rows of unplaced scans NaN) as a
    coloured line with dots, all in one frame, projected on the plane the true walk spans most
    (:func:`top_view_axes`). The first position is marked."""
    truth = np.asarray(truth, dtype=np.float64)
    if truth.ndim != 2 or truth.shape[1] != 3 or len(truth) < 2:
        raise InvalidInputError(f"truth: expected N x 3 positions, N >= 2, got shape {truth.shape}")
    for label, positions in estimates.items():
        if np.shape(positions) != truth.shape:
            raise InvalidInputError(f"estimates[{label!r}]: shape {np.shape(positions)}, expected {truth.shape}")
    axes_2d = top_view_axes(truth)
    origin = truth.mean(axis=0)
    figure = new_figure(PICTURE_WIDTH_PX / PICTURE_DPI, 5.0, PICTURE_DPI)
    axes = figure.subplots()
    flat = (truth - origin) @ axes_2d.T
    axes.plot(flat[:, 0], flat[:, 1], color="black", lw=2.2, label="ground truth", zorder=2)
    axes.scatter(flat[:1, 0], flat[:1, 1], s=60, marker="*", color="black", zorder=4, label="first scan")
    for index, (label, positions) in enumerate(estimates.items()):
        drawn = (np.asarray(positions, dtype=np.float64) - origin) @ axes_2d.T
        placed = np.isfinite(drawn).all(axis=1)
        axes.plot(drawn[:, 0], drawn[:, 1], color=f"C{index}", lw=1.0, marker="o", ms=2.5,
                  label=f"{label} ({placed.sum()} of {len(drawn)} placed)", zorder=3)
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel(f"({unit}) along the walk's main direction")
    axes.set_ylabel(f"({unit})")
    axes.grid(alpha=0.3, lw=0.4)
    axes.legend(fontsize=7.5, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    return figure


def write_picture(figure, path) -> Path:
    """Save ``figure`` as a PNG at ``path`` (replacing the picture a previous run drew there),
    with no time stamp or version in its metadata, so that the same records give the same file."""
    path = check_extension(path, (".png",), "picture")
    with atomic_write(path, overwrite=True) as handle:
        figure.savefig(handle, format="png", dpi=PICTURE_DPI, metadata={"Software": None})
    return path
