// Anderson acceleration of the local loop.
#pragma once

#include "arrays.hpp"

#include <cstdint>

namespace kernels {

// Anderson acceleration of the local loop (esmicp.methods.acceleration): the whole proposal in
// one call. Poses are parametrised relative to a reference pose as (rotation vector, radians;
// translation / scale). The state (Python-owned, ANDERSON_STATE(window) numbers): the number of
// stored steps (0: no reference yet), the reference pose (16), then window + 1 rows of 6 for
// the residuals G(x) - x and as many for the images G(x), oldest first.
inline int64_t anderson_state_size(int64_t window) { return 17 + 12 * (window + 1); }

// One Anderson step: stores the residual and image of plain = G(current) (4x4 row-major each),
// and, from two stored steps on, writes the combination of the last `window` into `out` (the
// pose, 16, then its motion from `current`: angle in radians, translation norm) and returns
// true. Returns false when `plain` itself is the next pose (fewer than two steps stored, or a
// non-finite combination, which also clears the state).
bool anderson_propose(CArr2 current_, CArr2 plain_, Arr1 state_, double scale, int64_t window, Arr1 out_);

}  // namespace kernels
