"""Many scans into one model: esmicp's merge against Open3D's pipelines and against pairwise
registration, measured in the same run; writes the results section of docs/merge.md.

Usage::

    python benchmarks/merge_scans.py --doc docs/merge.md       # everything; rewrites the results section
    python benchmarks/merge_scans.py --datasets kitchen --frames 20 --skip-peer   # a quick look
    python benchmarks/merge_scans.py --datasets bunny newer-college --json results.json
    python benchmarks/merge_scans.py --check-harness            # Open3D from the truth, 0 ICP iterations: errors ~0
    python benchmarks/merge_scans.py --datasets bunny kitchen --skip-peer --skip-pairwise --json run.json --pictures docs/images
    python benchmarks/merge_scans.py --pictures-from run.json --pictures docs/images   # the same pictures, no run

Data sets (``../shared/data`` or ``$ESMICP_SHARED_DATA``), each given to every method in the
same order:

- ``bunny``: the Stanford bunny's 10 raw range scans (``bunny_scans``, ground truth ``bun.conf``
  read by :func:`esmicp.io.stanford_conf.load_scans`), in a seeded shuffled order (``--seed``),
  every point. Methods: ``esmicp merge`` (the CLI, every default, a subprocess: its time includes
  Python's start and reading the files), ``register_scans`` (the library, every default), Open3D's
  multiway registration (its tutorial, from the identity), and the pairwise chain.
- ``kitchen``: the redkitchen walk (``sequences/redkitchen_seq01_every10``: depth frames as points
  in the camera frame, ``poses.txt`` = ``T_world_frame``), the first ``--frames`` frames.
  Methods: ``register_scans`` with the frames shuffled (order not given), ``register_scans(...,
  sequence=True)`` in order when the library has that argument (else reported "not supported"),
  Open3D's reconstruction-system pipeline in order (:func:`merge_open3d.reconstruction_walk`), and
  the pairwise chain.
- ``kitchen-every20``: every second frame of the walk (every 20th raw frame: 50 frames, twice the
  motion between frames), in order; ``kitchen-gap``: the walk with 30% of its frames (30 of 100)
  dropped from the middle, in order, so that the frames either side of the gap are far apart.
  Methods: ``register_scans(..., sequence=True)``, Open3D's reconstruction-system pipeline (its
  loop candidates as many raw frames apart as on the whole walk), and the pairwise chain.
- ``newer-college``: 5 LiDAR scans of ``real_pairs/newer_college_01`` (ground truth
  ``graph.txt``), listed order. Methods: ``register_scans``, Open3D multiway, the pairwise chain.
- ``bunny-off-sensor``: the bunny's 10 raw scans moved into their scanner's frame, then each
  0.1-0.3 m and 5-20 degrees off it (:mod:`esmicp_lab.bench.off_sensor`, seeded by ``--seed``),
  shuffled. ``turntable``: 15 range scans of the bunny's mesh (``bunny/bun_zipper.ply``) on a
  turntable turning 24 degrees at a time, stored in the turntable's frame, shuffled. Scans stored
  off their sensors' frames; the same methods as ``newer-college``. Their frames' origins are
  0.1-1.3 m from the data, so the translation errors (at the origins) carry the rotation errors'
  lever arm.

The pairwise chain: the N-1 neighbouring pairs registered one at a time with
``esmicp.register`` at its defaults (the walk: consecutive frames; the bunny: the spanning tree of
the pairs that overlap most under the ground truth) and chained from the reference. Its time is
the reference for "the merge costs K pairwise registrations"; its errors show what the pairs alone
give.

Errors: each scan's estimated ``T_reference_scan`` against the truth's (the reference: ``bun000``,
the first frame, ``v0``), rotation in degrees and translation, over the scans reported placed
(a method that reports no status: every scan it poses). A posed scan off by more than the data
set's ``wrong`` bound is *wrong* (a walk's frame positions after the best rigid fit of the
whole trajectory, as for the ATE); *silently* wrong when reported placed (not doubtful). ATE:
:func:`esmicp.metrics.absolute_trajectory_error` over the placed scans; relative errors:
:func:`esmicp.metrics.relative_pose_errors` over consecutive frames both placed. Times are wall
clock, loading excluded except for the CLI; with ``--repeat`` the methods take turns and the
median time is reported. Nothing is written unless ``--json``, ``--doc`` or ``--pictures`` is given;
``--doc`` replaces the blocks of the data sets run, so each can be regenerated on its own. The
``--json`` report holds every run's poses (``T_world_scan``, NaN rows unplaced) and the truth;
``--pictures`` draws from them the pictures docs/merge.md opens on (:data:`PICTURES`): the bunny's
scans placed by ``register_scans`` (else ``esmicp merge``), one colour per scan, and the kitchen
walk's positions as ``register_scans(..., sequence=True)`` places them (else shuffled) against the
truth, all in the reference scan's frame.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import esmicp
from esmicp.io import read_points
from esmicp.io.stanford_conf import load_scans
from esmicp_lab.bench.merge import Dataset, Run, dataset_table, evaluate, markers, read_poses_file, scan_status, write_doc
from esmicp_lab.bench.merge import cell as _f
from esmicp_lab.bench.real_pairs import pose_graph_poses

sys.path.insert(0, str(Path(__file__).resolve().parent))
import merge_open3d  # noqa: E402  (a sibling module of this script)

DATASETS = ("bunny", "kitchen", "kitchen-every20", "kitchen-gap", "newer-college", "bunny-off-sensor", "turntable")

#: Frames of the kitchen walk (of every 10th raw frame) between the frames kept by "kitchen-every20".
EVERY20_STEP = 2
#: Fraction of the kitchen walk's frames that "kitchen-gap" drops from its middle (30 of 100).
GAP_FRACTION = 0.3


def shared_data() -> Path:
    return Path(os.environ.get("ESMICP_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def bunny(seed: int, max_points: int | None = None) -> Dataset:
    folder = shared_data() / "bunny_scans"
    scans = load_scans(folder, max_points=max_points, rng=0)
    listed = list(scans)
    order = [int(k) for k in np.random.default_rng(seed).permutation(len(listed))]
    names = [listed[k] for k in order]
    clouds = [scans[n][0] for n in names]
    truth = np.array([scans[n][1] for n in names])
    data = Dataset("bunny", f"Stanford bunny, {len(names)} raw scans, shuffled (seed {seed})", names, clouds, truth,
                   names.index("bun000") if "bun000" in names else 0, "mm", 1000.0, (1.0, 0.002),
                   files=[folder / f"{n}.ply" for n in names])
    data.tree = overlap_tree(clouds, truth, data.reference, radius=0.002)
    return data


def _off_sensor(name: str, title: str, names, clouds, truth, reference_name: str, seed: int) -> Dataset:
    order = [int(k) for k in np.random.default_rng(seed).permutation(len(names))]
    names, clouds, truth = [names[k] for k in order], [clouds[k] for k in order], np.array([truth[k] for k in order])
    data = Dataset(name, f"{title}, shuffled (seed {seed})", names, clouds, truth, names.index(reference_name), "mm",
                   1000.0, (1.0, 0.002))
    data.tree = overlap_tree(clouds, truth, data.reference, radius=0.002)
    return data


def bunny_off_sensor(seed: int) -> Dataset:
    from esmicp_lab.bench.off_sensor import bunny_in_scanner_frames, moved_off

    names, clouds, truth = bunny_in_scanner_frames(shared_data() / "bunny_scans")
    clouds, truth = moved_off(clouds, truth, rng=seed)
    return _off_sensor("bunny-off-sensor", "Stanford bunny, 10 raw scans 0.1-0.3 m and 5-20 deg off their scanner's "
                       "frame", names, clouds, truth, "bun000", seed)


def turntable(seed: int) -> Dataset:
    from esmicp_lab.bench.off_sensor import turntable_scans

    (clouds, truth), _ = turntable_scans(read_points(shared_data() / "bunny" / "bun_zipper.ply"), 15)
    names = [f"turn{24 * k:03d}" for k in range(15)]
    return _off_sensor("turntable", "15 range scans of the bunny's mesh on a turntable, 24 deg apart, in the "
                       "turntable's frame", names, clouds, truth, "turn000", seed)


def kitchen(frames: int, step: int = 1, *, gap: float = 0.0, name: str = "kitchen") -> Dataset:
    """The first ``frames`` frames of the walk (of every ``step``-th frame), in the walk's order;
    ``gap``: that fraction of them dropped from the middle (the walk jumps there)."""
    from esmicp_lab.bench.sequences import read_poses

    folder = shared_data() / "sequences" / "redkitchen_seq01_every10"
    truth_of = read_poses(folder)
    files = sorted((folder / "frames").glob("frame-*.npy"))[::step][:frames]
    title = f"redkitchen walk, {len(files)} depth frames"
    if step > 1:
        title = f"redkitchen walk, every {10 * step}th frame, {len(files)} depth frames, in order"
    dropped = int(round(gap * len(files)))
    if dropped:
        first = (len(files) - dropped) // 2
        title = (f"redkitchen walk with a gap, {len(files) - dropped} depth frames in order "
                 f"({files[first].stem} to {files[first + dropped - 1].stem} dropped)")
        files = files[:first] + files[first + dropped:]
    names = [f.stem for f in files]
    data = Dataset(name, title, names,
                   [np.load(f).astype(float) for f in files], np.array([truth_of[n] for n in names]), 0, "cm", 100.0,
                   (5.0, 0.20), files=files, ordered=True)
    data.tree = [(k, k + 1) for k in range(len(names) - 1)]
    return data


def newer_college() -> Dataset:
    folder = shared_data() / "real_pairs" / "newer_college_01"
    truth = pose_graph_poses(folder / "graph.txt")
    names = [f"planes_{10 * k:06d}" for k in sorted(truth)]
    files = [folder / f"{name}.bin" for name in names]
    data = Dataset("newer-college", f"Newer College, {len(names)} LiDAR scans", names,
                   [read_points(f, bin_columns=3) for f in files], np.array([truth[k] for k in sorted(truth)]), 0,
                   "m", 1.0, (2.0, 0.5), files=files, ordered=True)
    data.tree = [(k, k + 1) for k in range(len(names) - 1)]
    return data


def overlap_tree(clouds, truth, reference, radius, points=3000):
    """The N-1 pairs (parent, child) of the maximum spanning tree of the true overlaps, from the
    reference: the neighbouring pairs a person knowing the truth would register. Overlap of a
    pair: the smaller fraction of either scan's points (a seeded subset) within ``radius`` of the
    other, both placed by the truth."""
    rng = np.random.default_rng(0)
    placed = []
    for cloud, pose in zip(clouds, truth):
        subset = cloud[rng.choice(len(cloud), min(points, len(cloud)), replace=False)]
        placed.append(subset @ pose[:3, :3].T + pose[:3, 3])
    trees = [cKDTree(p) for p in placed]
    count = len(clouds)
    overlap = np.zeros((count, count))
    for i in range(count):
        for j in range(count):
            if i != j:
                overlap[i, j] = np.mean(trees[j].query(placed[i], distance_upper_bound=radius)[0] <= radius)
    overlap = np.minimum(overlap, overlap.T)
    inside, pairs = {reference}, []
    while len(inside) < count:
        parent, child = max(((i, j) for i in inside for j in range(count) if j not in inside),
                            key=lambda pair: overlap[pair])
        pairs.append((parent, child))
        inside.add(child)
    return pairs


# -- methods: each returns a Run ---------------------------------------------------------------


def supports_sequence() -> bool:
    """Whether this esmicp's ``register_scans`` takes ``sequence=``."""
    return "sequence" in inspect.signature(esmicp.register_scans).parameters


