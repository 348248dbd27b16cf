"""The ``esmicp`` command line: a thin layer that parses arguments, reads files, calls the library
and prints. Bad input ends in one line on stderr and exit status 2; nothing is written then.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from . import __version__
from .errors import EsmicpError, EsmicpWarning, OutputExistsError
from .init.global_search import STRATEGIES
from .io import READ_EXTENSIONS, WRITE_EXTENSIONS
from .methods import METHODS
from .cli_args import positive_float, positive_int
from .cli_bench import add_parser as add_bench_parser
from .cli_viz import add_parser as add_viz_parser

#: ``--init`` values that name a strategy rather than a file.
INIT_NAMES = ("global", *STRATEGIES, "identity", "none")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line (and exit status 2)."""

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")






def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="esmicp",
        description="Rigid registration of 3D point clouds with ESM-ICP. Transforms are "
        "T_target_source: 4x4 matrices that map source coordinates into the target frame.",
    )
    parser.add_argument("--version", action="version", version=f"esmicp {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    commands.required = True
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
        "'features' (global with one strategy), 'identity' (local refinement only), or a file "
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
    reg.add_argument("--seed", type=int, default=0, help="seed of the global search and --sample-points (default 0)")
    reg.add_argument(
        "--output", type=Path, metavar="ALIGNED_FILE",
        help=f"write the aligned source here ({' '.join(WRITE_EXTENSIONS)})",
    )
    reg.add_argument("--transform-out", type=Path, metavar="FILE", help="write T_target_source here (4x4 text)")
    reg.add_argument("--force", action="store_true", help="overwrite existing output files")
    reg.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    reg.set_defaults(handler=_run_register)

    demo = commands.add_parser(
        "demo",
        help="register a built-in shape back onto itself (no files needed)",
        description="Sample a built-in asymmetric shape twice (independent samples, so no point "
        "pairs exactly), move one by a random rigid transform (any rotation, a translation of up to "
        "5 shape sizes per axis), register it back and compare with the truth. Exit status 0 when the "
        "transform is recovered (rotation error < 2 degrees and translation error at the shape < 2%% "
        "of its size), 1 otherwise.",
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--points", type=positive_int, default=2000, help="points per cloud (default 2000)")
    demo.add_argument("--method", choices=list(METHODS), default="esm", help="default esm")
    demo.add_argument(
        "--max-angle", type=positive_float, default=180.0,
        help="largest initial rotation, degrees (default 180: uniform over all rotations)",
    )
    demo.add_argument(
        "--init", default="global", choices=INIT_NAMES,
        help="where registration starts (default global; 'identity' shows a purely local method)",
    )
    demo.add_argument(
        "--copy", action="store_true",
        help="make the source a moved copy of the target in the same point order (the paper's protocol)",
    )
    demo.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    demo.set_defaults(handler=_run_demo)
    add_bench_parser(commands)  # bench
    add_viz_parser(commands)  # view, heatmap, animate
    return parser


def main(argv=None) -> int:
    """Entry point of the ``esmicp`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings():
        warnings.simplefilter("always", EsmicpWarning)
        warnings.showwarning = _show_warning
        try:
            return args.handler(args)
        except EsmicpError as exc:
            print(f"esmicp {args.command}: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except KeyboardInterrupt:
            print(f"esmicp {args.command}: interrupted; no partial output was written", file=sys.stderr)
            return EXIT_INTERRUPTED
        except MemoryError:
            print(f"esmicp {args.command}: error: out of memory (the clouds are too large for this "
                  "machine; downsample them or use a smaller --sample-points)", file=sys.stderr)
            return EXIT_BAD_INPUT
        except OSError as exc:  # a full disk, a folder that vanished: no traceback, one line
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"esmicp {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return EXIT_BAD_INPUT


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"esmicp: warning: {message}", file=sys.stderr)


def _check_output(path: Path | None, force: bool, kind: str) -> None:
    """Refuse early (before any work) an output that exists or has an unwritable format."""
    if path is None:
        return
    from .io import check_writable

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
    from . import io
    from .api import register
    from .core.procrustes import apply

    _check_distinct_outputs(output=args.output, transform_out=args.transform_out)
    _check_output(args.output, args.force, "points")
    _check_output(args.transform_out, args.force, "transform")
    source = io.read_points(args.source, sample_points=args.sample_points, rng=args.seed)
    target = io.read_points(args.target, sample_points=args.sample_points, rng=args.seed + 1)
    init = args.init if args.init in INIT_NAMES else io.read_transform(Path(args.init))
    result = register(
        source, target, method=args.method, init=init, sigma=args.sigma, rng=args.seed,
        max_iterations=args.max_iterations, tolerance=args.tolerance, inlier_distance=args.inlier_distance,
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
        _print_summary(result)
        for label, path in (("aligned source", args.output), ("transform", args.transform_out)):
            if path is not None:
                print(f"{label} written to {path}")
    return EXIT_OK


def _print_summary(result) -> None:
    state = "converged" if result.converged else "NOT converged"
    print(f"method {result.method}: {state}, {result.num_iterations} iterations, {result.runtime_s * 1000:.1f} ms")
    print(f"  start: {result.init}" + (f", {result.global_candidates} candidate poses verified" if result.global_candidates else ""))
    if result.ambiguous:
        print(
            f"  AMBIGUOUS: a clearly different pose fits almost as well (score ratio {result.runner_up_ratio:.3f}); "
            "the object may be symmetric or the overlap too small to tell"
        )
    print(f"  {result.message}")
    sigma = "n/a" if result.sigma is None else f"{result.sigma:.6g}"
    print(
        f"  fitness {result.fitness:.4f}, inlier RMSE {result.inlier_rmse:.6g} "
        f"(inliers within {result.inlier_distance:.6g}), sigma {sigma}"
    )
    print("T_target_source =")
    print(_format_matrix(result.transformation))


def _format_matrix(matrix: np.ndarray) -> str:
    return "\n".join("  " + " ".join(f"{value: .9f}" for value in row) for row in matrix)


def _run_demo(args) -> int:
    from .api import register
    from .core.procrustes import apply, to_matrix
    from .metrics import random_rotation, rotation_error_deg, translation_error
    from .shapes import asymmetric_shape

    rng = np.random.default_rng(args.seed)
    target = asymmetric_shape(args.points, rng)
    sample = target.copy() if args.copy else asymmetric_shape(args.points, rng)
    size = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
    # Move the source by G; the transform that brings it back is T_target_source = G^-1.
    moved_by = to_matrix(random_rotation(rng, args.max_angle), rng.uniform(-5.0, 5.0, 3) * size)
    truth = np.linalg.inv(moved_by)
    source = apply(moved_by, sample)
    result = register(source, target, method=args.method, init=args.init, rng=args.seed)
    rotation_error = rotation_error_deg(result.transformation, truth)
    translation_err = translation_error(result.transformation, truth, pivot=source.mean(axis=0))
    recovered = rotation_error < 2.0 and translation_err < 0.02 * size
    protocol = "copy (same points, same order)" if args.copy else "resampled (independent samples)"
    if args.json:
        report = result.to_dict()
        report.update(
            seed=args.seed, protocol=protocol, true_transformation=truth.tolist(),
            rotation_error_deg=rotation_error, translation_error=translation_err, recovered=recovered,
        )
        print(json.dumps(report))
    else:
        initial_angle = rotation_error_deg(np.eye(4), truth)
        print(f"built-in asymmetric shape, {args.points} points per cloud, {protocol}, seed {args.seed}")
        print(f"initial offset: {initial_angle:.2f} degrees, {np.linalg.norm(truth[:3, 3]):.4f} units "
              f"(shape size {size:.3f})")
        _print_summary(result)
        print("true T_target_source =")
        print(_format_matrix(truth))
        verdict = "recovered" if recovered else "NOT recovered"
        print(
            f"rotation error {rotation_error:.4g} degrees, translation error {translation_err:.4g} units "
            f"(at the source's centroid): {verdict}"
        )
    return EXIT_OK if recovered else EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
