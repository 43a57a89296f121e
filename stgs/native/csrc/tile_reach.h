// Stage 2's tile reach: which tiles of its rect a projected Gaussian's ellipse reaches, row by row (portable,
// and 8 tile rows at a time on AVX-512); binning.cpp lists each Gaussian in those tiles.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#if defined(__AVX512F__)
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#endif

#include "splat.h"

namespace stgs::splat {
namespace {

// Inclusive pixel range whose centres lie within [m - h, m + h], clipped to [0, size).
void pixel_range(float m, float h, int size, int32_t& lo, int32_t& hi) {
  const double first = std::ceil(double(m) - double(h) - 0.5);
  const double last = std::floor(double(m) + double(h) - 0.5);
  lo = int32_t(std::max(0.0, std::min(first, double(size))));
  hi = int32_t(std::max(-1.0, std::min(last, double(size - 1))));
}

// Which tiles of its rect a Gaussian reaches. The rect (the ellipse's bounding
// box) overestimates rotated and anisotropic ellipses, and every extra tile
// costs the compositor a pass over its rows, so each row of tiles gets the
// columns holding a pixel centre where the power can reach s.min_power (where
// alpha can reach 1/255), i.e. the ellipse q(d) <= level = -2 min_power.
// Margins keep this a superset of what the compositor's float arithmetic
// touches; degenerate conics keep the whole rect.
struct EllipseReach {
  double a, inv_a, b, det, level, y_reach, dy_left;
  bool exact;  // false: use the rect's columns
};

EllipseReach ellipse_reach(const Splat& s) {
  EllipseReach e{s.a, 1.0 / double(s.a), s.b, 0.0, 0.0, 0.0, 0.0, false};
  const double c = s.c;
  e.det = e.a * c - e.b * e.b;
  e.level = -2.0 * double(s.min_power) * (1.0 + 1e-3) + 1e-3;
  const bool narrow = s.rect.u0 / kTile == s.rect.u1 / kTile;  // one column: nothing to cull
  if (narrow || !(e.det > 0.0 && e.a > 0.0 && c > 0.0 && e.level > 0.0)) return e;
  e.y_reach = std::sqrt(e.level * e.a / e.det);
  // Over a band of rows the ellipse's left edge is convex in dy with its minimum at the
  // leftmost point, dy = b x_reach / c; the right edge mirrors it.
  e.dy_left = e.b * std::sqrt(e.level * c / e.det) / c;
  e.exact = true;
  return e;
}

// Tile columns of tile row ty, packed as tx0 | tx1 << 16 (tx0 > tx1: none).
uint32_t tile_columns(const Splat& s, const EllipseReach& e, int ty) {
  const Rect& r = s.rect;
  const auto pack = [](int tx0, int tx1) { return uint32_t(tx0) | (uint32_t(tx1) << 16); };
  if (!e.exact) return pack(r.u0 / kTile, r.u1 / kTile);
  const double y0 = std::max(double(std::max(ty * kTile, r.v0)) + 0.5 - double(s.my), -e.y_reach);
  const double y1 = std::min(double(std::min(ty * kTile + kTile - 1, r.v1)) + 0.5 - double(s.my), e.y_reach);
  if (y0 > y1) return pack(1, 0);
  const auto edge = [&](double dy, double side) {
    return (-e.b * dy + side * std::sqrt(std::max(0.0, e.a * e.level - e.det * dy * dy))) * e.inv_a;
  };
  const double first = std::ceil(double(s.mx) + edge(std::clamp(e.dy_left, y0, y1), -1.0) - 0.5 - 1e-2);
  const double last = std::floor(double(s.mx) + edge(std::clamp(-e.dy_left, y0, y1), 1.0) - 0.5 + 1e-2);
  const int u0 = int(std::max(double(r.u0), first)), u1 = int(std::min(double(r.u1), last));
  return u0 > u1 ? pack(1, 0) : pack(u0 / kTile, u1 / kTile);
}

#if defined(__AVX512F__)
// tile_columns of up to 8 tile rows (ty .. ty + rows - 1) at once, one double lane per row:
// the same operations in the same order, so the same spans bit for bit, without the scalar
// version's per-row branches and square-root latency chains.
void tile_columns_x8(const Splat& s, const EllipseReach& e, int ty, int rows, uint32_t* out) {
  const Rect& r = s.rect;
  const __mmask8 lanes = __mmask8((1u << rows) - 1u);
  const __m256i tyv = _mm256_add_epi32(_mm256_set1_epi32(ty), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
  const __m256i top = _mm256_slli_epi32(tyv, 4);  // ty * kTile
  const __m256i bottom = _mm256_add_epi32(top, _mm256_set1_epi32(kTile - 1));
  const __m512d row_lo = _mm512_cvtepi32_pd(_mm256_max_epi32(top, _mm256_set1_epi32(r.v0)));
  const __m512d row_hi = _mm512_cvtepi32_pd(_mm256_min_epi32(bottom, _mm256_set1_epi32(r.v1)));
  const __m512d half = _mm512_set1_pd(0.5), my = _mm512_set1_pd(double(s.my));
  const __m512d reach = _mm512_set1_pd(e.y_reach);
  const __m512d y0 = _mm512_max_pd(_mm512_sub_pd(_mm512_add_pd(row_lo, half), my), _mm512_set1_pd(-e.y_reach));
  const __m512d y1 = _mm512_min_pd(_mm512_sub_pd(_mm512_add_pd(row_hi, half), my), reach);
  const __m512d neg_b = _mm512_set1_pd(-e.b), det = _mm512_set1_pd(e.det), inv_a = _mm512_set1_pd(e.inv_a);
  const __m512d a_level = _mm512_set1_pd(e.a * e.level), mx = _mm512_set1_pd(double(s.mx));
  const auto root = [&](__m512d dy) {
    const __m512d det_dy2 = _mm512_mul_pd(_mm512_mul_pd(det, dy), dy);
    return _mm512_sqrt_pd(_mm512_max_pd(_mm512_sub_pd(a_level, det_dy2), _mm512_setzero_pd()));
  };
  const __m512d dl = _mm512_min_pd(_mm512_max_pd(_mm512_set1_pd(e.dy_left), y0), y1);
  const __m512d dr = _mm512_min_pd(_mm512_max_pd(_mm512_set1_pd(-e.dy_left), y0), y1);
  const __m512d left = _mm512_mul_pd(_mm512_sub_pd(_mm512_mul_pd(neg_b, dl), root(dl)), inv_a);
  const __m512d right = _mm512_mul_pd(_mm512_add_pd(_mm512_mul_pd(neg_b, dr), root(dr)), inv_a);
  const __m512d first = _mm512_roundscale_pd(
      _mm512_sub_pd(_mm512_sub_pd(_mm512_add_pd(mx, left), half), _mm512_set1_pd(1e-2)), _MM_FROUND_TO_POS_INF);
  const __m512d last = _mm512_roundscale_pd(
      _mm512_add_pd(_mm512_sub_pd(_mm512_add_pd(mx, right), half), _mm512_set1_pd(1e-2)), _MM_FROUND_TO_NEG_INF);
  const __m256i u0 = _mm512_cvttpd_epi32(_mm512_max_pd(_mm512_set1_pd(double(r.u0)), first));
  const __m256i u1 = _mm512_cvttpd_epi32(_mm512_min_pd(_mm512_set1_pd(double(r.u1)), last));
  const __mmask8 none = _mm512_cmp_pd_mask(y0, y1, _CMP_GT_OQ) | _mm256_cmpgt_epi32_mask(u0, u1);
  const __m256i packed = _mm256_or_si256(_mm256_srai_epi32(u0, 4), _mm256_slli_epi32(_mm256_srai_epi32(u1, 4), 16));
  _mm256_mask_storeu_epi32(out, lanes, _mm256_mask_blend_epi32(none, packed, _mm256_set1_epi32(1)));
}
#endif

// Appends a Gaussian's tile rows (ty0 | ty1 << 16) and each row's columns to spans.
void append_spans(const Splat& s, std::vector<uint32_t>& spans) {
  const EllipseReach e = ellipse_reach(s);
  const int ty0 = s.rect.v0 / kTile, ty1 = s.rect.v1 / kTile;
  const size_t at = spans.size();
  spans.resize(at + 1 + size_t(std::max(0, ty1 - ty0 + 1)));
  uint32_t* out = &spans[at];
  *out++ = uint32_t(ty0) | (uint32_t(ty1) << 16);
#if defined(__AVX512F__)
  if (e.exact) {
    for (int ty = ty0; ty <= ty1; ty += 8) tile_columns_x8(s, e, ty, std::min(8, ty1 - ty + 1), out + (ty - ty0));
    return;
  }
#endif
  for (int ty = ty0; ty <= ty1; ++ty) *out++ = tile_columns(s, e, ty);
}

}  // namespace
}  // namespace stgs::splat
