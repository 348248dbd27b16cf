"""Real scan pairs with ground truth, and partial-overlap object trials: the pure parts.

A real-pairs folder is laid out like ``shared/data/real_pairs``: a ``pairs.csv`` with the columns
``kind, target, source, T_target_source`` (paths relative to the folder; ``dataset`` and ``pair``
name the row, an optional ``bin_columns`` says the layout of ``.bin`` scans), each transform a
4x4 text file with ``target ~= R @ source + t``.

Each kind has its criteria (:data:`KIND_CRITERIA`), from the folder's README: 3DMatch fragments
succeed with a rotation error < 15 deg and a translation error < 0.30 m (the convention of
SC2-PCR, MAC, DGR); LiDAR scans with < 5 deg and < 0.6 m. Errors are measured in the pair's own
frame: for the ``turned`` variant (:func:`turn_source`) the estimate is first mapped back
(:func:`estimate_in_pair_frame`), so both variants are judged against the recorded truth.

The partial-overlap protocol (:func:`partial_trial`) cuts two disjoint random halves of an object
by one random plane each, keeping a fraction of each half's points, and reports the overlap the
trial actually has.

The low-overlap check (:func:`crop_to_overlap`) crops a real pair by one seeded plane, the source
kept on one side and the target on the other, with a slab between them where both remain, so that
the pair's true overlap falls to a chosen fraction (3DLoMatch's 10-30%); it reports the overlap
each way as measured after the crop.
"""

from __future__ import annotations

import csv
import statistics
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from esmicp.core.procrustes import apply, rigid_inverse, to_matrix
from esmicp.errors import InvalidInputError, PointCloudFileError
from esmicp.metrics import random_rotation, rotation_error_deg
from .protocols import random_rigid_transform

__all__ = [
    "KIND_CRITERIA",
    "PAIRS_FILE",
    "CroppedPair",
    "Criteria",
    "RealPair",
    "criteria_for",
    "crop_to_overlap",
    "estimate_in_pair_frame",
    "load_pair",
    "pair_errors",
    "partial_trial",
    "plane_cut",
    "quick_markdown_table",
    "read_pairs",
    "turn_source",
]

PAIRS_FILE = "pairs.csv"
_REQUIRED = ("kind", "target", "source", "T_target_source")


@dataclass(frozen=True)
class Criteria:
    """Success thresholds of a kind of pair, and the voxel the peers' documentation recommends.

    ``voxel_m`` is what the baselines get (KISS-Matcher, Open3D RANSAC / FGR): 0.05 m indoor,
    0.3 m LiDAR. esmicp's default gets none.
    """

    rotation_deg: float
    translation_m: float
    voxel_m: float

    def success(self, rotation_error: float, translation_error: float) -> bool:
        return bool(rotation_error < self.rotation_deg and translation_error < self.translation_m)


#: Criteria by kind (the ``kind`` column of ``pairs.csv``).
KIND_CRITERIA = {
    "3DMatch": Criteria(15.0, 0.30, 0.05),
    "3DLoMatch": Criteria(15.0, 0.30, 0.05),
    "LiDAR": Criteria(5.0, 0.6, 0.3),
    "LiDAR-coarse-GT": Criteria(5.0, 0.6, 0.3),
}


def criteria_for(kind: str) -> Criteria:
    """The :class:`Criteria` of ``kind``; raises :class:`KeyError` for an unknown kind."""
    return KIND_CRITERIA[kind]


@dataclass(frozen=True)
class RealPair:
    """One row of ``pairs.csv``: files resolved against the folder."""

    dataset: str
    pair: str
    kind: str
    target: Path
    source: Path
    transform: Path
    line: int
    bin_columns: int | None = None

    @property
    def name(self) -> str:
        return f"{self.dataset}/{self.pair}"

    @property
    def criteria(self) -> Criteria:
        return criteria_for(self.kind)


