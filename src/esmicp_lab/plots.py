"""Plots of benchmark rows (the JSON Lines rows ``esmicp bench`` writes, one per trial and method).

Each plot has a function returning the matplotlib Figure; :func:`write_bench_plots` writes them
all as PNG files. What counts:

- rows with ``status == "unavailable"`` (missing library or weights) are left out of every plot
  and listed under it; ``failed`` and ``timeout`` rows count as unsuccessful trials in success
  rates, and have no error or time to draw;
- rows whose ``sigma`` is set belong to a sigma sweep: only :func:`sigma_sweep_figure` uses them,
  the other plots use the rows with ``sigma`` null (each method's own choice);
- translation errors are drawn as a percentage of the target's bounding-box diagonal, so that
  datasets in different units can share an axis.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from esmicp.errors import InvalidInputError, OutputExistsError, PointCloudFileError
from esmicp.viz._deps import new_figure
from esmicp.viz.files import save_figure

#: Keys the plots read (the bench row schema has more).
REQUIRED_KEYS = (
    "method", "protocol", "dataset", "status", "sigma", "initial_rotation_deg", "rotation_error_deg",
    "translation_error", "diagonal", "success_strict", "success_symmetry", "time_s",
)

#: The success criteria a plot can use.
SUCCESS_KEYS = ("success_strict", "success_symmetry")

#: Errors below this are drawn at it on the log axes (exact recoveries reach 1e-14).
ERROR_FLOOR = 1e-6

#: File names written by :func:`write_bench_plots`.
PLOT_FILES = {
    "success_vs_angle": "success_vs_angle.png",
    "errors": "errors.png",
    "time": "time.png",
    "sigma_sweep": "sigma_sweep.png",
}

#: Success thresholds of ``success_strict`` (drawn as lines on the error plots).
STRICT_ROTATION_DEG, STRICT_TRANSLATION_PERCENT = 2.0, 2.0


def check_rows(rows: Iterable[dict]) -> list[dict]:
    """The rows as a list, each checked to hold the keys the plots read."""
    checked = []
    for number, row in enumerate(rows):
        if not isinstance(row, dict):
            raise InvalidInputError(f"rows[{number}]: expected a dict (one benchmark row), got {type(row).__name__}")
        missing = [key for key in REQUIRED_KEYS if key not in row]
        if missing:
            raise InvalidInputError(
                f"rows[{number}] ({row.get('trial_id', '?')}, {row.get('method', '?')}): missing key(s) "
                f"{', '.join(missing)} of the benchmark row schema"
            )
        checked.append(row)
    if not checked:
        raise InvalidInputError("rows: no benchmark rows to plot")
    return checked


def read_bench_rows(path) -> list[dict]:
    """Read the rows file of an ``esmicp bench`` run (its reader: blank lines and a torn last line
    skipped, errors name the line), checked against the row schema."""
    from .bench.results import read_rows

    path = Path(path)
    if not path.is_file():
        raise PointCloudFileError(path, "no such file")
    try:
        return check_rows(read_rows(path))
    except InvalidInputError as exc:
        raise PointCloudFileError(path, str(exc)) from None


def _ordered(values) -> list:
    return list(dict.fromkeys(values))


def _available(rows: list[dict]) -> list[dict]:
    return [row for row in rows if row["status"] != "unavailable"]


def _unavailable_note(rows: list[dict]) -> str:
    missing = _ordered(row["method"] for row in rows if row["status"] == "unavailable")
    if not missing:
        return ""
    counts = ", ".join(f"{m} ({sum(r['method'] == m and r['status'] == 'unavailable' for r in rows)} rows)" for m in missing)
    return f"not drawn (status unavailable): {counts}"


def _fixed(rows: list[dict]) -> list[dict]:
    return [row for row in rows if row["sigma"] is None]


def _succeeded(row: dict, success_key: str) -> bool:
    return row["status"] == "ok" and bool(row[success_key])


def _check_success_key(success_key: str) -> None:
    if success_key not in SUCCESS_KEYS:
        raise InvalidInputError(f"success_key: expected one of {', '.join(SUCCESS_KEYS)}, got {success_key!r}")


def _footer(figure, rows: list[dict], extra: str = "") -> None:
    notes = [note for note in (extra, _unavailable_note(rows)) if note]
    if notes:
        figure.text(0.01, 0.005, "\n".join(notes), fontsize=7, va="bottom", ha="left", color="#444444")


def success_vs_angle_figure(rows, *, bin_deg: float = 30.0, success_key: str = "success_strict"):
    """Success rate against the initial rotation angle, one curve per method, one panel per
    protocol. Bins of ``bin_deg`` degrees over [0, 180]; each point is the fraction of that bin's
    trials the method solved (``failed`` / ``timeout`` rows count as unsolved)."""
    _check_success_key(success_key)
    rows = check_rows(rows)
    drawn = _available(_fixed(rows))
    protocols = _ordered(row["protocol"] for row in drawn) or ["(none)"]
    figure = new_figure(4.2 * len(protocols) + 0.6, 3.8)
    edges = np.arange(0.0, 180.0 + bin_deg, bin_deg)
    edges[-1] = max(edges[-1], 180.0 + 1e-9)
    centres = (edges[:-1] + edges[1:]) / 2
    axes_list = figure.subplots(1, len(protocols), sharey=True, squeeze=False)[0]
    for axes, protocol in zip(axes_list, protocols):
        for method in _ordered(row["method"] for row in drawn):
            chosen = [r for r in drawn if r["protocol"] == protocol and r["method"] == method]
            if not chosen:
                continue
            angles = np.array([r["initial_rotation_deg"] for r in chosen], dtype=float)
            solved = np.array([_succeeded(r, success_key) for r in chosen])
            which = np.clip(np.digitize(angles, edges) - 1, 0, len(centres) - 1)
            rates = [solved[which == b].mean() if np.any(which == b) else np.nan for b in range(len(centres))]
            axes.plot(centres, 100 * np.array(rates), marker="o", label=f"{method} (n={len(chosen)})")
        axes.set_title(f"protocol: {protocol}", fontsize=9)
        axes.set_xlabel("initial rotation (deg)")
        axes.set_xlim(0, 180)
        axes.set_xticks(edges[edges <= 180])
        axes.set_ylim(-3, 103)
        axes.grid(alpha=0.3)
        axes.legend(fontsize=7)
    axes_list[0].set_ylabel(f"success rate (%), {success_key}")
    figure.suptitle(f"Success rate vs initial rotation ({bin_deg:g}-degree bins)", fontsize=10)
    figure.tight_layout(rect=(0, 0.06, 1, 1))
    _footer(figure, rows)
    return figure


def _box(axes, groups: list[tuple[str, str, np.ndarray]], protocols: list[str], methods: list[str]):
    colours = [f"C{k}" for k in range(len(protocols))]
    width = 0.8 / max(len(protocols), 1)
    for method_index, method in enumerate(methods):
        for protocol_index, protocol in enumerate(protocols):
            values = [v for m, p, v in groups if m == method and p == protocol]
            if not values or len(values[0]) == 0:
                continue
            position = method_index + (protocol_index - (len(protocols) - 1) / 2) * width
            parts = axes.boxplot(
                [values[0]], positions=[position], widths=width * 0.9, patch_artist=True, showfliers=True,
                flierprops={"markersize": 2}, medianprops={"color": "black"},
            )
            for patch in parts["boxes"]:
                patch.set_facecolor(colours[protocol_index])
                patch.set_alpha(0.6)
    axes.set_xticks(range(len(methods)))
    axes.set_xticklabels(methods, rotation=20, fontsize=8, ha="right")
    axes.set_yscale("log")
    axes.grid(alpha=0.3, axis="y")
    return colours


def error_boxplots_figure(rows):
    """Box plots of the rotation error (deg) and the translation error (% of the target's
    diagonal) per method (x) and protocol (colour), over the ``ok`` rows."""
    rows = check_rows(rows)
    drawn = [r for r in _available(_fixed(rows)) if r["status"] == "ok" and r["rotation_error_deg"] is not None]
    methods = _ordered(r["method"] for r in drawn)
    protocols = _ordered(r["protocol"] for r in drawn)
    figure = new_figure(max(6.0, 1.1 * len(methods) * max(1, len(protocols)) ** 0.5 + 2), 7.0)
    rotation_axes, translation_axes = figure.subplots(2, 1)
    rotation_groups, translation_groups = [], []
    for method in methods:
        for protocol in protocols:
            chosen = [r for r in drawn if r["method"] == method and r["protocol"] == protocol]
            rotation = np.array([r["rotation_error_deg"] for r in chosen], dtype=float)
            translation = np.array(
                [100 * r["translation_error"] / r["diagonal"] for r in chosen if r["translation_error"] is not None],
                dtype=float,
            )
            rotation_groups.append((method, protocol, np.maximum(rotation, ERROR_FLOOR)))
            translation_groups.append((method, protocol, np.maximum(translation, ERROR_FLOOR)))
    colours = _box(rotation_axes, rotation_groups, protocols, methods)
    _box(translation_axes, translation_groups, protocols, methods)
    rotation_axes.axhline(STRICT_ROTATION_DEG, color="k", lw=0.8, ls="--")
    translation_axes.axhline(STRICT_TRANSLATION_PERCENT, color="k", lw=0.8, ls="--")
    rotation_axes.set_ylabel("rotation error (deg)")
    translation_axes.set_ylabel("translation error\n(% of target diagonal)")
    from matplotlib.patches import Patch

    rotation_axes.legend(
        [Patch(facecolor=c, alpha=0.6) for c in colours], [f"protocol {p}" for p in protocols], fontsize=7, loc="best"
    )
    figure.suptitle("Registration errors per method and protocol (dashed: strict-success threshold)", fontsize=10)
    figure.tight_layout(rect=(0, 0.05, 1, 1))
    _footer(figure, rows, f"log scales; errors below {ERROR_FLOOR:g} drawn at {ERROR_FLOOR:g}; status ok rows only")
    return figure


def time_figure(rows):
    """Box plots of the registration wall time per method (all protocols pooled), log scale,
    with each method's median written above its box."""
    rows = check_rows(rows)
    drawn = [r for r in _available(_fixed(rows)) if r["status"] == "ok" and r["time_s"] is not None]
    methods = _ordered(r["method"] for r in drawn)
    figure = new_figure(max(5.0, 1.2 * len(methods) + 2), 4.0)
    axes = figure.subplots()
    times = [np.array([r["time_s"] for r in drawn if r["method"] == m], dtype=float) * 1000 for m in methods]
    if methods:
        axes.boxplot(times, positions=range(len(methods)), widths=0.6, flierprops={"markersize": 2},
                     medianprops={"color": "black"})
        for k, values in enumerate(times):
            axes.annotate(
                f"median {np.median(values):.3g} ms\n(n={len(values)})", (k, np.max(values)), xytext=(0, 4),
                textcoords="offset points", ha="center", fontsize=7,
            )
        axes.set_xticks(range(len(methods)))
        axes.set_xticklabels(methods, rotation=20, fontsize=8, ha="right")
    axes.set_yscale("log")
    axes.set_ylabel("time per registration (ms)")
    axes.grid(alpha=0.3, axis="y")
    figure.suptitle("Registration time per method (all protocols)", fontsize=10)
    figure.tight_layout(rect=(0, 0.06, 1, 1))
    _footer(figure, rows, "wall time of the registration call only; status ok rows")
    return figure


