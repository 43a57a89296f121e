// Native deformation field (inference only): all MLP layers evaluated per block
// of Gaussians while the block sits in cache. Mirrors stgs.model.gop
// (GOPModel.deform, the oracle). Weights arrive pre-arranged by
// stgs/model/native_deform.py: first layers transposed (in x out), second
// layers as torch stores them (out x in).

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "fastmath.h"

#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace {

constexpr int kFeat = 16;
constexpr int kHidden = 64;
constexpr int kBlock = 32;
constexpr int kMaxWindow = 8;
constexpr double kNearZ = 0.01;

#if defined(__AVX512F__)
// y[b, :M] = x[b, :K] @ wt (K x M, row-major): register tiles of 4 rows x 64
// columns (16 accumulators) so every weight load feeds four FMAs.
template <int M>
void matmul_rows(const float* x, int rows, int K, int ldx, const float* wt, float* y) {
  static_assert(M % 16 == 0, "M must be a multiple of 16");
  constexpr int kCols = M < 64 ? M : 64;
  constexpr int kVec = kCols / 16;
  int b = 0;
  for (; b + 4 <= rows; b += 4) {
    for (int c0 = 0; c0 < M; c0 += kCols) {
      __m512 acc[4][kVec];
      for (int r = 0; r < 4; ++r)
        for (int j = 0; j < kVec; ++j) acc[r][j] = _mm512_setzero_ps();
      for (int k = 0; k < K; ++k) {
        __m512 w[kVec];
        for (int j = 0; j < kVec; ++j) w[j] = _mm512_loadu_ps(wt + k * M + c0 + 16 * j);
        for (int r = 0; r < 4; ++r) {
          const __m512 xb = _mm512_set1_ps(x[(b + r) * ldx + k]);
          for (int j = 0; j < kVec; ++j) acc[r][j] = _mm512_fmadd_ps(xb, w[j], acc[r][j]);
        }
      }
      for (int r = 0; r < 4; ++r)
        for (int j = 0; j < kVec; ++j) _mm512_storeu_ps(y + (b + r) * M + c0 + 16 * j, acc[r][j]);
    }
  }
  for (; b < rows; ++b) {
    for (int m = 0; m < M; ++m) {
      float acc = 0.0f;
      for (int k = 0; k < K; ++k) acc += x[b * ldx + k] * wt[k * M + m];
      y[b * M + m] = acc;
    }
  }
}
#else
// Portable fallback: one row at a time, the compiler vectorises over columns.
template <int M>
void matmul_rows(const float* x, int rows, int K, int ldx, const float* wt, float* y) {
  for (int b = 0; b < rows; ++b) {
    float acc[M] = {0};
    for (int k = 0; k < K; ++k) {
      const float xv = x[b * ldx + k];
#pragma omp simd
      for (int m = 0; m < M; ++m) acc[m] += xv * wt[k * M + m];
    }
    std::memcpy(y + b * M, acc, sizeof(acc));
  }
}
#endif

inline float relu(float v) { return v > 0.0f ? v : 0.0f; }

constexpr int kOut = 16;  // padded width of the packed second layers

// Conservative visibility from the camera's frustum: false only when the
// Gaussian cannot put alpha >= 1/255 on any pixel whatever its opacity.
bool maybe_visible(const float* mean, const float* log_scale_out, const double* viewmat,
                   const double* K, int width, int height) {
  const double x = viewmat[0] * mean[0] + viewmat[1] * mean[1] + viewmat[2] * mean[2] + viewmat[3];
  const double y = viewmat[4] * mean[0] + viewmat[5] * mean[1] + viewmat[6] * mean[2] + viewmat[7];
  const double z = viewmat[8] * mean[0] + viewmat[9] * mean[1] + viewmat[10] * mean[2] + viewmat[11];
  if (!(z >= kNearZ)) return false;
  const double s = std::exp(double(std::max(log_scale_out[0], std::max(log_scale_out[1], log_scale_out[2]))));
  const double xn = x / z, yn = y / z;
  // The Frobenius norm of the projection Jacobian bounds its spectral norm.
  const double j00 = K[0] / z, j01 = K[1] / z, j02 = -(K[0] * xn + K[1] * yn) / z;
  const double j11 = K[4] / z, j12 = -K[4] * yn / z;
  const double jf2 = j00 * j00 + j01 * j01 + j02 * j02 + j11 * j11 + j12 * j12;
  const double radius = std::sqrt(2.0 * std::log(255.0) * (jf2 * s * s + 0.3)) * 1.01 + 1.0;
  const double u = K[0] * xn + K[1] * yn + K[2], v = K[4] * yn + K[5];
  return u + radius >= 0.0 && u - radius <= width && v + radius >= 0.0 && v - radius <= height;
}

void relu_inplace(float* x, int count) {
#pragma omp simd
  for (int i = 0; i < count; ++i) x[i] = relu(x[i]);
}

}  // namespace

