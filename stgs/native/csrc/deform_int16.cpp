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
#include "stgs_abi.h"
#include "fastmath.h"

#if defined(__AVX2__)
#define STGS_HAVE_INT16 1
#include <immintrin.h>
#else
#define STGS_HAVE_INT16 0
#endif

// The kernel stgs_deform_int16_available reports (its values: stgs_abi.h).
#if defined(__AVX512BW__) && defined(__AVX512VNNI__)
#define STGS_INT16_KERNEL 3
#elif defined(__AVX512BW__)
#define STGS_INT16_KERNEL 2
#elif STGS_HAVE_INT16
#define STGS_INT16_KERNEL 1
#else
#define STGS_INT16_KERNEL 0
#endif

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

// How a layer's input rows are scaled to integers of at most qx (the layer's q).
enum class Scale {
  kRow,      // by the row's own max |x|
  kReluRow,  // max(0, x) (NaN kept, as torch.relu), then by the row's own max
  kUnit,     // by 1: inputs within [-1, 1] (tanh outputs, unit view directions)
};

#if STGS_INT16_KERNEL >= 2
// A row in steps of 16 lanes; a K that is 8 past a multiple of 16 ends on 8.
inline __mmask16 step_lanes(int K, int k) { return K - k >= 16 ? 0xFFFF : 0x00FF; }

template <Scale S>
inline __m512 load_step(const float* x, __mmask16 lanes) {
  const __m512 v = _mm512_maskz_loadu_ps(lanes, x);
  return S == Scale::kReluRow ? _mm512_max_ps(_mm512_setzero_ps(), v) : v;  // NaN kept
}

// q[0, K) = rint(x · inv) saturated to int16 (round to nearest even); true when x holds a NaN.
template <Scale S>
bool store_row(const float* x, int K, float inv, int16_t* q) {
  const __m512 vinv = _mm512_set1_ps(inv);
  __mmask16 bad = 0;
  for (int k = 0; k < K; k += 16) {
    const __mmask16 lanes = step_lanes(K, k);
    const __m512 v = load_step<S>(x + k, lanes);
    bad |= _mm512_cmp_ps_mask(v, v, _CMP_UNORD_Q);
    _mm512_mask_cvtsepi32_storeu_epi16(q + k, lanes, _mm512_cvtps_epi32(_mm512_mul_ps(v, vinv)));
  }
  return bad != 0;
}

// The row's max |x|, NaN where it holds a NaN.
template <Scale S>
float row_absmax(const float* x, int K) {
  __m512 amax = _mm512_setzero_ps();
  __mmask16 nan = 0;
  for (int k = 0; k < K; k += 16) {
    const __m512 v = load_step<S>(x + k, step_lanes(K, k));
    nan |= _mm512_cmp_ps_mask(v, v, _CMP_UNORD_Q);
    amax = _mm512_max_ps(amax, _mm512_abs_ps(v));
  }
  return nan ? NAN : _mm512_reduce_max_ps(amax);
}
#else
template <Scale S>
inline __m256 load_step(const float* x) {
  const __m256 v = _mm256_loadu_ps(x);
  return S == Scale::kReluRow ? _mm256_max_ps(_mm256_setzero_ps(), v) : v;  // NaN kept
}

// q[0, K) = rint(x · inv) saturated to int16 (round to nearest even); true when x holds a NaN.
template <Scale S>
bool store_row(const float* x, int K, float inv, int16_t* q) {
  const __m256 vinv = _mm256_set1_ps(inv);
  __m256 bad = _mm256_setzero_ps();
  for (int k = 0; k < K; k += 8) {
    const __m256 v = load_step<S>(x + k);
    bad = _mm256_or_ps(bad, _mm256_cmp_ps(v, v, _CMP_UNORD_Q));
    const __m256i i32 = _mm256_cvtps_epi32(_mm256_mul_ps(v, vinv));
    const __m128i i16 = _mm_packs_epi32(_mm256_castsi256_si128(i32), _mm256_extracti128_si256(i32, 1));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(q + k), i16);
  }
  return _mm256_movemask_ps(bad) != 0;
}

// The row's max |x|, NaN where it holds a NaN.
template <Scale S>
float row_absmax(const float* x, int K) {
  const __m256 abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
  __m256 amax = _mm256_setzero_ps(), nan = _mm256_setzero_ps();
  for (int k = 0; k < K; k += 8) {
    const __m256 v = load_step<S>(x + k);
    nan = _mm256_or_ps(nan, _mm256_cmp_ps(v, v, _CMP_UNORD_Q));
    amax = _mm256_max_ps(amax, _mm256_and_ps(v, abs_mask));
  }
  if (_mm256_movemask_ps(nan)) return NAN;
  alignas(32) float lanes[8];
  _mm256_store_ps(lanes, amax);
  float m = 0.0f;
  for (float l : lanes) m = std::max(m, l);
  return m;
}
#endif

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

