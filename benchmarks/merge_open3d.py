"""Open3D's pipelines for many scans, the peers of ``benchmarks/merge_scans.py``.

Two pipelines, both written against the current Open3D API (``open3d.pipelines.registration``):

- :func:`multiway`: the multiway-registration tutorial (``pipelines/multiway_registration``),
  for a set of scans with no order: every pair by point-to-plane ICP, coarse then fine, odometry
  edges (k, k+1) and every other pair as an uncertain loop edge, one ``global_optimization``.
- :func:`reconstruction_walk`: the reconstruction system's scene registration
  (``reconstruction_system/register_fragments.py``) applied to the frames of a walk instead of
  RGB-D fragments (there are no images here): odometry by multi-scale point-to-plane ICP between
  consecutive frames, loop-closure candidates by FPFH features and RANSAC
  (``registration_ransac_based_on_feature_matching``) between frames at least ``loop_gap`` apart
  at a stride, each refined by the same ICP and kept when the system's own test passes, then
  ``global_optimization`` (Levenberg-Marquardt) over the pose graph with the loops uncertain.

Frames: an Open3D node pose is ``T_world_scan`` (world = scan 0); an edge (source, target) holds
``T_target_source``. Open3D is imported lazily (``pip install 'esmicp[baselines]'``).
"""

from __future__ import annotations

import time

import numpy as np

#: The reconstruction system's voxel size (metres) for room-scale depth data (its default config).
WALK_VOXEL = 0.05
#: Relative weight of loop closures against odometry in the walk's pose graph: Open3D's
#: documented recommendation for fragment registration (``preference_loop_closure``).
WALK_PREFERENCE_LOOP_CLOSURE = 2.0
#: A loop edge is kept when its information matrix's translation-z entry (the number of
#: correspondences within ``1.4 * voxel``) is at least this fraction of the smaller cloud: the
#: reconstruction system's test for a non-adjacent pair.
WALK_MIN_LOOP_OVERLAP = 0.3


def _registration():
    try:
        import open3d as o3d
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise SystemExit("Open3D is needed for the peer runs: pip install 'esmicp[baselines]' (or pass --skip-peer)") from error
    return o3d, o3d.pipelines.registration


def _cloud(points, voxel):
    o3d, _ = _registration()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))
    pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 2, max_nn=30))
    return pcd


def multiway(clouds, voxel, initial=None, *, icp_iterations=None, nodes_from_initial=True):
    """Open3D's multiway-registration tutorial on ``clouds`` (in the order given).

    Parameters
    ----------
    clouds : list of (N_k, 3) arrays
        The scans, each in its own frame.
    voxel : float
        Downsampling voxel; ICP runs coarse at ``15 * voxel`` then fine at ``1.5 * voxel``.
    initial : list of (4, 4) arrays, optional
        ``T_world_scan`` per scan to start every pairwise ICP from (else the identity, as in the
        tutorial). ``icp_iterations=0`` with the truth and ``nodes_from_initial=False`` is the
        harness check: the edges stay true and the chained odometry must rebuild the true poses.

    Returns
    -------
    poses : (N, 4, 4) array of ``T_world_scan`` (world = scan 0), seconds, pairs
        ``pairs``: (source, target, T_target_source, odometry?) as registered.
    """
    o3d, reg = _registration()
    start = time.perf_counter()
    pcds = [_cloud(points, voxel) for points in clouds]
    coarse, fine = voxel * 15, voxel * 1.5
    criteria = (reg.ICPConvergenceCriteria() if icp_iterations is None
                else reg.ICPConvergenceCriteria(max_iteration=icp_iterations))

    def pairwise(source, target):
        start_pose = np.eye(4) if initial is None else np.linalg.inv(initial[target]) @ initial[source]
        estimation = reg.TransformationEstimationPointToPlane()
        rough = reg.registration_icp(pcds[source], pcds[target], coarse, start_pose, estimation, criteria)
        final = reg.registration_icp(pcds[source], pcds[target], fine, rough.transformation, estimation, criteria)
        information = reg.get_information_matrix_from_point_clouds(pcds[source], pcds[target], fine,
                                                                   final.transformation)
        return np.array(final.transformation), information

    pairs = []
    graph = reg.PoseGraph()
    from_initial = initial is not None and nodes_from_initial
    odometry = np.linalg.inv(initial[0]) if initial is not None and not nodes_from_initial else np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(np.array(initial[0]) if from_initial else np.linalg.inv(odometry)))
    for source in range(len(pcds)):
        for target in range(source + 1, len(pcds)):
            T_target_source, information = pairwise(source, target)
            adjacent = target == source + 1
            pairs.append((source, target, T_target_source, adjacent))
            if adjacent:
                odometry = T_target_source @ odometry
                graph.nodes.append(reg.PoseGraphNode(np.array(initial[target]) if from_initial
                                                     else np.linalg.inv(odometry)))
            graph.edges.append(reg.PoseGraphEdge(source, target, T_target_source, information,
                                                 uncertain=not adjacent))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=fine, edge_prune_threshold=0.25,
                                          reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = np.array([np.asarray(node.pose) for node in graph.nodes])
    return poses, time.perf_counter() - start, pairs


