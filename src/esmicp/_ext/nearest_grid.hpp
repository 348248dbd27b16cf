// The global search's nearest-target lookup grid.
#pragma once

#include "arrays.hpp"

#include <cmath>
#include <cstdint>

namespace kernels {

// The global search's nearest-target lookup table (esmicp.core.nearest_grid.NearestGrid).
struct Grid {
    const double *target;   // (M, 3)
    const int64_t *lookup;  // cell (C order) -> target index
    double low[3], cell;
    int64_t shape[3];
};

// The cell (C order) of (x, y, z), clipped to the grid.
inline int64_t grid_cell(const Grid &g, double x, double y, double z) {
    const double p[3] = {x, y, z};
    int64_t ijk[3];
    for (int a = 0; a < 3; ++a) {
        double f = std::floor((p[a] - g.low[a]) / g.cell);
        // NaN and out-of-range values go to the border cells, as numpy.clip does after the cast.
        int64_t v = f >= double(g.shape[a] - 1) ? g.shape[a] - 1 : (f > 0.0 ? int64_t(f) : 0);
        ijk[a] = v;
    }
    return (ijk[0] * g.shape[1] + ijk[1]) * g.shape[2] + ijk[2];
}

// The global search's lookup grid (esmicp.core.nearest_grid.NearestGrid): each cell's nearest
// occupied cell (Euclidean, in cells) by the separable feature transform of Maurer, Qi and
// Raghavan (2003), computed as scipy.ndimage.distance_transform_edt(return_indices=True) does:
// lines along axis 0, then 1, then 2; on each line the sites kept by the same integer-exact tests
// and a tie going to the earlier site, so that every cell gets the occupied cell SciPy's gives.
// Then each cell's target point: the last target point (in input order) of that occupied cell.
// Fills out_lookup (prod(shape),) with each cell's target index (see above); cells are C-ordered
// over `shape`, a target point's cell is as in grid_cell.
void nearest_grid(CArr2 target, CArr1 low, double cell, CIdx shape_, Idx out_lookup);

}  // namespace kernels
