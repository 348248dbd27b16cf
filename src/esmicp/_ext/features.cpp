// Point features (features.hpp).
#include "features.hpp"

#include "common.hpp"
#include "pool.hpp"
#include "rotation.hpp"
#include "tree.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

namespace kernels {
namespace {

//: knn_normals runs on one thread below this many queries (each costs a k-nearest search and a
//: 3 x 3 eigen-decomposition, several microseconds: a few hundred pay for the threads).
constexpr int64_t PARALLEL_NORMALS_MIN = 512;

// ---------------------------------------------------------------------------------------------
// FPFH (features.fpfh documents the definition; the formulas and their order of operations are
// the ones there, so that the bins are those of the NumPy reference to the last bit).

//: Two cosines closer than this count as equal when choosing a pair's source point.
constexpr double FPFH_TIE = 1e-9;
//: Queries per piece of count_within.
constexpr int64_t COUNT_PIECE = 256;
//: Points per piece of the FPFH passes.
constexpr int64_t FPFH_PIECE = 64;
//: pi, the double NumPy's np.pi is (the POSIX macro for it is not standard C++).
constexpr double FPFH_PI = 3.141592653589793;

// Calls visit(s) for every tree slot s within squared distance `limit` of (x, y, z), in tree order.
template <class Visit>
void visit_near(const Tree &t, double x, double y, double z, double limit, Visit &&visit) {
    int64_t stack[STACK];
    stack[0] = 0;
    int depth = box_distance(t.boxes, x, y, z) <= limit ? 1 : 0;
    while (depth > 0) {
        const int64_t node = stack[--depth];
        const int64_t left = t.lefts[node];
        if (left < 0) {
            for (int64_t s = t.starts[node]; s < t.ends[node]; ++s) {
                const double ex = t.points[3 * s] - x, ey = t.points[3 * s + 1] - y, ez = t.points[3 * s + 2] - z;
                if (ex * ex + ey * ey + ez * ez <= limit) visit(s);
            }
            continue;
        }
        for (int64_t child : {left + 1, left})
            if (box_distance(t.boxes + 6 * child, x, y, z) <= limit) stack[depth++] = child;
    }
}

// Tree slots within squared distance `limit` of (x, y, z), appended to `found` (tree order).
void within(const Tree &t, double x, double y, double z, double limit, std::vector<int64_t> &found) {
    visit_near(t, x, y, z, limit, [&found](int64_t s) { found.push_back(s); });
}

// The number of tree points within squared distance `limit` of (x, y, z).
int64_t count_near(const Tree &t, double x, double y, double z, double limit) {
    int64_t count = 0;
    visit_near(t, x, y, z, limit, [&count](int64_t) { ++count; });
    return count;
}

inline int fpfh_bin(double scaled) {
    // Truncation toward zero, clipped to the bins (NaN to the first): the NumPy reference's
    // astype(intp) then clip.
    if (!(scaled >= 1.0)) return 0;
    return scaled >= double(FPFH_BINS - 1) ? FPFH_BINS - 1 : int(scaled);
}

// The offset o from point a to point b of the pair, a < b (points p, (N, 3)), and its length: the
// same operands from either end of the pair, so both ends see the same distance.
inline double pair_offset(const double *p, int64_t a, int64_t b, double o[3]) {
    const double *pa = p + 3 * a, *pb = p + 3 * b;
    for (int c = 0; c < 3; ++c) o[c] = pb[c] - pa[c];
    return std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
}

// The (theta, alpha, phi) bins of the pair (a, b), a < b (unit normals n, (N, 3)), from its offset o
// and length distance > 0 (pair_offset).
inline void pair_bins(const double *n, int64_t a, int64_t b, double o[3], double distance, int bins[3]) {
    const double *u = n + 3 * a, *m = n + 3 * b;
    for (int c = 0; c < 3; ++c) o[c] /= distance;
    const double cos_first = u[0] * o[0] + u[1] * o[1] + u[2] * o[2];
    const double cos_second = m[0] * o[0] + m[1] * o[1] + m[2] * o[2];
    const double normals_cos = u[0] * m[0] + u[1] * m[1] + u[2] * m[2];
    const double triple = o[0] * (u[1] * m[2] - u[2] * m[1]) + o[1] * (u[2] * m[0] - u[0] * m[2]) +
                          o[2] * (u[0] * m[1] - u[1] * m[0]);
    const double gap = std::fabs(cos_first) - std::fabs(cos_second);
    const bool swap = std::fabs(gap) <= FPFH_TIE ? -cos_second > cos_first : gap < 0.0;
    const double total = cos_first + cos_second, chosen = swap ? 1.0 : 0.0;
    const double phi = cos_first - chosen * total, target_cos = cos_second - chosen * total;
    const double frame_norm = std::sqrt(std::max(1.0 - phi * phi, 0.0));
    const double alpha = triple / std::max(frame_norm, std::numeric_limits<double>::min());
    const double theta = std::atan2(target_cos - phi * normals_cos, normals_cos * frame_norm);
    bins[0] = fpfh_bin((theta + FPFH_PI) * (FPFH_BINS / (2.0 * FPFH_PI)));
    bins[1] = FPFH_BINS + fpfh_bin((alpha + 1.0) * (0.5 * FPFH_BINS));
    bins[2] = 2 * FPFH_BINS + fpfh_bin((phi + 1.0) * (0.5 * FPFH_BINS));
}

}  // namespace

void knn_normals(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                 int64_t k, double upper, CArr1 centre, Arr2 out_normals, Idx out_counts, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = int64_t(queries.shape(0));
    if (queries.shape(1) != 3 || k < 1 || k > GRAPH_K_MAX || k > t.count || int64_t(out_normals.shape(0)) != count ||
        out_normals.shape(1) != 3 || int64_t(out_counts.shape(0)) != count || centre.shape(0) != 3)
        throw std::invalid_argument("knn_normals: queries and out_normals (Q, 3), out_counts (Q,), centre (3,), "
                                    "1 <= k <= min(M, 64)");
    const double *c = centre.data();
    const double limit = upper * upper;
    double *normals = out_normals.data();
    int64_t *counts = out_counts.data();
    each_k_nearest(t, queries.data(), count, k, threads, PARALLEL_NORMALS_MIN,
                   [&](int64_t i, const double *best, const int64_t *slots) {
        double sum[3] = {0.0, 0.0, 0.0}, moment[3][3] = {{0.0}};
        int64_t used = 0;
        for (int64_t j = 0; j < k; ++j) {
            if (slots[j] < 0 || !(best[j] <= limit)) continue;
            const double *point = t.points + 3 * slots[j];
            const double x[3] = {point[0] - c[0], point[1] - c[1], point[2] - c[2]};
            for (int a = 0; a < 3; ++a) {
                sum[a] += x[a];
                for (int b = 0; b < 3; ++b) moment[a][b] += x[a] * x[b];
            }
            ++used;
        }
        counts[i] = used;
        double *normal = normals + 3 * i;
        if (used < 3) {
            normal[0] = normal[1] = normal[2] = std::numeric_limits<double>::quiet_NaN();
            return;
        }
        double covariance[3][3], vectors[3][3];
        const double inverse = 1.0 / double(used);
        for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b)
                covariance[a][b] = moment[a][b] * inverse - (sum[a] * inverse) * (sum[b] * inverse);
        jacobi_eigen<3>(covariance, vectors);
        int least = 0;
        for (int a = 1; a < 3; ++a)
            if (covariance[a][a] < covariance[least][least]) least = a;
        for (int a = 0; a < 3; ++a) normal[a] = vectors[a][least];
    }, limit);
}