extern "C" {

// Deformed Gaussians of one frame (see stgs/model/native_deform.py for the
// weight packing). If viewmat is non-null, Gaussians that cannot reach the
// image get opacity 0 and skip the view-dependent decoders.
void stgs_deform(int64_t n, int window, int frame, const float* feats, const float* xyz,
                 const float* log_scale, const float* rotation, const float* opacity_logit,
                 const float* color, const float* temporal_t, const float* pe_bias,
                 const float* geo1_t, const float* geo2_t, const float* app1_t,
                 const float* app2_t, const float* camera_center, const double* viewmat,
                 const double* K, int width, int height, float* out_means, float* out_quats,
                 float* out_scales, float* out_opac, float* out_colors, int nthreads) {
  const int in_t = window * kFeat;
  const int64_t blocks = (n + kBlock - 1) / kBlock;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 8)
  for (int64_t blk = 0; blk < blocks; ++blk) {
    const int64_t first = blk * kBlock;
    const int rows = int(std::min<int64_t>(kBlock, n - first));
    alignas(64) float xin[kBlock * kMaxWindow * kFeat];
    alignas(64) float h[kBlock * kHidden];
    alignas(64) float hidden2[kBlock * 2 * kHidden];
    alignas(64) float app_in[kBlock * (kHidden + 3)];
    alignas(64) float out2[kBlock * kOut];
    for (int b = 0; b < rows; ++b)
      for (int w = 0; w < window; ++w)
        std::memcpy(&xin[b * in_t + w * kFeat], feats + ((frame + w) * n + first + b) * kFeat,
                    kFeat * sizeof(float));
    matmul_rows<kHidden>(xin, rows, in_t, in_t, temporal_t, h);
    for (int b = 0; b < rows; ++b) {
      float* hb = &h[b * kHidden];
#pragma omp simd
      for (int m = 0; m < kHidden; ++m) hb[m] = stgs::fast_tanh(hb[m] + pe_bias[m]);
    }
    // D_v and D_cov: [dx(3) ds(3) dq(4)] in out2.
    matmul_rows<2 * kHidden>(h, rows, kHidden, kHidden, geo1_t, hidden2);
    relu_inplace(hidden2, rows * 2 * kHidden);
    matmul_rows<kOut>(hidden2, rows, 2 * kHidden, 2 * kHidden, geo2_t, out2);
    bool keep[kBlock];
    int slot[kBlock];
    int kept = 0;
    for (int b = 0; b < rows; ++b) {
      const int64_t g = first + b;
      const float* d = &out2[b * kOut];
      float* mean = &out_means[3 * g];
      float dls[3];
      for (int c = 0; c < 3; ++c) {
        mean[c] = xyz[3 * g + c] + d[c];
        dls[c] = log_scale[3 * g + c] + d[3 + c];
        out_scales[3 * g + c] = std::exp(dls[c]);
      }
      for (int c = 0; c < 4; ++c) out_quats[4 * g + c] = rotation[4 * g + c] + d[6 + c];
      keep[b] = viewmat == nullptr || maybe_visible(mean, dls, viewmat, K, width, height);
      if (!keep[b]) {
        out_opac[g] = 0.0f;
        for (int c = 0; c < 3; ++c) out_colors[3 * g + c] = 0.0f;
        continue;
      }
      double norm2 = 0.0;
      float dir[3];
      for (int c = 0; c < 3; ++c) {
        dir[c] = mean[c] - camera_center[c];
        norm2 += double(dir[c]) * dir[c];
      }
      const float inv = float(1.0 / std::max(std::sqrt(norm2), 1e-12));
      float* row = &app_in[kept * (kHidden + 3)];
      std::memcpy(row, &h[b * kHidden], kHidden * sizeof(float));
      for (int c = 0; c < 3; ++c) row[kHidden + c] = dir[c] * inv;
      slot[b] = kept++;
    }
    if (kept == 0) continue;
    // D_o and D_c on [h, view direction]: [do(1) dc(3)] in out2.
    matmul_rows<2 * kHidden>(app_in, kept, kHidden + 3, kHidden + 3, app1_t, hidden2);
    relu_inplace(hidden2, kept * 2 * kHidden);
    matmul_rows<kOut>(hidden2, kept, 2 * kHidden, 2 * kHidden, app2_t, out2);
    for (int b = 0; b < rows; ++b) {
      if (!keep[b]) continue;
      const int64_t g = first + b;
      const float* d = &out2[slot[b] * kOut];
      const float base = 1.0f / (1.0f + std::exp(-opacity_logit[g]));
      out_opac[g] = std::min(1.0f, std::max(0.0f, base + std::tanh(d[0])));
      for (int c = 0; c < 3; ++c) out_colors[3 * g + c] = relu(color[3 * g + c]) + d[1 + c];
    }
  }
}

}  // extern "C"
