// Batched ESM of the global search (batched_esm.hpp).
#include "batched_esm.hpp"

#include "common.hpp"
#include "graph.hpp"
#include "moments.hpp"
#include "nearest_grid.hpp"
#include "pool.hpp"
#include "rotation.hpp"
#include "tree.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <vector>

namespace kernels {
namespace {

struct GridLookup {
    const Grid &g;
    const double *points() const { return g.target; }
    void operator()(double x, double y, double z, int64_t, double &distance, int64_t &index) const {
        index = g.lookup[grid_cell(g, x, y, z)];
        const double ex = x - g.target[3 * index], ey = y - g.target[3 * index + 1], ez = z - g.target[3 * index + 2];
        distance = std::sqrt(ex * ex + ey * ey + ez * ez);
    }
};

struct TreeLookup {
    const Tree &t;
    const int64_t *rank;
    const double *target;  // (M, 3) as given (the neighbours' coordinates)
    const NeighbourGraph<int64_t> &graph;
    bool walk;  // false: no graph (an empty one was given), the tree answers every query
    const Grid *seeds;  // or nullptr: a query without a warm start starts from its cell's point there
    const double *points() const { return target; }
    // Exact nearest target point: with a warm start, the certified walk (graph_descent) on the
    // graph of target indices; where it certifies none, the tree, seeded with the walk's end.
    void operator()(double x, double y, double z, int64_t warm, double &distance, int64_t &index) const {
        if (warm < 0 && seeds != nullptr) warm = seeds->lookup[grid_cell(*seeds, x, y, z)];
        if (warm >= 0) {
            int64_t p = warm;
            const double ex = target[3 * p] - x, ey = target[3 * p + 1] - y, ez = target[3 * p + 2] - z;
            double best = ex * ex + ey * ey + ez * ez;
            if (walk && graph_descent(graph, target, x, y, z, p, best)) {
                distance = std::sqrt(best);
                index = p;
                return;
            }
            warm = p;
        }
        tree_nearest(t, rank, x, y, z, warm, distance, index);
        if (index >= t.count) {  // a non-finite query point: no neighbour (NaN distance, point 0)
            index = 0;
            distance = std::numeric_limits<double>::quiet_NaN();
        }
    }
};

inline void compose_step(const double *step_r, const double *step_t, double *r, double *t) {
    double nr[9], nt[3];
    for (int a = 0; a < 3; ++a) {
        for (int b = 0; b < 3; ++b)
            nr[3 * a + b] = step_r[3 * a] * r[b] + step_r[3 * a + 1] * r[3 + b] + step_r[3 * a + 2] * r[6 + b];
        nt[a] = step_r[3 * a] * t[0] + step_r[3 * a + 1] * t[1] + step_r[3 * a + 2] * t[2] + step_t[a];
    }
    std::memcpy(r, nr, sizeof nr);
    std::memcpy(t, nt, sizeof nt);
}

template <class Lookup>
void esm_hypothesis(const Lookup &look, const double *source, int64_t n, double *r, double *t, int64_t iterations,
                    double floor, double factor, int64_t fine, double *distances, int64_t *indices,
                    std::vector<double> &moved, std::vector<double> &scratch) {
    const double *target = look.points();
    for (int64_t i = 0; i < n; ++i) indices[i] = -1;
    for (int64_t iteration = 0; iteration <= iterations; ++iteration) {
        for (int64_t i = 0; i < n; ++i) {
            double x, y, z;
            mapped(source, i, r, t, x, y, z);
            moved[3 * i] = x;
            moved[3 * i + 1] = y;
            moved[3 * i + 2] = z;
            look(x, y, z, indices[i], distances[i], indices[i]);
        }
        if (iteration == iterations) return;  // the last query: the final pose's distances
        double sigma = floor;
        if (iteration < iterations - fine) {
            scratch.assign(distances, distances + n);
            const int64_t half = n / 2;
            std::nth_element(scratch.begin(), scratch.begin() + half, scratch.end());
            double median = scratch[half];
            if (n % 2 == 0) median = 0.5 * (median + *std::max_element(scratch.begin(), scratch.begin() + half));
            sigma = std::max(floor, factor * median);
        }
        double smallest = INF;
        for (int64_t i = 0; i < n; ++i) smallest = std::min(smallest, distances[i] * distances[i]);
        const double spread = 2.0 * (sigma * sigma);
        double total = 0.0;
        for (int64_t i = 0; i < n; ++i) {
            scratch[i] = std::exp(-(distances[i] * distances[i] - smallest) / spread);
            total += scratch[i];
        }
        double cp[3] = {0, 0, 0}, cm[3] = {0, 0, 0};
        for (int64_t i = 0; i < n; ++i) {
            const double w = scratch[i] / total;
            scratch[i] = w;
            const double *m = target + 3 * indices[i];
            for (int a = 0; a < 3; ++a) {
                cp[a] += w * moved[3 * i + a];
                cm[a] += w * m[a];
            }
        }
        double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int64_t i = 0; i < n; ++i) {
            const double *m = target + 3 * indices[i];
            const double w = scratch[i];
            add_outer(h, w, moved[3 * i] - cp[0], moved[3 * i + 1] - cp[1], moved[3 * i + 2] - cp[2], m[0] - cm[0],
                      m[1] - cm[1], m[2] - cm[2]);
        }
        double step_r[9], step_t[3];
        best_rotation(h, step_r);
        for (int a = 0; a < 3; ++a)
            step_t[a] = cm[a] - (step_r[3 * a] * cp[0] + step_r[3 * a + 1] * cp[1] + step_r[3 * a + 2] * cp[2]);
        compose_step(step_r, step_t, r, t);
    }
}

template <class Lookup>
void esm_hypotheses(const Lookup &look, CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations,
                    double floor, double factor, int64_t fine, Arr2 out_distances, int threads) {
    const int64_t count = int64_t(rotations.shape(0)), n = int64_t(source.shape(0));
    if (rotations.shape(1) != 9 || translations.shape(0) != size_t(count) || translations.shape(1) != 3 ||
        out_distances.shape(0) != size_t(count) || out_distances.shape(1) != size_t(n) || source.shape(1) != 3)
        throw std::invalid_argument("batched ESM: rotations (K, 9), translations (K, 3), distances (K, n)");
    if (n == 0) throw std::invalid_argument("batched ESM: no source points");
    std::vector<int64_t> indices(size_t(count * n));
    double *r = rotations.data(), *t = translations.data(), *d = out_distances.data();
    const double *s = source.data();
    parallel_pieces(count, threads, [&](int64_t k) {
        std::vector<double> moved(static_cast<size_t>(3 * n)), scratch(static_cast<size_t>(n));
        esm_hypothesis(look, s, n, r + 9 * k, t + 3 * k, iterations, floor, factor, fine, d + n * k,
                       indices.data() + n * k, moved, scratch);
    });
}

}  // namespace