def sigma_sweep_figure(rows, *, success_key: str = "success_strict"):
    """The effect of sigma: success rate and median rotation error against the fixed sigma the
    method was given (cloud units), one curve per method and protocol (and dataset, when several),
    from the rows whose ``sigma`` is set."""
    _check_success_key(success_key)
    rows = check_rows(rows)
    sweep = [r for r in _available(rows) if r["sigma"] is not None]
    if not sweep:
        raise InvalidInputError("rows: no row has 'sigma' set, so there is no sigma sweep to plot")
    several = len(_ordered(r["dataset"] for r in sweep)) > 1
    figure = new_figure(9.5, 3.9)
    success_axes, error_axes = figure.subplots(1, 2)
    keys = _ordered((r["method"], r["protocol"], r["dataset"] if several else None) for r in sweep)
    for method, protocol, dataset in keys:
        chosen = [r for r in sweep if (r["method"], r["protocol"]) == (method, protocol)
                  and (dataset is None or r["dataset"] == dataset)]
        sigmas = sorted({float(r["sigma"]) for r in chosen})
        rates, errors = [], []
        for sigma in sigmas:
            at = [r for r in chosen if float(r["sigma"]) == sigma]
            rates.append(100 * np.mean([_succeeded(r, success_key) for r in at]))
            values = [r["rotation_error_deg"] for r in at if r["status"] == "ok" and r["rotation_error_deg"] is not None]
            errors.append(max(float(np.median(values)), ERROR_FLOOR) if values else np.nan)
        label = f"{method}, {protocol}" + (f", {dataset}" if dataset else "")
        success_axes.plot(sigmas, rates, marker="o", label=label)
        error_axes.plot(sigmas, errors, marker="o", label=label)
    for axes in (success_axes, error_axes):
        axes.set_xscale("log")
        axes.set_xlabel("sigma (cloud units)")
        axes.grid(alpha=0.3)
    success_axes.set_ylabel(f"success rate (%), {success_key}")
    success_axes.set_ylim(-3, 103)
    error_axes.set_yscale("log")
    error_axes.set_ylabel("median rotation error (deg)")
    success_axes.legend(fontsize=7)
    figure.suptitle("Effect of sigma (fixed-sigma rows)", fontsize=10)
    figure.tight_layout(rect=(0, 0.06, 1, 1))
    _footer(figure, rows)
    return figure


