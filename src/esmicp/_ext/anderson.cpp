// Anderson acceleration (anderson.hpp): pose parameters, the least-squares combination.
#include "anderson.hpp"

#include "rotation.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace kernels {
namespace {

// Rotation vector of a rotation (every angle in [0, pi]): the same branches as a closed-form log.
void rotation_log(const double *r, double *v) {
    const double skew[3] = {r[7] - r[5], r[2] - r[6], r[3] - r[1]};
    const double angle = angle_of(r);
    if (angle < 1e-4) {
        const double f = 0.5 * (1.0 + angle * angle / 6.0);
        for (int a = 0; a < 3; ++a) v[a] = f * skew[a];
        return;
    }
    if (angle < 3.141592653589793 - 1e-4) {  // pi - 1e-4
        const double f = 0.5 * angle / std::sin(angle);
        for (int a = 0; a < 3; ++a) v[a] = f * skew[a];
        return;
    }
    // Near a half turn the skew part vanishes: the axis from the symmetric part,
    // (R + R^T) / 2 = cos(angle) I + (1 - cos(angle)) a a^T, at its largest diagonal entry.
    const double cosine = std::cos(angle);
    double outer[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            outer[3 * i + j] = (0.5 * (r[3 * i + j] + r[3 * j + i]) - (i == j ? cosine : 0.0)) / (1.0 - cosine);
    int k = 0;
    for (int j = 1; j < 3; ++j)
        if (outer[4 * j] > outer[4 * k]) k = j;
    const double root = std::sqrt(std::max(outer[4 * k], 1e-300));
    double axis[3] = {outer[k] / root, outer[3 + k] / root, outer[6 + k] / root};
    if (axis[0] * skew[0] + axis[1] * skew[1] + axis[2] * skew[2] < 0.0)
        for (double &value : axis) value = -value;
    const double norm = std::sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
    for (int a = 0; a < 3; ++a) v[a] = angle * axis[a] / norm;
}

// Rotation of a rotation vector: Rodrigues' formula.
void rotation_exp(const double *v, double *r) {
    const double angle = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    const double k[9] = {0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0};
    double a, b;
    if (angle < 1e-4) {
        a = 1.0 - angle * angle / 6.0;
        b = 0.5 - angle * angle / 24.0;
    } else {
        a = std::sin(angle) / angle;
        b = (1.0 - std::cos(angle)) / (angle * angle);
    }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            const double kk = k[3 * i] * k[j] + k[3 * i + 1] * k[3 + j] + k[3 * i + 2] * k[6 + j];
            r[3 * i + j] = (i == j ? 1.0 : 0.0) + a * k[3 * i + j] + b * kk;
        }
}

// (rotation vector, translation / scale) of pose @ inv(reference), both 4x4 row-major.
void pose_parameters(const double *pose, const double *reference, double scale, double *p) {
    double rotation[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            rotation[3 * i + j] = pose[4 * i] * reference[4 * j] + pose[4 * i + 1] * reference[4 * j + 1] +
                                  pose[4 * i + 2] * reference[4 * j + 2];
    rotation_log(rotation, p);
    for (int i = 0; i < 3; ++i)
        p[3 + i] = (pose[4 * i + 3] - (rotation[3 * i] * reference[3] + rotation[3 * i + 1] * reference[7] +
                                       rotation[3 * i + 2] * reference[11])) / scale;
}

// Minimum-norm least-squares solution of A x = b (A: 6 x m, column j at a[6 j], m <= 8), singular
// values below 6 eps times the largest taken as zero (NumPy's lstsq default): one-sided Jacobi SVD.
void least_squares_6(double *a, int m, const double *b, double *x) {
    double v[64] = {0.0};
    for (int j = 0; j < m; ++j) v[9 * j] = 1.0;  // v[8 j + j]
    const double eps = std::numeric_limits<double>::epsilon();
    for (int sweep = 0; sweep < 60; ++sweep) {
        bool rotated = false;
        for (int p = 0; p < m - 1; ++p)
            for (int q = p + 1; q < m; ++q) {
                double alpha = 0.0, beta = 0.0, gamma = 0.0;
                for (int i = 0; i < 6; ++i) {
                    alpha += a[6 * p + i] * a[6 * p + i];
                    beta += a[6 * q + i] * a[6 * q + i];
                    gamma += a[6 * p + i] * a[6 * q + i];
                }
                if (!(std::fabs(gamma) > eps * std::sqrt(alpha * beta))) continue;
                rotated = true;
                const double zeta = (beta - alpha) / (2.0 * gamma);
                const double t = (zeta >= 0.0 ? 1.0 : -1.0) / (std::fabs(zeta) + std::sqrt(1.0 + zeta * zeta));
                const double c = 1.0 / std::sqrt(1.0 + t * t), s = c * t;
                for (int i = 0; i < 6; ++i) {
                    const double ap = a[6 * p + i], aq = a[6 * q + i];
                    a[6 * p + i] = c * ap - s * aq;
                    a[6 * q + i] = s * ap + c * aq;
                }
                for (int i = 0; i < m; ++i) {
                    const double vp = v[8 * p + i], vq = v[8 * q + i];
                    v[8 * p + i] = c * vp - s * vq;
                    v[8 * q + i] = s * vp + c * vq;
                }
            }
        if (!rotated) break;
    }
    double squared[8], largest = 0.0;
    for (int j = 0; j < m; ++j) {
        squared[j] = 0.0;
        for (int i = 0; i < 6; ++i) squared[j] += a[6 * j + i] * a[6 * j + i];
        largest = std::max(largest, squared[j]);
    }
    const double cutoff = 6.0 * eps * std::sqrt(largest);
    for (int i = 0; i < m; ++i) x[i] = 0.0;
    for (int j = 0; j < m; ++j) {
        if (!(std::sqrt(squared[j]) > cutoff)) continue;
        double projection = 0.0;
        for (int i = 0; i < 6; ++i) projection += a[6 * j + i] * b[i];
        for (int i = 0; i < m; ++i) x[i] += v[8 * j + i] * projection / squared[j];
    }
}

}  // namespace

bool anderson_propose(CArr2 current_, CArr2 plain_, Arr1 state_, double scale, int64_t window, Arr1 out_) {
    if (window < 1 || window > 8) throw std::invalid_argument("anderson_propose: window must be in [1, 8]");
    if (int64_t(state_.shape(0)) != anderson_state_size(window) || out_.shape(0) < 18 ||
        current_.shape(0) != 4 || current_.shape(1) != 4 || plain_.shape(0) != 4 || plain_.shape(1) != 4)
        throw std::invalid_argument("anderson_propose: wrong shapes");
    const double *current = current_.data(), *plain = plain_.data();
    double *state = state_.data(), *out = out_.data();
    double *reference = state + 1, *residuals = state + 17, *images = residuals + 6 * (window + 1);
    int64_t stored = int64_t(state[0]);
    if (stored == 0) std::copy(current, current + 16, reference);
    if (stored == window + 1) {  // drop the oldest
        std::copy(residuals + 6, residuals + 6 * (window + 1), residuals);
        std::copy(images + 6, images + 6 * (window + 1), images);
        --stored;
    }
    double *image = images + 6 * stored, *residual = residuals + 6 * stored, before[6];
    pose_parameters(plain, reference, scale, image);
    pose_parameters(current, reference, scale, before);
    for (int i = 0; i < 6; ++i) residual[i] = image[i] - before[i];
    state[0] = double(++stored);
    if (stored < 2) return false;
    bool finite = true;
    for (int64_t i = 0; i < 6 * stored; ++i) finite = finite && std::isfinite(residuals[i]) && std::isfinite(images[i]);
    double proposal[6];
    if (finite) {
        // gamma = lstsq(dF, residuals[-1]); proposal = images[-1] - dG gamma.
        const int m = int(stored - 1);
        double differences[48], gamma[8];
        for (int j = 0; j < m; ++j)
            for (int i = 0; i < 6; ++i) differences[6 * j + i] = residuals[6 * (j + 1) + i] - residuals[6 * j + i];
        least_squares_6(differences, m, residual, gamma);
        for (int i = 0; i < 6; ++i) {
            proposal[i] = image[i];
            for (int j = 0; j < m; ++j) proposal[i] -= (images[6 * (j + 1) + i] - images[6 * j + i]) * gamma[j];
            finite = finite && std::isfinite(proposal[i]);
        }
    }
    if (!finite) {
        state[0] = 0.0;
        return false;
    }
    // The pose [exp(r) | scale u] @ reference, and its motion from current.
    double rotation[9], pose_rotation[9];
    rotation_exp(proposal, rotation);
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j)
            pose_rotation[3 * i + j] = rotation[3 * i] * reference[j] + rotation[3 * i + 1] * reference[4 + j] +
                                       rotation[3 * i + 2] * reference[8 + j];
        out[4 * i + 3] = rotation[3 * i] * reference[3] + rotation[3 * i + 1] * reference[7] +
                         rotation[3 * i + 2] * reference[11] + proposal[3 + i] * scale;
        for (int j = 0; j < 3; ++j) out[4 * i + j] = pose_rotation[3 * i + j];
    }
    out[12] = out[13] = out[14] = 0.0;
    out[15] = 1.0;
    double relative[9], moved[3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            relative[3 * i + j] = out[4 * i] * current[4 * j] + out[4 * i + 1] * current[4 * j + 1] +
                                  out[4 * i + 2] * current[4 * j + 2];
    for (int i = 0; i < 3; ++i)
        moved[i] = out[4 * i + 3] - (relative[3 * i] * current[3] + relative[3 * i + 1] * current[7] +
                                     relative[3 * i + 2] * current[11]);
    out[16] = angle_of(relative);
    out[17] = std::sqrt(moved[0] * moved[0] + moved[1] * moved[1] + moved[2] * moved[2]);
    return true;
}

}  // namespace kernels
