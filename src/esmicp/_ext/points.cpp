// Passes over a cloud's points (points.hpp).
#include "points.hpp"

#include "common.hpp"
#include "graph.hpp"
#include "moments.hpp"
#include "pool.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <cstring>
#include <type_traits>
#include <vector>

namespace kernels {
namespace {

inline uint64_t coordinate_bits(double value) {
    value += 0.0;  // -0.0 -> +0.0
    uint64_t bits;
    std::memcpy(&bits, &value, sizeof bits);
    return bits;
}

}  // namespace

namespace {

// The occupied cells of edge `voxel` (corner at `low`) of `count` points p (N, 3), numbered in order
// of first sight: `cells` their integer coordinates (3 a cell), `seen[i]` the number of point i's
// cell when `seen` is given. False when a cell coordinate reaches 2^62 (too fine a voxel).
bool hash_cells(const double *p, int64_t count, const double *low, double voxel, std::vector<int64_t> &cells,
                int64_t *seen) {
    int bits = 4;
    while ((int64_t(1) << bits) < 2 * count) ++bits;
    const int64_t mask = (int64_t(1) << bits) - 1;
    const int shift = 64 - bits;
    std::vector<int64_t> table(size_t(mask + 1), -1);  // cell number in order of first sight
    cells.reserve(size_t(3) * 1024);
    const auto slot_of = [&](const int64_t *cell) {
        uint64_t key = uint64_t(cell[0]) * HASH_MULTIPLIER;
        key = (key ^ uint64_t(cell[1])) * HASH_MULTIPLIER;
        key = (key ^ uint64_t(cell[2])) * HASH_MULTIPLIER;
        return int64_t(key >> shift);
    };
    constexpr double LIMIT = 4611686018427387904.0;  // 2^62
    for (int64_t i = 0; i < count; ++i) {
        if ((i & ((int64_t(1) << 16) - 1)) == 0 && i > 0 && signal_raised()) throw PythonError();
        int64_t cell[3];
        for (int a = 0; a < 3; ++a) {
            const double scaled = std::floor((p[3 * i + a] - low[a]) / voxel);
            if (!(scaled < LIMIT)) return false;
            cell[a] = int64_t(scaled);
        }
        int64_t slot = slot_of(cell);
        for (;;) {
            const int64_t number = table[size_t(slot)];
            if (number < 0) {
                const int64_t made = int64_t(cells.size() / 3);
                table[size_t(slot)] = made;
                if (seen) seen[i] = made;
                cells.insert(cells.end(), cell, cell + 3);
                break;
            }
            const int64_t *other = cells.data() + 3 * number;
            if (other[0] == cell[0] && other[1] == cell[1] && other[2] == cell[2]) {
                if (seen) seen[i] = number;
                break;
            }
            slot = (slot + 1) & mask;
        }
    }
    return true;
}

}  // namespace

int64_t voxel_count(CArr2 points_, CArr1 low_, double voxel) {
    if (points_.shape(1) != 3 || low_.shape(0) != 3)
        throw std::invalid_argument("voxel_count: points (N, 3), low (3,)");
    std::vector<int64_t> cells;
    if (!hash_cells(points_.data(), int64_t(points_.shape(0)), low_.data(), voxel, cells, nullptr)) return -1;
    return int64_t(cells.size() / 3);
}

void knn_in_cells(CArr2 points_, CArr2 queries_, CArr1 low_, double cell, Idx2 out_indices_, U8Arr1 out_exact_,
                  int threads) {
    const int64_t count = int64_t(points_.shape(0)), queries = int64_t(queries_.shape(0));
    const int64_t k = int64_t(out_indices_.shape(1));
    if (points_.shape(1) != 3 || queries_.shape(1) != 3 || low_.shape(0) != 3 ||
        int64_t(out_indices_.shape(0)) != queries || int64_t(out_exact_.shape(0)) != queries || k < 1 ||
        k > GRAPH_K_MAX || !(cell > 0.0))
        throw std::invalid_argument("knn_in_cells: points (N, 3), queries (Q, 3), low (3,), out_indices (Q, k), "
                                    "out_exact (Q,), 1 <= k <= 64, cell > 0");
    const double *p = points_.data(), *q = queries_.data(), *low = low_.data();
    int64_t *out = out_indices_.data();
    uint8_t *exact = out_exact_.data();
    std::vector<int64_t> cells, seen(static_cast<size_t>(count));
    std::fill(exact, exact + queries, uint8_t(0));
    if (!hash_cells(p, count, low, cell, cells, seen.data())) return;  // too fine a cell: none exact
    const int64_t occupied = int64_t(cells.size() / 3);
    // The points of each cell, in point order (a counting sort by cell).
    std::vector<int64_t> first(static_cast<size_t>(occupied + 1), 0), members(static_cast<size_t>(count));
    for (int64_t i = 0; i < count; ++i) ++first[size_t(seen[size_t(i)] + 1)];
    for (int64_t c = 0; c < occupied; ++c) first[size_t(c + 1)] += first[size_t(c)];
    {
        std::vector<int64_t> fill(first.begin(), first.end() - 1);
        for (int64_t i = 0; i < count; ++i) members[size_t(fill[size_t(seen[size_t(i)])]++)] = i;
    }
    // A lookup of the cells by their coordinates (open addressing, as hash_cells numbers them).
    int bits = 4;
    while ((int64_t(1) << bits) < 2 * occupied) ++bits;
    const int64_t mask = (int64_t(1) << bits) - 1;
    const int shift = 64 - bits;
    const auto slot_of = [&](const int64_t *at) {
        uint64_t key = uint64_t(at[0]) * HASH_MULTIPLIER;
        key = (key ^ uint64_t(at[1])) * HASH_MULTIPLIER;
        key = (key ^ uint64_t(at[2])) * HASH_MULTIPLIER;
        return int64_t(key >> shift);
    };
    std::vector<int64_t> table(size_t(mask + 1), -1);
    for (int64_t c = 0; c < occupied; ++c) {
        int64_t slot = slot_of(cells.data() + 3 * c);
        while (table[size_t(slot)] >= 0) slot = (slot + 1) & mask;
        table[size_t(slot)] = c;
    }
    const auto find = [&](const int64_t *at) {
        int64_t slot = slot_of(at);
        for (;;) {
            const int64_t number = table[size_t(slot)];
            if (number < 0) return int64_t(-1);
            const int64_t *other = cells.data() + 3 * number;
            if (other[0] == at[0] && other[1] == at[1] && other[2] == at[2]) return number;
            slot = (slot + 1) & mask;
        }
    };
    // Every point outside the 27 cells around a query's own lies at least one cell away from it;
    // the margin covers the rounding of the cell coordinates.
    const double reach = 0.999 * cell;
    constexpr double LIMIT = 4611686018427387904.0;  // 2^62
    parallel_pieces(piece_count(queries, 64), queries < 256 ? 1 : threads, [&](int64_t piece) {
        double best[GRAPH_K_MAX];
        int64_t slots[GRAPH_K_MAX];
        const int64_t end = std::min(queries, (piece + 1) * int64_t(64));
        for (int64_t i = piece * 64; i < end; ++i) {
            const double x = q[3 * i], y = q[3 * i + 1], z = q[3 * i + 2];
            int64_t centre[3];
            bool inside = true;
            for (int a = 0; a < 3; ++a) {
                const double scaled = std::floor((q[3 * i + a] - low[a]) / cell);
                if (!(std::fabs(scaled) < LIMIT)) inside = false;
                else centre[a] = int64_t(scaled);
            }
            if (!inside) continue;
            std::fill(best, best + k, INF);
            std::fill(slots, slots + k, int64_t(-1));
            for (int64_t dx = -1; dx <= 1; ++dx)
                for (int64_t dy = -1; dy <= 1; ++dy)
                    for (int64_t dz = -1; dz <= 1; ++dz) {
                        const int64_t at[3] = {centre[0] + dx, centre[1] + dy, centre[2] + dz};
                        const int64_t number = find(at);
                        if (number < 0) continue;
                        for (int64_t m = first[size_t(number)]; m < first[size_t(number + 1)]; ++m) {
                            const int64_t j = members[size_t(m)];
                            const double ex = p[3 * j] - x, ey = p[3 * j + 1] - y, ez = p[3 * j + 2] - z;
                            const double distance = ex * ex + ey * ey + ez * ez;
                            if (!(distance < best[k - 1])) continue;
                            int64_t place = k - 1;
                            while (place > 0 && distance < best[place - 1]) {
                                best[place] = best[place - 1];
                                slots[place] = slots[place - 1];
                                --place;
                            }
                            best[place] = distance;
                            slots[place] = j;
                        }
                    }
            for (int64_t j = 0; j < k; ++j) out[k * i + j] = slots[j];
            exact[i] = slots[k - 1] >= 0 && best[k - 1] <= reach * reach;
        }
    });
}

int64_t voxel_cells(CArr2 points_, CArr1 low_, double voxel, Idx owner_, Arr2 sums_, Idx counts_) {
    const int64_t count = int64_t(points_.shape(0));
    if (points_.shape(1) != 3 || low_.shape(0) != 3 || int64_t(owner_.shape(0)) != count ||
        int64_t(sums_.shape(0)) < count || sums_.shape(1) != 3 || int64_t(counts_.shape(0)) < count)
        throw std::invalid_argument("voxel_cells: points (N, 3), low (3,), owner (N,), sums (>= N, 3), counts (>= N,)");
    const double *p = points_.data(), *low = low_.data();
    int64_t *owner = owner_.data(), *counts = counts_.data();
    double *sums = sums_.data();
    std::vector<int64_t> cells;                          // (cells, 3) integer coordinates
    std::vector<int64_t> seen(static_cast<size_t>(count));  // each point's cell, in order of first sight
    if (!hash_cells(p, count, low, voxel, cells, seen.data())) return -1;
    const int64_t occupied = int64_t(cells.size() / 3);
    std::vector<int64_t> sorted(static_cast<size_t>(occupied)), rank(static_cast<size_t>(occupied));
    for (int64_t c = 0; c < occupied; ++c) sorted[size_t(c)] = c;
    std::sort(sorted.begin(), sorted.end(), [&](int64_t a, int64_t b) {
        const int64_t *x = cells.data() + 3 * a, *y = cells.data() + 3 * b;
        return std::lexicographical_compare(x, x + 3, y, y + 3);
    });
    for (int64_t c = 0; c < occupied; ++c) rank[size_t(sorted[size_t(c)])] = c;
    std::fill(sums, sums + 3 * occupied, 0.0);
    std::fill(counts, counts + occupied, int64_t(0));
    for (int64_t i = 0; i < count; ++i) {
        const int64_t c = rank[size_t(seen[size_t(i)])];
        owner[i] = c;
        for (int a = 0; a < 3; ++a) sums[3 * c + a] += p[3 * i + a];
        ++counts[c];
    }
    return occupied;
}

Coincident coincident(CArr2 points_, U8Arr1 first_) {
    const int64_t count = int64_t(points_.shape(0));
    const double *p = points_.data();
    uint8_t *first = first_.data();
    int bits = 4;
    while ((int64_t(1) << bits) < 2 * count) ++bits;
    const int64_t size = int64_t(1) << bits, mask = size - 1;
    const int shift = 64 - bits;
    // Each slot holds the first point of its coordinates (-1: empty), 4 bytes while the points
    // allow (a table a quarter the size: fewer cache misses, each insertion's cost); the number of
    // copies of a first point is kept beside, read only on a repeat.
    const auto run = [&](auto *slots) {
        using Stored = std::remove_pointer_t<decltype(slots)>;
        std::fill(slots, slots + size, Stored(-1));
        std::vector<int64_t> copies;
        int64_t repeats = 0, most = 0, most_count = count > 0 ? 1 : 0;
        for (int64_t i = 0; i < count; ++i) {
            if ((i & ((int64_t(1) << 16) - 1)) == 0 && i > 0 && signal_raised()) throw PythonError();
            const uint64_t x = coordinate_bits(p[3 * i]), y = coordinate_bits(p[3 * i + 1]),
                           z = coordinate_bits(p[3 * i + 2]);
            uint64_t key = x * HASH_MULTIPLIER;
            key = (key ^ (key >> 29) ^ y) * HASH_MULTIPLIER;
            key = (key ^ (key >> 29) ^ z) * HASH_MULTIPLIER;
            int64_t slot = int64_t(key >> uint64_t(shift));
            while (true) {
                const int64_t stored = int64_t(slots[slot]);
                if (stored < 0) {
                    slots[slot] = Stored(i);
                    first[i] = 1;
                    break;
                }
                if (p[3 * stored] == p[3 * i] && p[3 * stored + 1] == p[3 * i + 1] &&
                    p[3 * stored + 2] == p[3 * i + 2]) {
                    first[i] = 0;
                    ++repeats;
                    if (copies.empty()) copies.assign(size_t(count), 1);
                    if (++copies[size_t(stored)] > most_count) {
                        most_count = copies[size_t(stored)];
                        most = stored;
                    }
                    break;
                }
                slot = (slot + 1) & mask;
            }
        }
        return Coincident{repeats, most, most_count};
    };
    if (count < (int64_t(1) << 31)) {
        std::vector<int32_t> slots(static_cast<size_t>(size));
        return run(slots.data());
    }
    std::vector<int64_t> slots(static_cast<size_t>(size));
    return run(slots.data());
}

void column_sums(CArr2 points_, Arr1 out_) {
    const int64_t count = int64_t(points_.shape(0));
    if (points_.shape(1) != 3 || out_.shape(0) != 3)
        throw std::invalid_argument("column_sums: points (N, 3), out (3,)");
    const double *p = points_.data();
    double x = 0.0, y = 0.0, z = 0.0;
    {
        GilReleased release;
        for (int64_t i = 0; i < count; ++i) {
            x += p[3 * i];
            y += p[3 * i + 1];
            z += p[3 * i + 2];
        }
    }
    double *o = out_.data();
    o[0] = x;
    o[1] = y;
    o[2] = z;
}

void centred_scatter(CArr2 points_, CArr1 centre_, double scale, Arr2 out_) {
    const int64_t count = int64_t(points_.shape(0));
    if (points_.shape(1) != 3 || centre_.shape(0) != 3 || out_.shape(0) != 3 || out_.shape(1) != 3)
        throw std::invalid_argument("centred_scatter: points (N, 3), centre (3,), out (3, 3)");
    const double *p = points_.data(), *c = centre_.data();
    // Sums of blocks of SCATTER_BLOCK points, then of the blocks' sums: a rounding error of about
    // (SCATTER_BLOCK + N / SCATTER_BLOCK) ulps of the total rather than N.
    constexpr int64_t SCATTER_BLOCK = 4096;
    double total[6] = {0.0};
    for (int64_t start = 0; start < count; start += SCATTER_BLOCK) {
        const int64_t end = std::min(count, start + SCATTER_BLOCK);
        double block[6] = {0.0};
        for (int64_t i = start; i < end; ++i) {
            const double x = (p[3 * i] - c[0]) / scale, y = (p[3 * i + 1] - c[1]) / scale,
                         z = (p[3 * i + 2] - c[2]) / scale;
            block[0] += x * x;
            block[1] += x * y;
            block[2] += x * z;
            block[3] += y * y;
            block[4] += y * z;
            block[5] += z * z;
        }
        for (int a = 0; a < 6; ++a) total[a] += block[a];
    }
    double *o = out_.data();
    o[0] = total[0];
    o[1] = o[3] = total[1];
    o[2] = o[6] = total[2];
    o[4] = total[3];
    o[5] = o[7] = total[4];
    o[8] = total[5];
}

void transform_points(CArr2 points, CArr2 rotation, CArr1 translation, Arr2 out_, int threads) {
    const int64_t count = int64_t(points.shape(0));
    const double *q = points.data(), *r = rotation.data(), *t = translation.data();
    double *o = out_.data();
    if (count < 65536) threads = 1;
    parallel_pieces(piece_count(count, SUM_PIECE), threads, [&](int64_t piece) {
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) mapped(q, i, r, t, o[3 * i], o[3 * i + 1], o[3 * i + 2]);
    });
}

}  // namespace kernels
