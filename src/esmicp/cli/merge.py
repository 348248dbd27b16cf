"""``esmicp merge``: many scans into one model (see :func:`esmicp.register_scans`).

All inputs are read and all outputs checked before any work; a scan that cannot be read is named
on stderr and, without ``--skip-bad``, nothing is written (exit status 2). Every default is
:func:`esmicp.register_scans`'s own (read from its signature). The command prints one row per
scan (file as given, status, edges kept, confidence, residual), or everything as JSON with
``--json``, and exits with status 3 (:data:`EXIT_PARTIAL`) when a scan is doubtful or unplaced
(the placed scans are still written), unless ``--allow-partial``.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import logging
import os
import sys
from pathlib import Path

from .args import (EXIT_BAD_INPUT, EXIT_OK, EXIT_PARTIAL, QUIET, VERBOSE, add_verbosity, add_workers,
                   check_distinct_files, output_path, positive_float, positive_int, whole_number)
from ..batch import dask_client
from ..errors import EsmicpError, InvalidInputError
from ..types import MIN_POINTS

#: ``--poses-format`` choices, the default first: :data:`esmicp.io.POSE_FORMATS` (spelled out here so
#: that building the parser loads no file reader).
POSE_FORMATS = ("matrix", "tum", "kitti")


def library_defaults() -> dict:
    """:func:`esmicp.register_scans`'s keyword defaults, the one source of the command's defaults:
    a keyword that defaults to None and is a field of :class:`esmicp.config.MergeConfig` takes
    the configuration's default."""
    from ..config import MergeConfig
    from ..multiview.scans import register_scans  # the definition itself, whatever wraps the export

    merge = MergeConfig().to_dict()
    return {name: merge[name] if p.default is None and name in merge else p.default
            for name, p in inspect.signature(register_scans).parameters.items()
            if p.default is not inspect.Parameter.empty}


class _LibraryDefault(str):
    """A help text that ends with the library's default for ``name``, looked up only when the help
    is shown (building the parser must not import the library: ``esmicp demo`` stays light)."""

    def __new__(cls, text: str, name: str):
        made = super().__new__(cls, text)
        made.name = name
        return made

    def __mod__(self, params) -> str:
        value = library_defaults()[self.name]
        return (str(self) + f" (default: {'every core' if value is None else value})") % params


#: The options that are :func:`esmicp.register_scans` keywords: absent from the parsed arguments
#: unless given (``argparse.SUPPRESS``), so that the library's own defaults apply.
LIBRARY_OPTIONS = ("reference", "sequence", "pair_points", "refine_points", "partners", "sequence_neighbours",
                   "range_images", "threads", "processes")