def run_api(data: Dataset, *, sequence=False, shuffle_seed=None) -> Run:
    """``register_scans`` at its defaults; ``shuffle_seed``: give the scans in that seeded order
    (the poses are mapped back)."""
    label = "esmicp register_scans" + (", sequence=True" if sequence else "")
    if sequence and not supports_sequence():
        return Run(label, None, None, note="not supported by this esmicp (register_scans has no sequence=)")
    order = list(range(len(data.clouds)))
    if shuffle_seed is not None:
        order = [int(k) for k in np.random.default_rng(shuffle_seed).permutation(len(order))]
        label += ", shuffled"
    kwargs = {"sequence": True} if sequence else {}
    start = time.perf_counter()
    result = esmicp.register_scans([data.clouds[k] for k in order], reference=order.index(data.reference), **kwargs)
    seconds = time.perf_counter() - start
    poses = np.full((len(order), 4, 4), np.nan)
    given_status = scan_status(result, len(order))
    status = None if given_status is None else [""] * len(order)
    for position, k in enumerate(order):
        poses[k] = result.poses[position]
        if status is not None:
            status[k] = given_status[position]
    kept = getattr(result, "kept_edges", ())
    note = f"{len(kept)} of {len(result.edges)} edges kept" if hasattr(result, "edges") else ""
    if getattr(result, "pairs_registered", None):
        note += f", {result.pairs_registered} registrations"
    return Run(label, poses, seconds, status, note)


