"""The refinement benchmark on the real scan pairs (its command line: ``benchmarks/scan_refinement.py``,
whose docstring states the protocol): the starts, the runs of ``esm``, ``esm-plane``, ``icp`` and
the peers from them, the tables, the picture and the page's section "Refinement on scans"."""

from __future__ import annotations

import statistics
from pathlib import Path

import numpy as np

import esmicp
from esmicp.core.procrustes import apply, to_matrix

from .real_pairs import load_pair, pair_errors, read_pairs

OURS = ("esm", "esm-plane", "icp")
PEERS = ("open3d-icp-p2l", "small-gicp")
#: The whole register() with a given refinement after its global search (global starts only).
PIPELINES = {"global+esm": "esm", "global+esm-plane": "esm-plane"}
REFERENCE = "open3d-icp-p2l"
LABELS = {"esm": "esm", "esm-plane": "esm-plane", "icp": "icp (esmicp)",
          "open3d-icp-p2l": "Open3D point-to-plane ICP", "small-gicp": "small_gicp GICP",
          "global+esm": "register() (its search, then its refinement)",
          "global+esm-plane": "register(method=\"esm-plane\") (its search, then esm-plane)"}
#: The picture's legend for the whole-call rows (the tables' labels are too long for it).
SHORT_LABELS = {"global+esm": "register()", "global+esm-plane": "register(method=\"esm-plane\")"}
#: (angle deg low, high; translation m low, high) of the perturbed starts, by kind family.
OFFSETS = {"3DMatch": (5.0, 5.0, 0.1, 0.1), "LiDAR": (5.0, 10.0, 0.2, 0.5)}
SECTION = "## Refinement on scans"
#: Where the generated tables of the section end and its notes (``--notes``) begin.
TABLES_END = "<!-- scan_refinement: end of the generated tables -->"


def family(kind: str) -> str:
    return "3DMatch" if "3DMatch" in kind else "LiDAR"


def perturbed(truth: np.ndarray, source: np.ndarray, kind: str, rng: np.random.Generator) -> np.ndarray:
    """``truth`` moved by a random rotation about the placed source's centroid and a translation."""
    low, high, near, far = OFFSETS[family(kind)]
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_rotvec(np.radians(rng.uniform(low, high)) * axis).as_matrix()
    direction = rng.normal(size=3)
    direction *= rng.uniform(near, far) / np.linalg.norm(direction)
    centre = apply(truth, source).mean(axis=0)
    return to_matrix(rotation, centre - rotation @ centre + direction) @ truth


def global_start(source: np.ndarray, target: np.ndarray, seed: int) -> tuple[np.ndarray, str]:
    """The default global search's pose, as :func:`esmicp.register` finds it (its working frame),
    and the strategy that found it."""
    from esmicp.core.correspondence import NearestNeighbors
    from esmicp.globalreg.search import global_estimate
    from esmicp.working_frame import WorkingFrame

    frame = WorkingFrame.for_target(target)
    moved_source, moved_target = frame.points(source), frame.points(target)
    index = NearestNeighbors(moved_target)
    found = global_estimate(moved_source, moved_target, rng=np.random.default_rng(seed), target_index=index,
                            target_spacing=index.spacing())
    return frame.transform_out(found.transformation), found.strategies[0]


def run(method: str, source, target, start, kind: str, iterations: int, seed: int = 0):
    """``(T_target_source, time_s, iterations or None)`` of ``method`` from ``start``; the
    ``global+`` methods ignore ``start`` and run the whole :func:`esmicp.register` (the global search
    with ``rng=seed``, then that method: what the default would do with it)."""
    if method in PIPELINES:
        result = esmicp.register(source, target, method=PIPELINES[method], rng=seed, max_iterations=iterations)
        return result.transformation, result.runtime_s, result.num_iterations
    if method in OURS:
        result = esmicp.register(source, target, method=method, init=start, max_iterations=iterations)
        return result.transformation, result.runtime_s, result.num_iterations
    from esmicp_lab.baselines import get_baseline

    voxel = 0.05 if family(kind) == "3DMatch" else 0.3
    result = get_baseline(method)(source, target, init=start, max_iterations=iterations, voxel_size=voxel)
    return np.asarray(result.transformation), result.runtime_s, None


