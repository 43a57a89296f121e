// Stage 1, projection: EWA projection of 3D Gaussians to screen space in double
// precision, float32 out. Mirrors stgs.render.project.project (its torch twin). The
// AVX-512 version (8 Gaussians per call) gives the same bits as the portable one.

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "project.h"
#include "project_avx512.h"
#include "splat.h"
#include "stgs_abi.h"

namespace stgs::splat {
namespace {

// The overflow-safe unit quaternion of quat (wxyz; zero -> identity) and its rotation matrix R
// (row-major); returns |quat| (0 for the zero quaternion).
inline double unit_rotation(const float* quat, double q[4], double R[9]) {
  for (int c = 0; c < 4; ++c) q[c] = quat[c];
  const double peak = std::max(std::max(std::fabs(q[0]), std::fabs(q[1])),
                               std::max(std::fabs(q[2]), std::fabs(q[3])));
  double norm = 0.0;
  if (peak > 0) {
    for (int c = 0; c < 4; ++c) q[c] /= peak;
    const double nrm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (int c = 0; c < 4; ++c) q[c] /= nrm;
    norm = nrm * peak;
  } else {
    q[0] = 1, q[1] = q[2] = q[3] = 0;
  }
  const double w = q[0], qx = q[1], qy = q[2], qz = q[3];
  const double rot[9] = {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
                         2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
                         2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)};
  for (int k = 0; k < 9; ++k) R[k] = rot[k];
  return norm;
}

// The EWA projection's factors for one Gaussian at camera-space depth z and normalised position (xn, yn):
// jac = K[:2,:2] @ d(xn,yn)/d(p_cam), jw = jac @ Rcw, P = jw @ R, M = P @ diag(s) (2x3 each, row-major), the
// unblurred 2D covariance M Mᵀ = [[a0, b0], [b0, c0]] and det(M Mᵀ + kBlur I) from M's squared 2x2 minors
// (Cauchy-Binet: positive and accurate for needles).
struct Ewa {
  double jac[6], jw[6], P[6], M[6];
  double a0, b0, c0, det;
};

inline void ewa(const double* K, const double* viewmat, double z, double xn, double yn, const double R[9],
                const float* scales, Ewa& e) {
  const double dn[6] = {1 / z, 0, -xn / z, 0, 1 / z, -yn / z};
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c) e.jac[3 * r + c] = K[3 * r] * dn[c] + K[3 * r + 1] * dn[3 + c];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      e.jw[3 * r + c] = e.jac[3 * r] * viewmat[c] + e.jac[3 * r + 1] * viewmat[4 + c] +
                        e.jac[3 * r + 2] * viewmat[8 + c];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c) {
      e.P[3 * r + c] = e.jw[3 * r] * R[c] + e.jw[3 * r + 1] * R[3 + c] + e.jw[3 * r + 2] * R[6 + c];
      e.M[3 * r + c] = e.P[3 * r + c] * double(scales[c]);
    }
  const double* M = e.M;
  e.a0 = M[0] * M[0] + M[1] * M[1] + M[2] * M[2];
  e.b0 = M[0] * M[3] + M[1] * M[4] + M[2] * M[5];
  e.c0 = M[3] * M[3] + M[4] * M[4] + M[5] * M[5];
  const double m01 = M[0] * M[4] - M[1] * M[3], m02 = M[0] * M[5] - M[2] * M[3], m12 = M[1] * M[5] - M[2] * M[4];
  e.det = m01 * m01 + m02 * m02 + m12 * m12 + kBlur * (e.a0 + e.c0) + kBlur * kBlur;
}

