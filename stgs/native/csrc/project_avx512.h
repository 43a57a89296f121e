// Stage 1's AVX-512 kernel: project_one (project.cpp) of 8 Gaussians per call, one double lane each.
#pragma once

#if defined(__AVX512F__)
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>

#include <cmath>
#include <cstdint>

#include "project.h"
#include "splat.h"

namespace stgs::splat {
namespace {

inline __m512d neg_pd(__m512d v) { return _mm512_castsi512_pd(_mm512_xor_si512(_mm512_castpd_si512(v), _mm512_set1_epi64(INT64_MIN))); }

// project_one of Gaussians i .. i + 7, one double lane each: the same operations in the same
// order, so the same outputs bit for bit, without the scalar version's division latency chains.
void project_x8(int64_t i, const ProjectIO& io) {
  alignas(64) double in[11][8];  // x y z, q0..q3, s0..s2, opacity (the inputs, as doubles)
  for (int l = 0; l < 8; ++l) {
    const int64_t g = i + l;
    for (int c = 0; c < 3; ++c) in[c][l] = io.means[3 * g + c];
    for (int c = 0; c < 4; ++c) in[3 + c][l] = io.quats[4 * g + c];
    for (int c = 0; c < 3; ++c) in[7 + c][l] = io.scales[3 * g + c];
    in[10][l] = io.opac[g];
  }
  const auto ld = [&](int k) { return _mm512_load_pd(in[k]); };
  const auto set = [](double v) { return _mm512_set1_pd(v); };
  const auto add = [](__m512d a, __m512d b) { return _mm512_add_pd(a, b); };
  const auto sub = [](__m512d a, __m512d b) { return _mm512_sub_pd(a, b); };
  const auto mul = [](__m512d a, __m512d b) { return _mm512_mul_pd(a, b); };
  const auto div = [](__m512d a, __m512d b) { return _mm512_div_pd(a, b); };
  const double* vm = io.viewmat;
  const double* K = io.K;
  const __m512d px = ld(0), py = ld(1), pz = ld(2);
  const auto cam = [&](const double* v) {
    return add(add(add(mul(set(v[0]), px), mul(set(v[1]), py)), mul(set(v[2]), pz)), set(v[3]));
  };
  const __m512d x = cam(vm), y = cam(vm + 4), z = cam(vm + 8);
  const __mmask8 valid = _mm512_cmp_pd_mask(z, set(kNearZ), _CMP_GE_OQ);
  const __m512d zs = _mm512_mask_blend_pd(valid, set(1.0), z);
  const __m512d xn = div(x, zs), yn = div(y, zs);
  alignas(64) double u[8], v[8], depth[8];
  _mm512_store_pd(u, add(add(mul(set(K[0]), xn), mul(set(K[1]), yn)), set(K[2])));
  _mm512_store_pd(v, add(mul(set(K[4]), yn), set(K[5])));
  _mm512_store_pd(depth, z);
  // Rotation from the overflow-safe normalised quaternion (zero -> identity).
  __m512d q0 = ld(3), q1 = ld(4), q2 = ld(5), q3 = ld(6);
  const __m512d peak = _mm512_max_pd(_mm512_max_pd(_mm512_abs_pd(q0), _mm512_abs_pd(q1)),
                                     _mm512_max_pd(_mm512_abs_pd(q2), _mm512_abs_pd(q3)));
  const __mmask8 nonzero = _mm512_cmp_pd_mask(peak, _mm512_setzero_pd(), _CMP_GT_OQ);
  q0 = div(q0, peak), q1 = div(q1, peak), q2 = div(q2, peak), q3 = div(q3, peak);
  const __m512d nrm = _mm512_sqrt_pd(add(add(add(mul(q0, q0), mul(q1, q1)), mul(q2, q2)), mul(q3, q3)));
  const __m512d w = _mm512_mask_blend_pd(nonzero, set(1.0), div(q0, nrm));
  const __m512d qx = _mm512_mask_blend_pd(nonzero, set(0.0), div(q1, nrm));
  const __m512d qy = _mm512_mask_blend_pd(nonzero, set(0.0), div(q2, nrm));
  const __m512d qz = _mm512_mask_blend_pd(nonzero, set(0.0), div(q3, nrm));
  const __m512d one = set(1.0), two = set(2.0);
  const __m512d R[9] = {sub(one, mul(two, add(mul(qy, qy), mul(qz, qz)))), mul(two, sub(mul(qx, qy), mul(w, qz))),
                        mul(two, add(mul(qx, qz), mul(w, qy))), mul(two, add(mul(qx, qy), mul(w, qz))),
                        sub(one, mul(two, add(mul(qx, qx), mul(qz, qz)))), mul(two, sub(mul(qy, qz), mul(w, qx))),
                        mul(two, sub(mul(qx, qz), mul(w, qy))), mul(two, add(mul(qy, qz), mul(w, qx))),
                        sub(one, mul(two, add(mul(qx, qx), mul(qy, qy))))};
  const __m512d zero = _mm512_setzero_pd();
  const __m512d dn[6] = {div(one, zs), zero, div(neg_pd(xn), zs), zero, div(one, zs), div(neg_pd(yn), zs)};
  __m512d jac[6], jw[6], M[6];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c) jac[3 * r + c] = add(mul(set(K[3 * r]), dn[c]), mul(set(K[3 * r + 1]), dn[3 + c]));
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      jw[3 * r + c] = add(add(mul(jac[3 * r], set(vm[c])), mul(jac[3 * r + 1], set(vm[4 + c]))),
                          mul(jac[3 * r + 2], set(vm[8 + c])));
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      M[3 * r + c] = mul(add(add(mul(jw[3 * r], R[c]), mul(jw[3 * r + 1], R[3 + c])), mul(jw[3 * r + 2], R[6 + c])),
                         ld(7 + c));
  const __m512d a0 = add(add(mul(M[0], M[0]), mul(M[1], M[1])), mul(M[2], M[2]));
  const __m512d b0 = add(add(mul(M[0], M[3]), mul(M[1], M[4])), mul(M[2], M[5]));
  const __m512d c0 = add(add(mul(M[3], M[3]), mul(M[4], M[4])), mul(M[5], M[5]));
  const __m512d m01 = sub(mul(M[0], M[4]), mul(M[1], M[3])), m02 = sub(mul(M[0], M[5]), mul(M[2], M[3]));
  const __m512d m12 = sub(mul(M[1], M[5]), mul(M[2], M[4]));
  const __m512d blur = set(kBlur);
  const __m512d det = add(add(add(add(mul(m01, m01), mul(m02, m02)), mul(m12, m12)), mul(blur, add(a0, c0))),
                          set(kBlur * kBlur));
  alignas(64) double con[3][8], ext[2][8], level[8];
  _mm512_store_pd(con[0], div(add(c0, blur), det));
  _mm512_store_pd(con[1], div(neg_pd(b0), det));
  _mm512_store_pd(con[2], div(add(a0, blur), det));
  _mm512_store_pd(ext[0], add(a0, blur));
  _mm512_store_pd(ext[1], add(c0, blur));
  _mm512_store_pd(level, mul(set(255.0), ld(10)));
  for (int l = 0; l < 8; ++l) {
    const int64_t g = i + l;
    const bool ok = (valid >> l) & 1u;
    io.means2d[2 * g] = float(u[l]);
    io.means2d[2 * g + 1] = float(v[l]);
    io.depths[g] = ok ? float(depth[l]) : -1.0f;
    for (int c = 0; c < 3; ++c) io.conics[3 * g + c] = float(con[c][l]);
    if (ok && level[l] >= 1.0) {
      const double quad = 2.0 * std::log(level[l]);
      io.extents[2 * g] = float(std::sqrt(quad * ext[0][l]) * kExtentMargin + 1e-3);
      io.extents[2 * g + 1] = float(std::sqrt(quad * ext[1][l]) * kExtentMargin + 1e-3);
    } else {
      io.extents[2 * g] = io.extents[2 * g + 1] = -1.0f;
    }
  }
}

}  // namespace
}  // namespace stgs::splat
#endif
