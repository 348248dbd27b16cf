// Rotations from 3x3 matrices (rotation.hpp).
#include "rotation.hpp"

#include <algorithm>
#include <limits>

namespace kernels {

void best_rotation(const double *h, double *r) {
    double scale = 0.0;
    for (int k = 0; k < 9; ++k) scale = std::max(scale, std::fabs(h[k]));
    if (!(scale > 0.0) || !std::isfinite(scale)) {
        if (std::isfinite(scale)) {  // H = 0: the identity, as the SVD gives
            for (int k = 0; k < 9; ++k) r[k] = (k % 4 == 0) ? 1.0 : 0.0;
        } else {
            for (int k = 0; k < 9; ++k) r[k] = std::numeric_limits<double>::quiet_NaN();
        }
        return;
    }
    const double xx = h[0] / scale, xy = h[1] / scale, xz = h[2] / scale, yx = h[3] / scale, yy = h[4] / scale,
                 yz = h[5] / scale, zx = h[6] / scale, zy = h[7] / scale, zz = h[8] / scale;
    double a[4][4] = {{xx + yy + zz, yz - zy, zx - xz, xy - yx},
                      {yz - zy, xx - yy - zz, xy + yx, zx + xz},
                      {zx - xz, xy + yx, -xx + yy - zz, yz + zy},
                      {xy - yx, zx + xz, yz + zy, -xx - yy + zz}};
    double v[4][4];
    jacobi_eigen<4>(a, v);
    int top = 0;
    for (int i = 1; i < 4; ++i)
        if (a[i][i] > a[top][top]) top = i;
    double w = v[0][top], x = v[1][top], y = v[2][top], z = v[3][top];
    const double norm = std::sqrt(w * w + x * x + y * y + z * z);
    w /= norm; x /= norm; y /= norm; z /= norm;
    r[0] = w * w + x * x - y * y - z * z; r[1] = 2 * (x * y - w * z);         r[2] = 2 * (x * z + w * y);
    r[3] = 2 * (x * y + w * z);         r[4] = w * w - x * x + y * y - z * z; r[5] = 2 * (y * z - w * x);
    r[6] = 2 * (x * z - w * y);         r[7] = 2 * (y * z + w * x);         r[8] = w * w - x * x - y * y + z * z;
}

void kabsch(CArr2 cross_covariance, Arr2 out) { best_rotation(cross_covariance.data(), out.data()); }

void closest_rotation(CArr2 matrix, Arr2 out) { nearest_rotation(matrix.data(), out.data()); }

}  // namespace kernels