def add_parser(commands) -> None:
    merge = commands.add_parser(
        "merge", help="register many scans into one model (no initial poses, any order)",
        description="Register scans pairwise (global, no initial poses), keep only the trusted pairs in a "
        "robust pose graph, refine all scans jointly, and write the merged cloud of the placed scans and one "
        "pose per scan. Prints one row per scan; exit status 3 when a scan is doubtful or unplaced "
        "(see --allow-partial). Every default is register_scans's own.",
    )
    merge.add_argument("scans", nargs="+", type=Path, metavar="SCAN", help="point-cloud files (2 or more)")
    merge.add_argument("-o", "--output", type=output_path, default=Path("merged.ply"),
                       help="merged cloud (default merged.ply); .ply and .pcd hold each point's scan_index and its "
                       "scan's colour, the other formats x y z only")
    merge.add_argument("--poses-out", type=output_path,
                       help="write T_world_scan per scan, as text in the --poses-format (esmicp.read_poses reads it "
                       "back; - for standard output)")
    merge.add_argument("--poses-format", choices=POSE_FORMATS, default=None,
                       help="matrix (default): 16 numbers a line (row-major 4x4, nan: no pose), then '# index status "
                       "file', np.loadtxt reads it; tum: 'timestamp tx ty tz qx qy qz qw', timestamp = scan index, no "
                       "line for a scan with no pose; kitti: 12 numbers a line (top 3x4), nan: no pose")
    merge.add_argument("--voxel", type=positive_float, help="voxel size of the merged cloud (cloud units)")
    merge.add_argument("--view", type=output_path, help="write an HTML view of the merged model coloured by scan (more "
                       "than 12 scans: a colour scale by scan index, the scan's name on hover; - for standard output)")
    merge.add_argument("--bin-columns", type=int, choices=(3, 4), metavar="{3,4}",
                       help=".bin scans: float32 values per point (4: KITTI x y z intensity, 3: x y z); "
                       "needed when a file's size fits both and its values cannot tell")
    library = argparse.SUPPRESS
    merge.add_argument("--reference", type=int, default=library,
                       help=_LibraryDefault("index of the scan whose frame is the world", "reference"))
    merge.add_argument("--sequence", action="store_true", default=library,
                       help="the scans are given in capture order, consecutive scans close in pose (a walk): "
                       "register neighbours in the order plus loop closures")
    merge.add_argument("--range-images", action=argparse.BooleanOptionalAction, default=library,
                       help="every scan is (or, with --no-range-images, is not) a range image seen from its own "
                       "origin (a depth frame or a LiDAR scan in its sensor frame): the premise of the free-space "
                       "check. Default: judged per scan from its points")
    merge.add_argument("--skip-bad", action="store_true", help="merge the readable scans when some cannot be read")
    merge.add_argument("--allow-partial", action="store_true",
                       help="exit 0 even when some scans are doubtful or unplaced (default: exit status 3)")
    merge.add_argument("--json", action="store_true", help="print the whole result as JSON instead of the table")
    merge.add_argument("--pair-points", type=whole_number(MIN_POINTS), default=library,
                       help=_LibraryDefault("points per scan for the pairwise global searches", "pair_points"))
    merge.add_argument("--refine-points", type=whole_number(MIN_POINTS), default=library,
                       help=_LibraryDefault("points per scan for checking each pair and the joint refinement",
                                            "refine_points"))
    merge.add_argument("--partners", type=positive_int, default=library,
                       help=_LibraryDefault("without --sequence: scans each scan is first registered with", "partners"))
    merge.add_argument("--sequence-neighbours", type=positive_int, default=library,
                       help=_LibraryDefault("with --sequence: next scans each scan is registered with",
                                            "sequence_neighbours"))
    merge.add_argument("--threads", type=positive_int, default=library,
                       help=_LibraryDefault("pairwise registrations run at once on threads", "threads"))
    merge.add_argument("--processes", type=positive_int, default=library,
                       help="run the pairwise registrations on this many worker processes instead of threads")
    add_workers(merge, "1 per registration when several run at once, else every core")
    merge.add_argument("--scheduler", help="address of an existing Dask scheduler to run the pairwise jobs on")
    merge.add_argument("--no-progress", action="store_true", help="no progress bar (-q: none either)")
    merge.add_argument("--force", action="store_true", help="overwrite existing output files")
    add_verbosity(merge, "each pairwise registration (kept, or why not) and the notes of the merge")
    merge.set_defaults(handler=run_merge)


def _progress(enabled: bool):
    """(``progress(stage, done, total)`` for :func:`esmicp.register_scans`, a function closing the
    display): one bar per stage on stderr, labelled with the stage (tqdm when installed, else a
    counter line)."""
    if not enabled:
        return None, lambda: None
    try:
        from tqdm import tqdm
    except ImportError:  # the bar is a nicety: tqdm is in the 'bench' extra
        def report(stage, done, total):
            print(f"\r{stage}: {done}/{total}", end="" if done < total else "\n", file=sys.stderr)
        return report, lambda: None
    bars: list = []

    def close():
        if bars:
            bars.pop().close()

    def update(stage, done, total):
        if done == 0 or not bars:
            close()
            pairs = "pairs" in stage  # its bar stays; a one-step stage's goes when it is done
            bars.append(tqdm(total=total, desc=stage, unit="registration" if pairs else "step", file=sys.stderr,
                             leave=pairs))
        bars[-1].n = done
        bars[-1].refresh()
        if done == total:
            close()

    return update, close


def _write_poses(path: Path, names, result, format: str, force: bool) -> None:
    from ..io import write_poses

    write_poses(path, result.poses, format=format, names=names, status=result.status, reference=result.reference,
                overwrite=force)


def _write_view(path: Path, points, labels, names, force: bool) -> None:
    from ..viz import merged_scans_figure, write_view

    write_view(merged_scans_figure(points, labels, names), path, overwrite=force)


def check_paths(args) -> None:
    """Refuse, before any scan is read or anything written, outputs (``--output``,
    ``--poses-out``, ``--view``) that are one file, an output that is one of the scans (even
    with ``--force``): see :func:`.args.check_distinct_files`; and each output that exists (without
    ``--force``), names what is not a regular file (a FIFO, a device, a dangling link: never
    replaced) or has a format that cannot be written (:func:`esmicp.io.check_writable`)."""
    from .. import io

    check_distinct_files({"--output": args.output, "--poses-out": args.poses_out, "--view": args.view}, args.scans)
    for path, kind in ((args.output, "points"), (args.poses_out, "transform"), (args.view, "transform")):
        if path is not None:
            io.check_writable(path, kind=kind, overwrite=args.force)
    if args.poses_format is not None and args.poses_out is None:
        raise InvalidInputError("--poses-format: give --poses-out FILE too (the file the poses are written to)")
    if args.view is not None:
        if not io.atomic.is_stream(args.view) and args.view.suffix.lower() not in (".html", ".htm"):
            raise InvalidInputError(f"--view: expected an .html file, got {shown(args.view)!r}")
        from ..viz import require

        require("plotly.graph_objects")  # before the work, not after it


