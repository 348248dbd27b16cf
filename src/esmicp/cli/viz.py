"""``esmicp view``, ``esmicp heatmap`` and ``esmicp animate``: pictures of a registration's local
iterations (a thin layer over :mod:`esmicp.viz`). ``view`` shows a given pose (``--transform``) or
the clouds as they are (``--as-is``) without registering, or registers as ``esmicp register`` does
(the global search by default) and shows that pose, its iterations too with ``--show-run``;
``heatmap`` and ``animate`` start from the identity by default.
Outputs are written atomically and never over an existing file without ``--force``; bad input
ends in one line on stderr (exit status 2).

Inputs, the same for all three: no file (the built-in shape, the source a rotated copy of it),
one file (the source a rotated copy of that cloud: the paper's protocol, index-aligned), or
SOURCE and TARGET files.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .args import nonnegative_int, output_path, positive_float, positive_int
from ..errors import InvalidInputError
from ..api import INIT_NAMES
from ..methods import METHODS



def _nonnegative_angle(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of degrees, got {text!r}") from None
    if not 0.0 <= value <= 180.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 180] degrees, got {text!r}")
    return value




def add_parser(commands) -> None:
    """Register the ``view``, ``heatmap`` and ``animate`` subcommands on ``commands`` (the
    subparsers object of :func:`esmicp.cli.build_parser`)."""

    def common(parser, *, points_default, points_help, output_help, init=True):
        parser.add_argument("clouds", nargs="*", type=Path, metavar="CLOUD",
                            help="none (built-in shape), one cloud (the source is a rotated copy of it), "
                            "or SOURCE TARGET")
        parser.add_argument("-o", "--output", type=output_path, required=True, help=output_help)
        if init:
            parser.add_argument("--init", default="identity", metavar="identity|global|FILE",
                                help="where the local iterations start: 'identity' (default), 'global' (or "
                                "a strategy, as in 'esmicp register'), or a file with a 4x4 T_target_source "
                                "(for instance one written by 'esmicp register --transform-out')")
        parser.add_argument("--sigma", type=positive_float, help="fixed Gaussian kernel width (cloud units)")
        parser.add_argument("--max-iterations", type=positive_int, default=100, help="default 100")
        parser.add_argument("--points", type=positive_int, default=points_default, metavar="N",
                            help=points_help)
        parser.add_argument("--angle", type=_nonnegative_angle, default=30.0, metavar="DEG",
                            help="rotation of the copy, with no file or one file (default 30 degrees)")
        parser.add_argument("--seed", type=int, default=0,
                            help="seed of the copy's rotation axis and of the built-in shape (default 0)")
        parser.add_argument("--title", help="title of the picture (default: what the input is)")
        parser.add_argument("--force", action="store_true", help="overwrite an existing output file")

    view = commands.add_parser(
        "view", help="interactive 3D viewer of a registration (one self-contained HTML file)",
        description="Write one self-contained HTML page (plotly.js inlined, opens offline in any browser) "
        "showing the target and the source placed by a pose, in 3D. --transform T.txt shows a given pose "
        "and --as-is the clouds as they are, without registering; otherwise the clouds are registered as "
        "'esmicp register' does (the global search, then the local refinement, the same defaults) and the "
        "page shows that pose with the confidence verdict; --show-run adds a slider over the local "
        "refinement's iterations, --compare a second method side by side on the same input. Large clouds "
        "are thinned evenly for display; a scene much wider than tall (a LiDAR scan) opens in a top view.",
    )
    common(view, points_default=None, points_help="downsample each cloud to N well-spread points first "
           "(default: keep all; large clouds are subsampled for display only)",
           output_help="the .html file (- for standard output)", init=False)
    shown = view.add_mutually_exclusive_group()
    shown.add_argument("--init", metavar="FILE|STRATEGY",
                       help=f"where the registration starts, as in 'esmicp register': {', '.join(INIT_NAMES)}, or "
                       "a file holding a 4x4 T_target_source to refine from (default: global)")
    shown.add_argument("--transform", type=Path, metavar="T_FILE",
                       help="show the source placed by this 4x4 T_target_source (for instance from "
                       "'esmicp register --transform-out'), or by the result 'esmicp register --json' wrote "
                       "(a .json file: its pose, its verdict in the caption), without registering")
    shown.add_argument("--as-is", action="store_true",
                       help="show the clouds as they are, without registering (files already aligned)")
    view.add_argument("--method", choices=list(METHODS), default="esm", help="default esm")
    view.add_argument("--compare", choices=list(METHODS), metavar="OTHER_METHOD",
                      help=f"a second method shown side by side ({', '.join(METHODS)})")
    view.add_argument("--show-run", action="store_true",
                      help="when registering: draw the local refinement's iterations too, with a slider")
    view.add_argument("--show-iteration", type=nonnegative_int, metavar="K",
                      help="with --show-run: the iteration the page opens at (default 0, the start; a large "
                      "K: the last)")
    view.add_argument("--max-display-points", type=positive_int, metavar="N",
                      help="most points drawn per cloud (default: more for a scene larger against its point "
                      "spacing, up to a cap; the page says when it thins a cloud)")
    view.add_argument("--camera", choices=["auto", "top", "oblique"], default="auto",
                      help="first view: 'top' looks down --up (orthographic), 'oblique' from above one side; "
                      "'auto' (default) takes the top view for a scene much wider than tall (a LiDAR scan)")
    view.add_argument("--up", default="z", metavar="AXIS",
                      help="the target frame's upward axis: x, y, z, -x, -y or -z (default z, as LiDAR; for "
                      "a depth camera's frame --up=-y, with '=')")
    view.set_defaults(handler=_run_view)

    heat = commands.add_parser(
        "heatmap", help="similarity matrix M over the iterations, as a grid of heat maps (paper Fig. 3)",
        description="Register with each method and draw its similarity matrix M at a few iterations: "
        "esm-paper's symmetric N x N matrix M(i, c(i)) = M(c(i), i) = w_i, esm's N x M matrix "
        "M(i, c(i)) = w_i. The clouds are downsampled to --points well-spread points first (default 21, "
        "as in the paper), so that M is readable.",
    )
    common(heat, points_default=21, points_help="downsample each cloud to N well-spread points (default 21)",
           output_help="the image (.png, .svg or .pdf)")
    heat.add_argument("--methods", default="esm-paper,esm",
                      help=f"comma-separated methods, one row each (default esm-paper,esm; from {', '.join(METHODS)})")
    heat.add_argument("--columns", type=positive_int, default=6, help="iterations shown per method (default 6)")
    heat.set_defaults(handler=_run_heatmap)

    anim = commands.add_parser(
        "animate", help="the alignment as an animated GIF (or MP4 with ffmpeg), rendered headlessly",
        description="Register, then write an animation with one frame per iteration plus the start "
        "(iterations + 1 frames): the target and the source as it moves, coloured by weight.",
    )
    common(anim, points_default=None, points_help="downsample each cloud to N well-spread points first "
           "(default: keep all)", output_help="the animation (.gif, or .mp4 where ffmpeg exists)")
    anim.add_argument("--method", choices=list(METHODS), default="esm", help="default esm")
    anim.add_argument("--fps", type=positive_float, default=4.0, help="frames per second (default 4)")
    anim.add_argument("--max-display-points", type=positive_int, default=1500, metavar="N",
                      help="points drawn per cloud (default 1500)")
    anim.set_defaults(handler=_run_animate)


def _check_output(path: Path, force: bool, allowed: tuple[str, ...], what: str) -> None:
    """Refuse, before any work, an output with the wrong extension, in a missing folder, that
    exists without --force, or that names what is not a regular file (a FIFO, a device, a dangling
    link: :func:`esmicp.io.atomic.output_target`). An HTML page may go to a stream (``-``)."""
    from ..io.atomic import is_stream, output_target
    from ..viz.files import check_extension

    if not (is_stream(path) and ".html" in allowed):
        check_extension(path, allowed, what)
    output_target(path, force)


def _require(*modules: str) -> None:
    """Fail before any work when a plotting library is missing (one line, with the install hint)."""
    from ..viz import require

    for module in modules:
        require(module)


def _inputs(args):
    """``(source, target, description, truth, init)`` from the positional clouds and options."""
    from .. import io
    from ..viz.inputs import builtin_pair, downsample, moved_copy

    if len(args.clouds) > 2:
        raise InvalidInputError(f"CLOUD: give at most two files (SOURCE TARGET), got {len(args.clouds)}")
    given = getattr(args, "init", None)
    init = None if given is None else (given if given in INIT_NAMES else io.read_transform(Path(given)))
    if not args.clouds:
        pair = builtin_pair(points=args.points, angle_deg=args.angle, seed=args.seed)
        return pair.source, pair.target, pair.description, pair.T_target_source, init
    if len(args.clouds) == 1:
        cloud = downsample(io.read_points(args.clouds[0]), args.points)
        pair = moved_copy(cloud, angle_deg=args.angle, seed=args.seed, name=args.clouds[0].name)
        return pair.source, pair.target, pair.description, pair.T_target_source, init
    source = downsample(io.read_points(args.clouds[0]), args.points)
    target = downsample(io.read_points(args.clouds[1]), args.points)
    description = f"{args.clouds[0].name} ({len(source)} points) -> {args.clouds[1].name} ({len(target)} points)"
    return source, target, description, None, init


#: Largest result file ``esmicp view --transform`` reads (bytes): ``esmicp register --json`` writes a
#: few kilobytes (a merge's stages more), so this is no limit for a real one.
MAX_RESULT_BYTES = 16 * 1024 * 1024


def given_pose_file(path: Path):
    """``(T_target_source, label)`` of ``--transform FILE``: a ``.json`` file is the result
    ``esmicp register --json`` wrote (its ``transformation``; its method, confidence and verdict
    label the view), any other file a 4x4 matrix as :func:`esmicp.io.read_transform` reads it."""
    from .. import io

    if path.suffix.lower() != ".json":
        return io.read_transform(path), f"source placed by {path.name}"
    import json

    import numpy as np

    from ..errors import PointCloudFileError
    from ..io._files import check_input_file
    from ..io.text import read_text_file
    from ..types import as_transform

    check_input_file(path)  # missing, a folder, a FIFO, empty: refused in the readers' words
    try:
        result = json.loads(read_text_file(path, max_bytes=MAX_RESULT_BYTES))
    except ValueError as exc:
        raise PointCloudFileError(path, f"not JSON ({exc}); expected the output of 'esmicp register --json'") from None
    if not isinstance(result, dict) or "transformation" not in result:
        raise PointCloudFileError(path, "no 'transformation' in it; expected the output of 'esmicp register --json' "
                                  "(or a text file of 16 numbers)")
    try:
        pose = as_transform(np.asarray(result["transformation"], dtype=np.float64), "transformation")
    except (TypeError, ValueError) as exc:
        raise PointCloudFileError(path, f"its transformation: {exc}") from None
    facts = [str(result["method"])] if isinstance(result.get("method"), str) else []
    if isinstance(result.get("confidence"), (int, float)):
        facts.append(f"confidence {result['confidence']:.2f}")
    if isinstance(result.get("trusted"), bool):
        facts.append("trusted" if result["trusted"] else "not trusted")
    return pose, f"source placed by {path.name}" + (f" ({', '.join(facts)})" if facts else "")


def _run_view(args) -> int:
    from .. import io
    from ..viz.view import view_figure, view_html, write_view

    _check_output(args.output, args.force, (".html", ".htm"), "viewer")
    _require("plotly.graph_objects", "plotly.subplots")
    fixed = args.transform is not None or args.as_is
    flag = "--as-is" if args.as_is else "--transform"
    if fixed and args.compare is not None:
        raise InvalidInputError(f"--compare: compares registrations; {flag} shows a pose without registering")
    if fixed and args.show_run:
        raise InvalidInputError(f"--show-run: draws a registration's iterations; {flag} shows a pose "
                                "without registering")
    if args.show_iteration is not None and not args.show_run:
        raise InvalidInputError("--show-iteration: a step of the registration run; add --show-run to draw the run")
    pose, label = given_pose_file(args.transform) if args.transform is not None else (None, "as given (not registered)")
    source, target, description, truth, init = _inputs(args)
    display = {"max_display_points": args.max_display_points, "camera": args.camera, "up": args.up}
    if fixed:
        import numpy as np

        from ..viz.trace import fixed_trace

        trace = fixed_trace(source, target, np.eye(4) if pose is None else pose, label)
        figure = view_figure([trace], title=args.title or description, truth=truth, **display,
                             subtitle=f"{label}, without registering")
        write_view(figure, args.output, overwrite=args.force)
        print(f"viewer written to {args.output} ({label})")
        return 0
    figure = view_html(
        source, target, show_run=args.show_run, method=args.method, compare=args.compare, init=init,
        sigma=args.sigma, max_iterations=args.max_iterations, title=args.title or description, truth=truth,
        shown_iteration=args.show_iteration, **display,
    )
    write_view(figure, args.output, overwrite=args.force)
    print(f"viewer written to {args.output} ({'; '.join(figure.layout.meta['verdicts'])})")
    return 0


def _run_heatmap(args) -> int:
    from ..viz.files import IMAGE_EXTENSIONS, save_figure
    from ..viz.heatmap import heatmap

    _check_output(args.output, args.force, IMAGE_EXTENSIONS, "image")
    _require("matplotlib.figure", "matplotlib.backends.backend_agg")
    methods = [name.strip() for name in args.methods.split(",") if name.strip()]
    unknown = [name for name in methods if name not in METHODS]
    if unknown or not methods:
        raise InvalidInputError(f"--methods: unknown method(s) {', '.join(unknown) or '(none given)'}; choose from {', '.join(METHODS)}")
    source, target, description, truth, init = _inputs(args)
    figure = heatmap(
        source, target, methods=methods, init=init, sigma=args.sigma, max_iterations=args.max_iterations,
        columns=args.columns, title=args.title or description, truth=truth,
    )
    save_figure(figure, args.output, overwrite=args.force)
    print(f"heat maps written to {args.output}")
    return 0


def _run_animate(args) -> int:
    from ..viz.animate import ANIMATION_EXTENSIONS, animation_figure, write_animation
    from ..viz.trace import trace_registration

    _check_output(args.output, args.force, ANIMATION_EXTENSIONS, "animation")
    _require("matplotlib.figure", "matplotlib.backends.backend_agg", "matplotlib.animation")
    source, target, description, truth, init = _inputs(args)
    trace = trace_registration(
        source, target, method=args.method, init=init, sigma=args.sigma, max_iterations=args.max_iterations
    )
    animation = animation_figure(
        trace, max_display_points=args.max_display_points, title=args.title or description, truth=truth, fps=args.fps
    )
    write_animation(animation, args.output, overwrite=args.force, fps=args.fps)
    print(f"animation written to {args.output} ({trace.label}; {trace.iterations + 1} frames)")
    return 0