def cli_supports(option: str) -> bool:
    help_text = subprocess.run([sys.executable, "-m", "esmicp", "merge", "--help"], capture_output=True,
                               text=True).stdout
    return option in help_text


def run_cli(data: Dataset) -> Run:
    """``esmicp merge FILE...`` at every default (the files in the data set's order), in a
    subprocess; the poses from ``--poses-out`` (index, file, [status,] 16 numbers per line)."""
    with tempfile.TemporaryDirectory() as folder:
        poses_file = Path(folder) / "poses.txt"
        command = [sys.executable, "-m", "esmicp", "merge", *map(str, data.files), "-o", str(Path(folder) / "merged.ply"),
                   "--poses-out", str(poses_file)]
        if cli_supports("--no-progress"):
            command.append("--no-progress")
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        if not poses_file.exists():
            return Run("esmicp merge (CLI)", None, None, note=f"exit {done.returncode}: {done.stderr.strip()[-300:]}")
        poses, status = read_poses_file(poses_file, len(data.files))
    return Run("esmicp merge (CLI)", poses, seconds, status, note=f"exit status {done.returncode}")


def run_pairwise(data: Dataset) -> Run:
    """The N-1 neighbouring pairs (``data.tree``) registered one by one by ``esmicp.register``
    at its defaults (child onto parent), chained from the reference."""
    poses = np.full((len(data.clouds), 4, 4), np.nan)
    poses[data.reference] = np.eye(4)
    start = time.perf_counter()
    results = [(parent, child, esmicp.register(data.clouds[child], data.clouds[parent]).transformation)
               for parent, child in data.tree]
    seconds = time.perf_counter() - start
    for parent, child, T_parent_child in results:  # the tree lists parents before their children
        poses[child] = poses[parent] @ T_parent_child
    return Run(f"{len(data.tree)} pairwise esmicp.register, chained", poses, seconds)


