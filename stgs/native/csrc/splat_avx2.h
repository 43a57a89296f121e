// AVX2 pieces for CPUs with AVX2 and FMA but no AVX-512 (internal; included by forward.cpp and
// backward.cpp). A tile row of 16 pixels is two 8-lane registers. The inference compositor has the
// AVX-512 inference kernel's arithmetic (opacity folded into the exponent, one 2^x per pixel, the same
// polynomial), so the two agree to the last bit or two; the tracked forward that training uses and its
// backward (backward.cpp) share SplatVec8 and eval_row8, the AVX-512 training kernels' row arithmetic,
// so the backward recomputes the forward's alphas bit for bit.
#pragma once

#if defined(__AVX2__) && defined(__FMA__) && !defined(__AVX512F__)
#include <immintrin.h>

#include "splat.h"

namespace stgs::splat {

// 2^x on 8 lanes: x = n + f, n the nearest integer (f in [-0.5, 0.5], exact), 2^f by kExp2Poly
// (splat.h), as the AVX-512 kernel. x is clamped at -127, where the exponent field is 0 and the
// result 0 (AVX2 has no vscalefps); NaN passes the clamp (the second operand of max) and stays NaN.
inline __m256 exp2_v8(__m256 x) {
  x = _mm256_max_ps(_mm256_set1_ps(-127.0f), x);
  const __m256 n = _mm256_round_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const __m256 f = _mm256_sub_ps(x, n);
  __m256 p = _mm256_set1_ps(kExp2Poly[0]);
  for (int i = 1; i < 6; ++i) p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(kExp2Poly[i]));
  const __m256i bits = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
  return _mm256_mul_ps(p, _mm256_castsi256_ps(bits));
}

