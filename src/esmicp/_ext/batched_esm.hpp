// Batched ESM of the global search: many hypotheses refined at once.
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

// Batched ESM of the global search (esmicp.globalreg.rotation_search.batched_esm): K hypotheses
// (poses T_target_source) each run `iterations` ESM steps on the same n source points, one
// hypothesis per piece from start to end (they are independent), so the result does not depend on
// the number of threads. Per step: the nearest target point of each placed source point (the
// exact tree, warm-started with the hypothesis' previous neighbours; or the global search's
// lookup grid), sigma = max(floor, factor * median distance) (the floor itself in the last
// `fine` steps), Gaussian weights exp(-(d^2 - min d^2) / (2 sigma^2)) normalised to sum 1, the
// weighted centroids and cross-covariance, Horn's rotation, the composed pose. After the last
// step, the distances of the placed source (out_distances, K x n).
//
// batched_esm_tree: on the exact tree, its neighbour graph (an empty one: none, the tree answers
// every query from its warm start), and optionally the lookup grid for the first queries' seeds
// (an empty seed_lookup: none).
void batched_esm_tree(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor,
                      double factor, int64_t fine, Arr2 out_distances, CArr2 target, CIdx rank, CArr2 tree_points,
                      CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, CIdx2 graph_neighbours,
                      CArr1 graph_radii, CIdx seed_lookup, CArr1 seed_low, double seed_cell, CIdx seed_shape,
                      int threads);

// batched_esm_grid: on the lookup grid.
void batched_esm_grid(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor,
                      double factor, int64_t fine, Arr2 out_distances, CArr2 target, CIdx lookup, CArr1 low,
                      double cell, CIdx shape, int threads);

}  // namespace kernels
