// The int16 deformation's AVX2 kernel (deform_int16.cpp): rows scaled to int16 8 lanes at a time, and the layer
// products by `vpmaddwd` on 256-bit registers.
#pragma once

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "deform_int16.h"

#if STGS_INT16_KERNEL == 1
namespace {

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

}  // namespace
#endif
