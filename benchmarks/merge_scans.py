"""Many scans into one model: ``esmicp.register_scans`` against Open3D's multiway registration, same run.

Usage::

    python benchmarks/merge_scans.py                     # bunny, bunny shuffled, Newer College; Open3D on both
    python benchmarks/merge_scans.py --cases bunny --no-open3d --processes 1
    python benchmarks/merge_scans.py --check-harness     # Open3D from the truth with 0 iterations: errors ~0

Data (``../shared/data`` or ``$ESMICP_SHARED_DATA``):

- ``bunny``: the Stanford bunny's 10 raw range scans (``bunny_scans``, ground truth ``bun.conf``
  read by :func:`esmicp.io.stanford_conf.load_scans`), every point of every scan, reference
  ``bun000``; ``bunny-shuffled``: the same scans in a seeded random order (``--seed``), the
  reference moved with ``bun000``, the poses mapped back to the conf order before comparing.
- ``newer-college``: the 5 LiDAR scans of ``real_pairs/newer_college_01`` (headerless float32
  ``x y z``, ``planes_0000K0.bin``), ground truth ``graph.txt`` (``vK x y z qx qy qz qw``,
  ``T_v0_vK``), reference ``v0``.

Every method is given the scans with no initial pose. Errors: for every scan k, the estimated
``T_reference_k`` against the truth's, rotation (degrees) and translation (mm for the bunny, m for
the LiDAR); worst and median over the non-reference scans; unplaced scans count as failures.

Open3D's multiway registration, with the settings of its tutorial
(``pipelines/multiway_registration``): voxel downsampling, normals (radius 2 voxels, 30
neighbours), every pair registered by point-to-plane ICP coarse (``voxel * 15``) then fine
(``voxel * 1.5``), the information matrix from ``get_information_matrix_from_point_clouds``, a
``PoseGraph`` with odometry edges (k, k+1, certain) and loop edges (all other pairs, uncertain),
nodes from the chained odometry, ``global_optimization`` with Levenberg-Marquardt, its default
``GlobalOptimizationConvergenceCriteria`` and ``GlobalOptimizationOption(max_correspondence_distance
= fine, edge_prune_threshold = 0.25, reference_node = 0)``. Run twice: from the identity (the
tutorial's start, no initial poses) and from the ground-truth poses (each ICP from the true
``T_target_source``, the nodes at the true ``T_world_scan``). Frames: an Open3D node pose is
``T_world_scan``; an edge (source, target) holds ``T_target_source``.

Times are wall clock of the registration call only (loading excluded); the machine is shared, so
read the ratios of the same run. Nothing is written unless ``--json`` is given.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import esmicp
from esmicp.io import read_points
from esmicp.io.stanford_conf import load_scans
from esmicp.metrics import rotation_error_deg

#: Open3D voxel size per case (the tutorial's 0.02 m is for room-scale scans; the bunny is 0.15 m).
OPEN3D_VOXEL = {"bunny": 0.002, "bunny-shuffled": 0.002, "newer-college": 0.2}
CASES = ("bunny", "bunny-shuffled", "newer-college")


def shared_data() -> Path:
    return Path(os.environ.get("ESMICP_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def bunny_case():
    """(names, clouds, truth T_world_scan, reference index, unit name, unit scale)."""
    scans = load_scans(shared_data() / "bunny_scans")
    names = list(scans)
    return names, [scans[n][0] for n in names], [scans[n][1] for n in names], names.index("bun000")


def newer_college_case():
    folder = shared_data() / "real_pairs" / "newer_college_01"
    truth = {}
    for line in (folder / "graph.txt").read_text().splitlines():
        fields = line.split()
        if len(fields) == 8 and fields[0].startswith("v"):
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat([float(v) for v in fields[4:8]]).as_matrix()
            T[:3, 3] = [float(v) for v in fields[1:4]]
            truth[int(fields[0][1:])] = T
    names = [f"planes_{10 * k:06d}" for k in sorted(truth)]
    clouds = [read_points(folder / f"{name}.bin", bin_columns=3) for name in names]
    return names, clouds, [truth[k] for k in sorted(truth)], 0


def errors(poses, truth, reference):
    """Per scan (rotation deg, translation) of T_reference_k against the truth; NaN if unplaced."""
    out = []
    for k in range(len(truth)):
        true = np.linalg.inv(truth[reference]) @ truth[k]
        if not np.isfinite(poses[k]).all() or not np.isfinite(poses[reference]).all():
            out.append((float("nan"), float("nan")))
            continue
        estimate = np.linalg.inv(poses[reference]) @ poses[k]
        out.append((rotation_error_deg(estimate, true), float(np.linalg.norm(estimate[:3, 3] - true[:3, 3]))))
    return out


def run_esmicp(clouds, reference, processes):
    start = time.perf_counter()
    result = esmicp.register_scans(clouds, reference=reference, processes=processes)
    return result.poses, time.perf_counter() - start, result


def run_open3d(clouds, voxel, initial=None, *, icp_iterations=None, nodes_from_initial=True):
    """Open3D's tutorial multiway registration; ``initial``: T_world_scan per scan (else identity
    ICP starts and nodes from the chained odometry, as in the tutorial). ``icp_iterations=0`` with
    the truth and ``nodes_from_initial=False`` is the harness check: ICP leaves the true edges
    as they are, the chained odometry must rebuild the true nodes, and the optimisation must keep
    them."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    start = time.perf_counter()
    pcds = []
    for points in clouds:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 2, max_nn=30))
        pcds.append(pcd)
    coarse, fine = voxel * 15, voxel * 1.5
    icp_criteria = (reg.ICPConvergenceCriteria() if icp_iterations is None
                    else reg.ICPConvergenceCriteria(max_iteration=icp_iterations))

    def pairwise(source, target):
        if initial is None:
            T_target_source = np.eye(4)
        else:
            T_target_source = np.linalg.inv(initial[target]) @ initial[source]
        estimation = reg.TransformationEstimationPointToPlane()
        rough = reg.registration_icp(pcds[source], pcds[target], coarse, T_target_source, estimation, icp_criteria)
        final = reg.registration_icp(pcds[source], pcds[target], fine, rough.transformation, estimation, icp_criteria)
        information = reg.get_information_matrix_from_point_clouds(pcds[source], pcds[target], fine, final.transformation)
        return final.transformation, information

    pairs = []  # (source, target, T_target_source, odometry?) as registered, before the optimisation
    graph = reg.PoseGraph()
    odometry = np.eye(4)  # T_scan_world of the last node (the tutorial's chained odometry)
    from_initial = initial is not None and nodes_from_initial
    if initial is not None and not nodes_from_initial:
        odometry = np.linalg.inv(initial[0])
    graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry) if not from_initial else np.array(initial[0])))
    for source in range(len(pcds)):
        for target in range(source + 1, len(pcds)):
            T_target_source, information = pairwise(source, target)
            pairs.append((source, target, np.array(T_target_source), target == source + 1))
            if target == source + 1:
                odometry = T_target_source @ odometry
                node = np.array(initial[target]) if from_initial else np.linalg.inv(odometry)
                graph.nodes.append(reg.PoseGraphNode(node))
                graph.edges.append(reg.PoseGraphEdge(source, target, T_target_source, information, uncertain=False))
            else:
                graph.edges.append(reg.PoseGraphEdge(source, target, T_target_source, information, uncertain=True))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=fine, edge_prune_threshold=0.25,
                                          reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = np.array([np.asarray(node.pose) for node in graph.nodes])
    return poses, time.perf_counter() - start, pairs