// One Gaussian's alpha along the rows of one tile: the column-only terms once, then two FMAs and a
// 2^x per half row.
struct InferRows8 {
  __m256 quad_x[2], cross[2], inside[2];
  __m256 pc, log2_o, amax;
  InferRows8(const Splat& s, int x0)
      : pc(_mm256_set1_ps(-0.5f * kLog2e * s.c)), log2_o(_mm256_set1_ps(s.log2_o)), amax(_mm256_set1_ps(kAlphaMax)) {
    const __m256 lane = _mm256_setr_ps(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256 lo = _mm256_set1_ps(float(s.rect.u0 - x0)), hi = _mm256_set1_ps(float(s.rect.u1 - x0));
    const __m256 pa = _mm256_set1_ps(-0.5f * kLog2e * s.a), pb2 = _mm256_set1_ps(-kLog2e * s.b);
    for (int h = 0; h < 2; ++h) {
      const __m256 col = _mm256_add_ps(lane, _mm256_set1_ps(float(8 * h)));
      const __m256 dx = _mm256_sub_ps(_mm256_add_ps(col, _mm256_set1_ps(float(x0) + 0.5f)), _mm256_set1_ps(s.mx));
      quad_x[h] = _mm256_fmadd_ps(_mm256_mul_ps(pa, dx), dx, log2_o);
      cross[h] = _mm256_mul_ps(pb2, dx);
      inside[h] = _mm256_and_ps(_mm256_cmp_ps(col, lo, _CMP_GE_OQ), _mm256_cmp_ps(col, hi, _CMP_LE_OQ));
    }
  }
  __m256 alpha(int h, __m256 dyv) const {
    const __m256 exponent = _mm256_fmadd_ps(_mm256_fmadd_ps(pc, dyv, cross[h]), dyv, quad_x[h]);
    return _mm256_and_ps(inside[h], _mm256_min_ps(exp2_v8(_mm256_min_ps(exponent, log2_o)), amax));
  }
};

inline bool any_lane(__m256 mask) { return !_mm256_testz_ps(mask, mask); }

// Writes a composited tile: colour sums over the background into out and, with `last` (then trans_final and
// n_contrib too), each pixel's final transmittance and last contributor.
inline void store_tile_avx2(const RasterCtx& ctx, const TileBox& box, const float* bg, const __m256 (*trans)[2],
                            const __m256 (*ar)[2], const __m256 (*ag)[2], const __m256 (*ab)[2],
                            const __m256i (*last)[2], float* out, float* trans_final, int32_t* n_contrib) {
  alignas(32) float tr[kTile], rr[kTile], gg[kTile], bb[kTile];
  alignas(32) int32_t ll[kTile];
  for (int v = 0; v < box.h; ++v) {
    for (int h = 0; h < 2; ++h) {
      _mm256_store_ps(tr + 8 * h, trans[v][h]);
      _mm256_store_ps(rr + 8 * h, ar[v][h]);
      _mm256_store_ps(gg + 8 * h, ag[v][h]);
      _mm256_store_ps(bb + 8 * h, ab[v][h]);
      if (last != nullptr) _mm256_store_si256(reinterpret_cast<__m256i*>(ll + 8 * h), last[v][h]);
    }
    for (int u = 0; u < box.w; ++u) {
      const int64_t pix = int64_t(box.y0 + v) * ctx.width + (box.x0 + u);
      out[3 * pix] = rr[u] + tr[u] * bg[0];
      out[3 * pix + 1] = gg[u] + tr[u] * bg[1];
      out[3 * pix + 2] = bb[u] + tr[u] * bg[2];
      if (last != nullptr) {
        trans_final[pix] = tr[u];
        n_contrib[pix] = ll[u];
      }
    }
  }
}

// The per-Gaussian constants of the training kernels (splat_avx512.h's SplatVec on 8 lanes): row powers
// in log2 units through the pre-scaled conic pa, pb2, pc; the gradients keep the natural-unit a, c.
struct SplatVec8 {
  __m256 mx, a, c, o, r, g, bl, amin, amax, tmin, one, half, pa, pb2, pc;
  explicit SplatVec8(const Splat& s)
      : mx(_mm256_set1_ps(s.mx)), a(_mm256_set1_ps(s.a)), c(_mm256_set1_ps(s.c)), o(_mm256_set1_ps(s.o)),
        r(_mm256_set1_ps(s.r)), g(_mm256_set1_ps(s.g)), bl(_mm256_set1_ps(s.bl)),
        amin(_mm256_set1_ps(kAlphaMin)), amax(_mm256_set1_ps(kAlphaMax)), tmin(_mm256_set1_ps(kTMin)),
        one(_mm256_set1_ps(1.0f)), half(_mm256_set1_ps(-0.5f)), pa(_mm256_set1_ps(-0.5f * kLog2e * s.a)),
        pb2(_mm256_set1_ps(-kLog2e * s.b)), pc(_mm256_set1_ps(-0.5f * kLog2e * s.c)) {}
};

// Pixel centres of half h (0: columns 0-7, 1: 8-15) of a tile row starting at x0.
inline __m256 pixel_centres8(int x0, int h) {
  return _mm256_add_ps(_mm256_set1_ps(float(x0 + 8 * h) + 0.5f), _mm256_setr_ps(0, 1, 2, 3, 4, 5, 6, 7));
}

// All-ones lanes of half h for the columns u0 - x0 ... u1 - x0 of a tile row.
inline __m256 span_mask8(int x0, int u0, int u1, int h) {
  const __m256 col = _mm256_setr_ps(float(8 * h), float(8 * h + 1), float(8 * h + 2), float(8 * h + 3),
                                    float(8 * h + 4), float(8 * h + 5), float(8 * h + 6), float(8 * h + 7));
  return _mm256_and_ps(_mm256_cmp_ps(col, _mm256_set1_ps(float(u0 - x0)), _CMP_GE_OQ),
                       _mm256_cmp_ps(col, _mm256_set1_ps(float(u1 - x0)), _CMP_LE_OQ));
}

// Power (-0.5 q log2 e, unclipped), falloff 2^min(power, 0) and alpha along half a row, as eval_row.
struct RowEval8 {
  __m256 dx, power, falloff, alpha;
};

inline RowEval8 eval_row8(const SplatVec8& v, __m256 px, float dy, __m256 inside) {
  RowEval8 e;
  e.dx = _mm256_sub_ps(px, v.mx);
  const __m256 dyv = _mm256_set1_ps(dy);
  const __m256 cdy2 = _mm256_mul_ps(_mm256_mul_ps(v.pc, dyv), dyv);
  e.power = _mm256_fmadd_ps(_mm256_mul_ps(v.pa, e.dx), e.dx, _mm256_fmadd_ps(_mm256_mul_ps(v.pb2, dyv), e.dx, cdy2));
  e.falloff = exp2_v8(_mm256_min_ps(e.power, _mm256_setzero_ps()));
  e.alpha = _mm256_and_ps(inside, _mm256_min_ps(_mm256_mul_ps(v.o, e.falloff), v.amax));
  return e;
}

// The tracked forward of one tile (splat_avx512.h's render_tile_avx512<true> on two halves per row):
// the image, and each pixel's final transmittance and last contributor for backward_tile_avx2.
inline void render_tile_tracked_avx2(const RasterCtx& ctx, int tile, const float* bg, float* out,
                                     float* trans_final, int32_t* n_contrib) {
  const TileBox box = tile_box(ctx, tile);
  __m256 trans[kTile][2], ar[kTile][2], ag[kTile][2], ab[kTile][2], live[kTile][2];
  __m256i last[kTile][2];
  const __m256 px[2] = {pixel_centres8(box.x0, 0), pixel_centres8(box.x0, 1)};
  const __m256 width_mask[2] = {span_mask8(0, 0, box.w - 1, 0), span_mask8(0, 0, box.w - 1, 1)};
  int live_rows = 0;
  for (int v = 0; v < kTile; ++v) {
    for (int h = 0; h < 2; ++h) {
      trans[v][h] = _mm256_set1_ps(1.0f);
      ar[v][h] = ag[v][h] = ab[v][h] = _mm256_setzero_ps();
      last[v][h] = _mm256_setzero_si256();
      live[v][h] = v < box.h ? width_mask[h] : _mm256_setzero_ps();
    }
    live_rows += v < box.h;
  }
  const int64_t begin = ctx.tile_start[tile], end = ctx.tile_start[tile + 1];
  for (int64_t k = begin; k < end; ++k) {
    if ((k - begin) % kScanEvery == 0 && live_rows == 0) break;
    if (k + kPrefetch < end) prefetch_splat(ctx, k + kPrefetch);
    const Splat& s = ctx.splats[ctx.ids[k]];
    const Rect& r = s.rect;
    const SplatVec8 sv(s);
    const __m256 inside[2] = {span_mask8(box.x0, r.u0, r.u1, 0), span_mask8(box.x0, r.u0, r.u1, 1)};
    const __m256i rank = _mm256_set1_epi32(int32_t(k - begin + 1));
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      const float dy = float(v) + 0.5f - s.my;
      for (int h = 0; h < 2; ++h) {
        const __m256 lv = _mm256_and_ps(live[row][h], inside[h]);
        if (!any_lane(lv)) continue;
        const RowEval8 e = eval_row8(sv, px[h], dy, inside[h]);
        const __m256 take = _mm256_and_ps(lv, _mm256_cmp_ps(e.alpha, sv.amin, _CMP_GE_OQ));
        const __m256 next = _mm256_mul_ps(trans[row][h], _mm256_sub_ps(sv.one, e.alpha));
        const __m256 stop = _mm256_and_ps(take, _mm256_cmp_ps(next, sv.tmin, _CMP_LT_OQ));
        const __m256 add = _mm256_andnot_ps(stop, take);
        const __m256 w = _mm256_and_ps(add, _mm256_mul_ps(e.alpha, trans[row][h]));
        ar[row][h] = _mm256_fmadd_ps(sv.r, w, ar[row][h]);
        ag[row][h] = _mm256_fmadd_ps(sv.g, w, ag[row][h]);
        ab[row][h] = _mm256_fmadd_ps(sv.bl, w, ab[row][h]);
        trans[row][h] = _mm256_blendv_ps(trans[row][h], next, add);
        last[row][h] = _mm256_blendv_epi8(last[row][h], rank, _mm256_castps_si256(add));
        live[row][h] = _mm256_andnot_ps(stop, live[row][h]);
      }
    }
    if ((k - begin) % kScanEvery == kScanEvery - 1) {
      live_rows = 0;
      for (int v = 0; v < kTile; ++v) live_rows += any_lane(_mm256_or_ps(live[v][0], live[v][1]));
    }
  }
  store_tile_avx2(ctx, box, bg, trans, ar, ag, ab, last, out, trans_final, n_contrib);
}

