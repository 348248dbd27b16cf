"""``esmicp merge``: many scans into one model (see :func:`esmicp.register_scans`).

All inputs are read and all outputs checked before any work; a scan that cannot be read is named
on stderr and, without ``--skip-bad``, nothing is written (exit status 2).
"""

from __future__ import annotations

import sys
from pathlib import Path

from .args import add_workers, check_distinct_files, positive_float, positive_int
from ..batch import dask_client
from ..errors import EsmicpError, InvalidInputError, OutputExistsError

#: Colours of the scans in the HTML view (cycled).
SCAN_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
                "#7f7f7f", "#bcbd22", "#17becf")


def add_parser(commands) -> None:
    merge = commands.add_parser(
        "merge", help="register many scans into one model (no initial poses, any order)",
        description="Register every scan against the others (global, no initial poses), solve a robust "
        "pose graph, refine all scans jointly, and write the merged cloud and one pose per scan.",
    )
    merge.add_argument("scans", nargs="+", type=Path, metavar="SCAN", help="point-cloud files (2 or more)")
    merge.add_argument("-o", "--output", type=Path, default=Path("merged.ply"), help="merged cloud (default merged.ply)")
    merge.add_argument("--poses-out", type=Path, help="write T_world_scan per scan (text: index, file, 16 numbers)")
    merge.add_argument("--voxel", type=positive_float, help="voxel size of the merged cloud (cloud units)")
    merge.add_argument("--view", type=Path, help="write an HTML view of the merged model coloured by scan")
    merge.add_argument("--bin-columns", type=int, choices=(3, 4), metavar="{3,4}",
                       help=".bin scans: float32 values per point (4: KITTI x y z intensity, 3: x y z); "
                       "needed when a file's size fits both")
    merge.add_argument("--reference", type=int, default=0, help="index of the scan whose frame is the world (default 0)")
    merge.add_argument("--skip-bad", action="store_true", help="merge the readable scans when some cannot be read")
    merge.add_argument("--pair-points", type=positive_int, default=800, help="points per scan for the pairwise registrations")
    merge.add_argument("--processes", type=positive_int, help="local worker processes (default: all cores)")
    add_workers(merge, "1 per registration when several run at once, else every core")
    merge.add_argument("--scheduler", help="address of an existing Dask scheduler to run the pairwise jobs on")
    merge.add_argument("--no-progress", action="store_true", help="no progress bar")
    merge.add_argument("--force", action="store_true", help="overwrite existing output files")
    merge.set_defaults(handler=run_merge)


def _progress(enabled: bool):
    if not enabled:
        return None, lambda: None
    try:
        from tqdm import tqdm
    except ImportError:  # the bar is a nicety: tqdm is in the 'bench' extra
        def report(done, total):
            print(f"\rpairwise registrations: {done}/{total}", end="" if done < total else "\n", file=sys.stderr)
        return report, lambda: None
    bar = tqdm(total=None, desc="pairwise registrations", unit="pair", file=sys.stderr)

    def update(done, total):
        bar.total = total
        bar.n = done
        bar.refresh()

    return update, bar.close


def _write_poses(path: Path, names, result, force: bool) -> None:
    from ..io.atomic import atomic_write

    with atomic_write(path, force, mode="w") as handle:
        handle.write(f"# T_world_scan per scan (world = scan {result.reference}), row-major 4x4; nan: not placed\n")
        for k, name in enumerate(names):
            handle.write(f"{k} {name} " + " ".join(f"{v:.17g}" for v in result.poses[k].ravel()) + "\n")


def _write_view(path: Path, points, labels, names, force: bool) -> None:
    from ..viz import display_subset, require, scatter_trace, write_view

    go = require("plotly.graph_objects")
    figure = go.Figure()
    for k in sorted(set(labels.tolist())):
        mine = points[labels == k]
        shown = display_subset(len(mine), 3000, seed=k)
        figure.add_trace(scatter_trace(go, mine[shown], f"{k}: {names[k]}", SCAN_COLOURS[k % len(SCAN_COLOURS)], "scene"))
    figure.update_layout(title="esmicp merge: merged model coloured by scan (subsampled for display)",
                         scene={"aspectmode": "data"})
    write_view(figure, path, overwrite=force)


