// Passes over a cloud's points (points.hpp).
#include "points.hpp"

#include "common.hpp"
#include "moments.hpp"
#include "pool.hpp"

#include <algorithm>
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
