"""A robust SE(3) pose graph: spanning-tree initial poses, SciPy ``least_squares`` optimisation.

Why SciPy: it is already a core dependency, ``least_squares`` is maintained and offers robust losses
(``cauchy``), and a graph of a few dozen scans is small enough for its dense-free trust-region solver.
No pose-graph library (g2o, GTSAM) is needed for that size.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


def pose_from_vector(vector: np.ndarray) -> np.ndarray:
    """The 4x4 rigid transform of a 6-vector ``(rotation vector (rad), translation)``: the pose
    parameters of :func:`optimise`, and the increments of the joint refinement (applied on the
    left, ``T = pose_from_vector(step) @ T``). Inverse of :func:`vector_from_pose`."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(vector[:3]).as_matrix()
    T[:3, 3] = vector[3:]
    return T


def vector_from_pose(T: np.ndarray) -> np.ndarray:
    """The 6-vector ``(rotation vector (rad), translation)`` of a 4x4 rigid transform."""
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def edge_error(T_world_i, T_world_j, T_i_j) -> tuple[float, float]:
    """(rotation error in degrees, translation error) of a measured ``T_i_j`` against two poses."""
    E = np.linalg.inv(T_i_j) @ np.linalg.inv(T_world_i) @ T_world_j
    angle = float(np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec())))
    return angle, float(np.linalg.norm(E[:3, 3]))


def consistent(T_world_i, T_world_j, T_i_j, max_angle_deg: float, max_shift: float) -> bool:
    angle, shift = edge_error(T_world_i, T_world_j, T_i_j)
    return angle <= max_angle_deg and shift <= max_shift


def _triangle_supported(edges, max_angle_deg, max_shift):
    by_pair = {}
    for n, (i, j, T, w) in enumerate(edges):
        by_pair[(i, j)] = (T, w)
        by_pair[(j, i)] = (np.linalg.inv(T), w)
    nodes = sorted({i for e in edges for i in e[:2]})
    out = []
    for n, (i, j, T_i_j, w) in enumerate(edges):
        support = w
        for k in nodes:
            if k in (i, j) or (i, k) not in by_pair or (k, j) not in by_pair:
                continue
            T_i_k, w_ik = by_pair[(i, k)]
            T_k_j, w_kj = by_pair[(k, j)]
            if consistent(np.eye(4), T_i_k @ T_k_j, T_i_j, max_angle_deg, max_shift(n)):
                support += min(w_ik, w_kj)
        out.append((i, j, T_i_j, support))
    return out


def consensus_tree(edges, reference: int, *, max_angle_deg: float, max_shift) -> dict[int, np.ndarray]:
    """Initial ``T_world_scan`` of every scan reachable from ``reference``, grown by consensus.

    ``edges`` are (i, j, T_i_j, weight); ``max_shift(edge_index)`` is an edge's translation
    tolerance. Components of scans are merged one at a time (as in Kruskal's maximum spanning
    tree), but each merge is a vote: every edge between two components proposes their relative
    pose, and the proposal backed by the largest total weight of agreeing edges wins. A wrong
    edge therefore only places a scan when nothing contradicts it. Unreachable scans are absent.
    """
    edges = _triangle_supported(edges, max_angle_deg, max_shift)
    nodes = {i for e in edges for i in e[:2]} | {reference}
    component = {k: k for k in nodes}  # scan -> component label
    frames = {k: np.eye(4) for k in nodes}  # T_component_scan
    while True:
        best = None
        groups: dict[tuple, list] = {}
        for n, (i, j, _, _) in enumerate(edges):
            a, b = component[i], component[j]
            if a != b:
                groups.setdefault((min(a, b), max(a, b)), []).append(n)
        if not groups:
            break
        for (a, b), members in groups.items():
            for n in members:
                i, j, T_i_j, w = edges[n]
                # proposal: T_a_b (component b's frame into component a's)
                if component[i] == a:
                    T_a_b = frames[i] @ T_i_j @ np.linalg.inv(frames[j])
                else:
                    T_a_b = frames[j] @ np.linalg.inv(T_i_j) @ np.linalg.inv(frames[i])
                support = 0.0
                for m in members:
                    p, q, T_p_q, v = edges[m]
                    if component[p] == a:
                        ok = consistent(frames[p], T_a_b @ frames[q], T_p_q, max_angle_deg, max_shift(m))
                    else:
                        ok = consistent(T_a_b @ frames[p], frames[q], T_p_q, max_angle_deg, max_shift(m))
                    support += v if ok else 0.0
                if best is None or support > best[0]:
                    best = (support, a, b, T_a_b)
        _, a, b, T_a_b = best
        for k in nodes:
            if component[k] == b:
                component[k], frames[k] = a, T_a_b @ frames[k]
    root = component[reference]
    T_root_reference = frames[reference]
    return {k: np.linalg.inv(T_root_reference) @ frames[k] for k in nodes if component[k] == root}


def optimise(poses: dict[int, np.ndarray], edges, reference: int, *, translation_scale: float,
             loss: str = "cauchy", rotation_scale_deg: float = 1.0) -> dict[int, np.ndarray]:
    """Minimise the robust edge errors over all placed poses (``reference`` held fixed).

    Each edge's residual is its relative-pose error (rotation vector in units of
    ``rotation_scale_deg``, translation in units of ``translation_scale``), weighted by the square
    root of its weight; the Cauchy loss (scale 1) flattens the pull of edges that disagree.
    """
    free = [k for k in sorted(poses) if k != reference]
    if not free:
        return dict(poses)
    slot = {k: n for n, k in enumerate(free)}
    slot[reference] = len(free)  # the fixed identity, after the free poses
    used = [(i, j, T, w) for i, j, T, w in edges if i in poses and j in poses]
    first = np.array([slot[i] for i, _, _, _ in used], dtype=np.intp)
    second = np.array([slot[j] for _, j, _, _ in used], dtype=np.intp)
    inverse_measured = np.array([np.linalg.inv(T) for _, _, T, _ in used]).reshape(-1, 4, 4)
    roots = np.sqrt(np.array([w for _, _, _, w in used], dtype=float))[:, None]
    rotation_unit = np.radians(rotation_scale_deg)

    def current(x, k):
        return np.eye(4) if k == reference else pose_from_vector(x[6 * slot[k]: 6 * slot[k] + 6])

    def residuals(x):
        # Every edge at once: E = T_i_j^-1 T_world_i^-1 T_world_j, as rotation vector and translation.
        vectors = x.reshape(-1, 6)
        rotations = np.concatenate([Rotation.from_rotvec(vectors[:, :3]).as_matrix(), np.eye(3)[None]])
        translations = np.concatenate([vectors[:, 3:], np.zeros((1, 3))])
        back = np.transpose(rotations[first], (0, 2, 1))  # R_world_i^T
        relative = back @ rotations[second]
        shift = np.einsum("nab,nb->na", back, translations[second] - translations[first])
        error_rotation = inverse_measured[:, :3, :3] @ relative
        error_shift = np.einsum("nab,nb->na", inverse_measured[:, :3, :3], shift) + inverse_measured[:, :3, 3]
        out = np.empty((len(used), 6))
        out[:, :3] = roots * Rotation.from_matrix(error_rotation).as_rotvec() / rotation_unit
        out[:, 3:] = roots * error_shift / translation_scale
        return out.ravel()

    x0 = np.concatenate([vector_from_pose(poses[k]) for k in free])
    solution = least_squares(residuals, x0, loss=loss, f_scale=1.0, x_scale="jac", max_nfev=200)
    result = {reference: np.eye(4)}
    for k in free:
        result[k] = current(solution.x, k)
    return result