def run_open3d_multiway(data: Dataset, voxel: float) -> Run:
    poses, seconds, _ = merge_open3d.multiway(data.clouds, voxel)
    return Run("Open3D multiway (tutorial, identity start)", poses, seconds)


def run_open3d_walk(data: Dataset, loop_gap: int, loop_stride: int) -> Run:
    poses, seconds, info = merge_open3d.reconstruction_walk(data.clouds, loop_gap=loop_gap, loop_stride=loop_stride)
    return Run("Open3D reconstruction system (odometry + FPFH loops + pose graph)", poses, seconds,
               note=f"{info['loops_kept']} of {info['loop_candidates']} loop candidates kept")


#: Open3D downsampling voxel of the multiway tutorial per data set (its 2 cm is for rooms; the bunny is 15 cm).
MULTIWAY_VOXEL = {"bunny": 0.002, "newer-college": 0.2, "bunny-off-sensor": 0.002, "turntable": 0.002}


# -- running ---------------------------------------------------------------------------------


def methods_for(data: Dataset, args) -> list[tuple[str, callable]]:
    """(key, zero-argument runner) of every method on this data set, in the order they take turns."""
    out = []
    if data.name == "bunny":
        out.append(("cli", lambda: run_cli(data)))
        out.append(("api", lambda: run_api(data)))
    elif data.name == "kitchen":
        out.append(("api", lambda: run_api(data, shuffle_seed=args.seed)))
        out.append(("api-sequence", lambda: run_api(data, sequence=True)))
    elif data.name.startswith("kitchen"):  # the walk's variants: in order only
        out.append(("api-sequence", lambda: run_api(data, sequence=True)))
    else:
        out.append(("api", lambda: run_api(data)))
    if not args.skip_peer:
        if data.name.startswith("kitchen"):
            # loop candidates as many raw frames apart on every variant
            step = EVERY20_STEP if data.name == "kitchen-every20" else 1
            gap, stride = max(1, args.loop_gap // step), max(1, args.loop_stride // step)
            out.append(("open3d", lambda: run_open3d_walk(data, gap, stride)))
        else:
            out.append(("open3d", lambda: run_open3d_multiway(data, MULTIWAY_VOXEL[data.name])))
    if not args.skip_pairwise:
        out.append(("pairwise", lambda: run_pairwise(data)))
    return out


def run_dataset(data: Dataset, args, log=print) -> dict:
    """Every method on ``data``, taking turns ``args.repeat`` times; figures of the last turn,
    the median time."""
    methods = methods_for(data, args)
    runs: dict[str, Run] = {}
    for _ in range(args.repeat):
        for key, runner in methods:
            run = runner()
            if key in runs:
                run.times = runs[key].times
            run.times.append(run.seconds)
            runs[key] = run
            log(f"  {run.method}: {'%.1f s' % run.seconds if run.seconds is not None else '-'} {run.note}")
    results = {}
    for key, run in runs.items():
        if run.seconds is not None:
            run.seconds = float(np.median(run.times))
        results[key] = {"method": run.method} | evaluate(data, run)
        if run.poses is not None:
            results[key]["poses"] = run.poses.tolist()
    return {"title": data.title, "unit": data.unit, "scale": data.scale, "wrong": data.wrong,
            "ordered": data.ordered, "reference": data.names[data.reference], "order": data.names,
            "pairs": [[data.names[p], data.names[c]] for p, c in data.tree], "results": results,
            "truth": data.truth.tolist()}


def load(name: str, args) -> Dataset:
    if name == "bunny":
        return bunny(args.seed, args.bunny_points)
    if name == "kitchen":
        return kitchen(args.frames, args.frame_step)
    if name == "bunny-off-sensor":
        return bunny_off_sensor(args.seed)
    if name == "turntable":
        return turntable(args.seed)
    if name == "kitchen-every20":
        return kitchen(args.frames, EVERY20_STEP, name=name)
    if name == "kitchen-gap":
        return kitchen(args.frames, gap=GAP_FRACTION, name=name)
    return newer_college()


# -- tables ----------------------------------------------------------------------------------


def ratio_rows(name: str, entry: dict) -> list[str]:
    """One row per esmicp run: its time against Open3D's and against the pairwise chain's."""
    rows = ["| esmicp run | esmicp time / Open3D time | esmicp time / its pairwise registrations' time |",
            "|---|---|---|"]
    results = entry["results"]
    peer = results.get("open3d", {}).get("seconds")
    pairwise = results.get("pairwise", {}).get("seconds")
    for key, result in results.items():
        if key in ("open3d", "pairwise") or not result["supported"]:
            continue
        rows.append(f"| {result['method']} | {_f(result['seconds'] / peer) if peer else '-'} | "
                    f"{_f(result['seconds'] / pairwise) if pairwise else '-'} |")
    return rows


#: Figures that are counts of scans: any difference is a difference.
COUNTED = ("wrong", "silently_wrong", "unplaced")
#: A measured figure (an error, a time) counts as better only when it is smaller by more than this
#: fraction: rounding and run-to-run noise are not a lead.
MARGIN = 0.05


def _better(theirs, mine, *, counted=False) -> bool:
    if not np.isfinite(theirs):
        return False
    if not np.isfinite(mine):
        return True
    return theirs < mine if counted else theirs < (1.0 - MARGIN) * mine


def where_we_lose(name: str, entry: dict) -> list[str]:
    """Bullets: every figure where Open3D's run or the pairwise chain beats an esmicp run."""
    figures = (("worst_rotation_deg", "worst rotation"), ("median_rotation_deg", "median rotation"),
               ("worst_translation", "worst translation"), ("median_translation", "median translation"),
               ("ate", "ATE"), ("median_rpe_deg", "median pair rotation"), ("median_rpe", "median pair translation"),
               ("wrong", "wrong scans"), ("silently_wrong", "silently wrong scans"), ("unplaced", "unplaced scans"),
               ("seconds", "time"))
    lines = []
    results = entry["results"]
    for key, mine in results.items():
        if key in ("open3d", "pairwise") or not mine["supported"]:
            continue
        for other_key in ("open3d", "pairwise"):
            other = results.get(other_key)
            if not other or not other["supported"]:
                continue
            lost = [label for figure, label in figures if figure in mine and figure in other
                    and _better(other[figure], mine[figure], counted=figure in COUNTED)]
            if lost:
                lines.append(f"- {mine['method']} against {other['method']}: {', '.join(lost)}.")
    return lines or ["- Nothing: every esmicp run matched (within 5%) or beat both references on every figure."]


def markdown(report: dict) -> dict[str, str]:
    """One Markdown block per data set (between its markers): the run's settings, one row per
    method, the time ratios and where a reference does better."""
    settings, versions_ = report["settings"], report["versions"]
    blocks = {}
    for name, entry in report["datasets"].items():
        start, end = markers(name)
        wrong_deg, wrong_units = entry["wrong"]
        lines = [start, "",
                 f"**{entry['title']}** (reference `{entry['reference']}`). Generated by `{settings['command']}` "
                 f"on {report['started']} (esmicp {versions_['esmicp']}, Open3D {versions_.get('open3d', 'not installed')}, "
                 f"{versions_['cpus']} cores shared with other jobs, load average {_f(entry['load'][0], 1)} at the "
                 f"start and {_f(entry['load'][1], 1)} at the end: read the times as ratios within the run). "
                 f"*Wrong*: more than {wrong_deg:g} deg or {wrong_units * entry['scale']:g} {entry['unit']} off"
                 f"{' (positions after the best rigid fit of the trajectory, as for the ATE)' if entry['ordered'] else ''}, "
                 "over every posed scan; *silently*: of those, reported placed. The errors, ATE and pair errors "
                 "are of the scans reported placed.", ""]
        lines += dataset_table(entry)
        notes = [f"{r['method']}: {r['note']}" for r in entry["results"].values() if r["supported"] and r["note"]]
        if notes:
            lines += ["", "; ".join(notes) + "."]
        lines += ["", "Time ratios, same run:", ""] + ratio_rows(name, entry)
        lines += ["", "Where a reference does better in this run (by more than 5%, or by a scan; computed from "
                  "the table):", ""]
        lines += where_we_lose(name, entry) + ["", end]
        blocks[name] = "\n".join(lines)
    return blocks


#: The pictures docs/merge.md opens on (file names in the --pictures folder): the bunny's scans
#: merged, coloured by scan, and the kitchen walk's estimated positions against the truth.
PICTURES = {"bunny": "merge-bunny.png", "kitchen": "merge-kitchen-trajectory.png"}
#: The bunny's views (panel title, horizontal axis, vertical axis; 0, 1, 2 = x, y, z of the
#: reference scan bun000, whose y axis points up).
BUNNY_VIEWS = (("front (x, y)", 0, 1), ("from above (x, z)", 0, 2))


def _relative(poses: np.ndarray, reference: int) -> np.ndarray:
    """``T_reference_scan`` of every scan from ``T_world_scan`` (NaN rows stay NaN)."""
    return np.linalg.inv(poses[reference]) @ poses


def draw_pictures(report: dict, folder: Path, datasets: dict) -> list[Path]:
    """Draw the pictures of :data:`PICTURES` whose data sets are in ``report``, into ``folder``,
    from the poses the report stores (``datasets``: the loaded :class:`Dataset` by name, for the
    bunny's points)."""
    from esmicp_lab.figures import merged_scans_figure, trajectory_figure, write_picture

    written = []
    for name, entry in report["datasets"].items():
        if name not in PICTURES:
            continue
        results = entry["results"]
        reference = entry["order"].index(entry["reference"])
        if name == "bunny":
            key = next((k for k in ("api", "cli") if results.get(k, {}).get("poses") is not None), None)
            if key is None:
                continue
            data = datasets[name]
            if list(data.names) != list(entry["order"]):
                raise SystemExit(f"bunny: the scans' order {data.names} is not the report's {entry['order']} "
                                 "(give the run's --seed)")
            poses = _relative(np.array(results[key]["poses"], dtype=float), reference)
            placed = sum(np.isfinite(pose).all() for pose in poses)
            figure = merged_scans_figure(
                data.clouds, poses, data.names, views=BUNNY_VIEWS,
                title=f"{results[key]['method']}: the bunny's {len(poses)} raw scans in {entry['reference']}'s "
                      f"frame, {placed} placed, one colour per scan")
        else:
            truth = _relative(np.array(entry["truth"], dtype=float), reference)
            key = next((k for k in ("api-sequence", "api") if results.get(k, {}).get("poses") is not None), None)
            if key is None:
                continue
            estimate = _relative(np.array(results[key]["poses"], dtype=float), reference)
            figure = trajectory_figure(
                truth[:, :3, 3], {results[key]["method"]: estimate[:, :3, 3]},
                title=f"{entry['title']}: positions in {entry['reference']}'s frame, seen from above")
        written.append(write_picture(figure, folder / PICTURES[name]))
    return written


def versions() -> dict:
    out = {"esmicp": esmicp.__version__, "numpy": np.__version__, "python": platform.python_version(),
           "cpus": os.cpu_count()}
    commit = subprocess.run(["git", "-C", str(Path(esmicp.__file__).parent), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True)
    if commit.returncode == 0:
        out["esmicp"] += f" at commit {commit.stdout.strip()}"
    try:
        import open3d

        out["open3d"] = open3d.__version__
    except ImportError:
        pass
    return out


def check_harness(args) -> int:
    """Open3D multiway from the true edges (0 ICP iterations), nodes from the chained odometry:
    every error must be ~0, or the frames and inversions of the harness are wrong."""
    worst = 0.0
    for name in ("bunny", "newer-college"):
        data = load(name, args)
        poses, _, _ = merge_open3d.multiway(data.clouds, MULTIWAY_VOXEL[name], initial=data.truth, icp_iterations=0,
                                            nodes_from_initial=False)
        result = evaluate(data, Run("harness", poses, 0.0))
        worst = max(worst, result["worst_rotation_deg"])
        print(f"{name}: worst {result['worst_rotation_deg']:.2e} deg, {result['worst_translation']:.2e} units")
    return 0 if worst < 1e-3 else 1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", nargs="+", choices=DATASETS,
                        default=["bunny", "kitchen", "kitchen-every20", "kitchen-gap"])
    parser.add_argument("--frames", type=int, default=100,
                        help="kitchen and its variants: the first N frames (default all 100; kitchen-every20 takes "
                        "every second of them, kitchen-gap drops 30%% from their middle)")
    parser.add_argument("--frame-step", type=int, default=1, help="kitchen: every K-th frame (default 1)")
    parser.add_argument("--bunny-points", type=int, help="bunny: a seeded subset of this many points per scan")
    parser.add_argument("--loop-gap", type=int, default=20,
                        help="Open3D walk: loop candidates this many frames apart or more (default 20)")
    parser.add_argument("--loop-stride", type=int, default=10,
                        help="Open3D walk: loop candidates among every K-th frame (default 10: one per 100 raw "
                        "frames, the reconstruction system's fragment length, matched against every non-adjacent one)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the shuffled orders")
    parser.add_argument("--repeat", type=int, default=1, help="turns of every method (median time)")
    parser.add_argument("--skip-peer", action="store_true", help="no Open3D runs")
    parser.add_argument("--skip-pairwise", action="store_true", help="no pairwise chain")
    parser.add_argument("--check-harness", action="store_true", help="only check the Open3D harness on the truth")
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--doc", type=Path, help="replace the generated section of this Markdown file")
    parser.add_argument("--pictures", type=Path, help="draw the pictures of the bunny and kitchen runs into this "
                        f"folder ({', '.join(PICTURES.values())}, replaced if they exist; needs matplotlib)")
    parser.add_argument("--pictures-from", type=Path, metavar="REPORT",
                        help="with --pictures: draw them from the --json of an earlier run instead of running "
                        "(the bunny's scans are read again, in the order of --seed)")
    args = parser.parse_args(argv)
    if args.check_harness:
        return check_harness(args)
    if args.pictures is not None and not args.pictures.is_dir():
        parser.error(f"--pictures {args.pictures}: no such folder")
    if args.pictures_from is not None:
        if args.pictures is None:
            parser.error("--pictures-from needs --pictures FOLDER")
        if not args.pictures_from.is_file():
            parser.error(f"--pictures-from {args.pictures_from}: no such file")
        report = json.loads(args.pictures_from.read_text())
        loaded = {name: load(name, args) for name in report["datasets"] if name == "bunny"}
        for path in draw_pictures(report, args.pictures, loaded):
            print(path)
        return 0
    given = list(argv if argv is not None else sys.argv[1:])
    if "--json" in given:  # where the figures were also written is the runner's business, not the page's
        del given[given.index("--json"):given.index("--json") + 2]
    report = {"started": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
              "settings": {"command": " ".join(["python benchmarks/merge_scans.py"] + given)},
              "versions": versions(), "datasets": {}}
    loaded = {}
    for name in args.datasets:
        data = load(name, args)
        print(f"== {data.title}: {sum(len(c) for c in data.clouds)} points, reference {data.names[data.reference]}")
        load_before = os.getloadavg()[0]
        report["datasets"][name] = run_dataset(data, args) | {"load": [load_before, os.getloadavg()[0]]}
        if name == "bunny":
            loaded[name] = data
    blocks = markdown(report)
    print("\n\n".join(blocks.values()))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=float))
    if args.doc:
        write_doc(args.doc, blocks)
    if args.pictures:
        for path in draw_pictures(report, args.pictures, loaded):
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
