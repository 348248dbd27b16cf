"""Speed and scale of ``esm`` against Open3D point-to-point ICP and small_gicp GICP, same run.

Usage::

    python benchmarks/speed.py                           # bunny + LiDAR at 1k, 10k, 100k, 1M, 3 repeats
    python benchmarks/speed.py --sizes 1000 10000 --clouds bunny --repeats 5
    python benchmarks/speed.py --plot docs/images/speed.png   # also draw time against N (log-log)
    python benchmarks/speed.py --clouds bunny --iterations-only --peers open3d   # per-iteration ratios against Open3D

Clouds (``../shared/data`` or ``$ESMICP_SHARED_DATA``), resampled to each size N:

- ``bunny``: the Stanford bunny mesh (``bunny/bun_zipper.ply``) sampled on its surface (trimesh,
  area-weighted), target and source from independent seeds, so no point pair is exact; the source
  is then rotated by 10 degrees about a fixed random axis through its centroid. Every method starts
  from the identity; the true pose is that rotation's inverse.
- ``lidar``: the small_gicp LiDAR pair (``lidar_pair_small_gicp``, 69k points each, ground-truth
  ``T_target_source``). Below 69k: a random subset; above: jittered repetition (each point repeated,
  the copies displaced by Gaussian noise of 0.25 median point spacings per axis). Every method
  starts from the ground truth turned by 10 degrees of yaw about the source's centroid.

Per size, interleaved within each repeat (the order rotates), medians over repeats:

- per-iteration cost, as a marginal cost: the same call with ``k`` and ``k + n`` iterations (no
  early stop; n = 20 from 100k points, 2,000,000 / N below, at most 200), difference / n, so that
  KD-tree builds never enter it; ``esm`` is timed at full
  resolution (its coarse phase off), from the same start as the peers; build times separately;
- a full local registration to convergence: ``esmicp.register(init=start)`` (defaults: 100
  iterations max), Open3D ``registration_icp`` (point-to-point, 100 iterations max, its default
  relative criteria), small_gicp GICP on the full clouds (covariances of 20 neighbours, 100
  iterations max, its default epsilons); each call includes its own tree builds;
- a full global registration ``esmicp.register()`` (no initial guess);
- peak memory (``--memory``): each registration at the largest size in a fresh child process,
  peak RSS (``VmHWM``), before (clouds loaded) and after.

Open3D and small_gicp get the same correspondence distance (10% of the target's bounding-box
diagonal, enough for a 10-degree offset) and the same iteration count; all use both cores. The
machine is shared: repeat, and read the ratios (same run, same clouds) rather than absolute times.
Nothing is written unless ``--plot`` / ``--json`` is given.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import esmicp
from esmicp.core.correspondence import NearestNeighbors
from esmicp.core.procrustes import rotation_angle, to_matrix
from esmicp.methods import ConvergenceCriteria, EsmEstimator, SigmaSchedule
from esmicp.methods.local import refine

SHARED = Path(os.environ.get("ESMICP_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
OFFSET_DEG = 10.0
CORRESPONDENCE_FRACTION = 0.1  # of the target's diagonal, for Open3D and small_gicp
ITERATIONS_K, ITERATIONS_N = 5, 20  # marginal cost: (time(k + n) - time(k)) / n; --skip sets k
MARGINAL_POINT_ITERATIONS = 2_000_000  # below 100k points n grows to this / N (200 at 1k, 20 from 100k)


def marginal_iterations(size: int) -> int:
    """n of the marginal cost at ``size`` points: 20, or more for small clouds, so that the timed
    difference is not a few milliseconds of scheduler noise (at 1k, 20 iterations of an Open3D ICP
    last 2 ms)."""
    return max(ITERATIONS_N, min(200, MARGINAL_POINT_ITERATIONS // size))
MAX_ITERATIONS = 100


# --------------------------------------------------------------------------------------- clouds
def _bunny(size: int):
    import trimesh

    mesh = trimesh.load(SHARED / "bunny" / "bun_zipper.ply", process=False)
    target = np.asarray(trimesh.sample.sample_surface(mesh, size, seed=1)[0], dtype=np.float64)
    sample = np.asarray(trimesh.sample.sample_surface(mesh, size, seed=2)[0], dtype=np.float64)
    axis = np.random.default_rng(0).normal(size=3)
    rotation = Rotation.from_rotvec(np.radians(OFFSET_DEG) * axis / np.linalg.norm(axis)).as_matrix()
    centroid = sample.mean(axis=0)
    source = (sample - centroid) @ rotation.T + centroid  # source = M(sample), true T = M^-1
    moved = to_matrix(rotation, centroid - rotation @ centroid)
    return source, target, np.eye(4), np.linalg.inv(moved)


def _resample(points: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    if size <= len(points):
        return points[rng.choice(len(points), size, replace=False)]
    spacing = NearestNeighbors(points).spacing()
    copies = -(-size // len(points))
    repeated = np.repeat(points[None], copies, axis=0)
    repeated[1:] += rng.normal(scale=0.25 * spacing, size=repeated[1:].shape)
    return repeated.reshape(-1, 3)[rng.choice(copies * len(points), size, replace=False)]


def _lidar(size: int):
    folder = SHARED / "lidar_pair_small_gicp"
    source_full = esmicp.read_points(folder / "source.ply")
    target_full = esmicp.read_points(folder / "target.ply")
    truth = esmicp.read_transform(folder / "T_target_source.txt")
    source = _resample(source_full, size, np.random.default_rng(2))
    target = _resample(target_full, size, np.random.default_rng(1))
    yaw = Rotation.from_euler("z", OFFSET_DEG, degrees=True).as_matrix()
    centroid = source.mean(axis=0)
    perturbation = to_matrix(yaw, centroid - yaw @ centroid)
    return source, target, truth @ perturbation, truth


CLOUDS = {"bunny": _bunny, "lidar": _lidar}


def rotation_error_deg(transformation: np.ndarray, truth: np.ndarray) -> float:
    return float(np.degrees(rotation_angle(transformation[:3, :3].T @ truth[:3, :3])))


# -------------------------------------------------------------------------------------- methods
def _timed(function):
    start = time.perf_counter()
    value = function()
    return time.perf_counter() - start, value


class Esm:
    name = "esm"

    def __init__(self, source, target, start):
        self.source, self.target, self.start = source, target, start
        self.index = None

    def build(self):
        index = NearestNeighbors(self.target)
        spacing = index.spacing()
        index.prepare_step(len(self.source))  # the hash and the neighbour graph, otherwise built on first use
        self.index, self.spacing = index, spacing

    def iterations(self, count):
        diagonal = float(np.linalg.norm(np.ptp(self.target, axis=0)))
        estimator = EsmEstimator(SigmaSchedule.auto(self.spacing, diagonal))
        # tolerance -1: never stop early (with 0 a run stops once its RMS distance repeats exactly).
        outcome = refine(self.source, self.index, estimator, init=self.start,
                         criteria=ConvergenceCriteria(count, tolerance=-1.0), scale=diagonal)
        return outcome.num_iterations

    def local(self):
        result = esmicp.register(self.source, self.target, init=self.start, max_iterations=MAX_ITERATIONS)
        return result.transformation, result.num_iterations

    def global_(self):
        result = esmicp.register(self.source, self.target, max_iterations=MAX_ITERATIONS)
        return result.transformation, result.num_iterations


class Open3dIcp:
    name = "open3d-icp"

    def __init__(self, source, target, start):
        import open3d as o3d

        self.o3d = o3d
        self.start = start
        self.source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
        self.target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
        self.distance = CORRESPONDENCE_FRACTION * float(np.linalg.norm(np.ptp(target, axis=0)))

    def build(self):
        self.o3d.geometry.KDTreeFlann(self.target)

    def _run(self, criteria):
        registration = self.o3d.pipelines.registration
        return registration.registration_icp(
            self.source, self.target, self.distance, self.start,
            registration.TransformationEstimationPointToPoint(), criteria,
        )

    def iterations(self, count):
        criteria = self.o3d.pipelines.registration.ICPConvergenceCriteria(0.0, 0.0, count)
        self._run(criteria)
        return count

    def local(self):
        result = self._run(self.o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=MAX_ITERATIONS))
        return np.asarray(result.transformation), None


class SmallGicp:
    name = "small_gicp-gicp"
    threads = 2

    def __init__(self, source, target, start):
        import small_gicp

        self.sg = small_gicp
        self.source_points, self.target_points, self.start = source, target, start
        self.distance = CORRESPONDENCE_FRACTION * float(np.linalg.norm(np.ptp(target, axis=0)))

    def build(self):
        sg = self.sg
        self.source = sg.PointCloud(self.source_points)
        self.target = sg.PointCloud(self.target_points)
        self.tree = sg.KdTree(self.target, num_threads=self.threads)
        sg.estimate_covariances(self.target, self.tree, num_threads=self.threads)
        sg.estimate_covariances(self.source, num_threads=self.threads)

    def _align(self, count, **epsilons):
        return self.sg.align(self.target, self.source, self.tree, self.start, registration_type="GICP",
                             max_correspondence_distance=self.distance, num_threads=self.threads,
                             max_iterations=count, **epsilons)

    def iterations(self, count):
        return self._align(count, rotation_epsilon=0.0, translation_epsilon=0.0).iterations

    def local(self):
        self.build()
        result = self._align(MAX_ITERATIONS)
        return np.array(result.T_target_source), result.iterations


# ------------------------------------------------------------------------------------ measuring
#: The peers ``--peers`` may name.
PEERS = {"open3d": Open3dIcp, "small_gicp": SmallGicp}


def measure(cloud: str, size: int, repeats: int, with_global: bool, with_local: bool = True,
            peers: tuple[str, ...] = tuple(PEERS)) -> dict:
    source, target, start, truth = CLOUDS[cloud](size)
    methods = [Esm(source, target, start), *(PEERS[name](source, target, start) for name in peers)]
    samples: dict[str, dict[str, list]] = {m.name: {} for m in methods}

    def add(method, key, value):
        samples[method.name].setdefault(key, []).append(value)

    if isinstance(methods[0], Esm):  # compile numba kernels outside the timings
        methods[0].build()
        methods[0].iterations(2)
    for repeat in range(repeats):
        order = methods[repeat % len(methods):] + methods[: repeat % len(methods)]
        for method in order:
            build_s, _ = _timed(method.build)
            add(method, "build_ms", 1e3 * build_s)
            extra = marginal_iterations(size)
            short_s, done_short = _timed(lambda: method.iterations(ITERATIONS_K))
            long_s, done_long = _timed(lambda: method.iterations(ITERATIONS_K + extra))
            if done_long - done_short >= extra // 2:  # small_gicp may still stop early
                add(method, "iteration_ms", 1e3 * (long_s - short_s) / (done_long - done_short))
            if not with_local:
                continue
            local_s, (transformation, iterations) = _timed(method.local)
            add(method, "local_s", local_s)
            add(method, "local_error_deg", rotation_error_deg(transformation, truth))
            if iterations is not None:
                add(method, "local_iterations", iterations)
            if with_global and isinstance(method, Esm):
                global_s, (transformation, _) = _timed(method.global_)
                add(method, "global_s", global_s)
                add(method, "global_error_deg", rotation_error_deg(transformation, truth))
    return {name: {key: float(np.median(values)) for key, values in keys.items()} for name, keys in samples.items()}


def paper_speed(size: int, repeats: int) -> tuple[float, float]:
    """Marginal ms per iteration of ``esm`` and ``esm-paper`` on the paper's protocol: the bunny
    sampled at ``size`` points, the source a copy in the same order moved by the 10-degree offset
    (interleaved, medians)."""
    from esmicp.methods import EsmPaperEstimator

    target, _, _, _ = _bunny(size)
    axis = np.array([0.0, 0.6, 0.8])
    rotation = Rotation.from_rotvec(np.radians(OFFSET_DEG) * axis).as_matrix()
    source = (target - target.mean(axis=0)) @ rotation + target.mean(axis=0)
    index = NearestNeighbors(target)
    spacing = index.spacing()
    diagonal = float(np.linalg.norm(np.ptp(target, axis=0)))
    makers = {"esm": lambda: EsmEstimator(SigmaSchedule.auto(spacing, diagonal)),
              "esm-paper": lambda: EsmPaperEstimator(0.1 * diagonal)}
    costs: dict[str, list[float]] = {name: [] for name in makers}

    def run(name, count):
        return refine(source, index, makers[name](), init=np.eye(4),
                      criteria=ConvergenceCriteria(count, tolerance=-1.0), scale=diagonal)

    run("esm", 2)
    for _ in range(repeats):
        for name in makers:
            short_s, _ = _timed(lambda: run(name, ITERATIONS_K))
            long_s, _ = _timed(lambda: run(name, ITERATIONS_K + ITERATIONS_N))
            costs[name].append(1e3 * (long_s - short_s) / ITERATIONS_N)
    return float(np.median(costs["esm"])), float(np.median(costs["esm-paper"]))


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB): ``VmHWM`` of ``/proc/self/status``, which starts
    afresh with the process image. (``getrusage``'s ``ru_maxrss`` does not: on Linux a child
    started by a large parent reports the parent's peak, which hides the child's own.)"""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def memory_child(cloud: str, size: int, mode: str) -> None:
    """Run in a fresh process: print peak RSS (MB) with the clouds loaded, then after registering."""
    source, target, start, truth = CLOUDS[cloud](size)
    before = peak_rss_mb()
    elapsed, result = _timed(lambda: esmicp.register(source, target, init=None if mode == "global" else start))
    after = peak_rss_mb()
    print(json.dumps({"before_mb": before, "after_mb": after, "seconds": elapsed,
                      "error_deg": rotation_error_deg(result.transformation, truth)}))


