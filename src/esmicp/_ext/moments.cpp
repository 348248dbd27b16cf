// Pair moments (moments.hpp).
#include "moments.hpp"

#include "common.hpp"
#include "pool.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

namespace kernels {

void moments_of_pairs(const double *s, int64_t count, const double *r, const double *tr, const double *tg,
                      const int64_t *ix, const double *d, double scale, double shift, double *o, int threads,
                      bool pooled) {
    double sref[3], tref[3];
    for (int a = 0; a < 3; ++a) {
        sref[a] = r[3 * a] * s[0] + r[3 * a + 1] * s[1] + r[3 * a + 2] * s[2] + tr[a];
        tref[a] = tg[3 * ix[0] + a];
    }
    const int64_t pieces = piece_count(count, SUM_PIECE);
    std::vector<double> partial(17 * pieces, 0.0);
    auto moments = [&](int64_t piece) {
        double w0 = 0, w1 = 0, ax = 0, ay = 0, az = 0, bx = 0, by = 0, bz = 0;
        double c[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) {
            double w = scale > 0.0 ? std::exp(-(d[i] * d[i] - shift) * scale) : 1.0;
            double sx, sy, sz;
            mapped(s, i, r, tr, sx, sy, sz);
            sx -= sref[0];
            sy -= sref[1];
            sz -= sref[2];
            int64_t j = ix[i];
            double tx = tg[3 * j] - tref[0], ty = tg[3 * j + 1] - tref[1], tz = tg[3 * j + 2] - tref[2];
            w0 += w;
            w1 += w * w;
            double wx = w * sx, wy = w * sy, wz = w * sz;
            ax += wx;
            ay += wy;
            az += wz;
            bx += w * tx;
            by += w * ty;
            bz += w * tz;
            c[0] += wx * tx; c[1] += wx * ty; c[2] += wx * tz;
            c[3] += wy * tx; c[4] += wy * ty; c[5] += wy * tz;
            c[6] += wz * tx; c[7] += wz * ty; c[8] += wz * tz;
        }
        double *row = partial.data() + 17 * piece;
        row[0] = w0; row[1] = w1; row[2] = ax; row[3] = ay; row[4] = az; row[5] = bx; row[6] = by; row[7] = bz;
        for (int k = 0; k < 9; ++k) row[8 + k] = c[k];
    };
    if (pooled) {
        pooled_pieces(pieces, threads, moments);
    } else {
        parallel_pieces(pieces, count < 8192 ? 1 : threads, moments);
    }
    double sums[17] = {0};
    for (int64_t p = 0; p < pieces; ++p)
        for (int k = 0; k < 17; ++k) sums[k] += partial[17 * p + k];
    const double total = sums[0];
    o[0] = total;
    o[1] = sums[1];
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
            o[8 + 3 * a + b] = sums[8 + 3 * a + b] / total - (sums[2 + a] / total) * (sums[5 + b] / total);
    for (int a = 0; a < 3; ++a) {
        o[2 + a] = sums[2 + a] / total + sref[a];
        o[5 + a] = sums[5 + a] / total + tref[a];
    }
}

void pair_moments(CArr2 source, CArr2 rotation, CArr1 translation, CArr2 target, CIdx indices, CArr1 distances,
                  double scale, double shift, Arr1 out, int threads) {
    moments_of_pairs(source.data(), int64_t(source.shape(0)), rotation.data(), translation.data(), target.data(),
                     indices.data(), distances.data(), scale, shift, out.data(), threads, false);
}

void paper_moments(CArr2 source, CArr2 rotation, CArr1 translation, CArr2 target, CIdx indices, CArr1 distances,
                   double scale, Arr1 out, int threads) {
    const int64_t count = int64_t(source.shape(0));
    const double *s = source.data(), *r = rotation.data(), *tr = translation.data(), *tg = target.data();
    const int64_t *ix = indices.data();
    const double *d = distances.data();
    const int64_t pieces = piece_count(count, SUM_PIECE);
    if (count < 8192) threads = 1;
    std::vector<double> partial(8 * pieces, 0.0);
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        double acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) {
            double x, y, z;
            mapped(s, i, r, tr, x, y, z);
            acc[0] += x; acc[1] += y; acc[2] += z;
            int64_t j = ix[i];
            acc[3] += tg[3 * j]; acc[4] += tg[3 * j + 1]; acc[5] += tg[3 * j + 2];
            double w = std::exp(-d[i] * d[i] * scale);
            acc[6] += w;
            acc[7] += w * w;
        }
        for (int k = 0; k < 8; ++k) partial[8 * piece + k] = acc[k];
    });
    double sums[8] = {0};
    for (int64_t p = 0; p < pieces; ++p)
        for (int k = 0; k < 8; ++k) sums[k] += partial[8 * p + k];
    double sb[3], tb[3];
    for (int a = 0; a < 3; ++a) {
        sb[a] = sums[a] / double(count);
        tb[a] = sums[3 + a] / double(count);
    }
    std::vector<double> blocks(9 * pieces, 0.0);
    parallel_pieces(pieces, threads, [&](int64_t piece) {
        double h[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
        int64_t end = std::min(count, (piece + 1) * SUM_PIECE);
        for (int64_t i = piece * SUM_PIECE; i < end; ++i) {
            int64_t partner = ix[i];
            if (partner >= count) continue;
            double w = std::exp(-d[i] * d[i] * scale);
            bool mutual = ix[partner] == i;
            double first = w;
            if (mutual && partner > i) first = std::exp(-d[partner] * d[partner] * scale);
            double x, y, z;
            mapped(s, i, r, tr, x, y, z);
            int64_t k = ix[partner];
            add_outer(h, first, x - sb[0], y - sb[1], z - sb[2], tg[3 * k] - tb[0], tg[3 * k + 1] - tb[1],
                      tg[3 * k + 2] - tb[2]);
            if (!mutual) {
                mapped(s, partner, r, tr, x, y, z);
                int64_t j = ix[i];
                add_outer(h, w, x - sb[0], y - sb[1], z - sb[2], tg[3 * j] - tb[0], tg[3 * j + 1] - tb[1],
                          tg[3 * j + 2] - tb[2]);
            }
        }
        for (int k = 0; k < 9; ++k) blocks[9 * piece + k] = h[k];
    });
    double *o = out.data();
    for (int k = 0; k < 17; ++k) o[k] = 0.0;
    o[0] = sums[6];
    o[1] = sums[7];
    for (int a = 0; a < 3; ++a) {
        o[2 + a] = sb[a];
        o[5 + a] = tb[a];
    }
    for (int64_t p = 0; p < pieces; ++p)
        for (int k = 0; k < 9; ++k) o[8 + k] += blocks[9 * p + k];
}

}  // namespace kernels
