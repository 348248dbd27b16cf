// Correspondences of the global search (matching.hpp).
#include "matching.hpp"

#include "pool.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace kernels {
namespace {

// Squared lengths |p - q|^2 of a pair of correspondences in the source and in the target, the
// coordinates summed x, y, z in turn (as SciPy's cdist and NumPy's norm sum them).
inline void squared_lengths(const double *sp, const double *sq, const double *tp, const double *tq, double &source,
                            double &target) {
    double a = 0.0, b = 0.0, d;
    d = sp[0] - sq[0]; a += d * d;
    d = sp[1] - sq[1]; a += d * d;
    d = sp[2] - sq[2]; a += d * d;
    d = tp[0] - tq[0]; b += d * d;
    d = tp[1] - tq[1]; b += d * d;
    d = tp[2] - tq[2]; b += d * d;
    source = a;
    target = b;
}

// Row `row` of `count` floats as a bitset (bit j: row[j] != 0), `(count + 63) / 64` words.
// Branch-free: a branch per entry mispredicts on rows that are half ones (LiDAR correspondences).
void pack_row(const float *row, int64_t count, uint64_t *word) {
    for (int64_t w = 0; w * 64 < count; ++w) {
        const float *part = row + 64 * w;
        const int64_t end = std::min<int64_t>(64, count - 64 * w);
        uint64_t value = 0;
        int64_t k = 0;
#if defined(__SSE2__)
        const __m128 zero = _mm_setzero_ps();
        for (; k + 4 <= end; k += 4)
            value |= uint64_t(_mm_movemask_ps(_mm_cmpneq_ps(_mm_loadu_ps(part + k), zero))) << k;
#endif
        for (; k < end; ++k) value |= uint64_t(part[k] != 0.0f) << k;
        word[w] = value;
    }
}

// Population count and lowest set bit of a 64-bit word: GCC's and Clang's builtins, or plain C++
// for other compilers (MSVC).
#if defined(__GNUC__) || defined(__clang__)
inline int64_t popcount64(uint64_t x) { return __builtin_popcountll(x); }
inline int64_t lowest_set_bit(uint64_t x) { return __builtin_ctzll(x); }
#else
inline int64_t popcount64(uint64_t x) {
    x = x - ((x >> 1) & 0x5555555555555555ULL);
    x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0FULL;
    return int64_t((x * 0x0101010101010101ULL) >> 56);
}
inline int64_t lowest_set_bit(uint64_t x) {
    int64_t bit = 0;
    while (!(x & 1)) {
        x >>= 1;
        ++bit;
    }
    return bit;
}
#endif

// Bits set in both of two bitsets of `words` 64-bit words. On x86-64 with GCC, a version with the
// processor's popcount instructions (AVX-512 VPOPCNTDQ, eight words at a time, or POPCNT) is
// chosen once at run time when the processor has them (the baseline x86-64 target has neither, and
// its software popcount costs several times more).
int64_t common_bits_plain(const uint64_t *a, const uint64_t *b, int64_t words) {
    int64_t both = 0;
    for (int64_t v = 0; v < words; ++v) both += popcount64(a[v] & b[v]);
    return both;
}
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
__attribute__((target("popcnt"))) int64_t common_bits_popcnt(const uint64_t *a, const uint64_t *b, int64_t words) {
    int64_t both = 0;
    for (int64_t v = 0; v < words; ++v) both += __builtin_popcountll(a[v] & b[v]);
    return both;
}
// (The AVX-512 version from GCC 11 on, where its feature test is known for certain.)
#if __GNUC__ >= 11
__attribute__((target("avx512f,avx512vpopcntdq,popcnt"), optimize("tree-vectorize")))
int64_t common_bits_avx512(const uint64_t *a, const uint64_t *b, int64_t words) {
    int64_t both = 0;
    for (int64_t v = 0; v < words; ++v) both += __builtin_popcountll(a[v] & b[v]);
    return both;
}
#endif
using CommonBits = int64_t (*)(const uint64_t *, const uint64_t *, int64_t);
CommonBits pick_common_bits() {
    __builtin_cpu_init();
#if __GNUC__ >= 11
    if (__builtin_cpu_supports("avx512vpopcntdq") && __builtin_cpu_supports("avx512f")) return common_bits_avx512;
#endif
    if (__builtin_cpu_supports("popcnt")) return common_bits_popcnt;
    return common_bits_plain;
}
const CommonBits common_bits = pick_common_bits();
#else
const auto common_bits = common_bits_plain;
#endif

//: Columns per piece of nearest_descriptors.
constexpr int64_t DESCRIPTOR_COLUMNS = 512;

//: Rows of nearest_descriptors whose dot products are formed together (count): each column value
//: loaded serves them all.
constexpr int64_t DESCRIPTOR_ROWS = 4;
//: Columns whose sums stay in registers while the dimensions are summed (count).
constexpr int64_t DESCRIPTOR_LANES = 16;

// values[r][j] = sum_k rows[r][k] * transposed[k * stride + j] for r < DESCRIPTOR_ROWS (rows past
// `count` are left alone) and j < width: a few descriptors against a piece of the (D, C) transposed
// others, float32, k in order, DESCRIPTOR_LANES columns at a time summed in registers. On x86-64
// with GCC also compiled with AVX and FMA, chosen at load time where the processor has FMA (the
// sums then round once per step: the same on every run of one machine, the nearest descriptors
// the same on every machine but where two lie within a rounding of each other).
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
__attribute__((target_clones("fma", "default")))
#endif
void dot_products(const float *const *rows, int64_t count, const float *transposed, int64_t stride,
                  int64_t dimension, int64_t width, float (*values)[DESCRIPTOR_COLUMNS]) {
    int64_t j0 = 0;
    if (count == DESCRIPTOR_ROWS) {
        for (; j0 + DESCRIPTOR_LANES <= width; j0 += DESCRIPTOR_LANES) {
            float sums[DESCRIPTOR_ROWS][DESCRIPTOR_LANES] = {};
            for (int64_t k = 0; k < dimension; ++k) {
                const float *column = transposed + stride * k + j0;
                for (int64_t r = 0; r < DESCRIPTOR_ROWS; ++r) {
                    const float weight = rows[r][k];
                    for (int64_t j = 0; j < DESCRIPTOR_LANES; ++j) sums[r][j] += weight * column[j];
                }
            }
            for (int64_t r = 0; r < DESCRIPTOR_ROWS; ++r)
                for (int64_t j = 0; j < DESCRIPTOR_LANES; ++j) values[r][j0 + j] = sums[r][j];
        }
    }
    for (int64_t r = 0; r < count; ++r) {
        for (int64_t j = j0; j < width; ++j) values[r][j] = 0.0f;
        for (int64_t k = 0; k < dimension; ++k) {
            const float weight = rows[r][k];
            const float *column = transposed + stride * k;
            for (int64_t j = j0; j < width; ++j) values[r][j] += weight * column[j];
        }
    }
}

}  // namespace

