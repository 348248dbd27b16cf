"""``esmicp register``: read two clouds, register, print the transform and its figures, write
the outputs asked for."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..api import INIT_NAMES
from ..errors import EsmicpError, OutputExistsError
from ..io import READ_EXTENSIONS, WRITE_EXTENSIONS
from ..methods import METHODS
from .args import EXIT_OK, add_workers, positive_float, positive_int


def add_parser(commands) -> None:
    """Register the ``register`` subcommand on ``commands`` (the subparsers of
    :func:`esmicp.cli.build_parser`)."""
    methods_help = "; ".join(f"{name}: {text}" for name, text in METHODS.items())

    reg = commands.add_parser(
        "register",
        help="register SOURCE onto TARGET and report the transform",
        description=f"Register SOURCE onto TARGET (files: {' '.join(READ_EXTENSIONS)}) and print "
        "T_target_source with fitness figures. Exit status: 0 done (see 'converged' in the report), "
        "2 bad input (nothing written), 130 interrupted (nothing written).",
    )
    reg.add_argument("source", type=Path, help="point cloud to move")
    reg.add_argument("target", type=Path, help="point cloud to align to")
    reg.add_argument("--method", choices=list(METHODS), default="esm", help=f"default esm. {methods_help}")
    reg.add_argument(
        "--sigma", type=positive_float,
        help="Gaussian kernel width in the clouds' units (default: esm chooses it from the data "
        "each iteration; esm-paper uses the paper's 1.0)",
    )
    reg.add_argument("--max-iterations", type=positive_int, default=100, help="default 100")
    reg.add_argument("--tolerance", type=float, default=1e-8, help="convergence tolerance (default 1e-8)")
    reg.add_argument(
        "--init", default="global", metavar="FILE|STRATEGY",
        help="where to start: 'global' (default: find the pose from anywhere), 'rotation-search' or "
        "'features' (global with one strategy), 'scan' (global, for partially overlapping scans: "
        "RGB-D fragments, LiDAR), 'identity' (local refinement only), or a file "
        "holding a 4x4 T_target_source to refine from",
    )
    reg.add_argument(
        "--inlier-distance", type=positive_float,
        help="distance (cloud units) that counts as an inlier for fitness (default 3 target point spacings)",
    )
    reg.add_argument(
        "--sample-points", type=positive_int, metavar="N",
        help="for mesh files (.off .obj .stl, .ply with faces): sample N points on the surface "
        "instead of taking the vertices (seeded by --seed)",
    )
    reg.add_argument(
        "--bin-columns", type=int, choices=(3, 4), metavar="{3,4}",
        help="for headerless float32 .bin scans: floats per point, 4 for KITTI velodyne (x y z "
        "intensity), 3 for x y z (default: from the file size; a size that fits both is refused)",
    )
    reg.add_argument("--seed", type=int, default=0, help="seed of the global search and --sample-points (default 0)")
    reg.add_argument(
        "--output", type=Path, metavar="ALIGNED_FILE",
        help=f"write the aligned source here ({' '.join(WRITE_EXTENSIONS)})",
    )
    reg.add_argument("--transform-out", type=Path, metavar="FILE", help="write T_target_source here (4x4 text)")
    reg.add_argument("--force", action="store_true", help="overwrite existing output files")
    reg.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    add_workers(reg)
    reg.set_defaults(handler=_run_register)



def _check_output(path: Path | None, force: bool, kind: str) -> None:
    """Refuse early (before any work) an output that exists or has an unwritable format."""
    if path is None:
        return
    from ..io import check_writable

    check_writable(path, kind=kind)
    if path.is_symlink() and not path.exists():
        raise EsmicpError(f"{path}: is a dangling symbolic link (to {os.readlink(path)!r}); remove it or "
                          "give another output path")
    if path.exists() and not force:
        raise OutputExistsError(path)


def _check_distinct_outputs(**paths) -> None:
    """Refuse two outputs that are one file (before any work: the second would replace the first)."""
    given = [(flag, path) for flag, path in paths.items() if path is not None]
    for index, (flag, path) in enumerate(given):
        for other_flag, other in given[index + 1:]:
            same = Path(os.path.abspath(path)) == Path(os.path.abspath(other))
            if not same and path.exists() and other.exists():
                same = os.path.samefile(path, other)
            if same:
                raise EsmicpError(f"--{other_flag.replace('_', '-')} {other}: is the same file as --{flag} "
                                  f"{path}; give two different files")


def _run_register(args) -> int:
    from .. import io
    from ..api import register
    from ..core.procrustes import apply

    _check_distinct_outputs(output=args.output, transform_out=args.transform_out)
    _check_output(args.output, args.force, "points")
    _check_output(args.transform_out, args.force, "transform")
    source = io.read_points(args.source, sample_points=args.sample_points, rng=args.seed, bin_columns=args.bin_columns)
    target = io.read_points(
        args.target, sample_points=args.sample_points, rng=args.seed + 1, bin_columns=args.bin_columns
    )
    init = args.init if args.init in INIT_NAMES else io.read_transform(Path(args.init))
    result = register(
        source, target, method=args.method, init=init, sigma=args.sigma, rng=args.seed,
        max_iterations=args.max_iterations, tolerance=args.tolerance, inlier_distance=args.inlier_distance,
        workers=args.workers,
    )
    if args.output is not None:
        io.write_points(args.output, apply(result.transformation, source), overwrite=args.force)
    if args.transform_out is not None:
        io.write_transform(args.transform_out, result.transformation, overwrite=args.force)
    if args.json:
        report = result.to_dict()
        report.update(source=str(args.source), target=str(args.target),
                      source_points=len(source), target_points=len(target))
        print(json.dumps(report))
    else:
        print(f"{args.source} ({len(source)} points) -> {args.target} ({len(target)} points)")
        print_summary(result)
        for label, path in (("aligned source", args.output), ("transform", args.transform_out)):
            if path is not None:
                print(f"{label} written to {path}")
    return EXIT_OK


def print_summary(result) -> None:
    state = "converged" if result.converged else "NOT converged"
    print(f"method {result.method}: {state}, {result.num_iterations} iterations, {result.runtime_s * 1000:.1f} ms")
    print(f"  start: {result.init}" + (f", {result.global_candidates} candidate poses verified" if result.global_candidates else ""))
    if result.ambiguous:
        print(
            f"  AMBIGUOUS: a clearly different pose fits almost as well (score ratio {result.runner_up_ratio:.3f}); "
            "the object may be symmetric or the overlap too small to tell"
        )
    if result.confidence is not None:
        from ..globalreg.scan import TRUSTED  # not at import: `esmicp --version` stays light

        low = result.confidence < TRUSTED
        print(f"  overlap confidence {result.confidence:.2f}" + (
            f" (LOW, below {TRUSTED:g}: do not trust the pose; the clouds may not coincide where it "
            "puts them, or their overlap may not hold it)" if low else ""))
    print(f"  {result.message}")
    sigma = "n/a" if result.sigma is None else f"{result.sigma:.6g}"
    print(
        f"  fitness {result.fitness:.4f}, inlier RMSE {result.inlier_rmse:.6g} "
        f"(inliers within {result.inlier_distance:.6g}), sigma {sigma}"
    )
    if result.covariance is not None:
        from ..uncertainty import describe

        for line in describe(result.covariance, result.degenerate_directions):
            print(f"  {line}")
    print("T_target_source =")
    print(format_matrix(result.transformation))


def format_matrix(matrix: np.ndarray) -> str:
    return "\n".join("  " + " ".join(f"{value: .9f}" for value in row) for row in matrix)


