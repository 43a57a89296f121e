// Pieces shared by the float32 (deform.cpp) and bf16/AMX (deform_amx.cpp)
// deformation kernels.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "fastmath.h"

namespace stgs {

constexpr int kFeat = 16;        // channels of one temporal feature
constexpr int kHidden = 64;      // width of every hidden layer
constexpr int kMaxWindow = 8;    // largest sliding window the kernels accept
constexpr int kOut = 16;         // padded width of the packed second layers
constexpr double kNearZ = 0.01;  // the splatter's near plane (DESIGN.md)

// Conservative visibility from the camera's frustum: false only when the
// Gaussian cannot put alpha >= 1/255 on any pixel whatever its opacity, or,
// with a guard band (near, x limit, y limit: stgs.model.view), when its mean
// lies outside it (z <= near, |x| > x limit * z or |y| > y limit * z).
inline bool maybe_visible(const float* mean, const float* scale, const double* viewmat,
                          const double* K, int width, int height, const double* guard) {
  const double x = viewmat[0] * mean[0] + viewmat[1] * mean[1] + viewmat[2] * mean[2] + viewmat[3];
  const double y = viewmat[4] * mean[0] + viewmat[5] * mean[1] + viewmat[6] * mean[2] + viewmat[7];
  const double z = viewmat[8] * mean[0] + viewmat[9] * mean[1] + viewmat[10] * mean[2] + viewmat[11];
  if (!(z >= kNearZ)) return false;
  if (guard != nullptr && !(z > guard[0] && std::fabs(x) <= guard[1] * z && std::fabs(y) <= guard[2] * z))
    return false;
  const double s = std::max(scale[0], std::max(scale[1], scale[2]));
  const double xn = x / z, yn = y / z;
  // The Frobenius norm of the projection Jacobian bounds its spectral norm.
  const double j00 = K[0] / z, j01 = K[1] / z, j02 = -(K[0] * xn + K[1] * yn) / z;
  const double j11 = K[4] / z, j12 = -K[4] * yn / z;
  const double jf2 = j00 * j00 + j01 * j01 + j02 * j02 + j11 * j11 + j12 * j12;
  const double radius = std::sqrt(2.0 * std::log(255.0) * (jf2 * s * s + 0.3)) * 1.01 + 1.0;
  const double u = K[0] * xn + K[1] * yn + K[2], v = K[4] * yn + K[5];
  return u + radius >= 0.0 && u - radius <= width && v + radius >= 0.0 && v - radius <= height;
}

// The canonical Gaussians, the camera and the output arrays of one deformation call.
struct DeformIO {
  const float *xyz, *log_scale, *rotation, *opacity_logit, *color, *camera_center;
  const double *viewmat, *K;  // viewmat null: no culling
  int width, height;
  float *means, *quats, *scales, *opacities, *colors;
  const double* guard;  // guard band (see maybe_visible); null: none
};

// Scales exp(log_scale + ds) of the Gaussians first .. first + rows - 1 from the geometry
// decoders' outputs (row b at d + b * stride: [dx(3) ds(3) dq(4)]), vectorised.
inline void deformed_scales(const DeformIO& io, int64_t first, int rows, const float* d, int stride) {
  const float* ls = io.log_scale + 3 * first;
  float* out = io.scales + 3 * first;
#pragma omp simd
  for (int i = 0; i < 3 * rows; ++i) out[i] = exp_or_inf(ls[i] + d[(i / 3) * stride + 3 + i % 3]);
}

// Deformed geometry of Gaussian g from the geometry decoders' outputs d = [dx(3) ds(3) dq(4)]
// (its scales come from deformed_scales, called first).
// Returns whether it can reach the image (always, without viewmat); if not, its opacity and
// colour are zeroed, else dir receives the unit direction from the camera centre.
inline bool deformed_geometry(const DeformIO& io, int64_t g, const float* d, float* dir) {
  float* mean = &io.means[3 * g];
  for (int c = 0; c < 3; ++c) mean[c] = io.xyz[3 * g + c] + d[c];
  for (int c = 0; c < 4; ++c) io.quats[4 * g + c] = io.rotation[4 * g + c] + d[6 + c];
  if (io.viewmat != nullptr &&
      !maybe_visible(mean, &io.scales[3 * g], io.viewmat, io.K, io.width, io.height, io.guard)) {
    io.opacities[g] = 0.0f;
    for (int c = 0; c < 3; ++c) io.colors[3 * g + c] = 0.0f;
    return false;
  }
  double norm2 = 0.0;
  for (int c = 0; c < 3; ++c) {
    dir[c] = mean[c] - io.camera_center[c];
    norm2 += double(dir[c]) * dir[c];
  }
  const float inv = float(1.0 / std::max(std::sqrt(norm2), 1e-12));
  for (int c = 0; c < 3; ++c) dir[c] *= inv;
  return true;
}

// Opacity and colour of Gaussian g from the appearance decoders' outputs d = [do(1) dc(3)].
inline void deformed_appearance(const DeformIO& io, int64_t g, const float* d) {
  const float base = 1.0f / (1.0f + fast_exp(-io.opacity_logit[g]));
  io.opacities[g] = std::min(1.0f, std::max(0.0f, base + fast_tanh(d[0])));
  for (int c = 0; c < 3; ++c) {
    const float base_color = io.color[3 * g + c];
    io.colors[3 * g + c] = (base_color > 0.0f ? base_color : 0.0f) + d[1 + c];
  }
}

}  // namespace stgs