void compatibility(CArr2 source, CArr2 target, double tolerance, F32Arr2 out, int threads) {
    const int64_t count = int64_t(source.shape(0));
    if (source.shape(1) != 3 || target.shape(1) != 3 || int64_t(target.shape(0)) != count ||
        int64_t(out.shape(0)) != count || int64_t(out.shape(1)) != count)
        throw std::invalid_argument("compatibility: source and target (K, 3), out (K, K)");
    const double *s = source.data(), *t = target.data();
    float *o = out.data();
    constexpr int64_t ROWS = 32;
    if (count < 256) threads = 1;
    parallel_pieces(piece_count(count, ROWS), threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * ROWS);
        for (int64_t i = piece * ROWS; i < end; ++i) {
            // Row i from its diagonal on; the entries below it are mirrored (the matrix is symmetric,
            // and each entry is written by the one row that computes it).
            float *row = o + count * i;
            const double *si = s + 3 * i, *ti = t + 3 * i;
            row[i] = 0.0f;
            for (int64_t j = i + 1; j < count; ++j) {
                double a, b;
                squared_lengths(si, s + 3 * j, ti, t + 3 * j, a, b);
                const float value = std::fabs(std::sqrt(a) - std::sqrt(b)) <= tolerance ? 1.0f : 0.0f;
                row[j] = value;
                o[count * j + i] = value;
            }
        }
    });
}