#if STGS_INT16_KERNEL == 1
// y[r, c0 .. c0 + 8 V) = sum over pairs p of q[r, 2p .. 2p+1] · w[p, c, 0 .. 1], scaled, for R rows.
// Always inlined with its loops unrolled, so that the accumulators stay in registers (as deform.cpp's
// matmul_strip).
template <int M, int R, int V>
__attribute__((always_inline)) inline void qmatmul_strip(const int16_t* q, int pairs, int ldq, const int16_t* w,
                                                         const float* row_scale, const float* col_scale, float* y) {
  __m256i acc[R][V];
#pragma GCC unroll 16
  for (int r = 0; r < R; ++r)
#pragma GCC unroll 4
    for (int j = 0; j < V; ++j) acc[r][j] = _mm256_setzero_si256();
  for (int p = 0; p < pairs; ++p) {
    __m256i wv[V];
#pragma GCC unroll 4
    for (int j = 0; j < V; ++j) wv[j] = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(w + (p * M + 8 * j) * 2));
#pragma GCC unroll 16
    for (int r = 0; r < R; ++r) {
      int32_t pair;
      std::memcpy(&pair, q + r * ldq + 2 * p, sizeof(pair));
      const __m256i xb = _mm256_set1_epi32(pair);
#pragma GCC unroll 4
      for (int j = 0; j < V; ++j) acc[r][j] = _mm256_add_epi32(acc[r][j], _mm256_madd_epi16(xb, wv[j]));
    }
  }
  for (int r = 0; r < R; ++r) {
    const __m256 rs = _mm256_set1_ps(row_scale[r]);
    for (int j = 0; j < V; ++j) {
      const __m256 s = _mm256_mul_ps(rs, _mm256_loadu_ps(col_scale + 8 * j));
      _mm256_storeu_ps(y + r * M + 8 * j, _mm256_mul_ps(_mm256_cvtepi32_ps(acc[r][j]), s));
    }
  }
}
#else
// acc + the pair products of x and w, summed per int32 lane (exact: see the header).
__attribute__((always_inline)) inline __m512i add_pair_products(__m512i acc, __m512i x, __m512i w) {
#if STGS_INT16_KERNEL == 3
  return _mm512_dpwssd_epi32(acc, x, w);
#else
  return _mm512_add_epi32(acc, _mm512_madd_epi16(x, w));
#endif
}

// y[r, c0 .. c0 + 16 V) = sum over pairs p of q[r, 2p .. 2p+1] · w[p, c, 0 .. 1], scaled, for R rows:
// qmatmul_strip on 512-bit registers.
template <int M, int R, int V>
__attribute__((always_inline)) inline void qmatmul_strip512(const int16_t* q, int pairs, int ldq, const int16_t* w,
                                                            const float* row_scale, const float* col_scale,
                                                            float* y) {
  __m512i acc[R][V];
#pragma GCC unroll 16
  for (int r = 0; r < R; ++r)
#pragma GCC unroll 4
    for (int j = 0; j < V; ++j) acc[r][j] = _mm512_setzero_si512();
  for (int p = 0; p < pairs; ++p) {
    __m512i wv[V];
#pragma GCC unroll 4
    for (int j = 0; j < V; ++j) wv[j] = _mm512_loadu_si512(w + (p * M + 16 * j) * 2);
#pragma GCC unroll 16
    for (int r = 0; r < R; ++r) {
      int32_t pair;
      std::memcpy(&pair, q + r * ldq + 2 * p, sizeof(pair));
      const __m512i xb = _mm512_set1_epi32(pair);
#pragma GCC unroll 4
      for (int j = 0; j < V; ++j) acc[r][j] = add_pair_products(acc[r][j], xb, wv[j]);
    }
  }
  for (int r = 0; r < R; ++r) {
    const __m512 rs = _mm512_set1_ps(row_scale[r]);
    for (int j = 0; j < V; ++j) {
      const __m512 s = _mm512_mul_ps(rs, _mm512_loadu_ps(col_scale + 16 * j));
      _mm512_storeu_ps(y + r * M + 16 * j, _mm512_mul_ps(_mm512_cvtepi32_ps(acc[r][j]), s));
    }
  }
}
#endif

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