def shown(path) -> str:
    """A file name as the user typed it, printable whatever its bytes: bytes that are not UTF-8 as
    ``\\xNN`` escapes (a terminal or a strict UTF-8 output cannot take them raw)."""
    return os.fsencode(str(path)).decode("utf-8", "backslashreplace")


def reference_among_readable(args, unreadable=()) -> int:
    """The position, among the readable scans, of the scan ``--reference`` names (an index into the
    scans as given on the command line, whichever of them ``--skip-bad`` leaves out).

    Raises
    ------
    InvalidInputError
        ``--reference`` is out of range, or names a scan that could not be read (``unreadable``:
        indices into ``args.scans``).
    """
    given = getattr(args, "reference", None)
    if given is None:
        given = library_defaults()["reference"]
    if not 0 <= given < len(args.scans):
        raise InvalidInputError(f"--reference: expected a scan index in [0, {len(args.scans)}), got {given}")
    if given in unreadable:
        raise InvalidInputError(f"--reference {given}: the scan {shown(args.scans[given])} could not be "
                                "read, so it cannot be the world frame; choose another --reference")
    return given - sum(1 for index in unreadable if index < given)


#: Fewest points a merged cloud must keep (what every point-cloud reader of esmicp accepts).
MIN_MERGED_POINTS = 3


def check_voxel(voxel: float | None, clouds) -> None:
    """Refuse, before the merge, a ``--voxel`` that would leave about one point per scan (not
    smaller than the largest scan's extent, its bounding box's longest side) or that is too small to
    number the voxels across the scans (over 2^62 per axis)."""
    if voxel is None or not clouds:
        return
    import numpy as np

    largest = max(float(np.ptp(cloud, axis=0).max()) for cloud in clouds)
    if voxel >= largest:
        raise InvalidInputError(f"--voxel {voxel:g}: not smaller than the largest scan ({largest:.4g} units across): "
                                "the merged cloud would keep about one point per scan; give a size well below the "
                                "scans' extent (a point spacing)")
    if largest / voxel >= 2.0**62:
        raise InvalidInputError(f"--voxel {voxel:g}: too small for the scans' extent ({largest:.4g} units across: "
                                "over 2^62 voxels per axis)")


def as_given(result, readable: list[int], count: int, problems: dict[int, str]):
    """``result`` (of the readable scans, in their order) over all ``count`` scans as the user
    listed them: every index, the reference and the edges' ends are positions in that list; a scan
    that could not be read (``problems``: index -> why) has no pose and the status ``unreadable``."""
    if len(readable) == count:
        return result
    import numpy as np

    where = {k: readable[k] for k in range(len(readable))}
    poses = np.full((count, 4, 4), np.nan)
    poses[readable] = result.poses
    per_scan = {name: [None] * count for name in ("status", "scan_confidence", "reasons", "edges_kept", "residual")}
    for k, index in where.items():
        for name, values in per_scan.items():
            values[index] = getattr(result, name)[k]
    for index, problem in problems.items():
        per_scan["status"][index], per_scan["reasons"][index] = "unreadable", (f"could not be read: {problem}",)
        per_scan["edges_kept"][index] = 0
    placed = tuple(per_scan["status"][k] == "placed" for k in range(count))
    return dataclasses.replace(
        result, poses=poses, reference=where[result.reference], placed=placed,
        unplaced=tuple(sorted([where[k] for k in result.unplaced] + list(problems))),
        edges=tuple(dataclasses.replace(e, i=where[e.i], j=where[e.j]) for e in result.edges),
        **{name: tuple(values) for name, values in per_scan.items()})


