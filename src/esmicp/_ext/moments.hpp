// Pair moments: the weighted sums of the local loop's pairs, in pieces summed in piece order.
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

inline constexpr int64_t SUM_PIECE = 4096;

// The 17 moments of the pairs (R x_i + t, target[indices[i]]) with weights
// exp(-(d_i^2 - shift) * scale) (1 where scale is 0): sum w, sum w^2, the weighted centroids and
// the weighted cross-covariance (see esmicp.core.moments.pair_moments). `pooled`: on the
// persistent helper threads (Index::step below POOLED_STEP_MAX points), else threads per call.
void moments_of_pairs(const double *s, int64_t count, const double *r, const double *tr, const double *tg,
                      const int64_t *ix, const double *d, double scale, double shift, double *o, int threads,
                      bool pooled);

void pair_moments(CArr2 source, CArr2 rotation, CArr1 translation, CArr2 target, CIdx indices, CArr1 distances,
                  double scale, double shift, Arr1 out, int threads);

// h += w a b^T (3 x 3, row-major).
inline void add_outer(double *h, double w, double ax, double ay, double az, double bx, double by, double bz) {
    h[0] += w * ax * bx; h[1] += w * ax * by; h[2] += w * ax * bz;
    h[3] += w * ay * bx; h[4] += w * ay * by; h[5] += w * ay * bz;
    h[6] += w * az * bx; h[7] += w * az * by; h[8] += w * az * bz;
}

// The paper's moments (esmicp.core.moments.paper_moments), in two passes: sum w, sum w^2, the
// unweighted centroids of the placed source and of the matched target points, and the
// cross-covariance of esmicp.methods.esm_paper.paper_cross_covariance.
void paper_moments(CArr2 source, CArr2 rotation, CArr1 translation, CArr2 target, CIdx indices, CArr1 distances,
                   double scale, Arr1 out, int threads);

}  // namespace kernels
