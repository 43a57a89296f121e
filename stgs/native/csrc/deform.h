// Pieces shared by the float32 (deform.cpp) and bf16 (deform_bf16.cpp)
// deformation kernels.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "fastmath.h"

#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace stgs {

constexpr int kFeat = 16;        // channels of one temporal feature
constexpr int kHidden = 64;      // width of every hidden layer
constexpr int kMaxWindow = 16;   // largest sliding window the fp32 kernel accepts (stgs.limits.MAX_WINDOW)
constexpr int kOut = 16;         // padded width of the packed second layers
constexpr double kNearZ = 0.01;  // the splatter's near plane (docs/ARCHITECTURE.md)

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

#if defined(__AVX512F__)
// maybe_visible for 8 Gaussians (one double lane each; mean and largest scale as float
// arrays): the same operations in the same order, so the same decisions bit for bit.
inline __mmask8 maybe_visible_x8(const float* mx, const float* my, const float* mz, const float* smax,
                                 const double* viewmat, const double* K, int width, int height,
                                 const double* guard) {
  const __m512d m0 = _mm512_cvtps_pd(_mm256_loadu_ps(mx)), m1 = _mm512_cvtps_pd(_mm256_loadu_ps(my));
  const __m512d m2 = _mm512_cvtps_pd(_mm256_loadu_ps(mz));
  const auto row = [&](const double* v) {
    const __m512d a = _mm512_add_pd(_mm512_mul_pd(_mm512_set1_pd(v[0]), m0), _mm512_mul_pd(_mm512_set1_pd(v[1]), m1));
    return _mm512_add_pd(_mm512_add_pd(a, _mm512_mul_pd(_mm512_set1_pd(v[2]), m2)), _mm512_set1_pd(v[3]));
  };
  const __m512d x = row(viewmat), y = row(viewmat + 4), z = row(viewmat + 8);
  __mmask8 ok = _mm512_cmp_pd_mask(z, _mm512_set1_pd(kNearZ), _CMP_GE_OQ);
  if (guard != nullptr) {
    ok &= _mm512_cmp_pd_mask(z, _mm512_set1_pd(guard[0]), _CMP_GT_OQ);
    ok &= _mm512_cmp_pd_mask(_mm512_abs_pd(x), _mm512_mul_pd(_mm512_set1_pd(guard[1]), z), _CMP_LE_OQ);
    ok &= _mm512_cmp_pd_mask(_mm512_abs_pd(y), _mm512_mul_pd(_mm512_set1_pd(guard[2]), z), _CMP_LE_OQ);
  }
  const __m512d s = _mm512_cvtps_pd(_mm256_loadu_ps(smax));
  const __m512d xn = _mm512_div_pd(x, z), yn = _mm512_div_pd(y, z);
  const __m512d k0 = _mm512_set1_pd(K[0]), k1 = _mm512_set1_pd(K[1]), k4 = _mm512_set1_pd(K[4]);
  const __m512d j00 = _mm512_div_pd(k0, z), j01 = _mm512_div_pd(k1, z);
  const __m512d j02 = _mm512_div_pd(
      _mm512_sub_pd(_mm512_setzero_pd(), _mm512_add_pd(_mm512_mul_pd(k0, xn), _mm512_mul_pd(k1, yn))), z);
  const __m512d j11 = _mm512_div_pd(k4, z);
  const __m512d j12 = _mm512_div_pd(_mm512_mul_pd(_mm512_set1_pd(-K[4]), yn), z);
  __m512d jf2 = _mm512_mul_pd(j00, j00);
  jf2 = _mm512_add_pd(jf2, _mm512_mul_pd(j01, j01));
  jf2 = _mm512_add_pd(jf2, _mm512_mul_pd(j02, j02));
  jf2 = _mm512_add_pd(jf2, _mm512_mul_pd(j11, j11));
  jf2 = _mm512_add_pd(jf2, _mm512_mul_pd(j12, j12));
  const __m512d spread = _mm512_add_pd(_mm512_mul_pd(_mm512_mul_pd(jf2, s), s), _mm512_set1_pd(0.3));
  const __m512d radius = _mm512_add_pd(
      _mm512_mul_pd(_mm512_sqrt_pd(_mm512_mul_pd(_mm512_set1_pd(2.0 * std::log(255.0)), spread)),
                    _mm512_set1_pd(1.01)),
      _mm512_set1_pd(1.0));
  const __m512d u = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(k0, xn), _mm512_mul_pd(k1, yn)), _mm512_set1_pd(K[2]));
  const __m512d v = _mm512_add_pd(_mm512_mul_pd(k4, yn), _mm512_set1_pd(K[5]));
  ok &= _mm512_cmp_pd_mask(_mm512_add_pd(u, radius), _mm512_setzero_pd(), _CMP_GE_OQ);
  ok &= _mm512_cmp_pd_mask(_mm512_sub_pd(u, radius), _mm512_set1_pd(double(width)), _CMP_LE_OQ);
  ok &= _mm512_cmp_pd_mask(_mm512_add_pd(v, radius), _mm512_setzero_pd(), _CMP_GE_OQ);
  ok &= _mm512_cmp_pd_mask(_mm512_sub_pd(v, radius), _mm512_set1_pd(double(height)), _CMP_LE_OQ);
  return ok;
}