def memory(cloud: str, size: int, mode: str) -> dict:
    output = subprocess.run(
        [sys.executable, __file__, "--memory-child", cloud, str(size), mode],
        check=True, capture_output=True, text=True,
    ).stdout
    return json.loads(output.strip().splitlines()[-1])


# -------------------------------------------------------------------------------------- reports
def _fmt(value, digits=3):
    return "n/a" if value is None else f"{value:.{digits}g}"


def _ratio(row, method, peer, key="iteration_ms"):
    a, b = row[method].get(key), row.get(peer, {}).get(key)  # a peer left out by --peers: n/a
    return "n/a" if a is None or not b or b <= 0 else f"{a / b:.2f}"


def report(results: dict) -> str:
    lines = [
        "| cloud | N | esm ms/iter | Open3D ms/iter | GICP ms/iter | esm / Open3D | esm / GICP "
        "| build ms esm / Open3D / GICP | esm local s (err deg, iters) | Open3D local s (err) "
        "| GICP local s (err) | esm global s (err) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (cloud, size), row in results.items():
        esm, o3d, gicp = row["esm"], row.get("open3d-icp", {}), row.get("small_gicp-gicp", {})
        lines.append(
            f"| {cloud} | {size:,} | {_fmt(esm.get('iteration_ms'))} | {_fmt(o3d.get('iteration_ms'))} "
            f"| {_fmt(gicp.get('iteration_ms'))} | {_ratio(row, 'esm', 'open3d-icp')} "
            f"| {_ratio(row, 'esm', 'small_gicp-gicp')} "
            f"| {_fmt(esm.get('build_ms'))} / {_fmt(o3d.get('build_ms'))} / {_fmt(gicp.get('build_ms'))} "
            f"| {_fmt(esm.get('local_s'))} ({_fmt(esm.get('local_error_deg'), 2)}, {esm.get('local_iterations', 0):.0f}) "
            f"| {_fmt(o3d.get('local_s'))} ({_fmt(o3d.get('local_error_deg'), 2)}) "
            f"| {_fmt(gicp.get('local_s'))} ({_fmt(gicp.get('local_error_deg'), 2)}) "
            f"| {_fmt(esm.get('global_s'))} ({_fmt(esm.get('global_error_deg'), 2)}) |"
        )
    return "\n".join(lines)


def growth(results: dict) -> str:
    """Log-log slopes of time against N between consecutive sizes (N log N is about 1.0-1.1)."""
    lines = ["| cloud | sizes | esm ms/iter slope | esm local slope | Open3D ms/iter slope |", "|---|---|---|---|---|"]
    for cloud in sorted({cloud for cloud, _ in results}):
        sizes = sorted(size for c, size in results if c == cloud)
        for low, high in zip(sizes, sizes[1:]):
            a, b = results[(cloud, low)], results[(cloud, high)]
            ratio = np.log(high / low)

            def slope(method, key):
                x, y = a.get(method, {}).get(key), b.get(method, {}).get(key)
                return "n/a" if not x or not y or x <= 0 or y <= 0 else f"{np.log(y / x) / ratio:.2f}"

            lines.append(f"| {cloud} | {low:,} -> {high:,} | {slope('esm', 'iteration_ms')} "
                         f"| {slope('esm', 'local_s')} | {slope('open3d-icp', 'iteration_ms')} |")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for cloud, marker in (("bunny", "o"), ("lidar", "s")):
        sizes = sorted(size for c, size in results if c == cloud)
        if not sizes:
            continue
        for method, key, axis in (("esm", "iteration_ms", 0), ("open3d-icp", "iteration_ms", 0),
                                  ("small_gicp-gicp", "iteration_ms", 0), ("esm", "local_s", 1),
                                  ("open3d-icp", "local_s", 1), ("esm", "global_s", 1)):
            values = [results[(cloud, size)].get(method, {}).get(key) for size in sizes]
            if all(v is not None and v > 0 for v in values):
                axes[axis].loglog(sizes, values, marker=marker, label=f"{method} {cloud}" + (" (global)" if key == "global_s" else ""))
    sizes = np.array([1e3, 1e6])
    for axis, base in ((axes[0], 0.1), (axes[1], 0.01)):
        axis.loglog(sizes, base * sizes * np.log(sizes) / (1e3 * np.log(1e3)), "k:", label="N log N")
        axis.set_xlabel("points N")
        axis.legend(fontsize=7)
    axes[0].set_ylabel("ms per iteration (marginal)")
    axes[1].set_ylabel("s per full registration")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)


