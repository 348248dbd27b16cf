"""``esmicp register``: read two clouds, register, print the transform and its figures, write
the outputs asked for."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..api import INIT_NAMES
from ..io import READ_EXTENSIONS, WRITE_EXTENSIONS
from ..methods import METHODS
from ..types import check_geometry
from .args import (EXIT_OK, EXIT_UNTRUSTED, NORMAL, QUIET, VERBOSE, add_verbosity, add_workers, check_distinct_files,
                   output_path, positive_float, positive_int)


def _confidence_bar(text: str) -> float | str:
    """``--min-confidence``'s value: a number in [0, 1] (``trusted`` is the library's bar)."""
    if text == "trusted":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1] or 'trusted', got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text!r}")
    return value


def add_parser(commands) -> None:
    """Register the ``register`` subcommand on ``commands`` (the subparsers of
    :func:`esmicp.cli.build_parser`)."""
    methods_help = "; ".join(f"{name}: {text}" for name, text in METHODS.items())

    reg = commands.add_parser(
        "register",
        help="register SOURCE onto TARGET and report the transform",
        description=f"Register SOURCE onto TARGET (files: {' '.join(READ_EXTENSIONS)}) and print "
        "the verdict first (the overlap confidence against the trust bar, 0-1: below it, or ambiguous, "
        "do not trust the pose), then the pose (its standard deviations when it is trusted), the run and "
        "the overlap in one line, and T_target_source; -v adds the run's detail, -q prints nothing but "
        "warnings and errors.",
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
        help="where to start: 'global' (default, also 'auto': find the pose from anywhere), "
        "'rotation-search' or 'features' (global with one strategy), 'scan' (global, for partially "
        "overlapping scans: RGB-D fragments, LiDAR), 'identity' (or 'none': local refinement only), "
        "or a file holding a 4x4 T_target_source to refine from",
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
        "intensity), 3 for x y z (default: from the file size, or from the values when the size fits both; "
        "a file whose values cannot tell is refused)",
    )
    reg.add_argument("--seed", type=int, default=0, help="seed of the global search and --sample-points (default 0)")
    reg.add_argument(
        "--output", type=output_path, metavar="ALIGNED_FILE",
        help=f"write the aligned source here ({' '.join(WRITE_EXTENSIONS)})",
    )
    reg.add_argument("--transform-out", type=output_path, metavar="FILE",
                     help="write T_target_source here (4x4 text; - for standard output)")
    reg.add_argument("--force", action="store_true", help="overwrite existing output files")
    reg.add_argument("--json", action="store_true",
                     help="print one JSON object instead of a summary (RegistrationResult.to_dict(): the fields, "
                     "trusted and doubts, the reasons not to trust the pose; and the files and their point counts)")
    reg.add_argument(
        "--min-confidence", type=_confidence_bar, nargs="?", const="trusted", metavar="X",
        help="exit with status 3 when the overlap confidence is below X (0-1), or the refinement did not converge, "
        "or the pose is ambiguous (another pose fits almost as well), degenerate (the overlap lets it slide) or "
        "fails the --range-images test (RegistrationResult.doubts); without X, or 'trusted': the library's trust bar "
        "(RegistrationResult.trusted). For scripts: 'esmicp register A B --min-confidence && ...'",
    )
    reg.add_argument(
        "--range-images", action=argparse.BooleanOptionalAction, default=None,
        help="the clouds are range images in their sensor frames (depth-camera frames, LiDAR scans as "
        "recorded): also check the pose against the space each sensor saw empty, and do not trust a "
        "pose that contradicts it (not for meshes, fused fragments or maps); --no-range-images: never "
        "check; neither: check when both clouds' own points show range images",
    )
    add_workers(reg)
    add_verbosity(reg, "the files, where the run started, why it stopped, the inlier RMSE and sigma, and the "
                  "standard deviation about and along each axis")
    reg.set_defaults(handler=_run_register)



def _check_output(path: Path | None, force: bool, kind: str) -> None:
    """Refuse early (before any work) an output that exists (without --force), has an unwritable
    format, or names what is not a regular file (a FIFO, a device, a dangling link: see
    :func:`esmicp.io.check_writable`)."""
    if path is None:
        return
    from ..io import check_writable

    check_writable(path, kind=kind, overwrite=force)


def _run_register(args) -> int:
    from .. import io
    from ..api import register
    from ..core.procrustes import apply

    check_distinct_files({"--output": args.output, "--transform-out": args.transform_out}, [args.source, args.target])
    _check_output(args.output, args.force, "points")
    _check_output(args.transform_out, args.force, "transform")
    source = io.read_points(args.source, sample_points=args.sample_points, rng=args.seed, bin_columns=args.bin_columns)
    target = io.read_points(
        args.target, sample_points=args.sample_points, rng=args.seed + 1, bin_columns=args.bin_columns
    )
    check_geometry({str(args.source): source, str(args.target): target})  # what register() checks first, by file
    init = args.init if args.init in INIT_NAMES else io.read_transform(Path(args.init))
    result = register(
        source, target, method=args.method, init=init, sigma=args.sigma, rng=args.seed,
        max_iterations=args.max_iterations, tolerance=args.tolerance, inlier_distance=args.inlier_distance,
        workers=args.workers, range_images=args.range_images,
    )
    with io.atomic.published_together():  # both outputs, or neither
        if args.output is not None:
            io.write_points(args.output, apply(result.transformation, source), overwrite=args.force)
        if args.transform_out is not None:
            io.write_transform(args.transform_out, result.transformation, overwrite=args.force)
    if args.json:
        report = result.to_dict()
        report.update(source=str(args.source), target=str(args.target),
                      source_points=len(source), target_points=len(target))
        print(json.dumps(report))
    elif args.verbosity > QUIET:
        if args.verbosity >= VERBOSE:
            print(f"{args.source} ({len(source)} points) -> {args.target} ({len(target)} points)")
        print_summary(result, args.verbosity)
        for label, path in (("aligned source", args.output), ("transform", args.transform_out)):
            if path is not None:
                print(f"{label} written to {path}")
    return _status(result, args.min_confidence)


def _status(result, bar: float | str | None) -> int:
    """``EXIT_UNTRUSTED`` (with one line on stderr) when ``--min-confidence`` was given and the pose
    is in doubt (:meth:`~esmicp.result.RegistrationResult.doubts` against ``bar``: the refinement
    not converged, the confidence below it, the pose ambiguous, degenerate or failing the free-space
    test); else ``EXIT_OK``."""
    if bar is None:
        return EXIT_OK
    bar = result.policy.trusted if bar == "trusted" else bar
    doubts = result.doubts(bar)
    if not doubts:
        return EXIT_OK
    print(f"esmicp register: --min-confidence {bar:g}: {'; '.join(doubts)} (exit status {EXIT_UNTRUSTED})",
          file=sys.stderr)
    return EXIT_UNTRUSTED


def verdict(result) -> str:
    """One line: the overlap confidence against the trust bar the result was judged by
    (``result.policy.trusted``), whether to trust the pose, and every reason not to
    (:meth:`~esmicp.result.RegistrationResult.doubts`)."""
    if result.confidence is None:
        return "confidence unknown: judge the pose yourself"
    bar = result.policy.trusted
    text = f"confidence {result.confidence:.2f}"
    if result.confidence < bar:
        return (f"{text} (LOW: below {bar:g}, do not trust this pose; the clouds may not coincide where it puts "
                f"them, or their overlap may not hold it{_also(result.doubts(0.0))})")
    if result.ambiguous:
        others = result.doubts(0.0, ignore=("ambiguous",))
        return (f"{text} (>= {bar:g}, but AMBIGUOUS: a clearly different pose fits almost as well, score ratio "
                f"{result.runner_up_ratio:.3f}; do not trust this pose: the object may be symmetric or the "
                f"overlap too small to tell{_also(others)})")
    doubts = result.doubts()
    if not result.converged:
        return (f"{text} (>= {bar:g}, but NOT CONVERGED: {'; '.join(doubts)}; do not trust this pose: the "
                "refinement stopped before it settled, raise --max-iterations)")
    if result.degenerate_directions:
        return (f"{text} (>= {bar:g}, but DEGENERATE: {'; '.join(doubts)}; do not trust this pose: the overlap "
                "lets it slide or turn there)")
    if doubts:
        return (f"{text} (>= {bar:g}, but the FREE-SPACE TEST FAILED: {'; '.join(doubts)}; do not trust this pose: "
                "the clouds may share no surface)")
    return f"{text} (trusted: >= {bar:g})"


def _also(doubts: list[str]) -> str:
    """The doubts besides the one a verdict is named after, for the end of its line."""
    return f"; also {'; '.join(doubts)}" if doubts else ""


def print_summary(result, verbosity: int = NORMAL) -> None:
    """Three lines: the verdict, the pose, the run; then ``T_target_source`` (and the runner-up of
    a pose not trusted). ``verbosity`` :data:`~.args.VERBOSE` adds, before the matrix, where the run
    started, why it stopped, the overlap's inlier RMSE and sigma, and the standard deviation about
    and along each axis (of a trusted pose) and each degenerate direction."""
    print(verdict(result))
    print(pose_line(result))
    print(run_line(result))
    if verbosity >= VERBOSE:
        for line in detail_lines(result):
            print(f"  {line}")
    print("T_target_source =")
    print(format_matrix(result.transformation))
    if result.runner_up is not None and not result.trusted:
        # The other place the source may belong (a symmetric twin, a slide along a road).
        print(f"runner-up T_target_source (score ratio {result.runner_up_ratio:.3f}, as verified, not polished) =")
        print(format_matrix(result.runner_up))


def pose_line(result) -> str:
    """How far the pose turns and moves the source, with the largest standard deviation about and
    along an axis when the pose is trusted (beside a pose in doubt they would claim a precision its
    verdict denies)."""
    line = f"pose: rotation {result.rotation_deg:.4g} deg, translation {result.translation_norm:.4g}"
    if result.covariance is not None and result.trusted:
        from ..trust.uncertainty import standard_deviations

        rotation, translation = standard_deviations(result.covariance)
        line += f" (standard deviation per axis at most {rotation.max():.2g} deg, {translation.max():.2g})"
    return line


def run_line(result) -> str:
    """The method, where it started, how it ended and took, and the overlap's fitness."""
    if result.init.startswith("global:"):
        start = f"after a global search ({result.init.removeprefix('global:')})"
    else:
        start = "from the given pose" if result.init == "given" else f"from the {result.init}"
    state = f"converged in {result.num_iterations}" if result.converged else f"NOT converged after {result.num_iterations}"
    return (f"{result.method} {start}: {state} iterations, {result.runtime_s:.2f} s; overlap (not a verdict): "
            f"fitness {result.fitness:.3f} within {result.inlier_distance:.3g}")


def detail_lines(result) -> list[str]:
    """The run's detail (``-v``): the global search, why the refinement stopped (its stages), the
    overlap's inlier RMSE and sigma; of a trusted pose the standard deviation about and along each
    axis; each degenerate direction."""
    lines = []
    if result.global_candidates:
        lines.append(f"global search: {result.global_candidates} candidate poses verified")
    lines.append(result.message)
    sigma = "n/a" if result.sigma is None else f"{result.sigma:.6g}"
    lines.append(f"overlap: fitness {result.fitness:.4f} of the source within {result.inlier_distance:.6g} of the "
                 f"target, inlier RMSE {result.inlier_rmse:.6g}; sigma {sigma}")
    from ..trust.uncertainty import describe

    lines.extend(describe(result.covariance if result.trusted else None, result.degenerate_directions))
    return lines


def format_matrix(matrix: np.ndarray) -> str:
    return "\n".join("  " + " ".join(f"{value: .9f}" for value in row) for row in matrix)


