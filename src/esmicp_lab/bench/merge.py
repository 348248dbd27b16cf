"""The merge benchmark's bookkeeping (``benchmarks/merge_scans.py``, ``merge_references.py``):
scans with their truth, one method's run, the errors of that run against the truth, and the
tables and marked blocks of docs/merge.md.

Errors: each scan's estimated ``T_reference_scan`` against the truth's, rotation in degrees and
translation in cloud units, over the scans reported placed (a method that reports no status:
every scan it poses). A posed scan off by more than the data set's ``wrong`` bound is *wrong* (a
walk's frame positions after the best rigid fit of the whole trajectory, as for the ATE);
*silently* wrong when reported placed (not doubtful). ATE:
:func:`esmicp.metrics.absolute_trajectory_error` over the placed scans; relative errors:
:func:`esmicp.metrics.relative_pose_errors` over consecutive frames both placed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import esmicp
from esmicp.metrics import absolute_trajectory_error, relative_pose_errors, rotation_error_deg

__all__ = ["Dataset", "Run", "cell", "dataset_table", "evaluate", "markers", "read_poses_file", "scan_status",
           "write_doc"]


@dataclass
class Dataset:
    """Scans in the order every method is given them, with their truth (``T_world_scan``)."""

    name: str
    title: str
    names: list[str]
    clouds: list[np.ndarray]
    truth: np.ndarray
    reference: int  # index into the given order
    unit: str  # translation unit of the tables
    scale: float  # metres (or cloud units) -> unit
    wrong: tuple[float, float]  # (deg, cloud units): beyond either, a scan is wrong
    files: list[Path] = field(default_factory=list)
    #: N-1 neighbouring pairs (parent, child) as a tree from the reference, for the pairwise chain.
    tree: list[tuple[int, int]] = field(default_factory=list)
    ordered: bool = False  # the given order is the walk's order (consecutive relative errors mean something)


@dataclass
class Run:
    """One method's result on one data set: ``T_world_scan`` per given scan (NaN: unplaced)."""

    method: str
    poses: np.ndarray | None  # None: the method could not run (see note)
    seconds: float | None
    status: list[str] | None = None  # per scan "placed" / "doubtful" / "unplaced", None if not reported
    note: str = ""
    times: list[float] = field(default_factory=list)


def scan_status(result, count) -> list[str] | None:
    """Per-scan "placed" / "doubtful" / "unplaced" from a merge result, as far as it reports one.

    Reads a per-scan status (``result.status``, or ``result.scans[k].status``) when the result
    has one, else only placed / unplaced (``result.placed``); None when neither is there."""
    raw = getattr(result, "status", None)
    if raw is None and getattr(result, "scans", None) is not None:
        raw = [getattr(scan, "status", None) for scan in result.scans]
    if raw is not None and len(raw) == count and all(value is not None for value in raw):
        return [_status_word(value) for value in raw]
    return None


def _status_word(value) -> str:
    """The benchmark's word for a status as a merge result reports it."""
    text = str(getattr(value, "value", value)).lower()
    if "unplaced" in text or "not placed" in text or "left out" in text:
        return "unplaced"
    if "doubt" in text or "uncertain" in text or "low" in text:
        return "doubtful"
    return "placed"


def read_poses_file(path: Path, count: int) -> tuple[np.ndarray, list[str] | None]:
    """``esmicp merge --poses-out``'s file, read by :func:`esmicp.read_poses`; or, as esmicp
    versions without it wrote it, one line per scan, its index first and the 16 numbers of
    ``T_world_scan`` last, with its status just before them when the CLI writes one.

    Returns the (count, 4, 4) poses (NaN where no line or ``nan``) and the statuses (None when the
    file has none)."""
    poses = np.full((count, 4, 4), np.nan)
    try:
        written = esmicp.read_poses(path)
    except (AttributeError, esmicp.EsmicpError):
        pass
    else:
        poses[: len(written.poses)] = written.poses[:count]
        return poses, None if written.status is None else list(written.status)
    status: list[str] | None = ["unplaced"] * count
    for line in path.read_text().splitlines():
        fields = line.split()
        if fields and not line.startswith("#"):
            k = int(fields[0])
            poses[k] = np.array(fields[-16:], dtype=float).reshape(4, 4)
            word = fields[-17] if len(fields) >= 19 else ""
            if status is not None and word in ("placed", "doubtful", "unplaced"):
                status[k] = word
            else:
                status = None
    return poses, status