inline void render_tile_infer_avx2(const RasterCtx& ctx, int tile, const float* bg, float* out) {
  const TileBox box = tile_box(ctx, tile);
  __m256 trans[kTile][2], ar[kTile][2], ag[kTile][2], ab[kTile][2], live[kTile][2];
  const __m256 lane = _mm256_setr_ps(0, 1, 2, 3, 4, 5, 6, 7);
  int live_rows = 0;
  for (int v = 0; v < kTile; ++v) {
    for (int h = 0; h < 2; ++h) {
      trans[v][h] = _mm256_set1_ps(1.0f);
      ar[v][h] = ag[v][h] = ab[v][h] = _mm256_setzero_ps();
      const __m256 in_width = _mm256_cmp_ps(_mm256_add_ps(lane, _mm256_set1_ps(float(8 * h))),
                                            _mm256_set1_ps(float(box.w)), _CMP_LT_OQ);
      live[v][h] = v < box.h ? in_width : _mm256_setzero_ps();
    }
    live_rows += v < box.h;
  }
  const __m256 amin = _mm256_set1_ps(kAlphaMin), tmin = _mm256_set1_ps(kTMin);
  const int64_t begin = ctx.tile_start[tile], end = ctx.tile_start[tile + 1];
  for (int64_t k = begin; k < end; ++k) {
    if ((k - begin) % kScanEvery == 0 && live_rows == 0) break;
    if (k + kPrefetch < end) prefetch_splat(ctx, k + kPrefetch);
    const Splat& s = ctx.splats[ctx.ids[k]];
    const int v0 = std::max(s.rect.v0, box.y0), v1 = std::min(s.rect.v1, box.y0 + box.h - 1);
    const InferRows8 ir(s, box.x0);
    const __m256 cr = _mm256_set1_ps(s.r), cg = _mm256_set1_ps(s.g), cb = _mm256_set1_ps(s.bl);
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      const __m256 lv0 = _mm256_and_ps(live[row][0], ir.inside[0]);
      const __m256 lv1 = _mm256_and_ps(live[row][1], ir.inside[1]);
      if (!any_lane(_mm256_or_ps(lv0, lv1))) continue;
      const __m256 dyv = _mm256_set1_ps(float(v) + 0.5f - s.my);
      for (int h = 0; h < 2; ++h) {
        const __m256 lv = h == 0 ? lv0 : lv1;
        const __m256 alpha = ir.alpha(h, dyv);
        const __m256 take = _mm256_and_ps(lv, _mm256_cmp_ps(alpha, amin, _CMP_GE_OQ));
        const __m256 w = _mm256_mul_ps(alpha, trans[row][h]);
        const __m256 next = _mm256_sub_ps(trans[row][h], w);
        const __m256 stop = _mm256_and_ps(take, _mm256_cmp_ps(next, tmin, _CMP_LT_OQ));
        const __m256 add = _mm256_andnot_ps(stop, take);
        const __m256 wa = _mm256_and_ps(add, w);  // adding +0 leaves a pixel's sums as they were
        ar[row][h] = _mm256_fmadd_ps(cr, wa, ar[row][h]);
        ag[row][h] = _mm256_fmadd_ps(cg, wa, ag[row][h]);
        ab[row][h] = _mm256_fmadd_ps(cb, wa, ab[row][h]);
        trans[row][h] = _mm256_blendv_ps(trans[row][h], next, add);
        live[row][h] = _mm256_andnot_ps(stop, live[row][h]);
      }
    }
    if ((k - begin) % kScanEvery == kScanEvery - 1) {
      live_rows = 0;
      for (int v = 0; v < kTile; ++v) live_rows += any_lane(_mm256_or_ps(live[v][0], live[v][1]));
    }
  }
  store_tile_avx2(ctx, box, bg, trans, ar, ag, ab, nullptr, out, nullptr, nullptr);
}

}  // namespace stgs::splat
#endif  // AVX2 and FMA without AVX-512
