// Small pieces every kernel shares.
#pragma once

#include <cstdint>
#include <limits>

namespace kernels {

inline constexpr double INF = std::numeric_limits<double>::infinity();
inline constexpr uint64_t HASH_MULTIPLIER = 0x9E3779B97F4A7C15ULL;

// Point i of q ((N, 3), row-major) mapped by the rotation r (3 x 3, row-major) and translation t.
inline void mapped(const double *q, int64_t i, const double *r, const double *t, double &x, double &y, double &z) {
    const double a = q[3 * i], b = q[3 * i + 1], c = q[3 * i + 2];
    x = r[0] * a + r[1] * b + r[2] * c + t[0];
    y = r[3] * a + r[4] * b + r[5] * c + t[1];
    z = r[6] * a + r[7] * b + r[8] * c + t[2];
}

}  // namespace kernels
