// int16 deformation field (inference only): the layers of deform.cpp as
// integer products, an accuracy knob for AVX2 CPUs without bf16 arithmetic
// (docs/BENCHMARKS.md measures what it costs). `vpmaddwd` multiplies 16 pairs
// of int16 and adds each pair into an int32 lane: twice the multiply-adds of
// a float32 FMA per instruction.
//
// Every layer input row is scaled to integers of at most q (round to nearest
// even): by its own max |x|, or by 1 where the inputs lie in [-1, 1] by
// construction (tanh outputs, unit view directions: no scan for the max);
// every weight column by its own max |w| to at most q. The packer
// (stgs/model/native_deform.py) picks q per layer so that K·q² < 2^31: the
// int32 sums are exact. A row's output is float(sum) · (row scale · column
// scale). A row with a NaN or Inf input gets the scale NaN, so NaN comes out as
// in the float32 kernel. Weights arrive as (K/2 pairs) x M x 2 int16: 8
// columns of one pair are one 256-bit operand of vpmaddwd.
//
// Where the compiler targets AVX512BW the products run on 512-bit registers, 16 columns of one pair per
// operand, accumulated by `vpdpwssd` (AVX512-VNNI: the multiply-add and the sum in one instruction) or,
// without VNNI, by `vpmaddwd` and an add. The int32 sums are exact either way, and the float epilogue does
// the same two multiplications per lane, so the AVX-512 and AVX2 kernels give the same bits.
//
// Built where the compiler targets AVX2; elsewhere stgs_deform_int16 returns -1.

#include <omp.h>

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "deform.h"
#include "deform_int16.h"
#include "deform_int16_avx2.h"
#include "deform_int16_avx512.h"
#include "fastmath.h"
#include "stgs_abi.h"

namespace {

#if STGS_HAVE_INT16
using stgs::kFeat;
using stgs::kHidden;
using stgs::kMaxWindow;
using stgs::kOut;

constexpr int kBlock = 32;
constexpr int kWide = 2 * kHidden;           // the two first decoder layers side by side
constexpr int kAppIn = kHidden + 8;          // [h(64), view direction(3)] padded to a multiple of 8
constexpr int kMaxIn = kMaxWindow * kFeat;

// The packed int16 weights of one layer: (pairs x M x 2) values, M column scales, the input bound qx.
struct Int16Layer {
  const int16_t* w;
  const float* col_scale;
  float qx;
};

// x (rows x K floats, stride ldx; K a multiple of 8) to int16 (stride ldq) and one scale per row:
// q = rint(x · (qx / m)), scale = m / qx, with m the row's max |x| (kRow, kReluRow) or 1 (kUnit).
// A row with NaN (or, scaled by its max, Inf) gets q = 0 and scale NaN; an all-zero row scale 0.
template <Scale S>
void quantize_rows(const float* x, int rows, int K, int ldx, float qx, int16_t* q, int ldq, float* scale) {
  for (int r = 0; r < rows; ++r) {
    const float* xr = x + r * ldx;
    int16_t* qr = q + r * ldq;
    if (S == Scale::kUnit) {  // one pass: |x| <= 1 by construction, only NaN can spoil the row
      const bool bad = store_row<S>(xr, K, qx, qr);
      scale[r] = bad ? NAN : 1.0f / qx;
      if (bad) std::memset(qr, 0, K * sizeof(int16_t));
      continue;
    }
    const float m = row_absmax<S>(xr, K);
    const bool finite = m <= FLT_MAX;  // false for NaN and Inf
    if (!finite || m == 0.0f) {
      std::memset(qr, 0, K * sizeof(int16_t));
      scale[r] = finite ? 0.0f : NAN;
      continue;
    }
    scale[r] = m / qx;
    store_row<S>(xr, K, qx / m, qr);
  }
}

// y (rows x M, columns from Cols on left unwritten) = the quantised rows q times layer L.
template <int M, int Cols = M>
void qmatmul_rows(const int16_t* q, int rows, int K, int ldq, const float* row_scale, const Int16Layer& L,
                  float* y) {
  static_assert(M % 16 == 0 && Cols % 8 == 0 && Cols <= M, "M: a multiple of 16, Cols: of 8");
  const int pairs = (K + 1) / 2;
#if STGS_INT16_KERNEL >= 2
  // 64-column strips four rows at a time (16 accumulators), then 16-column strips eight rows at a time
  // (a narrow layer's 8 used columns are computed as 16: M is a multiple of 16, and it costs no more).
  int c0 = 0;
  for (; c0 + 64 <= Cols; c0 += 64) {
    int r = 0;
    for (; r + 4 <= rows; r += 4)
      qmatmul_strip512<M, 4, 4>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0,
                                y + r * M + c0);
    for (; r < rows; ++r)
      qmatmul_strip512<M, 1, 4>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0,
                                y + r * M + c0);
  }
  for (; c0 < Cols; c0 += 16) {
    int r = 0;
    for (; r + 8 <= rows; r += 8)
      qmatmul_strip512<M, 8, 1>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0,
                                y + r * M + c0);
    for (; r < rows; ++r)
      qmatmul_strip512<M, 1, 1>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0,
                                y + r * M + c0);
  }