def run_merge(args) -> int:
    from .. import io
    from ..multiview import register_scans

    check_paths(args)
    reference_among_readable(args)
    clouds, bad = [], {}
    for index, path in enumerate(args.scans):
        try:
            clouds.append(io.read_points(path, bin_columns=args.bin_columns))
        except EsmicpError as exc:
            print(f"esmicp merge: error: {exc}", file=sys.stderr)
            bad[index] = str(exc).removeprefix(f"{path}: ")
            clouds.append(None)
    if bad and not args.skip_bad:
        print(f"esmicp merge: {len(bad)} scan(s) unreadable; nothing written (--skip-bad merges the rest)", file=sys.stderr)
        return EXIT_BAD_INPUT
    readable = [k for k in range(len(args.scans)) if k not in bad]
    if len(readable) < 2:
        raise InvalidInputError(f"scans: need at least 2 readable scans, got {len(readable)}")
    check_voxel(args.voxel, [clouds[k] for k in readable])
    options = {name: getattr(args, name) for name in LIBRARY_OPTIONS if hasattr(args, name)}
    options["reference"] = reference_among_readable(args, bad)
    client = None
    if args.scheduler:
        client = dask_client(args.scheduler)
    progress, close = _progress(not args.no_progress and args.verbosity > QUIET)
    # Without --workers the library picks the threads (one per registration run in parallel).
    threads = {} if args.workers is None else {"workers": args.workers}
    # The library logs each doubtful or unplaced scan by its index; the command names it by its file
    # below, so the library's own lines would only repeat them.
    scans_log = logging.getLogger("esmicp.multiview.scans")
    level = scans_log.level
    scans_log.setLevel(logging.ERROR)
    try:
        result = register_scans([clouds[k] for k in readable], client=client, progress=progress, **options, **threads)
    finally:
        scans_log.setLevel(level)
        close()
        if client is not None:
            client.close()
    result = as_given(result, readable, len(args.scans), bad)  # indices of the scans as listed
    if not any(result.placed):  # pragma: no cover - the reference is always placed
        raise InvalidInputError("scans: no scan could be placed")
    points, labels = result.merged(clouds, voxel=args.voxel)
    if len(points) < MIN_MERGED_POINTS:
        raise InvalidInputError(f"--voxel {args.voxel:g}: leaves {len(points)} point(s) of the merged cloud; give a "
                                "smaller size")
    names = [str(path) for path in args.scans]
    # All outputs or none (an interrupt, a full disk or a refused path leaves no partial set); the
    # scan index and a colour per scan, where the format holds them (a warning says when not).
    with io.atomic.published_together():
        io.write_points(args.output, points, overwrite=args.force, scan_index=labels,
                        colors=io.scan_palette(len(args.scans))[labels])
        if args.poses_out is not None:
            _write_poses(args.poses_out, names, result, args.poses_format or POSE_FORMATS[0], args.force)
        if args.view is not None:
            _write_view(args.view, points, labels, [shown(name) for name in names], args.force)
    if args.json:
        print(json.dumps({**result.to_dict(), "files": names, "output": str(args.output)}, indent=1))
    elif args.verbosity > QUIET:
        print(scan_table(result, [shown(name) for name in names]))
        if args.verbosity >= VERBOSE:
            for line in detail_lines(result):
                print(line)
        kept = len(result.kept_edges)
        print(f"merged {sum(result.placed)} of {len(args.scans)} scans ({len(points)} points) into {shown(args.output)}; "
              f"{result.pairs_registered} pairwise registrations, {kept} edges kept; "
              f"free-space check: {result.free_space_check}; {result.runtime_s:.1f} s")
    left_out = [k for k in readable if not result.placed[k]]
    for k in left_out:
        print(f"esmicp merge: warning: scan {shown(names[k])} {result.status[k]}: {'; '.join(result.reasons[k])}",
              file=sys.stderr)
    if left_out and not args.allow_partial:
        print(f"esmicp merge: {len(left_out)} scan(s) doubtful or unplaced, not merged (exit status {EXIT_PARTIAL}; "
              "--allow-partial exits 0)", file=sys.stderr)
        return EXIT_PARTIAL
    return EXIT_OK


def detail_lines(result) -> list[str]:
    """``-v``: one line per pairwise registration (its scans, how it started, the confidence and
    overlap, kept or why not), then the merge's notes."""
    lines = [f"pairwise registrations ({len(result.edges)}; T_i_j maps scan j into scan i):"]
    for edge in result.edges:
        confidence = "-" if edge.confidence is None else f"{edge.confidence:.2f}"
        lines.append(f"  {edge.i}-{edge.j} {edge.kind}: confidence {confidence}, overlap {edge.overlap:.2f}; "
                     f"{edge.reason}")
    lines.extend(f"note: {note}" for note in result.notes)
    return lines


def scan_table(result, names) -> str:
    """One row per scan: index, file as given, status, edges kept, confidence, residual (cloud units)."""
    rows = [("#", "scan", "status", "edges", "confidence", "residual")]
    for k, name in enumerate(names):
        confidence = result.scan_confidence[k]
        residual = result.residual[k]
        rows.append((str(k), name, result.status[k], str(result.edges_kept[k]),
                     "-" if confidence is None else f"{confidence:.2f}",
                     "-" if residual is None else f"{residual:.3g}"))
    widths = [max(len(row[c]) for row in rows) for c in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows)