// deformed_geometry of Gaussians first .. first + count - 1 (count <= 8; d: their decoder
// rows, stride apart), vectorised; bit k of the result says whether first + k is kept, and
// dirs[3 k .. 3 k + 2] then holds its view direction.
inline __mmask8 deformed_geometry_x8(const DeformIO& io, int64_t first, int count, const float* d, int stride,
                                     float* dirs) {
  alignas(32) float mx[8] = {}, my[8] = {}, mz[8] = {}, smax[8] = {};
  for (int b = 0; b < count; ++b) {
    const int64_t g = first + b;
    const float* db = d + b * stride;
    float* mean = &io.means[3 * g];
    for (int c = 0; c < 3; ++c) mean[c] = io.xyz[3 * g + c] + db[c];
    for (int c = 0; c < 4; ++c) io.quats[4 * g + c] = io.rotation[4 * g + c] + db[6 + c];
    mx[b] = mean[0], my[b] = mean[1], mz[b] = mean[2];
    const float* sc = &io.scales[3 * g];
    smax[b] = std::max(sc[0], std::max(sc[1], sc[2]));
  }
  __mmask8 keep = __mmask8((1u << count) - 1u);
  if (io.viewmat != nullptr)
    keep &= maybe_visible_x8(mx, my, mz, smax, io.viewmat, io.K, io.width, io.height, io.guard);
  // dir = mean - camera centre in float, its norm in double, as deformed_geometry.
  const __m256 dx = _mm256_sub_ps(_mm256_load_ps(mx), _mm256_set1_ps(io.camera_center[0]));
  const __m256 dy = _mm256_sub_ps(_mm256_load_ps(my), _mm256_set1_ps(io.camera_center[1]));
  const __m256 dz = _mm256_sub_ps(_mm256_load_ps(mz), _mm256_set1_ps(io.camera_center[2]));
  const __m512d ex = _mm512_cvtps_pd(dx), ey = _mm512_cvtps_pd(dy), ez = _mm512_cvtps_pd(dz);
  const __m512d norm2 = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(ex, ex), _mm512_mul_pd(ey, ey)), _mm512_mul_pd(ez, ez));
  const __m256 inv = _mm512_cvtpd_ps(
      _mm512_div_pd(_mm512_set1_pd(1.0), _mm512_max_pd(_mm512_sqrt_pd(norm2), _mm512_set1_pd(1e-12))));
  alignas(32) float ux[8], uy[8], uz[8];
  _mm256_store_ps(ux, _mm256_mul_ps(dx, inv));
  _mm256_store_ps(uy, _mm256_mul_ps(dy, inv));
  _mm256_store_ps(uz, _mm256_mul_ps(dz, inv));
  for (int b = 0; b < count; ++b) {
    if (keep & (1u << b)) {
      dirs[3 * b] = ux[b], dirs[3 * b + 1] = uy[b], dirs[3 * b + 2] = uz[b];
    } else {
      io.opacities[first + b] = 0.0f;
      for (int c = 0; c < 3; ++c) io.colors[3 * (first + b) + c] = 0.0f;
    }
  }
  return keep;
}
#endif

// deformed_geometry of count <= kGeometryLanes Gaussians (d: their decoder rows, stride apart): bit i of
// the result says whether first + i is kept, and dirs[3 i .. 3 i + 2] then holds its view direction.
#if defined(__AVX512F__)
constexpr int kGeometryLanes = 8;
inline unsigned block_geometry(const DeformIO& io, int64_t first, int count, const float* d, int stride,
                               float* dirs) {
  return deformed_geometry_x8(io, first, count, d, stride, dirs);
}
#else
constexpr int kGeometryLanes = 1;
inline unsigned block_geometry(const DeformIO& io, int64_t first, int, const float* d, int, float* dirs) {
  return deformed_geometry(io, first, d, dirs) ? 1u : 0u;
}
#endif

// block_geometry over the rows of one block (d: their geometry decoders' outputs, stride apart):
// keep[b] says whether row b can reach the image, and on_kept(b, dir) receives each kept row's
// unit view direction. Returns how many rows were kept.
template <class OnKept>
int cull_block(const DeformIO& io, int64_t first, int rows, const float* d, int stride, bool* keep,
               OnKept on_kept) {
  int kept = 0;
  for (int b0 = 0; b0 < rows; b0 += kGeometryLanes) {
    float dirs[3 * kGeometryLanes];
    const int count = std::min(kGeometryLanes, rows - b0);
    const unsigned lanes = block_geometry(io, first + b0, count, d + b0 * stride, stride, dirs);
    for (int i = 0; i < count; ++i) {
      keep[b0 + i] = (lanes >> i) & 1u;
      if (!keep[b0 + i]) continue;
      on_kept(b0 + i, &dirs[3 * i]);
      ++kept;
    }
  }
  return kept;
}

// body(first, rows) for every block of `block` Gaussians (the last one shorter), in parallel.
template <class Body>
void for_each_block(int64_t n, int block, int nthreads, Body body) {
  const int64_t blocks = (n + block - 1) / block;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 8)
  for (int64_t blk = 0; blk < blocks; ++blk) body(blk * block, int(std::min<int64_t>(block, n - blk * block)));
}

// D_t's input rows of Gaussians first .. first + rows - 1: their W feature frames side by side (row b at
// xin + b * W * kFeat).
inline void gather_window(const float* const* window_feats, int window, int64_t first, int rows, float* xin) {
  for (int b = 0; b < rows; ++b)
    for (int w = 0; w < window; ++w)
      std::memcpy(&xin[(b * window + w) * kFeat], window_feats[w] + (first + b) * kFeat, kFeat * sizeof(float));
}

// h = tanh(h + γ(t)'s bias) over rows of kHidden: the hidden state of D_t.
inline void tanh_hidden(float* h, int rows, const float* pe_bias) {
  for (int b = 0; b < rows; ++b) {
    float* hb = &h[b * kHidden];
#pragma omp simd
    for (int m = 0; m < kHidden; ++m) hb[m] = fast_tanh(hb[m] + pe_bias[m]);
  }
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
