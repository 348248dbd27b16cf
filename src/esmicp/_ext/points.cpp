// Passes over a cloud's points (points.hpp).
#include "points.hpp"

#include "common.hpp"
#include "moments.hpp"
#include "pool.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <cstring>
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
    struct Slot {
        int64_t index = -1, count = 0;
    };
    std::vector<Slot> slots(size);
    int64_t repeats = 0, most = 0, most_count = count > 0 ? 1 : 0;
    for (int64_t i = 0; i < count; ++i) {
        if ((i & ((int64_t(1) << 16) - 1)) == 0 && i > 0 && signal_raised()) throw PythonError();
        const uint64_t x = coordinate_bits(p[3 * i]), y = coordinate_bits(p[3 * i + 1]), z = coordinate_bits(p[3 * i + 2]);
        uint64_t key = x * HASH_MULTIPLIER;
        key = (key ^ (key >> 29) ^ y) * HASH_MULTIPLIER;
        key = (key ^ (key >> 29) ^ z) * HASH_MULTIPLIER;
        int64_t slot = int64_t(key >> uint64_t(shift));
        while (true) {
            const int64_t stored = slots[slot].index;
            if (stored < 0) {
                slots[slot].index = i;
                slots[slot].count = 1;
                first[i] = 1;
                break;
            }
            if (p[3 * stored] == p[3 * i] && p[3 * stored + 1] == p[3 * i + 1] && p[3 * stored + 2] == p[3 * i + 2]) {
                first[i] = 0;
                ++repeats;
                if (++slots[slot].count > most_count) {
                    most_count = slots[slot].count;
                    most = stored;
                }
                break;
            }
            slot = (slot + 1) & mask;
        }
    }
    return Coincident{repeats, most, most_count};
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