def main(argv=None) -> None:
    global ITERATIONS_K
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clouds", nargs="+", default=list(CLOUDS), choices=list(CLOUDS))
    parser.add_argument("--sizes", nargs="+", type=int, default=[1_000, 10_000, 100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-global", action="store_true", help="skip the global registrations")
    parser.add_argument("--skip", type=int, default=ITERATIONS_K,
                        help="k: iterations run before the n = 20 timed ones (default 5; 30 times them near convergence)")
    parser.add_argument("--iterations-only", action="store_true",
                        help="time only the per-iteration costs and builds (no full registrations)")
    parser.add_argument("--peers", nargs="+", default=list(PEERS), choices=list(PEERS),
                        help="the peers timed beside esm (default both; small_gicp's 1M iterations take minutes)")
    parser.add_argument("--memory", action="store_true", help="peak RSS at the largest size (child processes)")
    parser.add_argument("--plot", type=Path, help="write a log-log PNG of time against N")
    parser.add_argument("--json", type=Path, help="write the medians as JSON")
    parser.add_argument("--paper", action="store_true",
                        help="only time esm against esm-paper per iteration on index-aligned bunny copies")
    parser.add_argument("--from-json", nargs="+", type=Path, metavar="JSON",
                        help="print the tables (and --plot) from earlier --json outputs instead of measuring")
    parser.add_argument("--memory-child", nargs=3, metavar=("CLOUD", "SIZE", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    ITERATIONS_K = args.skip
    if args.memory_child:
        cloud, size, mode = args.memory_child
        memory_child(cloud, int(size), mode)
        return

    if args.from_json:
        results = {}
        for path in args.from_json:
            for key, row in json.loads(path.read_text()).items():
                cloud, size = key.rsplit(":", 1)
                results[(cloud, int(size))] = row
        results = dict(sorted(results.items()))
        print(report(results))
        print()
        print(growth(results))
        if args.plot:
            plot(results, args.plot)
        return

    if args.paper:
        print("| N | esm ms/iter | esm-paper ms/iter | esm-paper / esm |")
        print("|---|---|---|---|")
        for size in args.sizes:
            esm, paper = paper_speed(size, args.repeats)
            print(f"| {size:,} | {esm:.3g} | {paper:.3g} | {paper / esm:.2f} |", flush=True)
        return

    print(f"# esmicp {esmicp.__version__}, Python {platform.python_version()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f} at start; {args.repeats} repeats, medians")
    results = {}
    for cloud in args.clouds:
        for size in args.sizes:
            results[(cloud, size)] = measure(cloud, size, args.repeats, not (args.no_global or args.iterations_only),
                                             not args.iterations_only, tuple(args.peers))
            print(f"done {cloud} {size} (load {os.getloadavg()[0]:.1f}): {json.dumps(results[(cloud, size)])}",
                  file=sys.stderr, flush=True)
    print(report(results))
    print()
    print(growth(results))
    if args.memory:
        print()
        print("| cloud | N | mode | peak RSS before (MB) | peak RSS after (MB) | time s | error deg |")
        print("|---|---|---|---|---|---|---|")
        for cloud in args.clouds:
            for mode in ("local", "global"):
                row = memory(cloud, max(args.sizes), mode)
                print(f"| {cloud} | {max(args.sizes):,} | {mode} | {row['before_mb']:.0f} | {row['after_mb']:.0f} "
                      f"| {row['seconds']:.2f} | {row['error_deg']:.3g} |")
    print(f"\n# load average {os.getloadavg()[0]:.1f} at the end")
    if args.plot:
        plot(results, args.plot)
    if args.json:
        args.json.write_text(json.dumps({f"{c}:{s}": row for (c, s), row in results.items()}, indent=1))


if __name__ == "__main__":
    main()