void leading_vector(CF32Arr2 matrix, double tolerance, int64_t iterations, F32Arr1 out_, int threads) {
    const int64_t count = int64_t(matrix.shape(0));
    if (int64_t(matrix.shape(1)) != count || int64_t(out_.shape(0)) != count)
        throw std::invalid_argument("leading_vector: matrix (K, K), out (K,)");
    float *out = out_.data();
    if (count == 0) return;
    const float *m = matrix.data();
    constexpr int64_t ROWS = 64;
    const int64_t pieces = piece_count(count, ROWS);
    if (count < 256) threads = 1;
    // The non-zero entries of each row (column, value), gathered once.
    std::vector<std::vector<std::pair<int32_t, float>>> rows(static_cast<size_t>(count));
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * ROWS);
        for (int64_t i = piece * ROWS; i < end; ++i) {
            const float *row = m + count * i;
            auto &entries = rows[size_t(i)];
            for (int64_t j = 0; j < count; ++j)
                if (row[j] != 0.0f) entries.emplace_back(int32_t(j), row[j]);
        }
    });
    std::vector<float> vector(size_t(count), float(1.0 / std::sqrt(double(count))));
    std::vector<double> product(static_cast<size_t>(count));
    for (int64_t step = 0; step < iterations; ++step) {
        parallel_pieces(pieces, threads, [&](int64_t piece) {
            const int64_t end = std::min(count, (piece + 1) * ROWS);
            for (int64_t i = piece * ROWS; i < end; ++i) {
                double sum = 0.0;
                for (const auto &entry : rows[size_t(i)]) sum += double(entry.second) * double(vector[size_t(entry.first)]);
                product[size_t(i)] = sum;
            }
        });
        double norm = 0.0;
        for (int64_t i = 0; i < count; ++i) norm += product[size_t(i)] * product[size_t(i)];
        norm = std::sqrt(norm);
        const double scale = norm > 0.0 ? 1.0 / norm : 1.0;
        double moved = 0.0;
        for (int64_t i = 0; i < count; ++i) {
            const float next = float(product[size_t(i)] * scale);
            moved = std::max(moved, double(std::fabs(next - vector[size_t(i)])));
            vector[size_t(i)] = next;
        }
        if (moved <= tolerance) break;
    }
    std::copy(vector.begin(), vector.end(), out);
}

int64_t spread_seeds(CIdx order, CArr2 source, CArr2 target, double spread, int64_t seeds, Idx out) {
    const int64_t count = int64_t(order.shape(0));
    if (source.shape(1) != 3 || target.shape(1) != 3 || target.shape(0) != source.shape(0) ||
        int64_t(out.shape(0)) < std::min(count, seeds))
        throw std::invalid_argument("spread_seeds: source and target (N, 3), out as long as the seeds");
    const double *s = source.data(), *t = target.data();
    const int64_t *candidates = order.data();
    const int64_t points = int64_t(source.shape(0));
    int64_t *kept = out.data();
    int64_t chosen = 0;
    for (int64_t c = 0; c < count && chosen < seeds; ++c) {
        const int64_t i = candidates[c];
        if (i < 0 || i >= points) throw std::invalid_argument("spread_seeds: order holds an index out of range");
        const double *si = s + 3 * i, *ti = t + 3 * i;
        bool near = false;
        for (int64_t k = 0; k < chosen && !near; ++k) {
            double a, b;
            squared_lengths(s + 3 * kept[k], si, t + 3 * kept[k], ti, a, b);
            near = std::sqrt(a) < spread && std::sqrt(b) < spread;
        }
        if (!near) kept[chosen++] = i;
    }
    return chosen;
}

