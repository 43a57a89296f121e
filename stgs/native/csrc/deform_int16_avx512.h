// The int16 deformation's AVX-512BW kernel (deform_int16.cpp): rows scaled to int16 16 lanes at a time, and the
// layer products on 512-bit registers, summed by `vpdpwssd` where the compiler targets AVX512-VNNI.
#pragma once

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "deform_int16.h"

#if STGS_INT16_KERNEL >= 2
namespace {

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

}  // namespace
#endif
