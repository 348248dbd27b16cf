"""The joint refinement of :func:`esmicp.register_scans`: all placed scans against each other at once
(multi-view point-to-plane over the kept edges, Gauss-Newton with Huber weights, each direction of an
edge weighed by the inverse of its own residual variance, the reference held fixed, a few rounds with
a shrinking correspondence distance)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import pose_graph


def refine(poses: dict, clouds: dict, clouds_normals: dict, edges, reference: int, distances, *,
           query_points: int, rounds_per_distance: int, huber_ratio: float, min_pairs: int,
           trees: dict | None = None):
    """``(poses, rmse, residual per scan)`` after refining ``poses`` (``T_world_scan``, modified in
    place) over the pairs ``edges``; ``clouds`` and ``clouds_normals`` in each scan's frame.
    Each step turns a scan about the world's origin: the merge passes its scans in their centroid
    frames (the world the reference's), so the steps are well scaled wherever the data lie.

    ``distances`` are the correspondence cutoffs (cloud units), each used for
    ``rounds_per_distance`` Gauss-Newton steps, its residuals Huber-weighted beyond the cutoff over
    ``huber_ratio``; a direction of an edge with fewer than ``min_pairs`` correspondences within the
    cutoff adds nothing to a step. Each direction of an edge counts in a step with
    the inverse of its own Huber-weighted residual variance (cloud units squared) at that step: the
    maximum-likelihood weight when each pair of scans has a noise of its own. A pair whose surfaces
    agree less (a warped or noisy scan, a surface that is not the same in both, a thin overlap at
    the scans' borders) then pulls less than one whose surfaces coincide, in proportion to how much
    less they agree, instead of every correspondence weighing the same. Each direction of an edge queries at most
    ``query_points`` points of its scan (evenly strided): a 6-degree-of-freedom step needs no more,
    and the queries are its cost. They are strided over the part of the scan
    that lies within the first (largest) cutoff of the other scan at the poses given (found once, by
    one query of every point): the points outside the overlap have no correspondence, so a pair
    that shares a small part of its scans still gets up to ``query_points`` correspondences a step,
    not that share of them. ``rmse`` is the point-to-plane RMS over all
    correspondences of the last step; the residual of scan k is the same over the correspondences
    it takes part in (None for a scan with none, and everything None without a step). ``trees``:
    each scan's :class:`~esmicp.core.compiled_tree.CompiledTree` over ``clouds[k]``, when the caller
    has them (made here otherwise)."""
    from ..core.compiled_tree import CompiledTree

    free = [k for k in sorted(poses) if k != reference]
    slot = {k: n for n, k in enumerate(free)}
    given = trees or {}
    trees = {k: given[k] if k in given else CompiledTree(clouds[k]) for k in poses}  # each in its scan's frame, built once
    subset: dict[tuple[int, int], np.ndarray] = {}  # each direction's queried points, chosen once
    warm: dict[tuple[int, int], np.ndarray] = {}  # last nearest neighbours: seeds (speed only)
    directions = [(a, b) for i, j in edges for a, b in ((i, j), (j, i))]

    def linearise(a_scan, b_scan, cutoff):
        """(J^T W J, J^T W r, sum of r^2, count) of scan b's points against scan a's planes, J the
        derivative of the residuals by scan a's increment (scan b's is -J); None with under
        ``min_pairs``."""
        P_a, P_b = poses[a_scan], poses[b_scan]
        if (a_scan, b_scan) not in subset:
            # every point queried once; the overlap's strided subset keeps its answers for this step
            d, idx = trees[a_scan].query(clouds[b_scan], transform=np.linalg.inv(P_a) @ P_b, workers=1)
            inside = np.flatnonzero(d <= cutoff)
            chosen = subset[(a_scan, b_scan)] = inside[np.arange(0, len(inside), max(1, len(inside) // query_points))]
            mine, d, idx = clouds[b_scan][chosen], d[chosen], idx[chosen]
        else:
            mine = clouds[b_scan][subset[(a_scan, b_scan)]]
            d, idx = trees[a_scan].query(mine, transform=np.linalg.inv(P_a) @ P_b, warm=warm.get((a_scan, b_scan)),
                                         workers=1)
        warm[(a_scan, b_scan)] = idx
        ok = d <= cutoff
        if ok.sum() < min_pairs:
            return None
        b = mine[ok] @ P_b[:3, :3].T + P_b[:3, 3]  # world frame
        a = clouds[a_scan][idx[ok]] @ P_a[:3, :3].T + P_a[:3, 3]
        n = clouds_normals[a_scan][idx[ok]] @ P_a[:3, :3].T
        r = np.einsum("ij,ij->i", n, a - b)
        huber = cutoff / huber_ratio
        w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-300))
        J = np.empty((len(r), 6))  # (b x n, n): the cross product written out (np.cross's own products, less overhead)
        J[:, 0] = b[:, 1] * n[:, 2] - b[:, 2] * n[:, 1]
        J[:, 1] = b[:, 2] * n[:, 0] - b[:, 0] * n[:, 2]
        J[:, 2] = b[:, 0] * n[:, 1] - b[:, 1] * n[:, 0]
        J[:, 3:] = n
        # this direction's own noise, its Huber-weighted residual variance, weighs it (a variance under a
        # millionth of the cutoff, squared, is taken as that: exact data stay finite)
        w = w / max(float(np.sum(w * r * r) / np.sum(w)), (1e-6 * cutoff) ** 2)
        return (J * w[:, None]).T @ J, (J * (w * r)[:, None]).sum(axis=0), float(np.sum(r * r)), len(r)

    rmse, per_scan = None, {}
    # the directions run on a thread each (the queries release the GIL), the sums in order
    with ThreadPoolExecutor() as pool:
        for cutoff in distances:
            for _ in range(rounds_per_distance):
                blocks_H: dict[tuple[int, int], np.ndarray] = {}  # sparse: 6x6 blocks of the scans' pairs
                g = np.zeros(6 * len(free))
                squares, count = 0.0, 0
                scan_squares = {k: [0.0, 0] for k in poses}
                terms = pool.map(lambda direction: linearise(*direction, cutoff), directions)
                for (a_scan, b_scan), term in zip(directions, terms):
                    if term is None:
                        continue
                    JtJ, Jtr, sum_sq, used = term
                    squares += sum_sq
                    count += used
                    for scan in (a_scan, b_scan):
                        scan_squares[scan][0] += sum_sq
                        scan_squares[scan][1] += used
                    blocks = [(a_scan, 1.0), (b_scan, -1.0)]
                    for p, sp in blocks:
                        if p == reference:
                            continue
                        gp = slice(6 * slot[p], 6 * slot[p] + 6)
                        g[gp] += sp * Jtr
                        for q, sq in blocks:
                            if q == reference:
                                continue
                            key = (slot[p], slot[q])
                            block = sp * sq * JtJ
                            blocks_H[key] = blocks_H[key] + block if key in blocks_H else block
                if not free or count == 0:
                    return poses, rmse, per_scan
                rmse = float(np.sqrt(squares / count))
                per_scan = {k: (float(np.sqrt(s / c)) if c else None) for k, (s, c) in scan_squares.items()}
                step = _solve(blocks_H, g)
                for k in free:
                    poses[k] = pose_graph.pose_from_vector(step[6 * slot[k]: 6 * slot[k] + 6]) @ poses[k]
    return poses, rmse, per_scan


def _solve(blocks: dict, g: np.ndarray) -> np.ndarray:
    """``H^-1 (-g)`` for the block-sparse ``H`` (6x6 blocks keyed by slot pairs), with a tiny
    damping so that a scan without correspondences stays where it is. Sparse: the memory is that of
    the blocks (two per kept edge and one per scan), not of a dense (6N)^2 matrix."""
    from scipy.sparse import coo_matrix, identity
    from scipy.sparse.linalg import spsolve

    size = len(g)
    rows, cols, values = [], [], []
    offsets = np.arange(6)
    for (p, q), block in blocks.items():
        rows.append(np.repeat(6 * p + offsets, 6))
        cols.append(np.tile(6 * q + offsets, 6))
        values.append(block.ravel())
    if not values:
        return np.zeros(size)
    H = coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size)).tocsc()
    damping = 1e-9 * H.diagonal().sum() / size
    return np.atleast_1d(spsolve(H + damping * identity(size, format="csc"), -g))