// Projection of Gaussian i (stgs_project's outputs for one Gaussian).
inline void project_one(int64_t i, const ProjectIO& io) {
  const float *means = io.means, *quats = io.quats, *scales = io.scales, *opac = io.opac;
  const double *viewmat = io.viewmat, *K = io.K;
  float *means2d = io.means2d, *conics = io.conics, *depths = io.depths, *extents = io.extents;
  const double px = means[3 * i], py = means[3 * i + 1], pz = means[3 * i + 2];
  const double x = viewmat[0] * px + viewmat[1] * py + viewmat[2] * pz + viewmat[3];
  const double y = viewmat[4] * px + viewmat[5] * py + viewmat[6] * pz + viewmat[7];
  const double z = viewmat[8] * px + viewmat[9] * py + viewmat[10] * pz + viewmat[11];
  const bool valid = z >= kNearZ;
  const double zs = valid ? z : 1.0;
  const double xn = x / zs, yn = y / zs;
  means2d[2 * i] = float(K[0] * xn + K[1] * yn + K[2]);
  means2d[2 * i + 1] = float(K[4] * yn + K[5]);
  depths[i] = valid ? float(z) : -1.0f;
  double q[4], R[9];
  unit_rotation(quats + 4 * i, q, R);
  Ewa e;
  ewa(K, viewmat, zs, xn, yn, R, scales + 3 * i, e);
  const double a0 = e.a0, b0 = e.b0, c0 = e.c0, det = e.det;
  conics[3 * i] = float((c0 + kBlur) / det);
  conics[3 * i + 1] = float(-b0 / det);
  conics[3 * i + 2] = float((a0 + kBlur) / det);
  const double level = 255.0 * double(opac[i]);
  if (valid && level >= 1.0) {
    const double quad = 2.0 * std::log(level);
    extents[2 * i] = float(std::sqrt(quad * (a0 + kBlur)) * kExtentMargin + 1e-3);
    extents[2 * i + 1] = float(std::sqrt(quad * (c0 + kBlur)) * kExtentMargin + 1e-3);
  } else {
    extents[2 * i] = extents[2 * i + 1] = -1.0f;
  }
}


// Gradient of project_one's means2d and conics in Gaussian i's mean, quaternion and scales: the forward
// recomputed in double, then the chain rule back through the conic, M = J W R(q) diag(s), the
// projective Jacobian J and the pixel position. A culled Gaussian (z < kNearZ) has no gradient.
inline void project_backward_one(int64_t i, const ProjectIO& io, const float* grad_means2d,
                                 const float* grad_conics, float* grad_means, float* grad_quats,
                                 float* grad_scales) {
  const float *means = io.means, *quats = io.quats, *scales = io.scales;
  const double *vm = io.viewmat, *K = io.K;
  for (int c = 0; c < 3; ++c) grad_means[3 * i + c] = grad_scales[3 * i + c] = 0.0f;
  for (int c = 0; c < 4; ++c) grad_quats[4 * i + c] = 0.0f;
  const double px = means[3 * i], py = means[3 * i + 1], pz = means[3 * i + 2];
  const double x = vm[0] * px + vm[1] * py + vm[2] * pz + vm[3];
  const double y = vm[4] * px + vm[5] * py + vm[6] * pz + vm[7];
  const double z = vm[8] * px + vm[9] * py + vm[10] * pz + vm[11];
  if (!(z >= kNearZ)) return;
  double q[4], R[9];
  const double qnorm = unit_rotation(quats + 4 * i, q, R);  // 0: the zero quaternion (identity, no gradient)
  const double w = q[0], qx = q[1], qy = q[2], qz = q[3];
  Ewa e;
  ewa(K, vm, z, x / z, y / z, R, scales + 3 * i, e);
  const double *M = e.M, *P = e.P, *jw = e.jw;
  const double a0 = e.a0, b0 = e.b0, c0 = e.c0, det = e.det;
  const double A = a0 + kBlur, C = c0 + kBlur;  // det = A C - b0² (Lagrange's identity)
  // The conic (C, -b0, A) / det.
  const double ga = grad_conics[3 * i], gb = grad_conics[3 * i + 1], gc = grad_conics[3 * i + 2];
  const double g_det = -(ga * C - gb * b0 + gc * A) / (det * det);
  const double g_a0 = gc / det + g_det * C, g_c0 = ga / det + g_det * A, g_b0 = -gb / det - 2.0 * g_det * b0;
  double gM[6];
  for (int c = 0; c < 3; ++c) {
    gM[c] = 2.0 * g_a0 * M[c] + g_b0 * M[3 + c];
    gM[3 + c] = 2.0 * g_c0 * M[3 + c] + g_b0 * M[c];
  }
  // M = P diag(s), P = jw R, jw = jac W.
  double gP[6];
  for (int c = 0; c < 3; ++c) {
    grad_scales[3 * i + c] = float(gM[c] * P[c] + gM[3 + c] * P[3 + c]);
    gP[c] = gM[c] * scales[3 * i + c];
    gP[3 + c] = gM[3 + c] * scales[3 * i + c];
  }
  double gR[9], gjw[6], gjac[6];
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) gR[3 * a + b] = jw[a] * gP[b] + jw[3 + a] * gP[3 + b];
  for (int r = 0; r < 2; ++r)
    for (int a = 0; a < 3; ++a)
      gjw[3 * r + a] = gP[3 * r] * R[3 * a] + gP[3 * r + 1] * R[3 * a + 1] + gP[3 * r + 2] * R[3 * a + 2];
  for (int r = 0; r < 2; ++r)
    for (int a = 0; a < 3; ++a)
      gjac[3 * r + a] = gjw[3 * r] * vm[4 * a] + gjw[3 * r + 1] * vm[4 * a + 1] + gjw[3 * r + 2] * vm[4 * a + 2];
  // jac = K2 dn with K2 = [[K00, K01], [0, K11]] (K[3] = 0).
  double gdn[6];
  for (int c = 0; c < 3; ++c) {
    gdn[c] = K[0] * gjac[c] + K[3] * gjac[3 + c];
    gdn[3 + c] = K[1] * gjac[c] + K[4] * gjac[3 + c];
  }
  const double iz2 = 1.0 / (z * z), iz3 = iz2 / z;
  double gx = -gdn[2] * iz2, gy = -gdn[5] * iz2;
  double gz = -(gdn[0] + gdn[4]) * iz2 + 2.0 * x * iz3 * gdn[2] + 2.0 * y * iz3 * gdn[5];
  const double gu = grad_means2d[2 * i], gv = grad_means2d[2 * i + 1];
  gx += gu * K[0] / z;
  gy += (gu * K[1] + gv * K[4]) / z;
  gz -= (gu * (K[0] * x + K[1] * y) + gv * K[4] * y) * iz2;
  for (int c = 0; c < 3; ++c) grad_means[3 * i + c] = float(vm[c] * gx + vm[4 + c] * gy + vm[8 + c] * gz);
  if (qnorm == 0.0) return;
  const double gq[4] = {
      2 * (-qz * gR[1] + qy * gR[2] + qz * gR[3] - qx * gR[5] - qy * gR[6] + qx * gR[7]),
      2 * (qy * gR[1] + qz * gR[2] + qy * gR[3] - 2 * qx * gR[4] - w * gR[5] + qz * gR[6] + w * gR[7] - 2 * qx * gR[8]),
      2 * (-2 * qy * gR[0] + qx * gR[1] + w * gR[2] + qx * gR[3] + qz * gR[5] - w * gR[6] + qz * gR[7] - 2 * qy * gR[8]),
      2 * (-2 * qz * gR[0] - w * gR[1] + qx * gR[2] + w * gR[3] - 2 * qz * gR[4] + qy * gR[5] + qx * gR[6] + qy * gR[7])};
  const double along = w * gq[0] + qx * gq[1] + qy * gq[2] + qz * gq[3];  // through q / |q|
  for (int c = 0; c < 4; ++c) grad_quats[4 * i + c] = float((gq[c] - q[c] * along) / qnorm);
}

}  // namespace
}  // namespace stgs::splat

