// Neighbour graphs (built from the KD-tree, tree.cpp, or the voxel hash, voxel_hash.cpp) and the
// certified walk along them.
#pragma once

#include <cstdint>

namespace kernels {

// k near points of every point (itself among them) and a squared radius: every point strictly
// nearer than that to a point is in its list (the k nearest and the distance to the k-th, for the
// global search's graph by target index; see hash_graph for the step's, by hash order).
template <class I>
struct NeighbourGraph {
    const I *neighbours;  // (M, k) point numbers
    const double *radii;  // (M,) squared radii
    int64_t k;
};

//: Descent steps along the graph before a query goes to the tree.
inline constexpr int GRAPH_DESCENT_MAX = 8;

// The certified walk from a warm start p (best: squared distance from (x, y, z) to p, `points` the
// coordinates the graph's numbers refer to): moves p to a nearer member of its list while there
// is one; when p's list holds none nearer and 2 |q - p| is within p's radius, every point nearer
// to q than p (within 2 |q - p| of p) is in that list, so p is the exact nearest: returns true.
// Otherwise (no certificate within GRAPH_DESCENT_MAX steps) false, with p and best the nearest
// point met, a seed for an exact search.
template <class I>
inline bool graph_descent(const NeighbourGraph<I> &graph, const double *points, double x, double y, double z,
                          int64_t &p, double &best) {
    for (int step = 0; step < GRAPH_DESCENT_MAX; ++step) {
        const I *list = graph.neighbours + graph.k * p;
        int64_t next = -1;
        for (int64_t j = 0; j < graph.k; ++j) {
            const int64_t c = int64_t(list[j]);
            const double ex = points[3 * c] - x, ey = points[3 * c + 1] - y, ez = points[3 * c + 2] - z;
            const double candidate = ex * ex + ey * ey + ez * ez;
            if (candidate < best) {
                best = candidate;
                next = c;
            }
        }
        if (next < 0) return 4.0 * best * (1.0 + 1e-9) <= graph.radii[p];
        p = next;
    }
    return false;
}

//: Most neighbours per point of a neighbour graph.
inline constexpr int64_t GRAPH_K_MAX = 64;

}  // namespace kernels
