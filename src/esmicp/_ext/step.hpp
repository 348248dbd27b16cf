// The local loop's index over a target (its tree, voxel hash and neighbour graph) and one
// iteration of the loop in one call (Index::step).
#pragma once

#include "arrays.hpp"

#include <cstdint>
#include <vector>

namespace kernels {

//: Below this many source points, Index::step runs both its passes (queries, moments) on the
//: persistent helper threads (a call of that size lasts a few milliseconds at most: the loop
//: around it sees Ctrl-C in time).
inline constexpr int64_t POOLED_STEP_MAX = 32768;

// One iteration of the local loop in one call: nearest neighbours (hash and tree, warm-started),
// the weights' sigma, the pair moments, the Kabsch increment and the composed pose.
//
// Weighting (`weighting`, 5 numbers): fixed sigma (> 0) or 0; the sigma floor; the factor on the
// median distance; 1 in the fine phase (sigma = floor) else 0; 1 for Gaussian weights, 0 for
// weights of 1 (icp). Objective sigma (> 0: also return the mean of exp(-d^2 / (2 s^2))).
// `reject_below`: when that mean is below it (the loop's trial of an accelerated pose that fits
// worse than the pose it came from), the step stops after the queries: out holds the rmse, the
// objective, the misses and the certified queries, and out[39] = 1 (else 0).
// With `use_graph` and a neighbour graph (build_graph), each warm-started query first walks it
// (graph_descent); the queries it certifies skip the hash and the tree.
//
// out (STEP_OUT numbers): sigma, rmse, objective, misses, effective pairs, increment angle,
// increment translation norm, R (9), t (3), the composed pose (16, re-orthonormalised), the motion
// of the pose (angle, translation norm), sum of weights, sum of squared weights, rejected (1/0),
// queries certified by the graph walk.
inline constexpr int STEP_OUT = 41;

struct Index {
    CArr2 target;
    CArr2 tree_points;
    CIdx tree_order, tree_rank, tree_starts, tree_ends, tree_lefts;
    CArr2 tree_boxes;
    bool has_hash = false;
    CArr2 sorted_points;
    CIdx sorted_index, hash_rank, cell_starts, table_keys, table_cells, dims;
    CArr1 low;
    double cell = 0.0;
    // The neighbour graph of the hash's points by sorted position (build_graph), empty until built.
    std::vector<int32_t> graph_neighbours;
    std::vector<double> graph_radii;
    int64_t graph_k = 0;

    Index(CArr2 target_, CArr2 points, CIdx order, CIdx rank, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes)
        : target(target_), tree_points(points), tree_order(order), tree_rank(rank), tree_starts(starts),
          tree_ends(ends), tree_lefts(lefts), tree_boxes(boxes) {}

    void set_hash(CArr2 sorted_points_, CIdx sorted_index_, CIdx rank_, CIdx cell_starts_, CIdx table_keys_,
                  CIdx table_cells_, CArr1 low_, double cell_, CIdx dims_);

    // Builds the neighbour graph (k neighbours per target point) that the warm-started queries of
    // step() walk first; the walk certifies most of them near convergence (graph_descent) and
    // hands the rest, seeded with its end, to the hash or the tree.
    void build_graph(int64_t k, int threads);

    void step(CArr2 source, CArr2 pose, Idx indices, Arr1 distances, bool warm, bool use_hash, bool use_graph,
              CArr1 weighting_,
              double objective_sigma, double reject_below, Arr1 out_, int threads);
};

}  // namespace kernels