def rows_for(folder: Path, seeds: int, seed: int, iterations: int, methods, with_global: bool, progress):
    rng_warm = np.random.default_rng(0)
    cloud = rng_warm.normal(size=(500, 3))
    for method in methods:
        run(method, cloud, cloud, np.eye(4), "LiDAR", 2, seed)
    for number, pair in enumerate(read_pairs(folder)):
        source, target, truth = load_pair(pair, bin_columns=3)
        starts = []
        for k in range(seeds):
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(number, k)))
            starts.append(("perturbed", k, perturbed(truth, source, pair.kind, rng), None))
        if with_global:
            starts.append(("global", 0, *global_start(source, target, seed)))
        for start_kind, k, start, strategy in starts:
            start_rotation, start_translation = pair_errors(start, truth)
            for method in methods:
                if method in PIPELINES and start_kind != "global":
                    continue
                estimate, runtime, used = run(method, source, target, start, pair.kind, iterations, seed)
                rotation_error, translation_error = pair_errors(estimate, truth)
                row = {"pair": pair.name, "kind": pair.kind, "family": family(pair.kind), "start": start_kind,
                       "seed": k, "strategy": strategy, "method": method, "start_rotation_deg": start_rotation,
                       "start_translation_m": start_translation, "rotation_deg": rotation_error,
                       "translation_m": translation_error,
                       "success": pair.criteria.success(rotation_error, translation_error),
                       "time_s": runtime, "iterations": used, "source_points": len(source),
                       "target_points": len(target)}
                progress(row)
                yield row


def _median(values) -> float:
    return float(statistics.median(values)) if values else float("nan")


