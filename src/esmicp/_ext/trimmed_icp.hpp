// Batched trimmed point-to-point ICP on the exact tree: many maps of one source fitted at once
// (the handedness test, esmicp.trust.handedness; the scan strategy's keypoint ICP,
// esmicp.globalreg.scan).
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

// Each of K maps (rotations (K, 9): any 3x3 matrix, improper ones included; translations (K, 3))
// of the same n source points refined by at most `iterations` steps of trimmed point-to-point
// ICP onto the tree's target, in place, one map per piece from start to end (they are
// independent), so the result does not depend on the number of threads. Per step: the nearest
// target point of each mapped source point (warm-started with the map's previous neighbours), the
// bar max(floor, gain * median distance), the pairs within it (fewer than min_pairs: the map
// stops, unchanged), Horn's proper rotation and the translation fitted to them with equal
// weights, composed on the left of the map (so the map keeps its handedness). A map stops once
// no entry of it moves by tolerance or more (cloud units); with settle_on_points, once no mapped
// source point moves by more than tolerance along any axis. gain 0: the bar is the floor (no
// median taken). out_steps: the steps each map took.
void trimmed_icp_tree(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor, double gain,
                      int64_t min_pairs, double tolerance, bool settle_on_points, Idx out_steps, CArr2 target, CIdx rank,
                      CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, int threads);

}  // namespace kernels
