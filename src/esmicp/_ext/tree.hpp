// KD-tree: exact nearest and k nearest neighbours, warm-started.
#pragma once

#include "arrays.hpp"
#include "common.hpp"
#include "graph.hpp"
#include "pool.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <utility>

namespace kernels {

//: Depth of the search stacks (median splits: log2(M / leaf size) + 1 levels).
inline constexpr int STACK = 96;

// A KD-tree (build_tree) over M points: nodes in arrays, node 0 the root, a node's children at
// lefts[node] and lefts[node] + 1 (-1: a leaf, holding tree slots starts[node] to ends[node]).
struct Tree {
    const double *points;  // (M, 3) in tree order
    const int64_t *order;  // tree slot -> target index
    const int64_t *starts, *ends, *lefts;
    const double *boxes;  // (nodes, 6): low xyz, high xyz
    int64_t count;
};

inline double box_distance(const double *box, double x, double y, double z) {
    double total = 0.0, gap;
    const double q[3] = {x, y, z};
    for (int a = 0; a < 3; ++a) {
        gap = box[a] - q[a];
        if (gap > 0.0) {
            total += gap * gap;
        } else {
            gap = q[a] - box[3 + a];
            if (gap > 0.0) total += gap * gap;
        }
    }
    return total;
}

inline void nearest(const Tree &t, double x, double y, double z, double &best, int64_t &best_slot) {
    int64_t stack_nodes[STACK];
    double stack_bounds[STACK];
    stack_nodes[0] = 0;
    stack_bounds[0] = box_distance(t.boxes, x, y, z);
    int depth = 1;
    while (depth > 0) {
        --depth;
        int64_t node = stack_nodes[depth];
        if (stack_bounds[depth] >= best) continue;
        int64_t left = t.lefts[node];
        if (left < 0) {
            for (int64_t k = t.starts[node]; k < t.ends[node]; ++k) {
                double ex = t.points[3 * k] - x, ey = t.points[3 * k + 1] - y, ez = t.points[3 * k + 2] - z;
                double squared = ex * ex + ey * ey + ez * ez;
                if (squared < best) {
                    best = squared;
                    best_slot = k;
                }
            }
            continue;
        }
        double near_bound = box_distance(t.boxes + 6 * left, x, y, z);
        double far_bound = box_distance(t.boxes + 6 * (left + 1), x, y, z);
        int64_t near_node = left, far_node = left + 1;
        if (far_bound < near_bound) {
            std::swap(near_node, far_node);
            std::swap(near_bound, far_bound);
        }
        if (far_bound < best) {
            stack_nodes[depth] = far_node;
            stack_bounds[depth] = far_bound;
            ++depth;
        }
        if (near_bound < best) {
            stack_nodes[depth] = near_node;
            stack_bounds[depth] = near_bound;
            ++depth;
        }
    }
}

inline constexpr int64_t QUERY_PIECE = 256;

//: Queries of fewer points than this run on the calling thread alone.
inline constexpr int64_t PARALLEL_QUERY_MIN = 2048;

// Nearest point of the tree to (x, y, z), seeded with the target point `warm` (-1: none): its
// distance and target index (t.count when the tree is empty of candidates).
inline void tree_nearest(const Tree &t, const int64_t *tree_rank, double x, double y, double z, int64_t warm,
                         double &distance, int64_t &index) {
    double best = INF;
    int64_t slot = -1;
    if (warm >= 0) {
        slot = tree_rank[warm];
        double ex = t.points[3 * slot] - x, ey = t.points[3 * slot + 1] - y, ez = t.points[3 * slot + 2] - z;
        best = ex * ex + ey * ey + ez * ez;
    }
    nearest(t, x, y, z, best, slot);
    distance = std::sqrt(best);
    index = slot >= 0 ? t.order[slot] : t.count;
}

// Insert (squared, slot) into the k best so far (best ascending, slots alongside), if it is nearer
// than the k-th: the k-nearest searches of the tree and of the voxel hash share it.
inline void keep_nearer(double *best, int64_t *slots, int64_t k, double squared, int64_t slot) {
    if (squared >= best[k - 1]) return;
    int64_t j = k - 1;
    for (; j > 0 && best[j - 1] > squared; --j) {
        best[j] = best[j - 1];
        slots[j] = slots[j - 1];
    }
    best[j] = squared;
    slots[j] = slot;
}

//: Trees of fewer points than this are built on the calling thread alone.
inline constexpr int64_t PARALLEL_BUILD_MIN = 32768;

//: Subtrees per thread that a parallel build cuts the tree into below its top levels (count).
inline constexpr int BUILD_SUBTREES_PER_THREAD = 2;

// Builds the tree into the caller's arrays (capacity nodes) on `threads` threads (0: every core;
// the same arrays whatever the number); returns the number of nodes.
int64_t build_tree(CArr2 points, int64_t leaf_size, Arr2 tree_points, Idx order, Idx starts, Idx ends, Idx lefts,
                   Arr2 boxes, int threads);

// The nearest tree point of each query mapped by (rotation, translation), seeded with the target
// point warm[i] (-1: none): out_distances (cloud units) and out_indices (into the target as given).
void tree_query(CArr2 queries, CArr2 rotation, CArr1 translation, CIdx warm, CIdx rank, CArr2 tree_points,
                CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, Arr1 out_distances, Idx out_indices,
                int threads);

// The distance of each of the n points, mapped by each of K maps (rotations (K, 9): any 3x3
// matrix; translations (K, 3)), to its nearest tree point, when within `bound` (cloud units);
// infinity when none is: out_distances (K, n). A search bounded from the start visits only the
// nodes within the bound, so points far from the tree cost little.
void tree_within(CArr2 points, CArr2 rotations, CArr2 translations, double bound, Arr2 out_distances,
                 CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, int threads);

// The k nearest tree points of (x, y, z) below `node` into best (squared distances) and slots,
// nearest first: the caller fills both with (INF, -1) and starts at the root. Recursive, nearer
// child first, a child skipped when its box is beyond the current k-th distance.
void nearest_k(const Tree &t, int64_t node, double x, double y, double z, int64_t k, double *best, int64_t *slots);

// For each of `count` queries (rows of q, (count, 3)), its k nearest tree points (squared distances
// best[0..k), tree slots slots[0..k), nearest first; -1 where fewer exist), handed to
// emit(i, best, slots). Pieces of queries on `threads` threads (1 below `parallel_min` queries).
// `limit` (squared distance, INF for none): only points within it are wanted, so the search starts
// bounded by it and skips every branch beyond (the same points, found sooner; slots beyond the
// points within `limit` stay -1).
template <class Emit>
void each_k_nearest(const Tree &t, const double *q, int64_t count, int64_t k, int threads, int64_t parallel_min,
                    Emit &&emit, double limit = INF) {
    // keep_nearer takes a point strictly nearer than the k-th best: start just above the limit,
    // so that a point at exactly `limit` is still taken.
    const double start = limit < INF ? std::nextafter(limit, INF) : INF;
    if (count < parallel_min) threads = 1;
    parallel_pieces(piece_count(count, QUERY_PIECE), threads, [&](int64_t piece) {
        double best[GRAPH_K_MAX];
        int64_t slots[GRAPH_K_MAX];
        const int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        for (int64_t i = piece * QUERY_PIECE; i < end; ++i) {
            std::fill(best, best + k, start);
            std::fill(slots, slots + k, int64_t(-1));
            nearest_k(t, 0, q[3 * i], q[3 * i + 1], q[3 * i + 2], k, best, slots);
            emit(i, best, slots);
        }
    });
}

// The neighbour graph of the tree's target (out_neighbours (M, k), out_radii (M,); k <= min(M, 64)):
// each target point's k nearest (itself first), queried in tree order, written in the target's.
void neighbour_graph(CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                     Idx2 out_neighbours, Arr1 out_radii, int threads);

// The k nearest tree points of each query (out_distances, out_indices (Q, k), nearest first;
// Euclidean distances, indices into the target as given; k <= min(M, 64)).
void tree_knn(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
              Arr2 out_distances, Idx2 out_indices, int threads);

}  // namespace kernels