def markdown(rows: list[dict], command: str, iterations: int) -> str:
    methods = [m for m in (*OURS, *PEERS, *PIPELINES) if any(r["method"] == m for r in rows)]
    lines = [SECTION, "", f"Generated by `benchmarks/scan_refinement.py` from one run of", "", "```bash", command,
             "```", "",
             "Local refinement only, every method from the same start with the same cap of "
             f"{iterations} iterations: `perturbed`, the ground truth moved by a seeded offset about the "
             "placed source's centroid (LiDAR 5-10° and 0.2-0.5 m, 3DMatch 5° and 0.1 m); `global`, the "
             "pose the default global search gives (before its refinement), handed to each method as a given "
             "start. esmicp methods: `esmicp.register(method=..., init=start)`, every other default (from a "
             "given start `esm` begins in its coarse phase, and runs no `esm-plane` stage); "
             "`register()` rows: the whole default call, its own search (the same pose, the same seed) and "
             "the refinement it runs after a search, its time with the search. The peers get the voxel their "
             "documentation recommends (0.05 m indoor, 0.3 m LiDAR) for normals / covariances (small_gicp also "
             "downsamples by it). Errors in the pair's frame against the stored ground truth; success by the kind's "
             "criteria (3DMatch 15° / 0.30 m, LiDAR 5° / 0.6 m). Time: the registration call (normals and "
             "index included), on a machine shared by several engineers: only the ratios within the run count.",
             "", "| family | start | method | success | median rotation error | median translation error | "
             "worst translation error | median time | time / Open3D p2l (median of per-trial ratios) |",
             "|---|---|---|---|---|---|---|---|---|"]
    reference = {(r["pair"], r["start"], r["seed"]): r["time_s"] for r in rows if r["method"] == REFERENCE}
    groups = (("perturbed", lambda r: r["start"] == "perturbed"), ("global", lambda r: r["start"] == "global"))
    for fam in ("3DMatch", "LiDAR"):
        for start, member in groups:
            for method in methods:
                chosen = [r for r in rows if r["family"] == fam and member(r) and r["method"] == method]
                if not chosen:
                    continue
                wins = sum(r["success"] for r in chosen)
                ratios = [r["time_s"] / reference[(r["pair"], r["start"], r["seed"])] for r in chosen
                          if (r["pair"], r["start"], r["seed"]) in reference]
                ratio = "-" if method == REFERENCE or method in PIPELINES else f"{_median(ratios):.2f}"
                lines.append(
                    f"| {fam} | {start} | {LABELS[method]} | {wins}/{len(chosen)} | "
                    f"{_median([r['rotation_deg'] for r in chosen]):.3f}° | "
                    f"{_median([r['translation_m'] for r in chosen]):.3f} m | "
                    f"{max(r['translation_m'] for r in chosen):.3f} m | {_median([r['time_s'] for r in chosen]):.2f} s | "
                    f"{ratio} |")
    lines += ["", "Per pair (median over the perturbed seeds; `global`: its one start, and the strategy that "
              "found it):", "",
              "| pair | start | " + " | ".join(LABELS[m] for m in methods) + " |",
              "|---|---|" + "---|" * len(methods)]
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    for pair in pairs:
        for start in ("perturbed", "global"):
            cells = []
            for method in methods:
                chosen = [r for r in rows if r["pair"] == pair and r["start"] == start and r["method"] == method]
                if not chosen:
                    cells.append("-")
                    continue
                cells.append(f"{sum(r['success'] for r in chosen)}/{len(chosen)} "
                             f"{_median([r['rotation_deg'] for r in chosen]):.2f}° "
                             f"{_median([r['translation_m'] for r in chosen]):.3f} m "
                             f"{_median([r['time_s'] for r in chosen]):.2f} s")
            if any(cell != "-" for cell in cells):
                strategy = next(r.get("strategy") for r in rows if r["pair"] == pair and r["start"] == start)
                label = f"{start} ({strategy})" if strategy else start
                lines.append(f"| {pair} | {label} | " + " | ".join(cells) + " |")
    lines += ["", TABLES_END]
    return "\n".join(lines) + "\n"


def picture(rows: list[dict], path: Path) -> Path:
    """The page's picture: the share of right results per kind of pair and start, one bar per
    method (the peers beside esmicp's), from the same rows as the tables."""
    from esmicp_lab.figures import success_bars_figure, write_picture

    counts: dict[tuple[str, str], list[bool]] = {}
    for row in rows:
        label = SHORT_LABELS.get(row["method"], LABELS.get(row["method"], row["method"]))
        counts.setdefault((f"{row['family']}\n{row['start']} start", label), []).append(bool(row["success"]))
    rates = [{"group": group, "method": method, "successes": sum(found), "trials": len(found)}
             for (group, method), found in counts.items()]
    figure = success_bars_figure(rates, title="Local refinement on scan pairs: right results per kind of pair and start")
    return write_picture(figure, path)


def write_section(doc: Path, section: str, notes: str | None) -> None:
    """Replace (or append) the section of ``doc`` that starts with :data:`SECTION`: the generated
    tables, then ``notes`` (None: the notes the page has after its tables, :data:`TABLES_END`)."""
    text = doc.read_text(encoding="utf-8") if doc.exists() else ""
    if SECTION in text:
        head, rest = text.split(SECTION, 1)
        following = rest.find("\n## ")
        tail = rest[following + 1:] if following >= 0 else ""
        if notes is None:
            current = rest[:following + 1] if following >= 0 else rest
            notes = current.split(TABLES_END, 1)[1].strip("\n") + "\n" if TABLES_END in current else ""
        block = section + ("\n" + notes if notes else "")
        text = head + block + ("\n" + tail if tail else "")
    else:
        text = text.rstrip("\n") + "\n\n" + section + ("\n" + notes if notes else "")
    doc.write_text(text, encoding="utf-8")
