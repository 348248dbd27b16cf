"""A robust SE(3) pose graph: spanning-tree initial poses by consensus, then a robust least-squares
over every edge at once.

The optimiser is a Levenberg-Marquardt on left increments of the poses with the Jacobian in
closed form and iteratively reweighted Cauchy residuals (the loss of SciPy's ``least_squares``
with ``loss="cauchy"``), each step's sparse normal equations solved directly up to
``direct_solve_max_poses`` poses (:class:`esmicp.config.MergeConfig`) and by conjugate gradients
beyond: its memory grows with the edges. Measured (one solve, 2 cores): a 100-scan walk in 0.2 s; 1,000 scans
with 3,000 edges (1,000 of them random loop closures) in 6 s; a 1,000-scan walk with only local
loop closures (2,327 edges) in 14 s, where conjugate gradients need the most steps (a sparse
direct solve is faster on a walk, but fills in on random loop closures: 400 s). No pose-graph
library (g2o, GTSAM) is needed.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.procrustes import batched_rotation_angle, rigid_inverse, skew


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


def edge_errors(T_world_i, T_world_j, T_i_j) -> tuple[np.ndarray, np.ndarray]:
    """(rotation errors in degrees, translation errors) of measured ``T_i_j`` against two poses:
    ``E = T_i_j^-1 T_world_i^-1 T_world_j``; arrays of rigid transforms (..., 4, 4), broadcast.

    The translation error is how far ``E`` moves the origin of frame j: a rotation error moves it
    by the angle times the origin's distance from the data, so it measures the data's own
    displacement only when each frame's origin is at its data. :func:`esmicp.register_scans`
    passes every scan in its centroid frame for that reason."""
    E = rigid_inverse(T_i_j) @ rigid_inverse(T_world_i) @ np.asarray(T_world_j)
    return np.degrees(batched_rotation_angle(E[..., :3, :3])), np.linalg.norm(E[..., :3, 3], axis=-1)


def edge_error(T_world_i, T_world_j, T_i_j) -> tuple[float, float]:
    """(rotation error in degrees, translation error) of a measured ``T_i_j`` against two poses."""
    angle, shift = edge_errors(T_world_i, T_world_j, T_i_j)
    return float(angle), float(shift)


def _triangle_supported(edges, max_angle_deg, max_shift):
    """Each edge's weight plus, for every triangle it closes consistently, the smaller weight of the
    triangle's two other edges."""
    by_pair: dict[tuple[int, int], tuple[np.ndarray, float]] = {}
    neighbours: dict[int, set[int]] = {}
    for i, j, T, w in edges:
        by_pair[(i, j)] = (T, w)
        by_pair[(j, i)] = (rigid_inverse(T), w)
        neighbours.setdefault(i, set()).add(j)
        neighbours.setdefault(j, set()).add(i)
    out = []
    for n, (i, j, T_i_j, w) in enumerate(edges):
        common = sorted((neighbours[i] & neighbours[j]) - {i, j})
        support = w
        if common:
            through = np.array([by_pair[(i, k)][0] @ by_pair[(k, j)][0] for k in common])
            angle, shift = edge_errors(np.eye(4), through, T_i_j)
            ok = (angle <= max_angle_deg) & (shift <= max_shift(n))
            support += sum(min(by_pair[(i, k)][1], by_pair[(k, j)][1]) for k, good in zip(common, ok) if good)
        out.append((i, j, T_i_j, support))
    return out