void count_within(CArr2 queries, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
                  double radius, Idx out_counts, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = int64_t(queries.shape(0));
    if (queries.shape(1) != 3 || int64_t(out_counts.shape(0)) != count || !(radius >= 0.0))
        throw std::invalid_argument("count_within: queries (Q, 3), out_counts (Q,), radius >= 0");
    const double *q = queries.data(), limit = radius * radius;
    int64_t *counts = out_counts.data();
    parallel_pieces(piece_count(count, COUNT_PIECE), count < 4 * COUNT_PIECE ? 1 : threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * COUNT_PIECE);
        for (int64_t i = piece * COUNT_PIECE; i < end; ++i)
            counts[i] = count_near(t, q[3 * i], q[3 * i + 1], q[3 * i + 2], limit);
    });
}

void fpfh(CArr2 normals_, CArr2 tree_points, CIdx order, CIdx starts, CIdx ends, CIdx lefts, CArr2 boxes,
          double radius, Arr2 out_, int threads) {
    Tree t{tree_points.data(), order.data(), starts.data(), ends.data(), lefts.data(), boxes.data(),
           int64_t(tree_points.shape(0))};
    const int64_t count = t.count;
    if (int64_t(normals_.shape(0)) != count || normals_.shape(1) != 3 || int64_t(out_.shape(0)) != count ||
        out_.shape(1) != FPFH_DIMENSION || !(radius > 0.0))
        throw std::invalid_argument("fpfh: normals (N, 3) and out (N, 33) for the tree's N points, radius > 0");
    // The cloud in its own order (the pair features index points and normals alike).
    std::vector<double> cloud(3 * size_t(count));
    for (int64_t s = 0; s < count; ++s)
        for (int a = 0; a < 3; ++a) cloud[3 * t.order[s] + a] = t.points[3 * s + a];
    const double *p = cloud.data(), *n = normals_.data(), limit = radius * radius;
    double *out = out_.data();
    struct Neighbour {
        int64_t index;
        double weight;  // 1 / squared distance
    };
    std::vector<std::vector<Neighbour>> neighbours(count);
    std::vector<std::vector<uint32_t>> later_bins(count);  // the bins of (i, j > i), 8 bits each
    std::vector<int64_t> histograms(size_t(FPFH_DIMENSION) * size_t(count), 0), pairs(count, 0);
    std::vector<double> spfh(size_t(FPFH_DIMENSION) * size_t(count));
    const int64_t pieces = piece_count(count, FPFH_PIECE);
    if (count < 4 * FPFH_PIECE) threads = 1;
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        std::vector<int64_t> found;
        const int64_t end = std::min(count, (piece + 1) * FPFH_PIECE);
        for (int64_t i = piece * FPFH_PIECE; i < end; ++i) {
            found.clear();
            within(t, p[3 * i], p[3 * i + 1], p[3 * i + 2], limit, found);
            std::vector<Neighbour> &around = neighbours[i];
            around.reserve(found.size());
            for (int64_t slot : found) {
                const int64_t j = t.order[slot];
                double o[3];
                const double distance = j == i ? 0.0 : pair_offset(p, std::min(i, j), std::max(i, j), o);
                if (!(distance > 0.0)) continue;  // itself, or a coincident point: no direction
                around.push_back({j, 1.0 / (distance * distance)});
                if (j < i) continue;  // the features are computed from the pair's first point
                int bins[3];
                pair_bins(n, i, j, o, distance, bins);
                for (int b : bins) ++histograms[FPFH_DIMENSION * i + b];
                ++pairs[i];
                later_bins[i].push_back(uint32_t(bins[0]) | uint32_t(bins[1]) << 8 | uint32_t(bins[2]) << 16);
            }
        }
    });
    for (int64_t i = 0; i < count; ++i) {
        const uint32_t *packed = later_bins[i].data();
        for (const Neighbour &neighbour : neighbours[i]) {
            const int64_t j = neighbour.index;
            if (j < i) continue;
            const uint32_t bins = *packed++;
            int64_t *histogram = histograms.data() + FPFH_DIMENSION * j;
            ++histogram[bins & 0xFF];
            ++histogram[(bins >> 8) & 0xFF];
            ++histogram[bins >> 16];
            ++pairs[j];
        }
    }
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * FPFH_PIECE);
        for (int64_t i = piece * FPFH_PIECE; i < end; ++i) {
            const double scale = SPFH_BLOCK_SUM / double(std::max<int64_t>(pairs[i], 1));
            for (int b = 0; b < FPFH_DIMENSION; ++b)
                spfh[FPFH_DIMENSION * i + b] = double(histograms[FPFH_DIMENSION * i + b]) * scale;
        }
    });
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * FPFH_PIECE);
        for (int64_t i = piece * FPFH_PIECE; i < end; ++i) {
            double around[FPFH_DIMENSION] = {0.0};
            for (const Neighbour &neighbour : neighbours[i]) {
                const double *theirs = spfh.data() + FPFH_DIMENSION * neighbour.index;
                for (int k = 0; k < FPFH_DIMENSION; ++k) around[k] += neighbour.weight * theirs[k];
            }
            double *row = out + FPFH_DIMENSION * i;
            const double *own = spfh.data() + FPFH_DIMENSION * i;
            for (int block = 0; block < 3; ++block) {
                double sum = 0.0;
                for (int k = 0; k < FPFH_BINS; ++k) sum += around[FPFH_BINS * block + k];
                const double scale = SPFH_BLOCK_SUM / (sum > 0.0 ? sum : 1.0);
                for (int k = 0; k < FPFH_BINS; ++k) {
                    const int index = FPFH_BINS * block + k;
                    row[index] = own[index] + around[index] * scale;
                }
            }
        }
    });
}

}  // namespace kernels