using namespace stgs::splat;

extern "C" {

// Projection in double precision; mirrors stgs.render.project.project.
// viewmat: 4x4 row-major world-to-camera; K: 3x3 row-major.
void stgs_project(int64_t n, const float* means, const float* quats, const float* scales,
                  const float* opac, const double* viewmat, const double* K, float* means2d,
                  float* conics, float* depths, float* extents, int nthreads) {
  const ProjectIO io{means, quats, scales, opac, viewmat, K, means2d, conics, depths, extents};
#if defined(__AVX512F__)
  const int64_t blocks = n / 8;
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t blk = 0; blk < blocks; ++blk) project_x8(8 * blk, io);
  for (int64_t i = 8 * blocks; i < n; ++i) project_one(i, io);
#else
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < n; ++i) project_one(i, io);
#endif
}

void stgs_project_backward(int64_t n, const float* means, const float* quats, const float* scales,
                           const double* viewmat, const double* K, const float* grad_means2d,
                           const float* grad_conics, float* grad_means, float* grad_quats, float* grad_scales,
                           int nthreads) {
  const ProjectIO io{means, quats, scales, nullptr, viewmat, K, nullptr, nullptr, nullptr, nullptr};
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < n; ++i)
    project_backward_one(i, io, grad_means2d, grad_conics, grad_means, grad_quats, grad_scales);
}

}  // extern "C"