def _best_proposal(a, members, edges, component, frames, max_angle_deg, max_shift):
    """(support, T_a_b) of the relative pose of components a and b that the largest total weight of
    the edges between them (``members``) agrees with; each edge proposes one."""
    T_left, T_right, measured, weights, tolerance, from_a = [], [], [], [], [], []
    for m in members:
        p, q, T_p_q, v = edges[m]
        T_left.append(frames[p])
        T_right.append(frames[q])
        measured.append(T_p_q)
        weights.append(v)
        tolerance.append(max_shift(m))
        from_a.append(component[p] == a)
    T_left, T_right, measured = np.array(T_left), np.array(T_right), np.array(measured)
    weights, tolerance, from_a = np.array(weights), np.array(tolerance), np.array(from_a)
    # each member's proposal T_a_b (component b's frame into component a's)
    proposals = np.where(from_a[:, None, None],
                         T_left @ measured @ rigid_inverse(T_right),
                         T_right @ rigid_inverse(measured) @ rigid_inverse(T_left))
    # every proposal (rows) against every member (columns): move the member's b-side scan by it
    moved_left = np.where(from_a[None, :, None, None], T_left[None], proposals[:, None] @ T_left[None])
    moved_right = np.where(from_a[None, :, None, None], proposals[:, None] @ T_right[None], T_right[None])
    angle, shift = edge_errors(moved_left, moved_right, measured[None])
    support = ((angle <= max_angle_deg) & (shift <= tolerance[None])) @ weights
    best = int(np.argmax(support))  # the first of equals, as a loop would keep it
    return float(support[best]), proposals[best]


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
    members_of = {k: [k] for k in nodes}  # component label -> its scans
    frames = {k: np.eye(4) for k in nodes}  # T_component_scan
    groups: dict[tuple[int, int], list[int]] = {}  # (a, b) -> indices of the edges between them, ascending
    for n, (i, j, _, _) in enumerate(edges):
        if i != j:
            groups.setdefault((min(i, j), max(i, j)), []).append(n)
    votes: dict[tuple[int, int], tuple[float, np.ndarray]] = {}  # valid until the group changes
    while groups:
        best = None
        # the most supported vote; among equals, the group with the lowest edge index
        for key in sorted(groups, key=lambda key: groups[key][0]):
            if key not in votes:
                votes[key] = _best_proposal(key[0], groups[key], edges, component, frames, max_angle_deg, max_shift)
            support, T_a_b = votes[key]
            if best is None or support > best[0]:
                best = (support, key, T_a_b)
        _, (a, b), T_a_b = best
        for k in members_of[b]:
            component[k], frames[k] = a, T_a_b @ frames[k]
        members_of[a].extend(members_of.pop(b))
        # b's groups become a's; only the groups that gained edges vote again
        for key in [key for key in groups if b in key]:
            moved = groups.pop(key)
            votes.pop(key, None)
            other = key[0] if key[1] == b else key[1]
            if other != a:
                merged = (min(a, other), max(a, other))
                groups[merged] = sorted(groups.get(merged, []) + moved)
                votes.pop(merged, None)
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
                A = np.zeros((6, 6))
                A[:3, :3] = R
                A[3:, :3] = skew(t) @ R
                A[3:, 3:] = R
                return factor.T @ A
    root = np.sqrt(weight)
    return np.diag([root / np.radians(rotation_scale_deg)] * 3 + [root / translation_scale] * 3)