def read_pairs(folder) -> list[RealPair]:
    """The pairs listed in ``folder/pairs.csv``, in file order.

    Raises
    ------
    PointCloudFileError
        ``pairs.csv`` is missing, empty, lacks a column, or a line has the wrong number of
        fields, an unknown kind, an empty or missing file, or a bad ``bin_columns``; the message
        names ``pairs.csv`` and the line.
    """
    folder = Path(folder)
    path = folder / PAIRS_FILE
    if not path.is_file():
        raise PointCloudFileError(path, f"no such file: a real-pairs folder needs a {PAIRS_FILE}")
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            lines = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise PointCloudFileError(path, f"cannot read: {exc}") from None
    rows = [(number, fields) for number, fields in enumerate(lines, start=1) if any(f.strip() for f in fields)]
    if not rows:
        raise PointCloudFileError(path, "file is empty (expected a header line: kind,target,source,T_target_source)")
    header_line, header = rows[0]
    header = [name.strip() for name in header]
    missing = [name for name in _REQUIRED if name not in header]
    if missing:
        raise PointCloudFileError(path, f"line {header_line}: the header lacks the column(s) {', '.join(missing)}")
    pairs = []
    for number, fields in rows[1:]:
        if len(fields) != len(header):
            raise PointCloudFileError(path, f"line {number}: {len(fields)} fields, the header has {len(header)}")
        record = {name: value.strip() for name, value in zip(header, fields)}
        kind = record["kind"]
        if kind not in KIND_CRITERIA:
            raise PointCloudFileError(
                path, f"line {number}: unknown kind {kind!r}; known: {', '.join(KIND_CRITERIA)}"
            )
        files = {}
        for column in ("target", "source", "T_target_source"):
            if not record[column]:
                raise PointCloudFileError(path, f"line {number}: the {column} column is empty")
            files[column] = folder / record[column]
            if not files[column].is_file():
                raise PointCloudFileError(path, f"line {number}: {column} file {record[column]!r} not found in {folder}")
        columns = record.get("bin_columns") or None
        if columns is not None:
            if columns not in ("3", "4"):
                raise PointCloudFileError(path, f"line {number}: bin_columns must be 3 or 4, got {columns!r}")
            columns = int(columns)
        pairs.append(RealPair(
            dataset=record.get("dataset") or folder.name, pair=record.get("pair") or f"line{number}", kind=kind,
            target=files["target"], source=files["source"], transform=files["T_target_source"], line=number,
            bin_columns=columns,
        ))
    if not pairs:
        raise PointCloudFileError(path, "lists no pairs (only a header line)")
    return pairs


def pose_graph_poses(path) -> dict[int, np.ndarray]:
    """``{K: T_world_scanK}`` (4x4, the file's units) from a pose-graph file whose vertex lines read
    ``vK x y z qx qy qz qw`` (Newer College's ``graph.txt``); other lines are skipped."""
    from scipy.spatial.transform import Rotation

    poses = {}
    for line in Path(path).read_text().splitlines():
        fields = line.split()
        if len(fields) == 8 and fields[0].startswith("v"):
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat([float(v) for v in fields[4:8]]).as_matrix()
            pose[:3, 3] = [float(v) for v in fields[1:4]]
            poses[int(fields[0][1:])] = pose
    return poses


