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

#include "deform.h"
#include "stgs_abi.h"
#include "fastmath.h"

#if defined(__AVX2__)
#include <immintrin.h>
#endif

namespace {

using stgs::kFeat;
using stgs::kHidden;
using stgs::kMaxWindow;
using stgs::kOut;

constexpr int kBlock = 32;

#if defined(__AVX512F__)
// y[b, :M] = x[b, :K] @ wt (K x M, row-major): register tiles of R rows x 64 columns (16
// accumulators at R = 4) so every weight load feeds R FMAs; R = 4, then 1 for the last rows.
template <int M, int R>
void matmul_tile(const float* x, int K, int ldx, const float* wt, float* y) {
  constexpr int kCols = M < 64 ? M : 64;
  constexpr int kVec = kCols / 16;
  for (int c0 = 0; c0 < M; c0 += kCols) {
    __m512 acc[R][kVec];
    for (int r = 0; r < R; ++r)
      for (int j = 0; j < kVec; ++j) acc[r][j] = _mm512_setzero_ps();
    for (int k = 0; k < K; ++k) {
      __m512 w[kVec];
      for (int j = 0; j < kVec; ++j) w[j] = _mm512_loadu_ps(wt + k * M + c0 + 16 * j);
      for (int r = 0; r < R; ++r) {
        const __m512 xb = _mm512_set1_ps(x[r * ldx + k]);
        for (int j = 0; j < kVec; ++j) acc[r][j] = _mm512_fmadd_ps(xb, w[j], acc[r][j]);
      }
    }
    for (int r = 0; r < R; ++r)
      for (int j = 0; j < kVec; ++j) _mm512_storeu_ps(y + r * M + c0 + 16 * j, acc[r][j]);
  }
}
#elif defined(__AVX2__) && defined(__FMA__)
// AVX2 (16 registers of 8 lanes): y[b, c0 : c0 + 8 V] for R rows (R = 6, then 2 and 1 for the last
// rows: the culled appearance rows are any count), so every weight load feeds R FMAs. The same k order
// as the other kernels.
// Always inlined with every loop over r unrolled, so that the accumulators stay in registers: as an
// out-of-line call (M = 64) GCC kept them in a stack array and stored all twelve at every k.
template <int M, int R, int V>
__attribute__((always_inline)) inline void matmul_strip(const float* x, int K, int ldx, const float* wt,
                                                        float* y) {
  static_assert(V == 1 || V == 2, "a strip is one or two registers wide");
  __m256 acc0[R], acc1[R];
#pragma GCC unroll 8
  for (int r = 0; r < R; ++r) acc0[r] = acc1[r] = _mm256_setzero_ps();
  for (int k = 0; k < K; ++k) {
    const __m256 w0 = _mm256_loadu_ps(wt + k * M);
    const __m256 w1 = V == 2 ? _mm256_loadu_ps(wt + k * M + 8) : w0;
#pragma GCC unroll 8
    for (int r = 0; r < R; ++r) {
      const __m256 xb = _mm256_broadcast_ss(x + r * ldx + k);
      acc0[r] = _mm256_fmadd_ps(xb, w0, acc0[r]);
      if (V == 2) acc1[r] = _mm256_fmadd_ps(xb, w1, acc1[r]);
    }
  }
#pragma GCC unroll 8
  for (int r = 0; r < R; ++r) {
    _mm256_storeu_ps(y + r * M, acc0[r]);
    if (V == 2) _mm256_storeu_ps(y + r * M + 8, acc1[r]);
  }
}

template <int M, int V>
void matmul_strip_rows(const float* x, int rows, int K, int ldx, const float* wt, float* y) {
  // Six rows: 12 accumulators (at V = 2) keep both FMA pipes busy through the FMA's latency, where
  // four (8) left them idle a third of the time (kernel alone: 62 -> 82 GFLOP/s on one Zen 3 core).
  int b = 0;
  for (; b + 6 <= rows; b += 6) matmul_strip<M, 6, V>(x + b * ldx, K, ldx, wt, y + b * M);
  for (; b + 2 <= rows; b += 2) matmul_strip<M, 2, V>(x + b * ldx, K, ldx, wt, y + b * M);
  for (; b < rows; ++b) matmul_strip<M, 1, V>(x + b * ldx, K, ldx, wt, y + b * M);
}
#endif

#if defined(__AVX512F__) || (defined(__AVX2__) && defined(__FMA__))
// y[b, :M] = x[b, :K] @ wt; columns from Cols on may be left unwritten (the AVX2 kernel skips
// them: the appearance decoders' packed second layer uses 4 of its 16).
template <int M, int Cols = M>
void matmul_rows(const float* x, int rows, int K, int ldx, const float* wt, float* y) {
  static_assert(M % 16 == 0 && Cols % 8 == 0 && Cols <= M, "M: a multiple of 16, Cols: of 8");
#if defined(__AVX512F__)
  int b = 0;
  for (; b + 4 <= rows; b += 4) matmul_tile<M, 4>(x + b * ldx, K, ldx, wt, y + b * M);
  for (; b < rows; ++b) matmul_tile<M, 1>(x + b * ldx, K, ldx, wt, y + b * M);
#else
  // Strip by strip, so one K x 16 strip of the weights stays in L1 while every row passes it (a
  // 64 x 128 layer is 32 KiB, all of L1).
  int c0 = 0;
  for (; c0 + 16 <= Cols; c0 += 16) matmul_strip_rows<M, 2>(x, rows, K, ldx, wt + c0, y + c0);
  if (c0 < Cols) matmul_strip_rows<M, 1>(x, rows, K, ldx, wt + c0, y + c0);
#endif
}
#else
// Portable fallback: one row at a time, the compiler vectorises over columns.
template <int M, int Cols = M>
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

inline float relu(float v) { return v < 0.0f ? 0.0f : v; }  // NaN passes, as in torch.relu


void relu_inplace(float* x, int count) {
#pragma omp simd
  for (int i = 0; i < count; ++i) x[i] = relu(x[i]);
}

}  // namespace