def loop_candidates(count, loop_gap, loop_stride):
    """Frame pairs (i, j), i < j, both multiples of ``loop_stride``, ``j - i >= loop_gap``."""
    kept = range(0, count, loop_stride)
    return [(i, j) for i in kept for j in kept if j - i >= loop_gap]


def reconstruction_walk(clouds, *, voxel=WALK_VOXEL, loop_gap=20, loop_stride=10):
    """The reconstruction system's scene registration on the frames of a walk, in their order.

    Parameters
    ----------
    clouds : list of (N_k, 3) arrays
        Consecutive frames, each in its own (camera) frame, metres.
    voxel : float
        Downsampling voxel (metres); ICP at ``voxel, voxel/2, voxel/4`` (50, 30, 14 iterations),
        correspondences within ``1.4 * voxel``; normals within ``2 * voxel`` (30 neighbours); FPFH
        within ``5 * voxel`` (100 neighbours).
    loop_gap, loop_stride : int
        Loop-closure candidates: frames that are multiples of ``loop_stride`` and at least
        ``loop_gap`` frames apart (:func:`loop_candidates`).

    Returns
    -------
    poses : (N, 4, 4) array of ``T_world_frame`` (world = frame 0), seconds, info
        ``info``: counts of the loop candidates tried and kept.
    """
    o3d, reg = _registration()
    start = time.perf_counter()
    scales = (voxel, voxel / 2, voxel / 4)
    iterations = (50, 30, 14)
    distance = voxel * 1.4
    pyramid = [[_cloud(points, size) for size in scales] for points in clouds]
    features = [reg.compute_fpfh_feature(levels[0], o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 5, max_nn=100))
                for levels in pyramid]
    estimation = reg.TransformationEstimationPointToPlane()

    def refine(source, target, start_pose):
        current = start_pose
        for level, count in enumerate(iterations):
            result = reg.registration_icp(pyramid[source][level], pyramid[target][level], distance, current,
                                          estimation, reg.ICPConvergenceCriteria(max_iteration=count))
            current = result.transformation
        information = reg.get_information_matrix_from_point_clouds(pyramid[source][-1], pyramid[target][-1],
                                                                   distance, current)
        return np.array(current), information

    graph = reg.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(np.eye(4)))
    for source in range(len(clouds) - 1):
        T_target_source, information = refine(source, source + 1, np.eye(4))
        odometry = T_target_source @ odometry
        graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry)))
        graph.edges.append(reg.PoseGraphEdge(source, source + 1, T_target_source, information, uncertain=False))
    candidates = loop_candidates(len(clouds), loop_gap, loop_stride)
    kept = 0
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)]
    for source, target in candidates:
        coarse = reg.registration_ransac_based_on_feature_matching(
            pyramid[source][0], pyramid[target][0], features[source], features[target], False, distance,
            reg.TransformationEstimationPointToPoint(False), 4, checkers,
            reg.RANSACConvergenceCriteria(1000000, 0.999))
        if np.trace(coarse.transformation) == 4.0:  # RANSAC found nothing
            continue
        T_target_source, information = refine(source, target, coarse.transformation)
        smaller = min(len(pyramid[source][-1].points), len(pyramid[target][-1].points))
        if information[5, 5] / smaller < WALK_MIN_LOOP_OVERLAP:
            continue
        kept += 1
        graph.edges.append(reg.PoseGraphEdge(source, target, T_target_source, information, uncertain=True))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=distance, edge_prune_threshold=0.25,
                                          preference_loop_closure=WALK_PREFERENCE_LOOP_CLOSURE, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = np.array([np.asarray(node.pose) for node in graph.nodes])
    return poses, time.perf_counter() - start, {"loop_candidates": len(candidates), "loops_kept": kept}