def load_pair(pair: RealPair, bin_columns: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(source, target, T_target_source)`` of ``pair``; ``.bin`` scans read with the pair's own
    ``bin_columns``, else ``bin_columns``."""
    from esmicp import io

    columns = pair.bin_columns if pair.bin_columns is not None else bin_columns
    source = io.read_points(pair.source, bin_columns=columns)
    target = io.read_points(pair.target, bin_columns=columns)
    return source, target, io.read_transform(pair.transform)


def pair_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Rotation error (degrees) and translation error (``|t_estimate - t_truth|``, the pair's
    units) of two ``T_target_source``: the 3DMatch / KITTI convention."""
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    return rotation_error_deg(estimate, truth), float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


def turn_source(source: np.ndarray, truth: np.ndarray, rng: np.random.Generator, about: np.ndarray | None = None):
    """The ``turned`` variant: ``source`` rotated about its centroid by a rotation uniform on SO(3).

    ``about``: the point (source frame) to turn about instead of the centroid; the origin keeps a
    range image a range image (its sensor turned in place). Returns ``(turned_source,
    turned_truth, M)``: ``turned_source = apply(M, source)`` and ``turned_truth = truth @ M^-1``, so
    ``apply(turned_truth, turned_source) = apply(truth, source)``.
    """
    source = np.asarray(source, dtype=np.float64)
    rotation = random_rotation(rng)
    centre = source.mean(axis=0) if about is None else np.asarray(about, dtype=np.float64)
    moved_by = to_matrix(rotation, centre - rotation @ centre)
    return apply(moved_by, source), np.asarray(truth, dtype=np.float64) @ rigid_inverse(moved_by), moved_by


def estimate_in_pair_frame(estimate: np.ndarray, moved_by: np.ndarray | None) -> np.ndarray:
    """An estimate made on a turned source (:func:`turn_source`'s ``M``), as a pose of the
    recorded source: ``estimate @ M`` (``estimate`` itself when ``moved_by`` is None)."""
    estimate = np.asarray(estimate, dtype=np.float64)
    return estimate if moved_by is None else estimate @ np.asarray(moved_by, dtype=np.float64)


def plane_cut(points: np.ndarray, keep: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """The points on one side of a random plane, ``round(keep * N)`` of them.

    The plane's normal is uniform on the sphere; its offset the quantile that keeps ``keep`` of
    the points. Returns ``(mask, normal, offset)``: kept points satisfy ``points @ normal >= offset``.
    """
    if not 0.0 < keep <= 1.0:
        raise InvalidInputError(f"keep: expected a fraction in (0, 1], got {keep!r}")
    points = np.asarray(points, dtype=np.float64)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    heights = points @ normal
    count = max(3, round(keep * len(points)))
    order = np.argsort(-heights, kind="stable")
    mask = np.zeros(len(points), dtype=bool)
    mask[order[:count]] = True
    return mask, normal, float(heights[order[count - 1]])


@dataclass(frozen=True, eq=False)
class PartialTrial:
    """A partial-overlap trial: ``apply(T_target_source, source)`` lies on ``target`` where they overlap.

    ``overlap`` is the fraction of the source's points (in the object's frame) that lie in the
    target's part of the object (on the kept side of the target's plane). ``source_half`` is the
    source's half of the object before its plane cut, moved with it (source frame): success up to
    the *object's* symmetry is judged on it. A bottle's cut half turned about the bottle's axis
    still lies on the bottle, and no data can tell that pose from the truth, yet the kept points
    themselves land elsewhere: judged on them, such a pose fails whenever the cut does not share
    the symmetry (``docs/scans-partial-overlap.md``).
    """

    source: np.ndarray
    target: np.ndarray
    T_target_source: np.ndarray
    overlap: float
    keep: float
    source_half: np.ndarray


def partial_trial(cloud: np.ndarray, keep: float, rng: np.random.Generator, points: int | None = 2000) -> PartialTrial:
    """Split ``cloud`` into two disjoint random halves (``points`` each at most), cut each by its
    own random plane (:func:`plane_cut`) to ``keep`` of its points; the target is one, the
    other, moved by a random rigid transform (:func:`~esmicp_lab.bench.protocols.random_rigid_transform`),
    the source (and its whole half, moved the same way, as ``source_half``)."""
    cloud = np.asarray(cloud, dtype=np.float64)
    order = rng.permutation(len(cloud))
    half = len(cloud) // 2 if points is None else min(len(cloud) // 2, points)
    target_half, source_half = cloud[order[:half]], cloud[order[half : 2 * half]]
    target_mask, normal, offset = plane_cut(target_half, keep, rng)
    source_mask, _, _ = plane_cut(source_half, keep, rng)
    target, source_object = target_half[target_mask], source_half[source_mask]
    overlap = float(np.mean(source_object @ normal >= offset))
    from esmicp.core.procrustes import bounding_box_diagonal

    moved_by = random_rigid_transform(rng, bounding_box_diagonal(target))
    return PartialTrial(apply(moved_by, source_object), target, rigid_inverse(moved_by), overlap, keep,
                        apply(moved_by, source_half))


@dataclass(frozen=True, eq=False)
class CroppedPair:
    """A real pair cropped to a low overlap (:func:`crop_to_overlap`).

    ``source`` and ``target`` are the kept points (in their own frames; the pose between them is
    unchanged); ``source_overlap`` is the fraction of the kept source lying on the kept target
    under the true pose (:func:`~esmicp_lab.bench.protocols.scan_overlap`), ``target_overlap`` the same
    the other way; ``normal`` the cut direction (target frame) and ``offset`` / ``width`` the slab
    (target units) where both clouds remain.
    """

    source: np.ndarray
    target: np.ndarray
    source_overlap: float
    target_overlap: float
    normal: np.ndarray
    offset: float
    width: float


#: Bisection steps on the slab width of :func:`crop_to_overlap`.
CROP_STEPS = 24


def crop_to_overlap(source: np.ndarray, target: np.ndarray, T_target_source: np.ndarray, overlap: float,
                    rng: np.random.Generator) -> CroppedPair:
    """Crop a pair so that about ``overlap`` of the kept source lies on the kept target.

    A direction ``n`` uniform on the sphere (target frame) and the median height ``c`` (along
    ``n``) of the source points that lie on the target under ``T_target_source`` define the cut:
    the source keeps its points with ``height >= c - width / 2``, the target those with
    ``height <= c + width / 2``, and ``width`` (target units) is bisected until the kept source's
    overlap (:func:`~esmicp_lab.bench.protocols.scan_overlap`, 3 target spacings) is as close to
    ``overlap`` as the data allows. Both clouds keep at least 3 points.

    Raises
    ------
    InvalidInputError
        ``overlap`` is not in (0, 1), or the pair overlaps nowhere under ``T_target_source``.
    """
    from .protocols import median_spacing, scan_overlap

    if not 0.0 < overlap < 1.0:
        raise InvalidInputError(f"overlap: expected a fraction in (0, 1), got {overlap!r}")
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    truth = np.asarray(T_target_source, dtype=np.float64)
    distance = 3.0 * median_spacing(target)
    moved = apply(truth, source)
    gaps, _ = cKDTree(target).query(moved, distance_upper_bound=distance)
    on_target = gaps <= distance
    if not on_target.any():
        raise InvalidInputError("crop_to_overlap: the pair overlaps nowhere under T_target_source")
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    source_heights, target_heights = moved @ normal, target @ normal
    offset = float(np.median(source_heights[on_target]))
    # A target point within `distance` of a source point lies within `distance` of its height, so
    # the cut decides alone for the source points farther than that from the target's face: all of
    # their target neighbours kept, or none. Only those near the face are queried, against the kept
    # target points near it. (`reach`: `distance` with room for the heights' rounding.)
    reach = distance * (1.0 + 1e-6)
    by_height = np.argsort(target_heights, kind="stable")
    sorted_heights = target_heights[by_height]

    def crop(width):
        """``(keep_source, keep_target, overlap)``: the overlap is the kept source's fraction within
        ``distance`` of the kept target, as :func:`scan_overlap` measures it; None if a cloud keeps
        fewer than 3 points."""
        face = offset + 0.5 * width
        keep_source = source_heights >= offset - 0.5 * width
        keep_target = target_heights <= face
        if keep_source.sum() < 3 or keep_target.sum() < 3:
            return None
        candidates = keep_source & on_target
        near_face = candidates & (np.abs(source_heights - face) < reach)
        on_kept = int(np.count_nonzero(candidates & (source_heights + reach <= face)))
        if near_face.any():
            slab = by_height[np.searchsorted(sorted_heights, face - 2.0 * reach, side="left"):
                             np.searchsorted(sorted_heights, face, side="right")]
            if len(slab):
                gaps, _ = cKDTree(target[slab]).query(moved[near_face], distance_upper_bound=distance)
                on_kept += int(np.count_nonzero(gaps <= distance))
        return keep_source, keep_target, on_kept / float(np.count_nonzero(keep_source))

    low, high = 0.0, float(np.ptp(np.concatenate([source_heights, target_heights])))
    best = None
    for _ in range(CROP_STEPS):
        width = 0.5 * (low + high)
        found = crop(width)
        if found is None or found[2] > overlap:
            high = width
        else:
            low = width
        if found is not None and (best is None or abs(found[2] - overlap) < abs(best[1][2] - overlap)):
            best = (width, found)
    if best is None:
        raise InvalidInputError("crop_to_overlap: no cut keeps 3 points of each cloud")
    width, (keep_source, keep_target, source_overlap) = best
    kept_source, kept_target = source[keep_source], target[keep_target]
    target_overlap = scan_overlap(kept_target, kept_source, rigid_inverse(truth), 3.0 * median_spacing(kept_source))
    return CroppedPair(kept_source, kept_target, source_overlap, target_overlap, normal, offset, width)


def quick_markdown_table(rows, methods) -> str:
    """One Markdown row per (pair, variant): each method's result and time, and the first method's
    time over the fastest *successful* other method's ("no peer succeeds" when none does), with
    the median and maximum of that ratio below (``benchmarks/scan_pairs_quick.py``'s table).

    ``rows``: ``(pair, variant, method, success, rotation error deg, translation error m, time s)``
    tuples, one per (pair, variant, method) of ``methods``; ``methods``: the first is the one timed
    against the others (its peers)."""
    cells = {(row[0], row[1], row[2]): row for row in rows}
    keys = list(dict.fromkeys((row[0], row[1]) for row in rows))
    lines = [
        "| pair | variant | " + " | ".join(methods) + f" | {methods[0]} / fastest successful peer |",
        "|---|---|" + "---|" * (len(methods) + 1),
    ]
    ratios = []
    for label, variant in keys:
        found = [cells[label, variant, name] for name in methods]
        peers = [row[6] for row in found[1:] if row[3]]
        shown = [f"{'ok' if row[3] else 'FAIL'} {row[4]:.2f}° {row[5]:.3f}m {row[6]:.2f}s" for row in found]
        if peers:
            ratios.append(found[0][6] / min(peers))
            lines.append(f"| {label} | {variant} | " + " | ".join(shown) + f" | {ratios[-1]:.2f} |")
        else:
            lines.append(f"| {label} | {variant} | " + " | ".join(shown) + " | no peer succeeds |")
    successes = [sum(cells[key[0], key[1], name][3] for key in keys) for name in methods]
    summary = f"\n{' / '.join(f'{name} {count}/{len(keys)}' for name, count in zip(methods, successes))}"
    if ratios:
        summary += (f"; {methods[0]} / fastest successful peer: median {statistics.median(ratios):.2f}, "
                    f"max {max(ratios):.2f}")
    lines.append(summary)
    return "\n".join(lines)