def edge_report(pairs, truth, max_angle_deg=1.0):
    """How many pairwise ICP results (all, odometry) are off the true T_target_source."""
    off = [odometry for s, t, T, odometry in pairs
           if rotation_error_deg(T, np.linalg.inv(truth[t]) @ truth[s]) > max_angle_deg]
    return (f"{len(off)} of {len(pairs)} pairwise ICP results > {max_angle_deg:g} deg off the truth "
            f"({sum(off)} of {sum(o for *_, o in pairs)} odometry edges, which the optimisation never prunes)")


def summary(errs, reference, scale):
    rows = [e for k, e in enumerate(errs) if k != reference]
    rotation = np.array([r for r, _ in rows])
    shift = np.array([t for _, t in rows]) * scale
    placed = np.isfinite(rotation)
    if not placed.all():
        worst_r = worst_t = float("inf")
    else:
        worst_r, worst_t = float(rotation.max()), float(shift.max())
    return {
        "worst_rotation_deg": worst_r, "median_rotation_deg": float(np.nanmedian(rotation)) if placed.any() else float("nan"),
        "worst_translation": worst_t, "median_translation": float(np.nanmedian(shift)) if placed.any() else float("nan"),
        "placed": int(placed.sum()) + 1, "scans": len(errs),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--seed", type=int, default=0, help="seed of the shuffled order")
    parser.add_argument("--processes", type=int, help="register_scans processes (default: all cores)")
    parser.add_argument("--no-open3d", action="store_true")
    parser.add_argument("--check-harness", action="store_true",
                        help="only run Open3D with true edges (ICP from the truth, 0 iterations), nodes from "
                        "their chained odometry, and the global optimisation: every error must be ~0")
    parser.add_argument("--per-scan", action="store_true", help="print every scan's errors")
    parser.add_argument("--json", type=Path, help="write every figure, the settings and the versions here")
    args = parser.parse_args(argv)

    loaded = {}
    report = {"settings": vars(args) | {"json": str(args.json) if args.json else None,
                                        "open3d_voxel": OPEN3D_VOXEL},
              "versions": versions(), "cases": {}}
    for case in args.cases:
        if case.startswith("bunny"):
            names, clouds, truth, reference = loaded.setdefault("bunny", bunny_case())
            unit, scale, target = "mm", 1000.0, (1.0, 1.0)
        else:
            names, clouds, truth, reference = newer_college_case()
            unit, scale, target = "m", 1.0, (1.0, 0.1)
        order = list(range(len(clouds)))
        if case == "bunny-shuffled":
            order = [int(k) for k in np.random.default_rng(args.seed).permutation(len(clouds))]
        given = [clouds[k] for k in order]
        given_truth = [truth[k] for k in order]
        given_reference = order.index(reference)

        def back(poses):  # poses in the given order -> the original order
            out = np.full((len(clouds), 4, 4), np.nan)
            for position, k in enumerate(order):
                out[k] = poses[position]
            return out

        print(f"\n== {case}: {len(clouds)} scans ({sum(len(c) for c in clouds)} points), reference "
              f"{names[reference]}, order {[names[k] for k in order] if order != sorted(order) else 'as listed'}")
        runs = {}
        if args.check_harness:
            poses, seconds, _ = run_open3d(given, OPEN3D_VOXEL[case], initial=given_truth, icp_iterations=0,
                                           nodes_from_initial=False)
            runs["open3d, truth edges, odometry nodes"] = (back(poses), seconds)
        else:
            poses, seconds, result = run_esmicp(given, given_reference, args.processes)
            runs["esmicp register_scans"] = (back(poses), seconds)
            rejected = [(names[order[e.i]], names[order[e.j]], e.reason) for e in result.rejected_edges]
            print(f"esmicp: {len(result.kept_edges)} edges kept, {len(rejected)} rejected, unplaced "
                  f"{[names[order[k]] for k in result.unplaced]}")
            if not args.no_open3d:
                poses, seconds, pairs = run_open3d(given, OPEN3D_VOXEL[case])
                runs["open3d multiway, identity start"] = (back(poses), seconds)
                print("open3d, identity start: " + edge_report(pairs, given_truth))
                poses, seconds, pairs = run_open3d(given, OPEN3D_VOXEL[case], initial=given_truth)
                runs["open3d multiway, truth start"] = (back(poses), seconds)
                print("open3d, truth start: " + edge_report(pairs, given_truth))
        base = next(iter(runs.values()))[1]
        print(f"{'method':36s} {'worst deg':>10s} {'median deg':>10s} {'worst ' + unit:>10s} "
              f"{'median ' + unit:>10s} {'placed':>7s} {'time s':>7s} {'x esmicp':>8s} target")
        report["cases"][case] = {"order": [names[k] for k in order], "runs": {}}
        for label, (poses, seconds) in runs.items():
            errs = errors(poses, truth, reference)
            s = summary(errs, reference, scale)
            met = s["worst_rotation_deg"] <= target[0] and s["worst_translation"] <= target[1]
            print(f"{label:36s} {s['worst_rotation_deg']:10.3f} {s['median_rotation_deg']:10.3f} "
                  f"{s['worst_translation']:10.3f} {s['median_translation']:10.3f} {s['placed']:3d}/{s['scans']:<3d} "
                  f"{seconds:7.1f} {seconds / base:8.2f} {'met' if met else 'MISSED'}")
            if args.per_scan:
                for k, (r, t) in enumerate(errs):
                    print(f"    {names[k]:14s} {r:9.4f} deg {t * scale:10.4f} {unit}")
            report["cases"][case]["runs"][label] = s | {"time_s": seconds, "target_met": bool(met),
                                                        "per_scan": {names[k]: e for k, e in enumerate(errs)}}
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=float))
    return 0


def versions() -> dict:
    out = {"esmicp": esmicp.__version__, "numpy": np.__version__, "python": platform.python_version(),
           "cpus": os.cpu_count()}
    try:
        import open3d

        out["open3d"] = open3d.__version__
    except ImportError:
        pass
    try:
        out["load_average"] = os.getloadavg()
    except OSError:
        pass
    return out


if __name__ == "__main__":
    sys.exit(main())
