"""The pose graph and the joint refinement of ``register_scans`` at scale: time and peak memory.

A synthetic walk of N scans (each a step of about 3 degrees and 0.17 cloud units from the last),
every scan a view of one bumpy sheet of ``--points`` points in its own frame; edges between each
scan and its next two, plus N loop closures between random pairs; each edge's measured pose off
the truth by about 0.2 degrees and 0.9 cm. Runs the stages ``register_scans`` runs on its kept
edges: the consensus tree, the robust pose-graph optimisation, then the joint refinement
(normals, 6 correspondence distances). The pairwise registrations are not run: their cost is N
times a pair's (see docs/merge.md).

    python benchmarks/merge_scale.py --scans 1000 --points 8000

Prints each stage's time, the worst pose error against the truth and the process's peak memory
(resident set, MB: everything this process holds, the clouds and normals included).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from esmicp.config import MergeConfig  # noqa: E402
from esmicp.core.features import estimate_normals  # noqa: E402
from esmicp.multiview import pose_graph  # noqa: E402
from esmicp.multiview.refine import refine  # noqa: E402


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def walk(count: int, rng) -> list[np.ndarray]:
    """``T_world_scan`` of each scan: each a random small step from the last."""
    poses = [np.eye(4)]
    for _ in range(count - 1):
        step = np.concatenate([rng.normal(scale=0.05, size=3), rng.normal(scale=0.1, size=3)])
        poses.append(poses[-1] @ pose_graph.pose_from_vector(step))
    return poses


def worst_error(poses: dict, truth: list) -> tuple[float, float]:
    angles, shifts = zip(*(pose_graph.edge_error(np.eye(4), poses[k], truth[k]) for k in poses))
    return max(angles), max(shifts)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=int, default=1000)
    parser.add_argument("--points", type=int, default=8000, help="points a scan (register_scans' refine_points)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    n = args.scans
    truth = walk(n, rng)
    pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 3))}
    while len(pairs) < 3 * n - 3:  # loop closures between random scans
        i, j = sorted(int(k) for k in rng.choice(n, 2, replace=False))
        pairs.add((i, j))
    pairs = sorted(pairs)

    def measured(i, j):
        noise = np.concatenate([rng.normal(scale=0.003, size=3), rng.normal(scale=0.005, size=3)])
        return pose_graph.pose_from_vector(noise) @ np.linalg.inv(truth[i]) @ truth[j]

    edges = [(i, j, measured(i, j), 1.0, None) for i, j in pairs]
    print(f"{n} scans, {len(edges)} edges ({len(edges) - (2 * n - 3)} loop closures), {args.points} points a scan")

    start = time.perf_counter()
    tree = pose_graph.consensus_tree([e[:4] for e in edges], 0, max_angle_deg=4.0, max_shift=lambda m: 0.1)
    print(f"consensus tree: {time.perf_counter() - start:.1f} s")
    start = time.perf_counter()
    poses = pose_graph.optimise(tree, edges, 0, translation_scale=0.01,
                                direct_solve_max_poses=MergeConfig().direct_solve_max_poses)
    angle, shift = worst_error(poses, truth)
    print(f"pose graph: {time.perf_counter() - start:.1f} s; worst {angle:.2f} deg / {shift:.3f} off the truth; "
          f"peak memory {peak_mb():.0f} MB")

    u = rng.uniform(-1.0, 1.0, (args.points, 2))
    sheet = np.column_stack([u, 0.1 * np.sin(3 * u[:, 0]) * np.cos(2 * u[:, 1])])
    clouds = {k: (sheet - T[:3, 3]) @ T[:3, :3] for k, T in enumerate(truth)}  # each in its scan's frame
    start = time.perf_counter()
    normals = {k: estimate_normals(cloud, k=12, workers=None) for k, cloud in clouds.items()}
    print(f"normals: {time.perf_counter() - start:.1f} s; peak memory {peak_mb():.0f} MB")
    nudged = {k: (pose_graph.pose_from_vector(rng.normal(scale=0.002, size=6)) @ T if k else np.eye(4))
              for k, T in enumerate(truth)}
    start = time.perf_counter()
    merge = MergeConfig()
    refined, rmse, _ = refine(nudged, clouds, normals, pairs, 0, np.geomspace(0.05, 0.02, 6),
                              query_points=merge.query_points, rounds_per_distance=merge.refine_steps,
                              huber_ratio=merge.refine_huber_ratio, min_pairs=merge.refine_min_pairs)
    angle, shift = worst_error(refined, truth)
    print(f"joint refinement: {time.perf_counter() - start:.1f} s; worst {angle:.3f} deg / {shift:.4f} off the truth; "
          f"peak memory {peak_mb():.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
