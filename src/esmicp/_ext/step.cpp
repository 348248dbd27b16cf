// One iteration of the local loop (step.hpp): queries, weights, moments, increment, pose.
#include "step.hpp"

#include "common.hpp"
#include "graph.hpp"
#include "moments.hpp"
#include "pool.hpp"
#include "rotation.hpp"
#include "tree.hpp"
#include "voxel_hash.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace kernels {

void Index::set_hash(CArr2 sorted_points_, CIdx sorted_index_, CIdx rank_, CIdx cell_starts_, CIdx table_keys_,
                     CIdx table_cells_, CArr1 low_, double cell_, CIdx dims_) {
    sorted_points = sorted_points_;
    sorted_index = sorted_index_;
    hash_rank = rank_;
    cell_starts = cell_starts_;
    table_keys = table_keys_;
    table_cells = table_cells_;
    low = low_;
    cell = cell_;
    dims = dims_;
    has_hash = true;
}

void Index::build_graph(int64_t k, int threads) {
    const int64_t count = int64_t(tree_points.shape(0));
    if (!has_hash) throw std::invalid_argument("build_graph: set_hash first");
    if (k < 1 || k > GRAPH_K_MAX || k > count) throw std::invalid_argument("build_graph: 1 <= k <= min(M, 64)");
    if (count > int64_t(std::numeric_limits<int32_t>::max()))
        throw std::invalid_argument("build_graph: more than 2**31 - 1 target points");
    std::vector<int32_t> neighbours(static_cast<size_t>(count * k));
    std::vector<double> radii(static_cast<size_t>(count));
    const Hash h = make_hash(sorted_points, sorted_index, hash_rank, cell_starts, table_keys, table_cells, low,
                             cell, dims);
    hash_graph(h, count, k, neighbours.data(), radii.data(), threads);
    graph_neighbours.swap(neighbours);
    graph_radii.swap(radii);
    graph_k = k;
}

