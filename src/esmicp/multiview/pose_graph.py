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


def whitening(weight: float, information, T_i_j: np.ndarray, *, translation_scale: float,
              rotation_scale_deg: float = 1.0) -> np.ndarray:
    """The 6x6 ``W`` whose ``W @ error`` is an edge's whitened residual, ``error`` being the 6-vector
    (rotation vector, rad, then translation) of ``E = T_i_j^-1 T_world_i^-1 T_world_j`` (a right
    perturbation of the measured ``T_i_j``).

    With a 6x6 ``information`` matrix (inverse covariance of the *left* perturbation ``delta`` of
    ``T_i_j`` in frame i, rotation vector then translation, ``T = pose_from_vector(delta) @ T_i_j``):
    ``W = L^T A`` with ``L L^T = information`` and ``A`` the first-order map ``delta = A error``
    (``A = [[R, 0], [[t]x R, R]]`` for ``T_i_j = (R, t)``), so ``|W error|^2 = delta^T information
    delta``. Without one (or one that is not positive definite): ``sqrt(weight)`` over the units
    ``rotation_scale_deg`` (rotation) and ``translation_scale`` (translation)."""
    if information is not None:
        matrix = np.asarray(information, dtype=float)
        if matrix.shape == (6, 6) and np.isfinite(matrix).all():
            try:
                factor = np.linalg.cholesky(0.5 * (matrix + matrix.T))
            except np.linalg.LinAlgError:
                factor = None
            if factor is not None:
                R, t = T_i_j[:3, :3], T_i_j[:3, 3]
                skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
                A = np.zeros((6, 6))
                A[:3, :3] = R
                A[3:, :3] = skew @ R
                A[3:, 3:] = R
                return factor.T @ A
    root = np.sqrt(weight)
    return np.diag([root / np.radians(rotation_scale_deg)] * 3 + [root / translation_scale] * 3)


def _sparsity(first: np.ndarray, second: np.ndarray, free: int):
    """Which parameters each residual depends on: edge e's 6 residuals on the 6 parameters of each
    of its two poses (the reference, slot ``free``, has none). Sparse, so the solver's memory grows
    with the edges, not with edges x scans."""
    from scipy.sparse import coo_matrix

    rows, cols = [], []
    block_rows = np.repeat(np.arange(6), 6)
    block_cols = np.tile(np.arange(6), 6)
    for e, (a, b) in enumerate(zip(first, second)):
        for k in (a, b):
            if k < free:
                rows.append(6 * e + block_rows)
                cols.append(6 * k + block_cols)
    if not rows:
        return None
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(6 * len(first), 6 * free)).tocsr()


def optimise(poses: dict[int, np.ndarray], edges, reference: int, *, translation_scale: float,
             loss: str = "cauchy", rotation_scale_deg: float = 1.0) -> dict[int, np.ndarray]:
    """Minimise the robust edge errors over all placed poses (``reference`` held fixed).

    ``edges`` are ``(i, j, T_i_j, weight)`` or ``(i, j, T_i_j, weight, information)`` (information
    None or a 6x6 matrix). Each edge's residual is its relative-pose error
    ``E = T_i_j^-1 T_world_i^-1 T_world_j`` (rotation vector, then translation), whitened by
    :func:`whitening`: by the edge's 6x6 information matrix when it has one, else by the square
    root of its weight in units of ``rotation_scale_deg`` and ``translation_scale``. The Cauchy loss
    (scale 1) flattens the pull of edges that disagree.
    """
    free = [k for k in sorted(poses) if k != reference]
    if not free:
        return dict(poses)
    slot = {k: n for n, k in enumerate(free)}
    slot[reference] = len(free)  # the fixed identity, after the free poses
    used = [e for e in edges if e[0] in poses and e[1] in poses]
    if not used:
        return dict(poses)
    first = np.array([slot[e[0]] for e in used], dtype=np.intp)
    second = np.array([slot[e[1]] for e in used], dtype=np.intp)
    inverse_measured = np.array([np.linalg.inv(e[2]) for e in used]).reshape(-1, 4, 4)
    whiten = np.array([whitening(e[3], e[4] if len(e) > 4 else None, e[2], translation_scale=translation_scale,
                                 rotation_scale_deg=rotation_scale_deg) for e in used])

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
        error = np.concatenate([Rotation.from_matrix(error_rotation).as_rotvec(), error_shift], axis=1)
        return np.einsum("nab,nb->na", whiten, error).ravel()

    x0 = np.concatenate([vector_from_pose(poses[k]) for k in free])
    solution = least_squares(residuals, x0, loss=loss, f_scale=1.0, x_scale="jac", max_nfev=200,
                             jac_sparsity=_sparsity(first, second, len(free)))
    result = {reference: np.eye(4)}
    for k in free:
        result[k] = current(solution.x, k)
    return result