void batched_esm_tree(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor,
                      double factor, int64_t fine, Arr2 out_distances, CArr2 target, CIdx rank, CArr2 tree_points,
                      CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, CIdx2 graph_neighbours,
                      CArr1 graph_radii, CIdx seed_lookup, CArr1 seed_low, double seed_cell, CIdx seed_shape,
                      int threads) {
    Tree tree{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
              int64_t(tree_points.shape(0))};
    const int64_t k = int64_t(graph_neighbours.shape(1));
    // An empty graph ((0, k) neighbours, (0,) radii): none, the tree answers every query from its warm start.
    const bool walk = graph_neighbours.shape(0) > 0 || graph_radii.shape(0) > 0;
    if (walk && (int64_t(graph_radii.shape(0)) != tree.count || k < 1 || int64_t(graph_neighbours.shape(0)) != tree.count))
        throw std::invalid_argument("batched ESM: the neighbour graph does not match the target");
    const NeighbourGraph<int64_t> graph{graph_neighbours.data(), graph_radii.data(), k};
    // The seeds' grid (esmicp.core.nearest_grid.NearestGrid over the same target), if any (an empty lookup: none).
    const Grid seeds{target.data(), seed_lookup.data(), {seed_low.data()[0], seed_low.data()[1], seed_low.data()[2]},
                     seed_cell, {seed_shape.data()[0], seed_shape.data()[1], seed_shape.data()[2]}};
    const bool seeded = seed_lookup.shape(0) > 0;
    if (seeded && int64_t(seed_lookup.shape(0)) != seeds.shape[0] * seeds.shape[1] * seeds.shape[2])
        throw std::invalid_argument("batched ESM: the seeds' lookup table does not match its grid's shape");
    esm_hypotheses(TreeLookup{tree, rank.data(), target.data(), graph, walk, seeded ? &seeds : nullptr}, source, rotations,
                   translations, iterations, floor, factor, fine, out_distances, threads);
}

void batched_esm_grid(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor,
                      double factor, int64_t fine, Arr2 out_distances, CArr2 target, CIdx lookup, CArr1 low,
                      double cell, CIdx shape, int threads) {
    Grid grid{target.data(), lookup.data(), {low.data()[0], low.data()[1], low.data()[2]}, cell,
              {shape.data()[0], shape.data()[1], shape.data()[2]}};
    if (int64_t(lookup.shape(0)) != grid.shape[0] * grid.shape[1] * grid.shape[2])
        throw std::invalid_argument("batched ESM: the lookup table does not match the grid's shape");
    esm_hypotheses(GridLookup{grid}, source, rotations, translations, iterations, floor, factor, fine, out_distances,
                   threads);
}

}  // namespace kernels
