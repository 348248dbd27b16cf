// The global search's lookup grid (nearest_grid.hpp): a separable feature transform.
#include "nearest_grid.hpp"

#include "pool.hpp"

#include <algorithm>
#include <cstring>
#include <stdexcept>
#include <vector>

namespace kernels {
namespace {

// One line of the feature transform along axis d. `feature` holds each cell's nearest occupied
// cell so far, 3 coordinates per cell (the first -1: none yet); the line starts at cell `base`
// with step `stride`, `length` cells; `fixed` holds its coordinates on the other axes. SciPy's
// tests, in doubles on small integers, are exact: integer arithmetic takes the same branches.
struct LineScratch {
    std::vector<int64_t> along, off, sites;  // a site's coordinate on axis d, squared distance off the line
    std::vector<int32_t> coordinates;         // a site's 3 coordinates
};

void voronoi_line(int32_t *feature, int64_t base, int64_t stride, int64_t length, int d, const int64_t *fixed,
                  LineScratch &work) {
    int64_t found = 0;
    for (int64_t i = 0; i < length; ++i) {
        const int32_t *f = feature + 3 * (base + i * stride);
        if (f[0] < 0) continue;
        int64_t off = 0;
        for (int a = 0; a < 3; ++a) {
            if (a == d) continue;
            const int64_t gap = int64_t(f[a]) - fixed[a];
            off += gap * gap;
        }
        std::memcpy(work.coordinates.data() + 3 * found, f, 3 * sizeof(int32_t));
        work.along[size_t(found)] = f[d];
        work.off[size_t(found)] = off;
        ++found;
    }
    if (found == 0) return;
    // The lower envelope of the sites' parabolas (SciPy's first loop).
    int64_t *sites = work.sites.data();
    const int64_t *along = work.along.data(), *off = work.off.data();
    int64_t last = -1;
    for (int64_t s = 0; s < found; ++s) {
        while (last >= 1) {
            const int64_t one = sites[last], two = sites[last - 1];
            const int64_t a = along[one] - along[two], b = along[s] - along[one], c = a + b;
            if (c * off[one] - b * off[two] - a * off[s] - a * b * c <= 0) break;
            --last;
        }
        sites[++last] = s;
    }
    // Each cell's nearest site along the envelope, a tie to the earlier one (its second loop).
    int64_t l = 0;
    for (int64_t i = 0; i < length; ++i) {
        int64_t gap = along[sites[l]] - i, nearest = gap * gap + off[sites[l]];
        while (l < last) {
            gap = along[sites[l + 1]] - i;
            const int64_t next = gap * gap + off[sites[l + 1]];
            if (nearest <= next) break;
            nearest = next;
            ++l;
        }
        std::memcpy(feature + 3 * (base + i * stride), work.coordinates.data() + 3 * sites[l], 3 * sizeof(int32_t));
    }
}

}  // namespace

void nearest_grid(CArr2 target, CArr1 low, double cell, CIdx shape_, Idx out_lookup) {
    const int64_t shape[3] = {shape_.data()[0], shape_.data()[1], shape_.data()[2]};
    const int64_t size = shape[0] * shape[1] * shape[2], count = int64_t(target.shape(0));
    if (int64_t(out_lookup.shape(0)) != size || size <= 0 || count == 0 || target.shape(1) != 3)
        throw std::invalid_argument("nearest_grid: target (M, 3) with M >= 1, out_lookup (prod(shape),)");
    if (size > (int64_t(1) << 31) - 1) throw std::invalid_argument("nearest_grid: more than 2^31 - 1 cells");
    // The envelope test's products reach 4 L^3 on an axis of L cells: within int64 up to 10^6.
    if (std::max({shape[0], shape[1], shape[2]}) > 1000000)
        throw std::invalid_argument("nearest_grid: more than 10^6 cells along an axis");
    Grid grid{target.data(), nullptr, {low.data()[0], low.data()[1], low.data()[2]}, cell,
              {shape[0], shape[1], shape[2]}};
    std::vector<int64_t> representative(size_t(size), -1);
    for (int64_t i = 0; i < count; ++i) {
        const double *p = target.data() + 3 * i;
        representative[size_t(grid_cell(grid, p[0], p[1], p[2]))] = i;
    }
    std::vector<int32_t> feature(size_t(3 * size), -1);
    for (int64_t c = 0; c < size; ++c) {
        if (representative[size_t(c)] < 0) continue;
        feature[size_t(3 * c)] = int32_t(c / (shape[1] * shape[2]));
        feature[size_t(3 * c + 1)] = int32_t((c / shape[2]) % shape[1]);
        feature[size_t(3 * c + 2)] = int32_t(c % shape[2]);
    }
    const int64_t strides[3] = {shape[1] * shape[2], shape[2], 1};
    const size_t longest = size_t(std::max({shape[0], shape[1], shape[2]}));
    LineScratch work{std::vector<int64_t>(longest), std::vector<int64_t>(longest), std::vector<int64_t>(longest),
                     std::vector<int32_t>(3 * longest)};
    for (int d = 0; d < 3; ++d) {
        const int u = d == 0 ? 1 : 0, v = d == 2 ? 1 : 2;  // the other two axes
        int64_t fixed[3] = {0, 0, 0};
        for (int64_t i = 0; i < shape[u]; ++i) {
            if (signal_raised()) throw PythonError();
            for (int64_t j = 0; j < shape[v]; ++j) {
                fixed[u] = i;
                fixed[v] = j;
                voronoi_line(feature.data(), i * strides[u] + j * strides[v], strides[d], shape[d], d, fixed, work);
            }
        }
    }
    int64_t *lookup = out_lookup.data();
    for (int64_t c = 0; c < size; ++c) {
        const int32_t *f = feature.data() + 3 * c;
        lookup[c] = representative[size_t((int64_t(f[0]) * shape[1] + f[1]) * shape[2] + f[2])];
    }
}

}  // namespace kernels
