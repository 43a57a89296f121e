// AVX-512 pieces shared by the forward and backward tile kernels (internal): one tile row
// of 16 pixels is one register. Same numerics as the portable kernels beside them.
#pragma once

#if defined(__AVX512F__)
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#endif

#include "splat.h"

#if defined(__AVX512F__)
namespace stgs::splat {


// Row powers are evaluated in log2 units (kLog2e, splat.h): the conic comes pre-scaled by
// -0.5 log2(e) (pa, pb2, pc), which also saves the multiply by -0.5. The gradients keep the
// natural-unit conic (a, c, half).
struct SplatVec {
  __m512 mx, a, c, o, r, g, bl, amin, amax, tmin, one, half, pa, pb2, pc;
  explicit SplatVec(const Splat& s)
      : mx(_mm512_set1_ps(s.mx)), a(_mm512_set1_ps(s.a)), c(_mm512_set1_ps(s.c)), o(_mm512_set1_ps(s.o)),
        r(_mm512_set1_ps(s.r)), g(_mm512_set1_ps(s.g)), bl(_mm512_set1_ps(s.bl)),
        amin(_mm512_set1_ps(kAlphaMin)), amax(_mm512_set1_ps(kAlphaMax)), tmin(_mm512_set1_ps(kTMin)),
        one(_mm512_set1_ps(1.0f)), half(_mm512_set1_ps(-0.5f)), pa(_mm512_set1_ps(-0.5f * kLog2e * s.a)),
        pb2(_mm512_set1_ps(-kLog2e * s.b)), pc(_mm512_set1_ps(-0.5f * kLog2e * s.c)) {}
};

// 2^x for x <= 0: x = n + f with n the nearest integer (f in [-0.5, 0.5], exact),
// 2^f by kExp2Poly (splat.h).
inline __m512 exp2_v(__m512 x) {
  // No clamp from below: far under -126 vscalefps underflows to 0 (n is exact for any float). Rows
  // far from the ellipse give denormals or 0 here; a clamp at 2^-64 to avoid them measured 1-4 % slower.
  const __m512 n = _mm512_roundscale_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const __m512 f = _mm512_sub_ps(x, n);
  __m512 p = _mm512_set1_ps(kExp2Poly[0]);
  for (int i = 1; i < 6; ++i) p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(kExp2Poly[i]));
  return _mm512_scalef_ps(p, n);
}

// Power (-0.5 q log2 e, unclipped), falloff 2^min(power, 0) and clamped alpha along a row.
struct RowEval {
  __m512 dx, power, falloff, alpha;
};

inline __m512 row_power(const SplatVec& v, __m512 px, float dy) {
  const __m512 dx = _mm512_sub_ps(px, v.mx);
  const __m512 dyv = _mm512_set1_ps(dy);
  const __m512 cdy2 = _mm512_mul_ps(_mm512_mul_ps(v.pc, dyv), dyv);
  return _mm512_fmadd_ps(_mm512_mul_ps(v.pa, dx), dx, _mm512_fmadd_ps(_mm512_mul_ps(v.pb2, dyv), dx, cdy2));
}

// `power` is row_power(v, px, dy), which callers already need for their early exits.
inline RowEval eval_row(const SplatVec& v, __m512 px, __m512 power, __mmask16 inside) {
  RowEval e;
  e.dx = _mm512_sub_ps(px, v.mx);
  e.power = power;
  e.falloff = exp2_v(_mm512_min_ps(e.power, _mm512_setzero_ps()));
  e.alpha = _mm512_maskz_min_ps(inside, _mm512_mul_ps(v.o, e.falloff), v.amax);
  return e;
}

inline __mmask16 span_mask(int x0, int u0, int u1) {
  const int lo = std::max(0, u0 - x0), hi = std::min(kTile - 1, u1 - x0);
  if (lo > hi) return 0;
  return __mmask16(((1u << (hi - lo + 1)) - 1u) << lo);
}

inline __m512 pixel_centres(int x0) {
  return _mm512_add_ps(_mm512_set1_ps(float(x0) + 0.5f),
                       _mm512_setr_ps(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
}

}  // namespace stgs::splat
#endif  // __AVX512F__