def figures(rows: Sequence[dict], *, success_key: str = "success_strict") -> dict:
    """All the plots as ``{name: Figure}`` (the sigma sweep only when some row has ``sigma`` set)."""
    rows = check_rows(rows)
    result = {
        "success_vs_angle": success_vs_angle_figure(rows, success_key=success_key),
        "errors": error_boxplots_figure(rows),
        "time": time_figure(rows),
    }
    if any(row["sigma"] is not None for row in rows):
        result["sigma_sweep"] = sigma_sweep_figure(rows, success_key=success_key)
    return result


def write_bench_plots(rows, out_dir, *, overwrite: bool = False, success_key: str = "success_strict") -> list[Path]:
    """Write the benchmark plots as PNG files in ``out_dir`` (created if missing; its parent must
    exist) and return their paths: :data:`PLOT_FILES` names, the sigma sweep only when some row
    has ``sigma`` set. Existing files are refused before anything is written, unless
    ``overwrite``; each file is written atomically."""
    rows = check_rows(rows)
    _check_success_key(success_key)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise PointCloudFileError(out_dir, "is not a folder, cannot write the plots there")
    if not out_dir.parent.is_dir():
        raise PointCloudFileError(out_dir, f"cannot write: the folder {str(out_dir.parent)!r} does not exist")
    names = list(PLOT_FILES) if any(row["sigma"] is not None for row in rows) else list(PLOT_FILES)[:3]
    paths = {name: out_dir / PLOT_FILES[name] for name in names}
    if not overwrite:
        for path in paths.values():
            if path.exists():
                raise OutputExistsError(path)
    drawn = figures(rows, success_key=success_key)
    out_dir.mkdir(exist_ok=True)
    for name, path in paths.items():
        save_figure(drawn[name], path, overwrite=overwrite)
    return list(paths.values())