def _right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_r^-1(phi)`` (..., 3, 3): ``log(exp(phi) exp(d)) = phi + J_r^-1(phi) d`` to first order."""
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    coefficient = np.where(small, 1.0 / 12.0,
                           1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(np.where(small, 1.0, safe))))
    return np.eye(3) + 0.5 * K + coefficient * (K @ K)


def _conjugate_gradients(matrix, right, blocks: np.ndarray) -> np.ndarray:
    """``matrix^-1 right`` for a sparse symmetric positive definite ``matrix`` (a damped normal
    matrix), by conjugate gradients preconditioned by the inverses of its 6x6 diagonal ``blocks``
    (one per pose), to a relative residual of 10^-6 (Levenberg-Marquardt keeps a step only when it
    lowers the cost, so an inexact step costs time, never the result)."""
    from scipy.sparse.linalg import LinearOperator, cg

    inverse = np.linalg.inv(blocks)
    preconditioner = LinearOperator(matrix.shape, matvec=lambda v: np.einsum("kab,kb->ka", inverse, v.reshape(-1, 6)).ravel())
    solution, _ = cg(matrix, right, M=preconditioner, rtol=1e-6, atol=0.0, maxiter=10 * len(right))
    return solution


def optimise(poses: dict[int, np.ndarray], edges, reference: int, *, translation_scale: float,
             direct_solve_max_poses: int, loss: str = "cauchy", rotation_scale_deg: float = 1.0,
             max_iterations: int = 100) -> dict[int, np.ndarray]:
    """Minimise the robust edge errors over all placed poses (``reference`` held fixed).

    ``edges`` are ``(i, j, T_i_j, weight)`` or ``(i, j, T_i_j, weight, information)`` (information
    None or a 6x6 matrix). Each edge's residual is its relative-pose error
    ``E = T_i_j^-1 T_world_i^-1 T_world_j`` (rotation vector, then translation), whitened by
    :func:`whitening`: by the edge's 6x6 information matrix when it has one, else by the square
    root of its weight in units of ``rotation_scale_deg`` and ``translation_scale``. The cost is
    ``sum log(1 + r^2)`` over the whitened residuals' components (``loss="cauchy"``, scale 1: it
    flattens the pull of edges that disagree) or ``sum r^2`` (``loss="linear"``).

    Translations, and the information matrices' translation parts, are taken at the frames'
    origins (see :func:`edge_errors`): the merge's frames are its scans' centroid frames.

    Levenberg-Marquardt over left increments of the free poses (``R <- exp(phi) R``,
    ``t <- t + rho``), the Jacobian in closed form, the Cauchy loss as weights ``1 / (1 + r^2)``
    recomputed every step; at most ``max_iterations`` steps, until the cost changes by less than
    one part in 10^8. Each step's normal equations are solved by a sparse direct solve (minimum
    degree ordering) up to ``direct_solve_max_poses`` free poses, exact and fastest on walks, and
    beyond by conjugate gradients (:func:`_conjugate_gradients`), as a direct solve fills in when
    loop closures join far-apart scans.
    """
    from scipy.sparse import csc_matrix, csr_matrix
    from scipy.sparse.linalg import spsolve

    if loss not in ("cauchy", "linear"):
        raise ValueError(f"loss: expected 'cauchy' or 'linear', got {loss!r}")
    free = [k for k in sorted(poses) if k != reference]
    used = [e for e in edges if e[0] in poses and e[1] in poses and e[0] != e[1]]
    if not free or not used:
        return dict(poses)
    slot = {k: n for n, k in enumerate(free)}
    slot[reference] = len(free)  # the fixed identity, after the free poses
    first = np.array([slot[e[0]] for e in used], dtype=np.intp)
    second = np.array([slot[e[1]] for e in used], dtype=np.intp)
    inverse_measured = np.array([np.linalg.inv(e[2]) for e in used]).reshape(-1, 4, 4)
    M_R, M_t = inverse_measured[:, :3, :3], inverse_measured[:, :3, 3]
    whiten = np.array([whitening(e[3], e[4] if len(e) > 4 else None, e[2], translation_scale=translation_scale,
                                 rotation_scale_deg=rotation_scale_deg) for e in used])
    rotations = np.array([poses[k][:3, :3] for k in free] + [np.eye(3)])
    translations = np.array([poses[k][:3, 3] for k in free] + [np.zeros(3)])

    def errors(R, t):
        back = np.swapaxes(R[first], 1, 2)  # R_world_i^T
        relative = M_R @ back @ R[second]
        d = t[second] - t[first]
        shift = np.einsum("nab,nb->na", M_R @ back, d) + M_t
        phi = Rotation.from_matrix(relative).as_rotvec()
        return np.einsum("nab,nb->na", whiten, np.concatenate([phi, shift], axis=1)), phi, back, d

    def cost(r):
        return float(np.sum(np.log1p(r**2)) if loss == "cauchy" else np.sum(r**2))

    size = 6 * len(free)
    # where each edge's 12x12 block lands in the free poses' normal matrix (the reference's dropped)
    index = np.concatenate([6 * first[:, None] + np.arange(6), 6 * second[:, None] + np.arange(6)], axis=1)
    keep = index < size
    pair = keep[:, :, None] & keep[:, None, :]
    H_rows = np.broadcast_to(index[:, :, None], pair.shape)[pair]
    H_cols = np.broadcast_to(index[:, None, :], pair.shape)[pair]
    # the normal matrix's pattern, made once: its nonzeros (and its whole diagonal, for the damping)
    # sorted by row, then column (CSR order), and which of them each block entry adds to
    where = np.concatenate([H_rows.astype(np.int64) * size + H_cols, np.arange(size, dtype=np.int64) * (size + 1)])
    entries, entry_of = np.unique(where, return_inverse=True)
    entry_of = entry_of[:len(H_rows)]
    columns = (entries % size).astype(np.int32)
    starts = np.concatenate([[0], np.cumsum(np.bincount(entries // size, minlength=size))]).astype(np.int32)
    on_diagonal = np.searchsorted(entries, np.arange(size, dtype=np.int64) * (size + 1))
    r, phi, back, d = errors(rotations, translations)
    current = cost(r)
    damping = 1e-4
    for _ in range(max_iterations):
        Jinv = _right_jacobian_inverse(phi)
        R_j_T = np.swapaxes(rotations[second], 1, 2)
        rotate_i = M_R @ back
        # each edge's 6x12 Jacobian of its error by (phi_i, rho_i, phi_j, rho_j)
        J = np.zeros((len(used), 6, 12))
        J[:, :3, 0:3] = -Jinv @ R_j_T
        J[:, 3:, 0:3] = rotate_i @ skew(d)
        J[:, 3:, 3:6] = -rotate_i
        J[:, :3, 6:9] = Jinv @ R_j_T
        J[:, 3:, 9:12] = rotate_i
        J = whiten @ J
        weight = 1.0 / (1.0 + r**2) if loss == "cauchy" else np.ones_like(r)
        H = np.einsum("nai,na,naj->nij", J, weight, J)
        g = np.einsum("nai,na->ni", J, weight * r)
        normal = np.bincount(entry_of, weights=H[pair], minlength=len(entries))
        gradient = np.bincount(index[keep], weights=g[keep], minlength=size)
        diagonal = normal[on_diagonal]
        # the 6x6 diagonal blocks of the free poses, for the preconditioner
        own = np.zeros((len(free) + 1, 6, 6))
        np.add.at(own, first, H[:, :6, :6])
        np.add.at(own, second, H[:, 6:, 6:])
        own = own[:-1]
        while True:
            lift = damping * np.maximum(diagonal, 1e-12)
            damped = normal.copy()
            damped[on_diagonal] += lift
            if len(free) <= direct_solve_max_poses:
                # symmetric: its CSR arrays read as CSC are the same matrix
                step = -spsolve(csc_matrix((damped, columns, starts), shape=(size, size)), gradient,
                                permc_spec="MMD_AT_PLUS_A")
            else:
                step = -_conjugate_gradients(csr_matrix((damped, columns, starts), shape=(size, size)), gradient,
                                             own + lift.reshape(-1, 6)[:, :, None] * np.eye(6))
            step = step.reshape(-1, 6)
            trial_R = rotations.copy()
            trial_t = translations.copy()
            trial_R[:-1] = Rotation.from_rotvec(step[:, :3]).as_matrix() @ rotations[:-1]
            trial_t[:-1] = translations[:-1] + step[:, 3:]
            trial = errors(trial_R, trial_t)
            trial_cost = cost(trial[0])
            if trial_cost <= current or damping > 1e8:
                break
            damping *= 10.0
        if trial_cost > current:
            break
        rotations, translations = trial_R, trial_t
        r, phi, back, d = trial
        change = current - trial_cost
        current = trial_cost
        damping = max(damping / 10.0, 1e-10)
        if change <= 1e-8 * max(current, 1e-300) or np.abs(step).max() < 1e-12:
            break
    result = {reference: np.eye(4)}
    for k in free:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rotations[slot[k]], translations[slot[k]]
        result[k] = T
    return result