def evaluate(data: Dataset, run: Run) -> dict:
    """Every figure of one run against the truth (translations in cloud units; see ``data.scale``): a
    scan's translation error is the displacement of its centroid, so it does not depend on where the
    scan's frame has its origin."""
    if run.poses is None:
        return {"supported": False, "note": run.note}
    count = len(data.clouds)
    finite = np.array([np.isfinite(pose).all() for pose in run.poses])
    status = list(run.status) if run.status is not None else ["placed" if ok else "unplaced" for ok in finite]
    status = [s if finite[k] else "unplaced" for k, s in enumerate(status)]
    true_reference = np.linalg.inv(data.truth[data.reference])
    rotation, translation = np.full(count, np.nan), np.full(count, np.nan)
    if finite[data.reference]:
        estimated_reference = np.linalg.inv(run.poses[data.reference])
        for k in np.flatnonzero(finite):
            estimate = estimated_reference @ run.poses[k]
            true = true_reference @ data.truth[k]
            rotation[k] = rotation_error_deg(estimate, true)
            # where the scan lies, not where its frame's origin does: a scan stored far from its
            # origin (a turntable frame, a sensor 1 m away) would turn a rotation error into a shift
            centroid = np.asarray(data.clouds[k], dtype=np.float64).mean(axis=0)
            translation[k] = float(np.linalg.norm((estimate[:3, :3] - true[:3, :3]) @ centroid
                                                  + estimate[:3, 3] - true[:3, 3]))
    others = [k for k in range(count) if k != data.reference]
    posed = [k for k in others if np.isfinite(rotation[k])]
    measured = [k for k in posed if status[k] == "placed"]  # the errors: of the scans reported placed
    placed = finite & np.array([s == "placed" for s in status])
    off_translation = translation
    alignment = None
    if placed.sum() >= 3:
        ate, alignment = absolute_trajectory_error(run.poses[placed], data.truth[placed])
    if data.ordered and alignment is not None:
        # A walk's frame positions are judged where the best rigid fit of the whole trajectory
        # puts them: drift seen from the reference frame is the ATE's business, not a misplaced
        # frame. Rotations stay judged from the reference (no lever arm; the fit is of positions).
        off_translation = np.full(count, np.nan)
        for k in posed:
            off_translation[k] = float(np.linalg.norm(alignment[:3, :3] @ run.poses[k][:3, 3] + alignment[:3, 3]
                                                      - data.truth[k][:3, 3]))
    wrong = [k for k in posed if rotation[k] > data.wrong[0] or off_translation[k] > data.wrong[1]]
    out = {
        "supported": True, "note": run.note, "seconds": run.seconds, "times": run.times,
        "scans": count, "placed": status.count("placed"), "doubtful": status.count("doubtful"),
        "unplaced": status.count("unplaced"), "status_reported": run.status is not None,
        "wrong": len(wrong), "silently_wrong": sum(status[k] == "placed" for k in wrong),
        "worst_rotation_deg": max((rotation[k] for k in measured), default=float("nan")),
        "median_rotation_deg": float(np.median(rotation[measured])) if measured else float("nan"),
        "worst_translation": max((translation[k] for k in measured), default=float("nan")),
        "median_translation": float(np.median(translation[measured])) if measured else float("nan"),
        "per_scan": {data.names[k]: [float(rotation[k]), float(translation[k]), status[k]] for k in range(count)},
    }
    if alignment is not None:
        out["ate"] = ate
    if data.ordered:
        pairs = [(k, k + 1) for k in range(count - 1) if placed[k] and placed[k + 1]]
        if pairs:
            rpe_rotation, rpe_translation = relative_pose_errors(np.where(placed[:, None, None], run.poses, np.eye(4)),
                                                                 data.truth, pairs)
            out |= {"rpe_pairs": len(pairs), "median_rpe_deg": float(np.median(rpe_rotation)),
                    "median_rpe": float(np.median(rpe_translation)), "worst_rpe_deg": float(rpe_rotation.max()),
                    "worst_rpe": float(rpe_translation.max())}
    return out


def cell(value, digits=2) -> str:
    """A table cell: ``value`` with ``digits`` decimals; ``-`` when it is missing or not finite."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def dataset_table(entry: dict) -> list[str]:
    """Markdown rows of one data set: one row per method."""
    unit, scale = entry["unit"], entry["scale"]
    rows = [f"| method | placed / doubtful / unplaced | wrong (silently) | worst deg | median deg | worst {unit} | "
            f"median {unit} | ATE {unit} | median pair error deg / {unit} | time s | time / esmicp |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    base = entry["results"].get("api", {}).get("seconds")
    for result in entry["results"].values():
        if not result["supported"]:
            rows.append(f"| {result['method']} | {result['note']} | | | | | | | | | |")
            continue
        doubtful = str(result["doubtful"]) if result["status_reported"] else "n/a"
        rpe = (f"{cell(result['median_rpe_deg'])} / {cell(result['median_rpe'] * scale)}"
               if "median_rpe_deg" in result else "-")
        ratio = cell(result["seconds"] / base) if base else "-"
        rows.append(
            f"| {result['method']} | {result['placed']} / {doubtful} / {result['unplaced']} | "
            f"{result['wrong']} ({result['silently_wrong']}) | {cell(result['worst_rotation_deg'])} | "
            f"{cell(result['median_rotation_deg'])} | {cell(result['worst_translation'] * scale)} | "
            f"{cell(result['median_translation'] * scale)} | {cell(result.get('ate', float('nan')) * scale)} | {rpe} | "
            f"{cell(result['seconds'], 1)} | {ratio} |")
    return rows


def markers(name: str) -> tuple[str, str]:
    """The comment lines around one data set's generated block in docs/merge.md."""
    return f"<!-- merge_scans.py {name}: start -->", f"<!-- merge_scans.py {name}: end -->"


def write_doc(path: Path, blocks: dict[str, str], markers_of=markers) -> None:
    """Replace each named block of ``path`` (between its markers, ``markers_of(name)``: by default
    a data set's) with the new one; the rest of the file, and the blocks not given, are kept."""
    text = path.read_text()
    for name, block in blocks.items():
        start, end = markers_of(name)
        if start not in text or end not in text:
            raise SystemExit(f"{path}: no '{start}' ... '{end}' markers to replace between")
        before, rest = text.split(start, 1)
        text = before + block + rest.split(end, 1)[1]
    path.write_text(text)