void second_order_partners(CF32Arr2 compatible, CIdx seeds, Idx2 partners, U8Arr2 valid, int threads) {
    const int64_t count = int64_t(compatible.shape(0));
    const int64_t groups = int64_t(seeds.shape(0));
    const int64_t size = int64_t(partners.shape(1));
    if (int64_t(compatible.shape(1)) != count || int64_t(partners.shape(0)) != groups ||
        int64_t(valid.shape(0)) != groups || int64_t(valid.shape(1)) != size || size > count)
        throw std::invalid_argument("second_order_partners: compatible (K, K), partners and valid (S, size <= K)");
    const float *c = compatible.data();
    const int64_t *seed = seeds.data();
    int64_t *out = partners.data();
    uint8_t *ok = valid.data();
    for (int64_t g = 0; g < groups; ++g)
        if (seed[g] < 0 || seed[g] >= count) throw std::invalid_argument("second_order_partners: seed out of range");
    // Each row as a bitset (bit j of row i: C[i][j] != 0): the count of candidates compatible with
    // both seed and partner is then the popcount of two rows' AND.
    const int64_t words = (count + 63) / 64;
    std::vector<uint64_t> bits(size_t(count * words), 0);
    parallel_pieces(piece_count(count, 64), threads, [&](int64_t piece) {
        const int64_t end = std::min(count, (piece + 1) * 64);
        for (int64_t i = piece * 64; i < end; ++i)
            pack_row(c + count * i, count, bits.data() + words * i);
    });
    parallel_pieces(groups, groups < 16 ? 1 : threads, [&](int64_t g) {
        const uint64_t *mine = bits.data() + words * seed[g];
        std::vector<std::pair<int64_t, int64_t>> ranked;  // (-second order, index)
        for (int64_t w = 0; w < words; ++w) {
            for (uint64_t word = mine[w]; word; word &= word - 1) {
                const int64_t j = w * 64 + lowest_set_bit(word);
                const uint64_t *other = bits.data() + words * j;
                const int64_t both = common_bits(mine, other, words);
                if (both > 0) ranked.emplace_back(-both, j);
            }
        }
        const int64_t top = std::min<int64_t>(size, int64_t(ranked.size()));
        std::partial_sort(ranked.begin(), ranked.begin() + top, ranked.end());
        int64_t *partner = out + size * g;
        uint8_t *flag = ok + size * g;
        for (int64_t k = 0; k < top; ++k) {
            partner[k] = ranked[k].second;
            flag[k] = 1;
        }
        if (top < size) {
            // The candidates at 0, in index order: every index not among the positive ones.
            std::vector<uint8_t> positive(count, 0);
            for (const auto &entry : ranked) positive[entry.second] = 1;
            int64_t k = top;
            for (int64_t j = 0; j < count && k < size; ++j)
                if (!positive[j]) {
                    partner[k] = j;
                    flag[k++] = 0;
                }
        }
    });
}

