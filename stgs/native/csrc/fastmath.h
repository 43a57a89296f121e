// Branch-free exp and tanh that the compiler can vectorise inside simd loops
// (libm's expf/tanhf are scalar calls unless -ffast-math is on, which we avoid
// so NaN/Inf keep their IEEE meaning). Relative error of fast_exp is about
// 2e-7 over the clamped range, tanh's absolute error about 1e-7.
#pragma once

#include <cstdint>
#include <cstring>

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

}  // namespace stgs