def check_paths(args) -> None:
    """Refuse, before any scan is read or anything written, outputs (``--output``,
    ``--poses-out``, ``--view``) that are one file, and an output that is one of the scans (even
    with ``--force``): see :func:`.args.check_distinct_files`."""
    check_distinct_files({"--output": args.output, "--poses-out": args.poses_out, "--view": args.view}, args.scans)


def reference_among_readable(args, unreadable=()) -> int:
    """The position, among the readable scans, of the scan ``--reference`` names (an index into the
    scans as given on the command line, whichever of them ``--skip-bad`` leaves out).

    Raises
    ------
    InvalidInputError
        ``--reference`` is out of range, or names a scan that could not be read (``unreadable``:
        indices into ``args.scans``).
    """
    if not 0 <= args.reference < len(args.scans):
        raise InvalidInputError(f"--reference: expected a scan index in [0, {len(args.scans)}), got {args.reference}")
    if args.reference in unreadable:
        raise InvalidInputError(f"--reference {args.reference}: the scan {args.scans[args.reference]} could not be "
                                "read, so it cannot be the world frame; choose another --reference")
    return args.reference - sum(1 for index in unreadable if index < args.reference)


def run_merge(args) -> int:
    from .. import io
    from ..multiview import register_scans

    check_paths(args)
    outputs = [(args.output, "points"), (args.poses_out, "transform"), (args.view, "transform")]
    for path, kind in outputs:
        if path is None:
            continue
        io.check_writable(path, kind=kind)
        if path.exists() and not args.force:
            raise OutputExistsError(path)
    if args.view is not None and args.view.suffix.lower() not in (".html", ".htm"):
        raise InvalidInputError(f"--view: expected an .html file, got {str(args.view)!r}")
    reference_among_readable(args)
    clouds, names, bad = [], [], []
    for index, path in enumerate(args.scans):
        try:
            clouds.append(io.read_points(path, bin_columns=args.bin_columns))
            names.append(path.name)
        except EsmicpError as exc:
            print(f"esmicp merge: error: {exc}", file=sys.stderr)
            bad.append(index)
    if bad and not args.skip_bad:
        print(f"esmicp merge: {len(bad)} scan(s) unreadable; nothing written (--skip-bad merges the rest)", file=sys.stderr)
        return 2
    if len(clouds) < 2:
        raise InvalidInputError(f"scans: need at least 2 readable scans, got {len(clouds)}")
    reference = reference_among_readable(args, bad)
    client = None
    if args.scheduler:
        client = dask_client(args.scheduler)
    progress, close = _progress(not args.no_progress)
    # Without --workers the library picks the threads (one per registration run in parallel).
    threads = {} if args.workers is None else {"workers": args.workers}
    try:
        result = register_scans(clouds, reference=reference, pair_points=args.pair_points,
                                processes=args.processes, client=client, progress=progress, **threads)
    finally:
        close()
        if client is not None:
            client.close()
    points, labels = result.merged(clouds, voxel=args.voxel)
    io.write_points(args.output, points, overwrite=args.force)
    if args.poses_out is not None:
        _write_poses(args.poses_out, names, result, args.force)
    if args.view is not None:
        _write_view(args.view, points, labels, names, args.force)
    kept = len(result.kept_edges)
    print(f"merged {sum(result.placed)} of {len(clouds)} scans ({len(points)} points) into {args.output}; "
          f"{kept} edges kept, {len(result.edges) - kept} rejected; {result.runtime_s:.1f} s")
    for k in result.unplaced:
        print(f"esmicp merge: warning: scan {names[k]} could not be placed (no confident, consistent edge)", file=sys.stderr)
    return 0