extern "C" {

// Deformed Gaussians of one frame (see stgs/model/native_deform.py for the
// weight packing). If viewmat is non-null, Gaussians that cannot reach the
// image (or, with guard non-null, lie outside the guard band) get opacity 0
// and skip the view-dependent decoders.
void stgs_deform(int64_t n, int window, const float* const* window_feats, const float* xyz,
                 const float* log_scale, const float* rotation, const float* opacity_logit,
                 const float* color, const float* temporal_t, const float* pe_bias,
                 const float* geo1_t, const float* geo2_t, const float* app1_t,
                 const float* app2_t, const float* camera_center, const double* viewmat,
                 const double* K, int width, int height, float* out_means, float* out_quats,
                 float* out_scales, float* out_opac, float* out_colors, const double* guard, int nthreads) {
  const stgs::DeformIO io{xyz, log_scale, rotation, opacity_logit, color, camera_center, viewmat, K, width,
                          height, out_means, out_quats, out_scales, out_opac, out_colors, guard};
  const int in_t = window * kFeat;
  stgs::for_each_block(n, kBlock, nthreads, [&](int64_t first, int rows) {
    alignas(64) float xin[kBlock * kMaxWindow * kFeat];
    alignas(64) float h[kBlock * kHidden];
    alignas(64) float hidden2[kBlock * 2 * kHidden];
    alignas(64) float app_in[kBlock * (kHidden + 3)];
    alignas(64) float out2[kBlock * kOut];
    stgs::gather_window(window_feats, window, first, rows, xin);
    matmul_rows<kHidden>(xin, rows, in_t, in_t, temporal_t, h);
    stgs::tanh_hidden(h, rows, pe_bias);
    // D_v and D_cov: [dx(3) ds(3) dq(4)] in out2.
    matmul_rows<2 * kHidden>(h, rows, kHidden, kHidden, geo1_t, hidden2);
    relu_inplace(hidden2, rows * 2 * kHidden);
    matmul_rows<kOut>(hidden2, rows, 2 * kHidden, 2 * kHidden, geo2_t, out2);
    stgs::deformed_scales(io, first, rows, out2, kOut);
    bool keep[kBlock];
    int slot[kBlock];
    int kept = 0;  // kept rows go to app_in densely, row b to slot[b]
    stgs::cull_block(io, first, rows, out2, kOut, keep, [&](int b, const float* dir) {
      float* row = &app_in[kept * (kHidden + 3)];
      std::memcpy(row, &h[b * kHidden], kHidden * sizeof(float));
      std::memcpy(row + kHidden, dir, 3 * sizeof(float));
      slot[b] = kept++;
    });
    if (kept == 0) return;
    // D_o and D_c on [h, view direction]: [do(1) dc(3)] in out2.
    matmul_rows<2 * kHidden>(app_in, kept, kHidden + 3, kHidden + 3, app1_t, hidden2);
    relu_inplace(hidden2, kept * 2 * kHidden);
    matmul_rows<kOut, 8>(hidden2, kept, 2 * kHidden, 2 * kHidden, app2_t, out2);  // [do dc] in 0..3
    for (int b = 0; b < rows; ++b)
      if (keep[b])
        stgs::deformed_appearance(io, first + b, &out2[slot[b] * kOut]);
  });
}

}  // extern "C"