void group_second_order(CF32Arr2 compatible, CIdx2 groups_, U8Arr2 valid_, F32Arr2 out_, int threads) {
    const int64_t count = int64_t(compatible.shape(0));
    const int64_t groups = int64_t(groups_.shape(0)), size = int64_t(groups_.shape(1));
    if (int64_t(compatible.shape(1)) != count || int64_t(valid_.shape(0)) != groups ||
        int64_t(valid_.shape(1)) != size || int64_t(out_.shape(0)) != groups || int64_t(out_.shape(1)) != size * size)
        throw std::invalid_argument("group_second_order: compatible (K, K), groups and valid (S, G), out (S, G * G)");
    const float *c = compatible.data();
    const int64_t *members = groups_.data();
    const uint8_t *valid = valid_.data();
    float *out = out_.data();
    for (int64_t k = 0; k < groups * size; ++k)
        if (members[k] < 0 || members[k] >= count) throw std::invalid_argument("group_second_order: member out of range");
    parallel_pieces(groups, groups < 16 ? 1 : threads, [&](int64_t g) {
        const int64_t *member = members + size * g;
        const uint8_t *ok = valid + size * g;
        std::vector<float> local(size_t(size * size));
        for (int64_t i = 0; i < size; ++i)
            for (int64_t j = 0; j < size; ++j)
                local[size_t(i * size + j)] = ok[i] && ok[j] ? c[count * member[i] + member[j]] : 0.0f;
        // Row i of local @ local: the rows k of local that row i holds, added (whole numbers: exact).
        float *result = out + size * size * g;
        for (int64_t i = 0; i < size; ++i) {
            const float *row = local.data() + size * i;
            float *both = result + size * i;
            std::fill(both, both + size, 0.0f);
            for (int64_t k = 0; k < size; ++k) {
                if (row[k] == 0.0f) continue;
                const float *other = local.data() + size * k;
                for (int64_t j = 0; j < size; ++j) both[j] += row[k] * other[j];
            }
            for (int64_t j = 0; j < size; ++j) both[j] *= row[j];
        }
    });
}

void pair_inlier_counts(CArr2 rotations, CArr2 translations, CArr2 source, CArr2 target, double distance, Idx out,
                        int threads) {
    const int64_t poses = int64_t(rotations.shape(0));
    const int64_t count = int64_t(source.shape(0));
    if (rotations.shape(1) != 9 || translations.shape(1) != 3 || int64_t(translations.shape(0)) != poses ||
        source.shape(1) != 3 || target.shape(1) != 3 || int64_t(target.shape(0)) != count ||
        int64_t(out.shape(0)) != poses)
        throw std::invalid_argument("pair_inlier_counts: rotations (S, 9), translations (S, 3), source and target (K, 3), out (S,)");
    const double *r = rotations.data(), *t = translations.data(), *s = source.data(), *d = target.data();
    const double limit = distance * distance;
    int64_t *counts = out.data();
    parallel_pieces(poses, poses * count < 65536 ? 1 : threads, [&](int64_t c) {
        const double *rc = r + 9 * c, *tc = t + 3 * c;
        int64_t inside = 0;
        for (int64_t k = 0; k < count; ++k) {
            const double *sk = s + 3 * k, *dk = d + 3 * k;
            double sum = 0.0;
            for (int i = 0; i < 3; ++i) {
                const double e = rc[3 * i] * sk[0] + rc[3 * i + 1] * sk[1] + rc[3 * i + 2] * sk[2] + tc[i] - dk[i];
                sum += e * e;
            }
            inside += sum <= limit;
        }
        counts[c] = inside;
    });
}