#else
  // 32-column strips two rows at a time (8 accumulators, the weights as memory operands), then the narrow
  // layers' 8-column strips four rows at a time: the fastest shapes in a harness on AMD Zen 3.
  int c0 = 0;
  for (; c0 + 32 <= Cols; c0 += 32) {
    int r = 0;
    for (; r + 2 <= rows; r += 2)
      qmatmul_strip<M, 2, 4>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0, y + r * M + c0);
    for (; r < rows; ++r)
      qmatmul_strip<M, 1, 4>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0, y + r * M + c0);
  }
  for (; c0 < Cols; c0 += 8) {
    int r = 0;
    for (; r + 4 <= rows; r += 4)
      qmatmul_strip<M, 4, 1>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0, y + r * M + c0);
    for (; r < rows; ++r)
      qmatmul_strip<M, 1, 1>(q + r * ldq, pairs, ldq, L.w + 2 * c0, row_scale + r, L.col_scale + c0, y + r * M + c0);
  }
#endif
}

struct Int16Weights {
  Int16Layer temporal, geo1, geo2, app1, app2;
};

void deform_blocks(const stgs::DeformIO& io, int64_t n, int window, const float* const* window_feats,
                   const Int16Weights& L, const float* pe_bias, int nthreads) {
  const int in_t = window * kFeat;
  stgs::for_each_block(n, kBlock, nthreads, [&](int64_t first, int rows) {
    alignas(64) float xin[kBlock * kMaxIn];
    alignas(64) float h[kBlock * kHidden];
    alignas(64) float wide[kBlock * kWide];
    alignas(64) float app_in[kBlock * kAppIn];
    alignas(64) float out2[kBlock * kOut];
    alignas(64) int16_t q[kBlock * kMaxIn];
    float scale[kBlock];
    stgs::gather_window(window_feats, window, first, rows, xin);
    quantize_rows<Scale::kRow>(xin, rows, in_t, in_t, L.temporal.qx, q, in_t, scale);
    qmatmul_rows<kHidden>(q, rows, in_t, in_t, scale, L.temporal, h);
    stgs::tanh_hidden(h, rows, pe_bias);
    // D_v and D_cov: [dx(3) ds(3) dq(4)] in out2.
    quantize_rows<Scale::kUnit>(h, rows, kHidden, kHidden, L.geo1.qx, q, kHidden, scale);
    qmatmul_rows<kWide>(q, rows, kHidden, kHidden, scale, L.geo1, wide);
    quantize_rows<Scale::kReluRow>(wide, rows, kWide, kWide, L.geo2.qx, q, kWide, scale);
    qmatmul_rows<kOut>(q, rows, kWide, kWide, scale, L.geo2, out2);
    stgs::deformed_scales(io, first, rows, out2, kOut);
    bool keep[kBlock];
    int slot[kBlock];
    int kept = 0;  // kept rows go to app_in densely, row b to slot[b]
    stgs::cull_block(io, first, rows, out2, kOut, keep, [&](int b, const float* dir) {
      float* row = &app_in[kept * kAppIn];
      std::memcpy(row, &h[b * kHidden], kHidden * sizeof(float));
      std::memcpy(row + kHidden, dir, 3 * sizeof(float));
      std::fill(row + kHidden + 3, row + kAppIn, 0.0f);
      slot[b] = kept++;
    });
    if (kept == 0) return;
    // D_o and D_c on [h, view direction]: [do(1) dc(3)] in out2.
    quantize_rows<Scale::kUnit>(app_in, kept, kAppIn, kAppIn, L.app1.qx, q, kAppIn, scale);
    qmatmul_rows<kWide>(q, kept, kHidden + 3, kAppIn, scale, L.app1, wide);
    quantize_rows<Scale::kReluRow>(wide, kept, kWide, kWide, L.app2.qx, q, kWide, scale);
    qmatmul_rows<kOut, 8>(q, kept, kWide, kWide, scale, L.app2, out2);  // [do dc] in 0..3
    for (int b = 0; b < rows; ++b)
      if (keep[b]) stgs::deformed_appearance(io, first + b, &out2[slot[b] * kOut]);
  });
}
#endif  // STGS_HAVE_INT16

}  // namespace

extern "C" {

int stgs_deform_int16_available() { return STGS_INT16_KERNEL; }

int stgs_deform_int16(int64_t n, int window, const float* const* window_feats, const float* xyz,
                      const float* log_scale, const float* rotation, const float* opacity_logit,
                      const float* color, const int16_t* const* layer_weights, const float* const* col_scales,
                      const float* qx, const float* pe_bias, const float* camera_center, const double* viewmat,
                      const double* K, int width, int height, float* out_means, float* out_quats,
                      float* out_scales, float* out_opac, float* out_colors, const double* guard, int nthreads) {
#if STGS_HAVE_INT16
  if (window < 1 || window > kMaxWindow) return -1;
  Int16Layer layers[5];
  for (int i = 0; i < 5; ++i) layers[i] = Int16Layer{layer_weights[i], col_scales[i], qx[i]};
  const Int16Weights weights{layers[0], layers[1], layers[2], layers[3], layers[4]};
  const stgs::DeformIO io{xyz, log_scale, rotation, opacity_logit, color, camera_center, viewmat, K, width,
                          height, out_means, out_quats, out_scales, out_opac, out_colors, guard};
  deform_blocks(io, n, window, window_feats, weights, pe_bias, nthreads);
  return 0;
#else
  (void)n, (void)window, (void)window_feats, (void)xyz, (void)log_scale, (void)rotation;
  (void)opacity_logit, (void)color, (void)layer_weights, (void)col_scales, (void)qx, (void)pe_bias;
  (void)camera_center, (void)viewmat, (void)K, (void)width, (void)height, (void)out_means, (void)out_quats;
  (void)out_scales, (void)out_opac, (void)out_colors, (void)guard, (void)nthreads;
  return -1;
#endif
}

}  // extern "C"
