// Branch-free exp and tanh that the compiler can vectorise inside simd loops
// (libm's expf/tanhf are scalar calls unless -ffast-math is on, which we avoid
// so NaN/Inf keep their IEEE meaning). Relative error of fast_exp is about
// 2e-7 over the clamped range, tanh's absolute error about 1e-7.
#pragma once

#include <cstdint>
#include <cstring>

#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace stgs {

inline float fast_exp(float x) {
  x = x < -87.0f ? -87.0f : (x > 88.0f ? 88.0f : x);
  const float n = __builtin_floorf(x * 1.44269504088896341f + 0.5f);
  // Cody-Waite reduction: r = x - n ln2 with ln2 split in two parts.
  float r = x - n * 0.693145751953125f;
  r = r - n * 1.428606765330187045e-06f;
  // Minimax polynomial for e^r on [-ln2/2, ln2/2].
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const int32_t bits = (int32_t(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}

// fast_exp with IEEE overflow: +inf above the largest finite exp (fast_exp alone clamps there).
inline float exp_or_inf(float x) { return x > 88.72283f ? __builtin_inff() : fast_exp(x); }

inline float fast_tanh(float x) {
  const float ax = x < 0.0f ? -x : x;
  const float e = fast_exp(-2.0f * ax);  // in (0, 1]: no overflow
  const float t = (1.0f - e) / (1.0f + e);
  return x < 0.0f ? -t : t;
}

#if defined(__AVX512F__)
// fast_exp on 16 lanes (the same reduction and polynomial; fused multiply-adds, so the last
// bit may differ from fast_exp's).
inline __m512 fast_exp_v(__m512 x) {
  // Clamp with x as the second operand, which max/min return when either is NaN: NaN propagates, as in fast_exp.
  x = _mm512_min_ps(_mm512_set1_ps(88.0f), _mm512_max_ps(_mm512_set1_ps(-87.0f), x));
  const __m512 n = _mm512_roundscale_ps(_mm512_fmadd_ps(x, _mm512_set1_ps(1.44269504088896341f), _mm512_set1_ps(0.5f)),
                                        _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693145751953125f), x);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(1.428606765330187045e-06f), r);
  __m512 p = _mm512_set1_ps(1.9875691500e-4f);
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.3981999507e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(8.3334519073e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(4.1665795894e-2f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.6666665459e-1f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(5.0000001201e-1f));
  p = _mm512_add_ps(_mm512_fmadd_ps(_mm512_mul_ps(p, r), r, r), _mm512_set1_ps(1.0f));
  return _mm512_scalef_ps(p, n);
}

// fast_tanh on 16 lanes, its division replaced by rcp14 and one Newton step (relative error
// ~2^-28 before the final rounding), for the bf16 deformation's hidden layer (64 per Gaussian).
// Within an ulp or two of fast_tanh; the float32 deformation keeps fast_tanh.
inline __m512 fast_tanh_v(__m512 x) {
  const __m512 one = _mm512_set1_ps(1.0f);
  const __m512 e = fast_exp_v(_mm512_mul_ps(_mm512_set1_ps(-2.0f), _mm512_abs_ps(x)));  // in (0, 1]
  const __m512 den = _mm512_add_ps(one, e);
  __m512 inv = _mm512_rcp14_ps(den);
  inv = _mm512_mul_ps(inv, _mm512_fnmadd_ps(den, inv, _mm512_set1_ps(2.0f)));
  const __m512 t = _mm512_mul_ps(_mm512_sub_ps(one, e), inv);  // >= 0: takes x's sign
  const __m512i sign = _mm512_and_si512(_mm512_castps_si512(x), _mm512_set1_epi32(INT32_MIN));
  return _mm512_castsi512_ps(_mm512_or_si512(_mm512_castps_si512(t), sign));
}
#endif

}  // namespace stgs