void nearest_descriptors(CF32Arr2 rows_, CF32Arr2 columns_, CF32Arr1 row_squares_, CF32Arr1 column_squares_,
                         Idx out_row_index_, F32Arr1 out_row_best_, F32Arr1 out_row_second_, F32Arr2 column_best_,
                         Idx column_index_, int threads) {
    const int64_t rows = int64_t(rows_.shape(0)), columns = int64_t(columns_.shape(1));
    const int64_t dimension = int64_t(rows_.shape(1));
    if (int64_t(columns_.shape(0)) != dimension || int64_t(row_squares_.shape(0)) != rows ||
        int64_t(column_squares_.shape(0)) != columns || int64_t(out_row_index_.shape(0)) != rows ||
        int64_t(out_row_best_.shape(0)) != rows || int64_t(out_row_second_.shape(0)) != rows ||
        column_best_.shape(0) != 2 || int64_t(column_best_.shape(1)) != columns ||
        int64_t(column_index_.shape(0)) != columns || rows < 1 || columns < 1)
        throw std::invalid_argument("nearest_descriptors: rows (R, D), columns (D, C), row arrays (R,), "
                                    "column_best (2, C), column_index (C,), R, C >= 1");
    const float *descriptors = rows_.data(), *transposed = columns_.data();
    const float *row_squares = row_squares_.data(), *column_squares = column_squares_.data();
    float *first = column_best_.data(), *second = column_best_.data() + columns;
    int64_t *column_index = column_index_.data();
    const int64_t pieces = piece_count(columns, DESCRIPTOR_COLUMNS);
    const float inf = std::numeric_limits<float>::infinity();
    std::fill(first, first + 2 * columns, inf);
    std::fill(column_index, column_index + columns, int64_t(0));
    std::vector<float> piece_best(size_t(pieces) * size_t(rows)), piece_second(size_t(pieces) * size_t(rows));
    std::vector<int64_t> piece_index(size_t(pieces) * size_t(rows));
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        const int64_t begin = piece * DESCRIPTOR_COLUMNS, end = std::min(columns, begin + DESCRIPTOR_COLUMNS);
        float block[DESCRIPTOR_ROWS][DESCRIPTOR_COLUMNS];
        float values[DESCRIPTOR_COLUMNS];
        int32_t moved[DESCRIPTOR_COLUMNS];
        const int64_t width = end - begin;
        for (int64_t i = 0; i < rows; ++i) {
            if (i % DESCRIPTOR_ROWS == 0) {
                // The dot products of this row and the next few, together.
                const float *block_rows[DESCRIPTOR_ROWS];
                const int64_t count = std::min(DESCRIPTOR_ROWS, rows - i);
                for (int64_t r = 0; r < count; ++r) block_rows[r] = descriptors + dimension * (i + r);
                dot_products(block_rows, count, transposed + begin, columns, dimension, width, block);
            }
            const float *dots = block[i % DESCRIPTOR_ROWS];
            const float own = row_squares[i];
            const int64_t label = i;
            // Distances, then the columns' running minima, row by row: no dependence between
            // columns, so the loops vectorise; then the row's minima, whose branches are rarely taken.
            for (int64_t j = 0; j < width; ++j) values[j] = dots[j];
            for (int64_t j = 0; j < width; ++j) {
                float value = values[j] * -2.0f;
                value = value + column_squares[begin + j];
                value = value + own;
                values[j] = value < 0.0f ? 0.0f : value;
            }
            float *column_first = first + begin, *column_second = second + begin;
            int64_t *column_label = column_index + begin;
            for (int64_t j = 0; j < width; ++j) {
                const float value = values[j], low = column_first[j];
                const bool lower = value < low;
                column_second[j] = lower ? low : std::min(column_second[j], value);
                column_first[j] = lower ? value : low;
                moved[j] = lower ? 1 : 0;  // int32 beside float32: the loop vectorises
            }
            for (int64_t j = 0; j < width; ++j)
                if (moved[j]) column_label[j] = label;
            float best = inf, runner_up = inf;
            int64_t nearest = 0;
            for (int64_t j = 0; j < width; ++j) {
                const float value = values[j];
                if (value < runner_up) {
                    if (value < best) {
                        runner_up = best;
                        best = value;
                        nearest = j;
                    } else {
                        runner_up = value;
                    }
                }
            }
            const size_t slot = size_t(piece) * size_t(rows) + size_t(i);
            piece_best[slot] = best;
            piece_second[slot] = runner_up;
            piece_index[slot] = begin + nearest;
        }
    });
    int64_t *row_index = out_row_index_.data();
    float *row_best = out_row_best_.data(), *row_second = out_row_second_.data();
    for (int64_t i = 0; i < rows; ++i) {
        float best = piece_best[size_t(i)], runner_up = piece_second[size_t(i)];
        int64_t nearest = piece_index[size_t(i)];
        for (int64_t piece = 1; piece < pieces; ++piece) {
            const size_t slot = size_t(piece) * size_t(rows) + size_t(i);
            if (piece_best[slot] < best) {
                runner_up = std::min(best, piece_second[slot]);
                best = piece_best[slot];
                nearest = piece_index[slot];
            } else {
                runner_up = std::min(runner_up, piece_best[slot]);
            }
        }
        row_index[i] = nearest;
        row_best[i] = best;
        row_second[i] = runner_up;
    }
}

}  // namespace kernels
