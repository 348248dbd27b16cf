// The nearest occupied cell of every cell of a 3-D grid: an exact Euclidean feature transform.
//
// What `scipy.ndimage.distance_transform_edt(..., return_indices=True)` gives the global search's
// lookup grid (core/nearest_grid.py), without importing SciPy (whose import is most of a first
// `esmicp demo`). Separable, one axis at a time (Felzenszwalb and Huttenlocher, "Distance
// Transforms of Sampled Functions", 2012): along each line of an axis, the lower envelope of the
// parabolas (x - q)^2 + f(q) gives every cell its nearest site, f being the squared distance found
// by the passes over the earlier axes. The squared distances are integers below 2^53, exact in a
// double; where two occupied cells are equally near, which one is returned may differ from SciPy.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <algorithm>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <vector>

namespace nb = nanobind;

namespace {

constexpr double NONE = std::numeric_limits<double>::infinity();

// One line of `count` cells `stride` apart: squared distances `f` and sites `site` in place
// (NONE / -1 where no site is known). `v`, `z`, `line_f`, `line_site` are scratch of count (+1).
void envelope(double *f, int64_t *site, int64_t count, int64_t stride, std::vector<int64_t> &v,
              std::vector<double> &z, std::vector<double> &line_f, std::vector<int64_t> &line_site) {
    for (int64_t q = 0; q < count; ++q) {
        line_f[q] = f[q * stride];
        line_site[q] = site[q * stride];
    }
    int64_t k = -1;  // the envelope's last parabola
    for (int64_t q = 0; q < count; ++q) {
        if (line_f[q] == NONE) continue;
        const double fq = line_f[q] + double(q) * double(q);
        double s = -NONE;
        while (k >= 0) {
            const int64_t p = v[k];
            s = (fq - (line_f[p] + double(p) * double(p))) / (2.0 * double(q - p));
            if (s > z[k]) break;
            --k;
        }
        if (k < 0) s = -NONE;
        ++k;
        v[k] = q;
        z[k] = s;
    }
    if (k < 0) return;  // no site on this line: it stays as it was (all NONE)
    int64_t j = 0;
    for (int64_t q = 0; q < count; ++q) {
        while (j < k && z[j + 1] < double(q)) ++j;
        const int64_t p = v[j];
        const double offset = double(q - p);
        f[q * stride] = offset * offset + line_f[p];
        site[q * stride] = line_site[p];
    }
}

// occupied: (nx, ny, nz) uint8, C order; out: (nx * ny * nz,) int64, the flat C-order index of the
// nearest occupied cell of each cell (-1 everywhere when no cell is occupied).
void nearest_occupied(nb::ndarray<const uint8_t, nb::ndim<3>, nb::c_contig, nb::device::cpu> occupied,
                      nb::ndarray<int64_t, nb::ndim<1>, nb::c_contig, nb::device::cpu> out) {
    const int64_t nx = int64_t(occupied.shape(0)), ny = int64_t(occupied.shape(1)), nz = int64_t(occupied.shape(2));
    const int64_t cells = nx * ny * nz;
    if (int64_t(out.shape(0)) != cells) throw std::invalid_argument("nearest_occupied: out must hold one entry per cell");
    const uint8_t *full = occupied.data();
    int64_t *site = out.data();
    std::vector<double> f(size_t(cells), NONE);
    for (int64_t c = 0; c < cells; ++c) {
        site[c] = full[c] ? c : -1;
        if (full[c]) f[c] = 0.0;
    }
    const int64_t longest = std::max(nx, std::max(ny, nz));
    const size_t length = static_cast<size_t>(longest);
    std::vector<int64_t> v(length), line_site(length);
    std::vector<double> z(length + 1), line_f(length);
    nb::gil_scoped_release release;
    // Axis 0 first, then 1, then 2: where two occupied cells are equally near, the one found
    // first along the earlier axes wins (the order SciPy's transform also resolves ties in, as far
    // as tests/test_search_parts.py measures).
    for (int64_t y = 0; y < ny; ++y)  // along x
        for (int64_t zz = 0; zz < nz; ++zz) {
            const int64_t start = y * nz + zz;
            envelope(f.data() + start, site + start, nx, ny * nz, v, z, line_f, line_site);
        }
    for (int64_t x = 0; x < nx; ++x)  // along y
        for (int64_t zz = 0; zz < nz; ++zz) {
            const int64_t start = x * ny * nz + zz;
            envelope(f.data() + start, site + start, ny, nz, v, z, line_f, line_site);
        }
    for (int64_t x = 0; x < nx; ++x)  // along z (contiguous)
        for (int64_t y = 0; y < ny; ++y) {
            const int64_t start = (x * ny + y) * nz;
            envelope(f.data() + start, site + start, nz, 1, v, z, line_f, line_site);
        }
}

}  // namespace

void add_distance_transform(nb::module_ &m) { m.def("nearest_occupied", &nearest_occupied); }
