// The backward's AVX-512 and AVX2 tile kernels (internal; included by backward.cpp, whose portable kernel
// they mirror): a tile row is one 16-lane register, or two 8-lane ones, and each list entry is one generic
// lambda instantiated for a trainable Gaussian and for a kept one, whose compositing is only undone.
#pragma once

#include <algorithm>
#include <cstdint>
#include <type_traits>

#if defined(__AVX512F__)
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#endif

#include "splat.h"
#include "splat_avx2.h"
#include "splat_avx512.h"

#if defined(__AVX512F__) || (defined(__AVX2__) && defined(__FMA__))
namespace stgs::splat {
namespace {

// Walks a tile's list back to front from its last walked entry (max_last), prefetching ahead: a trainable
// Gaussian's entry as entry(k, id, std::true_type), a kept one's (ctx.frozen), which is only undone, as
// entry(k, id, std::false_type).
template <class Entry>
inline void walk_list(const RasterCtx& ctx, int tile, int32_t max_last, const Entry& entry) {
  const int64_t begin = ctx.tile_start[tile];
  for (int32_t k = max_last - 1; k >= 0; --k) {
    if (k >= kPrefetch) prefetch_splat(ctx, begin + k - kPrefetch);
    const int32_t id = ctx.ids[begin + k];
    if (id >= ctx.frozen)
      entry(k, id, std::true_type{});
    else
      entry(k, id, std::false_type{});
  }
}

#if defined(__AVX512F__)
inline float hsum(__m512 v) { return _mm512_reduce_add_ps(v); }
#elif defined(__AVX2__) && defined(__FMA__)
inline float hsum(__m256 v) {
  const __m128 four = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  const __m128 two = _mm_add_ps(four, _mm_movehl_ps(four, four));
  return _mm_cvtss_f32(_mm_add_ss(two, _mm_movehdup_ps(two)));
}
#endif

// Adds one trainable entry's nine sums (per lane, reduced by hsum) to its row of grads.
template <class V>
inline void add_sums(const RasterCtx& ctx, float* grads, int32_t id, V gmx, V gmy, V ga, V gb, V gc, V go, V gr,
                     V gg, V gbl) {
  float* o = &grads[int64_t(id - ctx.frozen) * kGradStride];
  o[0] += hsum(gmx); o[1] += hsum(gmy);
  o[2] += hsum(ga); o[3] += hsum(gb); o[4] += hsum(gc);
  o[5] += hsum(go);
  o[6] += hsum(gr); o[7] += hsum(gg); o[8] += hsum(gbl);
}

#if defined(__AVX512F__)

void backward_tile_avx512(const RasterCtx& ctx, int tile, const float* bg, const float* grad_out,
                          float* grads, double* grad_bg) {
  const TileBox box = tile_box(ctx, tile);
  __m512 trans[kTile], ar[kTile], ag[kTile], ab[kTile], dr[kTile], dg[kTile], db[kTile];
  __m512i last[kTile];
  int32_t max_last = 0;
  for (int v = 0; v < kTile; ++v) {
    alignas(64) float t[kTile], r[kTile], g[kTile], b[kTile];
    alignas(64) int32_t l[kTile];
    max_last = std::max(max_last, load_tile_row(ctx, box, v, grad_out, t, l, r, g, b, grad_bg));
    trans[v] = _mm512_load_ps(t);
    last[v] = _mm512_load_si512(l);
    dr[v] = _mm512_load_ps(r);
    dg[v] = _mm512_load_ps(g);
    db[v] = _mm512_load_ps(b);
    ar[v] = _mm512_mul_ps(trans[v], _mm512_set1_ps(bg[0]));
    ag[v] = _mm512_mul_ps(trans[v], _mm512_set1_ps(bg[1]));
    ab[v] = _mm512_mul_ps(trans[v], _mm512_set1_ps(bg[2]));
  }
  const __m512 px = pixel_centres(box.x0);
  // One list entry; a kept Gaussian's (not trainable) compositing is only undone.
  const auto entry = [&](int32_t k, int32_t g, auto trainable_tag) {
    constexpr bool trainable = decltype(trainable_tag)::value;
    const Splat& s = ctx.splats[g];
    const Rect& r = s.rect;
    const SplatVec sv(s);
    const __mmask16 inside = span_mask(box.x0, r.u0, r.u1);
    const __m512i rank = _mm512_set1_epi32(k);
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    __m512 gmx = _mm512_setzero_ps(), gmy = gmx, ga = gmx, gb = gmx, gc = gmx, go = gmx;
    __m512 gr = gmx, gg = gmx, gbl = gmx;
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      // Pixels whose compositing reached this Gaussian (rank < last) inside its span.
      const __mmask16 reached = _mm512_mask_cmp_epi32_mask(inside, rank, last[row], _MM_CMPINT_LT);
      if (!reached) continue;
      const float dy = float(v) + 0.5f - s.my;
      const RowEval e = eval_row(sv, px, row_power(sv, px, dy), inside);
      const __mmask16 took = _mm512_mask_cmp_ps_mask(reached, e.alpha, sv.amin, _CMP_GE_OQ);
      if (!took) continue;
      const __m512 inv = _mm512_div_ps(sv.one, _mm512_sub_ps(sv.one, e.alpha));
      const __m512 t_before = _mm512_mask_mul_ps(trans[row], took, trans[row], inv);
      const __m512 w = _mm512_maskz_mul_ps(took, e.alpha, t_before);
      if constexpr (trainable) {
        gr = _mm512_fmadd_ps(w, dr[row], gr);
        gg = _mm512_fmadd_ps(w, dg[row], gg);
        gbl = _mm512_fmadd_ps(w, db[row], gbl);
        __m512 g_alpha = _mm512_mul_ps(dr[row], _mm512_fmsub_ps(sv.r, t_before, _mm512_mul_ps(ar[row], inv)));
        g_alpha = _mm512_fmadd_ps(dg[row], _mm512_fmsub_ps(sv.g, t_before, _mm512_mul_ps(ag[row], inv)), g_alpha);
        g_alpha = _mm512_fmadd_ps(db[row], _mm512_fmsub_ps(sv.bl, t_before, _mm512_mul_ps(ab[row], inv)), g_alpha);
        g_alpha = _mm512_maskz_mov_ps(took, g_alpha);
        // No gradient through the 0.99 clamp, nor through the power clip at 0.
        const __m512 raw_alpha = _mm512_mul_ps(sv.o, e.falloff);
        const __mmask16 open = _mm512_mask_cmp_ps_mask(took, raw_alpha, sv.amax, _CMP_LE_OQ);
        go = _mm512_mask3_fmadd_ps(g_alpha, e.falloff, go, open);
        const __mmask16 flows = _mm512_mask_cmp_ps_mask(open, e.power, _mm512_setzero_ps(), _CMP_LE_OQ);
        const __m512 g_power = _mm512_maskz_mul_ps(flows, g_alpha, raw_alpha);
        const __m512 dyv = _mm512_set1_ps(dy);
        gmx = _mm512_fmadd_ps(g_power, _mm512_fmadd_ps(sv.a, e.dx, _mm512_mul_ps(_mm512_set1_ps(s.b), dyv)), gmx);
        gmy = _mm512_fmadd_ps(g_power, _mm512_fmadd_ps(_mm512_set1_ps(s.b), e.dx, _mm512_mul_ps(sv.c, dyv)), gmy);
        ga = _mm512_fmadd_ps(g_power, _mm512_mul_ps(sv.half, _mm512_mul_ps(e.dx, e.dx)), ga);
        gb = _mm512_fnmadd_ps(g_power, _mm512_mul_ps(e.dx, dyv), gb);
        gc = _mm512_fmadd_ps(g_power, _mm512_set1_ps(-0.5f * dy * dy), gc);
      }
      ar[row] = _mm512_fmadd_ps(sv.r, w, ar[row]);
      ag[row] = _mm512_fmadd_ps(sv.g, w, ag[row]);
      ab[row] = _mm512_fmadd_ps(sv.bl, w, ab[row]);
      trans[row] = t_before;
    }
    if constexpr (trainable) add_sums(ctx, grads, g, gmx, gmy, ga, gb, gc, go, gr, gg, gbl);
  };
  walk_list(ctx, tile, max_last, entry);
}

#elif defined(__AVX2__) && defined(__FMA__)
// backward_tile_avx512 on two 8-lane halves per tile row, mirroring render_tile_tracked_avx2.
void backward_tile_avx2(const RasterCtx& ctx, int tile, const float* bg, const float* grad_out,
                        float* grads, double* grad_bg) {
  const TileBox box = tile_box(ctx, tile);
  __m256 trans[kTile][2], ar[kTile][2], ag[kTile][2], ab[kTile][2], dr[kTile][2], dg[kTile][2], db[kTile][2];
  __m256i last[kTile][2];
  int32_t max_last = 0;
  for (int v = 0; v < kTile; ++v) {
    alignas(32) float t[kTile], r[kTile], g[kTile], b[kTile];
    alignas(32) int32_t l[kTile];
    max_last = std::max(max_last, load_tile_row(ctx, box, v, grad_out, t, l, r, g, b, grad_bg));
    for (int h = 0; h < 2; ++h) {
      trans[v][h] = _mm256_load_ps(t + 8 * h);
      last[v][h] = _mm256_load_si256(reinterpret_cast<const __m256i*>(l + 8 * h));
      dr[v][h] = _mm256_load_ps(r + 8 * h);
      dg[v][h] = _mm256_load_ps(g + 8 * h);
      db[v][h] = _mm256_load_ps(b + 8 * h);
      ar[v][h] = _mm256_mul_ps(trans[v][h], _mm256_set1_ps(bg[0]));
      ag[v][h] = _mm256_mul_ps(trans[v][h], _mm256_set1_ps(bg[1]));
      ab[v][h] = _mm256_mul_ps(trans[v][h], _mm256_set1_ps(bg[2]));
    }
  }
  const __m256 px[2] = {pixel_centres8(box.x0, 0), pixel_centres8(box.x0, 1)};
  // One list entry; a kept Gaussian's (not trainable) compositing is only undone.
  const auto entry = [&](int32_t k, int32_t id, auto trainable_tag) {
    constexpr bool trainable = decltype(trainable_tag)::value;
    const Splat& s = ctx.splats[id];
    const Rect& r = s.rect;
    const SplatVec8 sv(s);
    const __m256 inside[2] = {span_mask8(box.x0, r.u0, r.u1, 0), span_mask8(box.x0, r.u0, r.u1, 1)};
    const __m256i rank = _mm256_set1_epi32(k);
    const __m256 vb = _mm256_set1_ps(s.b);
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    __m256 gmx = _mm256_setzero_ps(), gmy = gmx, ga = gmx, gb = gmx, gc = gmx, go = gmx;
    __m256 gr = gmx, gg = gmx, gbl = gmx;
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      const float dy = float(v) + 0.5f - s.my;
      const __m256 dyv = _mm256_set1_ps(dy);
      for (int h = 0; h < 2; ++h) {
        // Pixels whose compositing reached this Gaussian (rank < last) inside its span.
        const __m256 reached = _mm256_and_ps(inside[h], _mm256_castsi256_ps(_mm256_cmpgt_epi32(last[row][h], rank)));
        if (!any_lane(reached)) continue;
        const RowEval8 e = eval_row8(sv, px[h], dy, inside[h]);
        const __m256 took = _mm256_and_ps(reached, _mm256_cmp_ps(e.alpha, sv.amin, _CMP_GE_OQ));
        if (!any_lane(took)) continue;
        const __m256 inv = _mm256_div_ps(sv.one, _mm256_sub_ps(sv.one, e.alpha));
        const __m256 t_before = _mm256_blendv_ps(trans[row][h], _mm256_mul_ps(trans[row][h], inv), took);
        const __m256 w = _mm256_and_ps(took, _mm256_mul_ps(e.alpha, t_before));
        if constexpr (trainable) {
          gr = _mm256_fmadd_ps(w, dr[row][h], gr);
          gg = _mm256_fmadd_ps(w, dg[row][h], gg);
          gbl = _mm256_fmadd_ps(w, db[row][h], gbl);
          __m256 g_alpha = _mm256_mul_ps(dr[row][h], _mm256_fmsub_ps(sv.r, t_before, _mm256_mul_ps(ar[row][h], inv)));
          g_alpha = _mm256_fmadd_ps(dg[row][h], _mm256_fmsub_ps(sv.g, t_before, _mm256_mul_ps(ag[row][h], inv)),
                                    g_alpha);
          g_alpha = _mm256_fmadd_ps(db[row][h], _mm256_fmsub_ps(sv.bl, t_before, _mm256_mul_ps(ab[row][h], inv)),
                                    g_alpha);
          g_alpha = _mm256_and_ps(took, g_alpha);
          // No gradient through the 0.99 clamp, nor through the power clip at 0.
          const __m256 raw_alpha = _mm256_mul_ps(sv.o, e.falloff);
          const __m256 open = _mm256_and_ps(took, _mm256_cmp_ps(raw_alpha, sv.amax, _CMP_LE_OQ));
          go = _mm256_blendv_ps(go, _mm256_fmadd_ps(g_alpha, e.falloff, go), open);
          const __m256 flows = _mm256_and_ps(open, _mm256_cmp_ps(e.power, _mm256_setzero_ps(), _CMP_LE_OQ));
          const __m256 g_power = _mm256_and_ps(flows, _mm256_mul_ps(g_alpha, raw_alpha));
          gmx = _mm256_fmadd_ps(g_power, _mm256_fmadd_ps(sv.a, e.dx, _mm256_mul_ps(vb, dyv)), gmx);
          gmy = _mm256_fmadd_ps(g_power, _mm256_fmadd_ps(vb, e.dx, _mm256_mul_ps(sv.c, dyv)), gmy);
          ga = _mm256_fmadd_ps(g_power, _mm256_mul_ps(sv.half, _mm256_mul_ps(e.dx, e.dx)), ga);
          gb = _mm256_fnmadd_ps(g_power, _mm256_mul_ps(e.dx, dyv), gb);
          gc = _mm256_fmadd_ps(g_power, _mm256_set1_ps(-0.5f * dy * dy), gc);
        }
        ar[row][h] = _mm256_fmadd_ps(sv.r, w, ar[row][h]);
        ag[row][h] = _mm256_fmadd_ps(sv.g, w, ag[row][h]);
        ab[row][h] = _mm256_fmadd_ps(sv.bl, w, ab[row][h]);
        trans[row][h] = t_before;
      }
    }
    if constexpr (trainable) add_sums(ctx, grads, id, gmx, gmy, ga, gb, gc, go, gr, gg, gbl);
  };
  walk_list(ctx, tile, max_last, entry);
}

#endif  // __AVX512F__

}  // namespace
}  // namespace stgs::splat
#endif
