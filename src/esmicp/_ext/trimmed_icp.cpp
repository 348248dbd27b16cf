// Batched trimmed point-to-point ICP on the exact tree (trimmed_icp.hpp).
#include "trimmed_icp.hpp"

#include "common.hpp"
#include "moments.hpp"
#include "pool.hpp"
#include "rotation.hpp"
#include "tree.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <vector>

namespace kernels {
namespace {

// One map (r: 3x3 row-major, t) refined in place; returns the steps taken.
int64_t fit_map(const Tree &tree, const int64_t *rank, const double *target, const double *source, int64_t n,
                double *r, double *t, int64_t iterations, double floor, double gain, int64_t min_pairs,
                double tolerance, bool settle_on_points) {
    std::vector<double> moved(static_cast<size_t>(3 * n)), distances(static_cast<size_t>(n)), scratch(static_cast<size_t>(n));
    std::vector<int64_t> indices(static_cast<size_t>(n), -1);
    int64_t steps = 0;
    for (int64_t iteration = 0; iteration < iterations; ++iteration) {
        for (int64_t i = 0; i < n; ++i) {
            double x, y, z;
            mapped(source, i, r, t, x, y, z);
            moved[3 * i] = x;
            moved[3 * i + 1] = y;
            moved[3 * i + 2] = z;
            tree_nearest(tree, rank, x, y, z, indices[i], distances[i], indices[i]);
            if (indices[i] >= tree.count) return steps;  // a non-finite map: nothing to fit
        }
        double bar = floor;
        if (gain != 0.0) {
            scratch.assign(distances.begin(), distances.end());
            const int64_t half = n / 2;
            std::nth_element(scratch.begin(), scratch.begin() + half, scratch.end());
            double median = scratch[half];
            if (n % 2 == 0) median = 0.5 * (median + *std::max_element(scratch.begin(), scratch.begin() + half));
            bar = std::max(floor, gain * median);
        }
        int64_t pairs = 0;
        double cp[3] = {0, 0, 0}, cm[3] = {0, 0, 0};
        for (int64_t i = 0; i < n; ++i) {
            if (!(distances[i] <= bar)) continue;
            ++pairs;
            const double *m = target + 3 * indices[i];
            for (int a = 0; a < 3; ++a) {
                cp[a] += moved[3 * i + a];
                cm[a] += m[a];
            }
        }
        if (pairs < min_pairs || pairs == 0) return steps;
        for (int a = 0; a < 3; ++a) {
            cp[a] /= double(pairs);
            cm[a] /= double(pairs);
        }
        double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int64_t i = 0; i < n; ++i) {
            if (!(distances[i] <= bar)) continue;
            const double *m = target + 3 * indices[i];
            add_outer(h, 1.0, moved[3 * i] - cp[0], moved[3 * i + 1] - cp[1], moved[3 * i + 2] - cp[2], m[0] - cm[0],
                      m[1] - cm[1], m[2] - cm[2]);
        }
        double step_r[9], step_t[3], nr[9], nt[3];
        best_rotation(h, step_r);
        for (int a = 0; a < 3; ++a)
            step_t[a] = cm[a] - (step_r[3 * a] * cp[0] + step_r[3 * a + 1] * cp[1] + step_r[3 * a + 2] * cp[2]);
        double moved_by = 0.0;
        for (int a = 0; a < 3; ++a) {
            for (int b = 0; b < 3; ++b) {
                nr[3 * a + b] = step_r[3 * a] * r[b] + step_r[3 * a + 1] * r[3 + b] + step_r[3 * a + 2] * r[6 + b];
                moved_by = std::max(moved_by, std::fabs(nr[3 * a + b] - r[3 * a + b]));
            }
            nt[a] = step_r[3 * a] * t[0] + step_r[3 * a + 1] * t[1] + step_r[3 * a + 2] * t[2] + step_t[a];
            moved_by = std::max(moved_by, std::fabs(nt[a] - t[a]));
        }
        if (settle_on_points) {
            moved_by = 0.0;
            for (int64_t i = 0; i < n; ++i) {
                double x, y, z;
                mapped(source, i, nr, nt, x, y, z);
                moved_by = std::max({moved_by, std::fabs(x - moved[3 * i]), std::fabs(y - moved[3 * i + 1]),
                                     std::fabs(z - moved[3 * i + 2])});
            }
        }
        std::memcpy(r, nr, sizeof nr);
        std::memcpy(t, nt, sizeof nt);
        ++steps;
        if (settle_on_points ? !(moved_by > tolerance) : !(moved_by >= tolerance)) return steps;
    }
    return steps;
}

}  // namespace

void trimmed_icp_tree(CArr2 source, Arr2 rotations, Arr2 translations, int64_t iterations, double floor, double gain,
                      int64_t min_pairs, double tolerance, bool settle_on_points, Idx out_steps, CArr2 target, CIdx rank,
                      CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes, int threads) {
    const int64_t count = int64_t(rotations.shape(0)), n = int64_t(source.shape(0));
    if (source.shape(1) != 3 || rotations.shape(1) != 9 || translations.shape(0) != size_t(count) ||
        translations.shape(1) != 3 || out_steps.shape(0) != size_t(count))
        throw std::invalid_argument("trimmed ICP: source (n, 3), rotations (K, 9), translations (K, 3), steps (K,)");
    if (n == 0) throw std::invalid_argument("trimmed ICP: no source points");
    Tree tree{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
              int64_t(tree_points.shape(0))};
    if (tree.count == 0 || int64_t(target.shape(0)) != tree.count || int64_t(rank.shape(0)) != tree.count)
        throw std::invalid_argument("trimmed ICP: the tree does not match the target");
    double *r = rotations.data(), *t = translations.data();
    int64_t *steps = out_steps.data();
    const double *s = source.data(), *m = target.data();
    parallel_pieces(count, threads, [&](int64_t k) {
        steps[k] = fit_map(tree, rank.data(), m, s, n, r + 9 * k, t + 3 * k, iterations, floor, gain, min_pairs,
                           tolerance, settle_on_points);
    });
}

}  // namespace kernels