void Index::step(CArr2 source, CArr2 pose, Idx indices, Arr1 distances, bool warm, bool use_hash, bool use_graph,
                 CArr1 weighting_,
                 double objective_sigma, double reject_below, Arr1 out_, int threads) {
    const int64_t count = int64_t(source.shape(0));
    if (count == 0) throw std::invalid_argument("step needs at least one source point");
    if (int64_t(indices.shape(0)) != count || int64_t(distances.shape(0)) != count)
        throw std::invalid_argument("step: indices and distances must have one entry per source point");
    if (pose.shape(0) != 4 || pose.shape(1) != 4) throw std::invalid_argument("step: pose must be 4x4");
    if (int64_t(out_.shape(0)) < STEP_OUT) throw std::invalid_argument("step: out must hold STEP_OUT numbers");
    const double *T = pose.data(), *s = source.data(), *weighting = weighting_.data();
    const double r0[9] = {T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]};
    const double t0[3] = {T[3], T[7], T[11]};
    double *out = out_.data();
    Tree t{tree_points.data(), tree_order.data(), tree_starts.data(), tree_ends.data(), tree_lefts.data(),
           tree_boxes.data(), int64_t(tree_points.shape(0))};
    const int64_t *trank = tree_rank.data();
    const bool hashed = has_hash && use_hash;
    const bool graphed = use_graph && warm && graph_k > 0 && has_hash;
    const NeighbourGraph<int32_t> graph{graph_neighbours.data(), graph_radii.data(), graph_k};
    Hash h{};
    if (has_hash) h = make_hash(sorted_points, sorted_index, hash_rank, cell_starts, table_keys, table_cells, low,
                                cell, dims);
    int64_t *ix = indices.data();
    double *d = distances.data();
    const double objective_scale =
        objective_sigma > 0.0 ? 1.0 / (2.0 * std::max(objective_sigma, 1e-150) * std::max(objective_sigma, 1e-150))
                              : 0.0;
    // Pass 1: the queries; per piece the misses, sum d^2, min d^2, the objective's sum and the
    // certified queries.
    const int64_t pieces = piece_count(count, QUERY_PIECE);
    std::vector<double> partial(5 * pieces, 0.0);
    auto query = [&](int64_t piece) {
        int64_t end = std::min(count, (piece + 1) * QUERY_PIECE);
        double misses = 0.0, squares = 0.0, least = INF, objective = 0.0, certified = 0.0;
        for (int64_t i = piece * QUERY_PIECE; i < end; ++i) {
            double x, y, z;
            mapped(s, i, r0, t0, x, y, z);
            int64_t seed = warm ? ix[i] : -1;
            bool found = false;
            if (graphed && seed >= 0) {
                const double *sp = h.sorted_points;
                int64_t p = h.rank[seed];
                const double ex = sp[3 * p] - x, ey = sp[3 * p + 1] - y, ez = sp[3 * p + 2] - z;
                double best = ex * ex + ey * ey + ez * ez;
                found = graph_descent(graph, sp, x, y, z, p, best);
                seed = h.sorted_index[p];
                if (found) {
                    d[i] = std::sqrt(best);
                    ix[i] = seed;
                    misses += best > h.limit;
                    certified += 1.0;
                }
            }
            if (!found) {  // the hash and the tree, seeded with the walk's end
                if (has_hash) {
                    misses += hash_nearest(h, t, trank, x, y, z, seed, hashed, d[i], ix[i]);
                } else {
                    tree_nearest(t, trank, x, y, z, seed, d[i], ix[i]);
                }
            }
            double squared = d[i] * d[i];
            squares += squared;
            least = std::min(least, squared);
            if (objective_scale > 0.0) objective += std::exp(-squared * objective_scale);
        }
        double *row = partial.data() + 5 * piece;
        row[0] = misses; row[1] = squares; row[2] = least; row[3] = objective; row[4] = certified;
    };
    // Up to POOLED_STEP_MAX points the persistent helpers (a thread started per call costs a
    // large part of the work there); beyond, threads per call, with their Ctrl-C checks.
    if (count < POOLED_STEP_MAX) {
        pooled_pieces(pieces, threads, query);
    } else {
        parallel_pieces(pieces, threads, query);
    }
    double misses = 0.0, squares = 0.0, least = INF, objective = 0.0, certified = 0.0;
    for (int64_t p = 0; p < pieces; ++p) {
        misses += partial[5 * p];
        squares += partial[5 * p + 1];
        least = std::min(least, partial[5 * p + 2]);
        objective += partial[5 * p + 3];
        certified += partial[5 * p + 4];
    }
    out[1] = std::sqrt(squares / double(count));
    out[2] = objective / double(count);
    out[3] = misses;
    out[40] = certified;
    out[39] = out[2] < reject_below ? 1.0 : 0.0;
    if (out[39] != 0.0) return;
    // The sigma of this step.
    const double fixed = weighting[0], floor = weighting[1], factor = weighting[2];
    const bool fine = weighting[3] != 0.0, gaussian = weighting[4] != 0.0;
    double sigma = std::numeric_limits<double>::quiet_NaN(), scale = 0.0;
    if (gaussian) {
        if (fixed > 0.0) {
            sigma = fixed;
        } else if (fine) {
            sigma = floor;
        } else {
            std::vector<double> copy(d, d + count);
            const int64_t middle = count / 2;
            std::nth_element(copy.begin(), copy.begin() + middle, copy.end());
            double median = copy[middle];
            if (count % 2 == 0) median = (*std::max_element(copy.begin(), copy.begin() + middle) + median) / 2.0;
            sigma = std::max(floor, factor * median);
        }
        const double bounded = std::max(sigma, 1e-150);
        scale = 1.0 / (2.0 * bounded * bounded);
    }
    // Pass 2: the moments, and the increment.
    double m[17];
    moments_of_pairs(s, count, r0, t0, target.data(), ix, d, scale, gaussian ? least : 0.0, m, threads,
                     count < POOLED_STEP_MAX);
    double r[9], tr[3];
    best_rotation(m + 8, r);
    for (int a = 0; a < 3; ++a) tr[a] = m[5 + a] - (r[3 * a] * m[2] + r[3 * a + 1] * m[3] + r[3 * a + 2] * m[4]);
    // The composed pose [R | t] @ T, its rotation re-orthonormalised.
    double product[9], rotation[9], translation[3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            product[3 * i + j] = r[3 * i] * r0[j] + r[3 * i + 1] * r0[3 + j] + r[3 * i + 2] * r0[6 + j];
    nearest_rotation(product, rotation);
    for (int i = 0; i < 3; ++i) translation[i] = r[3 * i] * t0[0] + r[3 * i + 1] * t0[1] + r[3 * i + 2] * t0[2] + tr[i];
    // Its motion from T: rotation part rotation @ r0^T, translation translation - (that) t0.
    double relative[9], moved[3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            relative[3 * i + j] = rotation[3 * i] * r0[3 * j] + rotation[3 * i + 1] * r0[3 * j + 1] +
                                  rotation[3 * i + 2] * r0[3 * j + 2];
    for (int i = 0; i < 3; ++i)
        moved[i] = translation[i] - (relative[3 * i] * t0[0] + relative[3 * i + 1] * t0[1] + relative[3 * i + 2] * t0[2]);
    out[0] = sigma;
    out[4] = m[1] > 0.0 ? m[0] * m[0] / m[1] : 0.0;
    out[5] = angle_of(r);
    out[6] = std::sqrt(tr[0] * tr[0] + tr[1] * tr[1] + tr[2] * tr[2]);
    for (int k = 0; k < 9; ++k) out[7 + k] = r[k];
    for (int k = 0; k < 3; ++k) out[16 + k] = tr[k];
    double *composed = out + 19;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) composed[4 * i + j] = rotation[3 * i + j];
        composed[4 * i + 3] = translation[i];
    }
    composed[12] = composed[13] = composed[14] = 0.0;
    composed[15] = 1.0;
    out[35] = angle_of(relative);
    out[36] = std::sqrt(moved[0] * moved[0] + moved[1] * moved[1] + moved[2] * moved[2]);
    out[37] = m[0];
    out[38] = m[1];
}

}  // namespace kernels
