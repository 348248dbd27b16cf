// Rotations from 3x3 matrices (Horn's quaternion method) and the symmetric eigen-decomposition.
#pragma once

#include "arrays.hpp"

#include <cmath>

namespace kernels {

// Eigen-decomposition of a symmetric N x N matrix by cyclic Jacobi sweeps (accurate to rounding, no
// special case for rank-deficient matrices): on return a is diagonal (the eigenvalues) and the
// columns of v are the unit eigenvectors. Used by best_rotation (N = 4) and knn_normals (N = 3).
template <int N>
void jacobi_eigen(double (&a)[N][N], double (&v)[N][N]) {
    for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) v[i][j] = i == j ? 1.0 : 0.0;
    for (int sweep = 0; sweep < 64; ++sweep) {
        double off = 0.0, diagonal = 0.0;
        for (int i = 0; i < N; ++i) {
            diagonal += a[i][i] * a[i][i];
            for (int j = i + 1; j < N; ++j) off += a[i][j] * a[i][j];
        }
        if (off <= 1e-36 * diagonal || off == 0.0) break;
        for (int p = 0; p < N - 1; ++p) {
            for (int q = p + 1; q < N; ++q) {
                if (a[p][q] == 0.0) continue;
                double theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                double t = (theta >= 0 ? 1.0 : -1.0) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
                double c = 1.0 / std::sqrt(t * t + 1.0), sn = t * c;
                for (int k = 0; k < N; ++k) {  // columns p, q of A
                    double akp = a[k][p], akq = a[k][q];
                    a[k][p] = c * akp - sn * akq;
                    a[k][q] = sn * akp + c * akq;
                }
                for (int k = 0; k < N; ++k) {  // rows p, q of A
                    double apk = a[p][k], aqk = a[q][k];
                    a[p][k] = c * apk - sn * aqk;
                    a[q][k] = sn * apk + c * aqk;
                }
                for (int k = 0; k < N; ++k) {
                    double vkp = v[k][p], vkq = v[k][q];
                    v[k][p] = c * vkp - sn * vkq;
                    v[k][q] = sn * vkp + c * vkq;
                }
            }
        }
    }
}

// Rotations from 3x3 matrices: Horn's quaternion method. The rotation R maximising trace(R H)
// (H = sum s t^T: the Kabsch rotation taking s onto t, reflection excluded) is the rotation of the
// eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (jacobi_eigen).
void best_rotation(const double *h, double *r);

// The rotation nearest (Frobenius) to the 3x3 matrix m: the one maximising trace(R^T m).
inline void nearest_rotation(const double *m, double *r) {
    const double transposed[9] = {m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]};
    best_rotation(transposed, r);
}

// The angle of the rotation r (radians, in [0, pi]).
inline double angle_of(const double *r) {
    const double sx = r[7] - r[5], sy = r[2] - r[6], sz = r[3] - r[1];
    return std::atan2(0.5 * std::sqrt(sx * sx + sy * sy + sz * sz), 0.5 * (r[0] + r[4] + r[8] - 1.0));
}

// The Kabsch rotation of a 3x3 cross-covariance (best_rotation) into out.
void kabsch(CArr2 cross_covariance, Arr2 out);

// The rotation nearest to a 3x3 matrix (nearest_rotation) into out.
void closest_rotation(CArr2 matrix, Arr2 out);

}  // namespace kernels
