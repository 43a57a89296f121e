// Stage 3, forward: front-to-back compositing of each tile's list (docs/ARCHITECTURE.md's per-pixel
// loop), with the per-pixel bookkeeping (final transmittance, last contributor) the backward
// pass reads. Its torch twin is stgs.render.stages.composite_tiles. The AVX-512 kernels sit
// beside the portable one; AVX2 CPUs without AVX-512 take splat_avx2.h's kernels.

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#if defined(__AVX512F__)
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#endif

#include "splat.h"
#include "splat_avx2.h"
#include "splat_avx512.h"
#include "stgs_abi.h"

namespace stgs::splat {
namespace {

void render_tile(const RasterCtx& ctx, int tile, const float* bg, float* out, float* trans_final,
                 int32_t* n_contrib) {
  const TileBox box = tile_box(ctx, tile);
  TileState st;
  for (int p = 0; p < kTilePixels; ++p) {
    st.trans[p] = 1.0f;
    st.acc_r[p] = st.acc_g[p] = st.acc_b[p] = 0.0f;
    st.last[p] = 0;
    st.live[p] = (p % kTile < box.w && p / kTile < box.h) ? 1 : 0;
  }
  // row_live[v]: the row still has a compositing pixel; refreshed every kScanEvery Gaussians.
  bool row_live[kTile];
  for (int v = 0; v < kTile; ++v) row_live[v] = v < box.h;
  const int64_t begin = ctx.tile_start[tile], end = ctx.tile_start[tile + 1];
  alignas(64) float alpha[kTile], falloff[kTile], power[kTile];
  for (int64_t k = begin; k < end; ++k) {
    if ((k - begin) % kScanEvery == kScanEvery - 1 && !refresh_live_rows(st, row_live)) break;
    const int32_t g = ctx.ids[k];
    const Splat& s = ctx.splats[g];
    const Rect& r = s.rect;
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    const int32_t rank = int32_t(k - begin + 1);
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      if (!row_live[row]) continue;
      const float dy = float(v) + 0.5f - s.my;
      row_alpha(s, box.x0, dy, r.u0, r.u1, alpha, falloff, power);
      const TileState::Row px = st.row(row);
      float *trans = px.trans, *ar = px.r, *ag = px.g, *ab = px.b;
      int32_t *last = px.last, *live = px.live;
#pragma omp simd
      for (int i = 0; i < kTile; ++i) {
        const float a = alpha[i];
        const bool take = live[i] && a >= kAlphaMin;
        const float next = trans[i] * (1.0f - a);
        const bool stop = take && next < kTMin;
        const bool add = take && !stop;
        const float w = add ? a * trans[i] : 0.0f;
        ar[i] += s.r * w;
        ag[i] += s.g * w;
        ab[i] += s.bl * w;
        trans[i] = add ? next : trans[i];
        last[i] = add ? rank : last[i];
        live[i] = stop ? 0 : live[i];
      }
    }
  }
  for (int v = 0; v < box.h; ++v) {
    for (int u = 0; u < box.w; ++u) {
      const int p = v * kTile + u;
      const int64_t pix = int64_t(box.y0 + v) * ctx.width + (box.x0 + u);
      out[3 * pix] = st.acc_r[p] + st.trans[p] * bg[0];
      out[3 * pix + 1] = st.acc_g[p] + st.trans[p] * bg[1];
      out[3 * pix + 2] = st.acc_b[p] + st.trans[p] * bg[2];
      if (trans_final != nullptr) {
        trans_final[pix] = st.trans[p];
        n_contrib[pix] = st.last[p];
      }
    }
  }
}

#if defined(__AVX512F__)
// Alpha along tile rows for inference (no backward reads it): what depends only on the
// column is computed once per Gaussian, and the opacity is folded into the exponent,
// alpha = 2^min(power + log2 o, log2 o), so a row costs ~20 % fewer vector operations
// than eval_row. The float32 rounding order differs from eval_row's (and the reference's)
// by a few ulps; the tracked forward keeps eval_row, which its backward mirrors.
struct InferRows {
  __m512 quad_x;  // power + log2 o at dy = 0
  __m512 cross;   // the dx dy coefficient
  __m512 pc, log2_o, amax;
  InferRows(const Splat& s, __m512 px)
      : pc(_mm512_set1_ps(-0.5f * kLog2e * s.c)), log2_o(_mm512_set1_ps(s.log2_o)),
        amax(_mm512_set1_ps(kAlphaMax)) {
    const __m512 dx = _mm512_sub_ps(px, _mm512_set1_ps(s.mx));
    quad_x = _mm512_fmadd_ps(_mm512_mul_ps(_mm512_set1_ps(-0.5f * kLog2e * s.a), dx), dx, log2_o);
    cross = _mm512_mul_ps(_mm512_set1_ps(-kLog2e * s.b), dx);
  }
  __m512 alpha(float dy, __mmask16 inside) const {
    const __m512 dyv = _mm512_set1_ps(dy);
    const __m512 exponent = _mm512_fmadd_ps(_mm512_fmadd_ps(pc, dyv, cross), dyv, quad_x);
    return _mm512_maskz_min_ps(inside, exp2_v(_mm512_min_ps(exponent, log2_o)), amax);
  }
};

// kTrack: keep each pixel's final transmittance and last contributor for the backward pass.
template <bool kTrack>
void render_tile_avx512(const RasterCtx& ctx, int tile, const float* bg, float* out,
                        float* trans_final, int32_t* n_contrib) {
  const TileBox box = tile_box(ctx, tile);
  __m512 trans[kTile], ar[kTile], ag[kTile], ab[kTile];
  __m512i last[kTile];
  __mmask16 live[kTile];
  int live_rows = 0;
  const __mmask16 width_mask = __mmask16((1u << box.w) - 1u);
  for (int v = 0; v < kTile; ++v) {
    trans[v] = _mm512_set1_ps(1.0f);
    ar[v] = ag[v] = ab[v] = _mm512_setzero_ps();
    last[v] = _mm512_setzero_si512();
    live[v] = v < box.h ? width_mask : 0;
    live_rows += v < box.h;
  }
  const __m512 px = pixel_centres(box.x0);
  const int64_t begin = ctx.tile_start[tile], end = ctx.tile_start[tile + 1];
  for (int64_t k = begin; k < end; ++k) {
    if ((k - begin) % kScanEvery == 0 && live_rows == 0) break;
    if (k + kPrefetch < end) prefetch_splat(ctx, k + kPrefetch);
    const int32_t g = ctx.ids[k];
    const Splat& s = ctx.splats[g];
    const Rect& r = s.rect;
    const __mmask16 inside = span_mask(box.x0, r.u0, r.u1);
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    const __m512 amin = _mm512_set1_ps(kAlphaMin), tmin = _mm512_set1_ps(kTMin);
    const __m512 cr = _mm512_set1_ps(s.r), cg = _mm512_set1_ps(s.g), cb = _mm512_set1_ps(s.bl);
    if constexpr (kTrack) {
      const SplatVec sv(s);
      const __m512i rank = _mm512_set1_epi32(int32_t(k - begin + 1));
      for (int v = v0; v <= v1; ++v) {
        const int row = v - box.y0;
        const __mmask16 lv = live[row] & inside;
        if (!lv) continue;
        const float dy = float(v) + 0.5f - s.my;
        // Rows the ellipse misses are evaluated too: a test for them (power < min_power) cost more in
        // mispredicted branches than the evaluation it saved (A/B x0.96); alpha < 1/255 there anyway.
        const RowEval e = eval_row(sv, px, row_power(sv, px, dy), inside);
        const __mmask16 take = _mm512_mask_cmp_ps_mask(lv, e.alpha, amin, _CMP_GE_OQ);
        const __m512 next = _mm512_mul_ps(trans[row], _mm512_sub_ps(sv.one, e.alpha));
        const __mmask16 stop = _mm512_mask_cmp_ps_mask(take, next, tmin, _CMP_LT_OQ);
        const __mmask16 add = take & ~stop;
        const __m512 w = _mm512_maskz_mul_ps(add, e.alpha, trans[row]);
        ar[row] = _mm512_fmadd_ps(cr, w, ar[row]);
        ag[row] = _mm512_fmadd_ps(cg, w, ag[row]);
        ab[row] = _mm512_fmadd_ps(cb, w, ab[row]);
        trans[row] = _mm512_mask_mov_ps(trans[row], add, next);
        last[row] = _mm512_mask_mov_epi32(last[row], add, rank);
        live[row] &= ~stop;
      }
    } else {
      const InferRows ir(s, px);
      for (int v = v0; v <= v1; ++v) {
        const int row = v - box.y0;
        const __mmask16 lv = live[row] & inside;
        if (!lv) continue;
        const __m512 alpha = ir.alpha(float(v) + 0.5f - s.my, inside);
        const __mmask16 take = _mm512_mask_cmp_ps_mask(lv, alpha, amin, _CMP_GE_OQ);
        const __m512 w = _mm512_mul_ps(alpha, trans[row]);
        const __m512 next = _mm512_sub_ps(trans[row], w);
        const __mmask16 stop = _mm512_mask_cmp_ps_mask(take, next, tmin, _CMP_LT_OQ);
        const __mmask16 add = take & ~stop;
        ar[row] = _mm512_mask3_fmadd_ps(cr, w, ar[row], add);
        ag[row] = _mm512_mask3_fmadd_ps(cg, w, ag[row], add);
        ab[row] = _mm512_mask3_fmadd_ps(cb, w, ab[row], add);
        trans[row] = _mm512_mask_mov_ps(trans[row], add, next);
        live[row] &= ~stop;
      }
    }
    if ((k - begin) % kScanEvery == kScanEvery - 1) {
      live_rows = 0;
      for (int v = 0; v < kTile; ++v) live_rows += live[v] != 0;
    }
  }
  alignas(64) float tr[kTile], rr[kTile], gg[kTile], bb[kTile];
  alignas(64) int32_t ll[kTile];
  for (int v = 0; v < box.h; ++v) {
    _mm512_store_ps(tr, trans[v]);
    _mm512_store_ps(rr, ar[v]);
    _mm512_store_ps(gg, ag[v]);
    _mm512_store_ps(bb, ab[v]);
    _mm512_store_si512(ll, last[v]);
    for (int u = 0; u < box.w; ++u) {
      const int64_t pix = int64_t(box.y0 + v) * ctx.width + (box.x0 + u);
      out[3 * pix] = rr[u] + tr[u] * bg[0];
      out[3 * pix + 1] = gg[u] + tr[u] * bg[1];
      out[3 * pix + 2] = bb[u] + tr[u] * bg[2];
      if constexpr (kTrack) {
        trans_final[pix] = tr[u];
        n_contrib[pix] = ll[u];
      }
    }
  }
}

void render_tile_fast(const RasterCtx& ctx, int tile, const float* bg, float* out, float* trans_final,
                      int32_t* n_contrib) {
  if (trans_final != nullptr)
    render_tile_avx512<true>(ctx, tile, bg, out, trans_final, n_contrib);
  else
    render_tile_avx512<false>(ctx, tile, bg, out, nullptr, nullptr);
}

constexpr auto kRenderTile = render_tile_fast;
#elif defined(__AVX2__) && defined(__FMA__)
void render_tile_fast(const RasterCtx& ctx, int tile, const float* bg, float* out, float* trans_final,
                      int32_t* n_contrib) {
  if (trans_final != nullptr)
    render_tile_tracked_avx2(ctx, tile, bg, out, trans_final, n_contrib);
  else
    render_tile_infer_avx2(ctx, tile, bg, out);
}

constexpr auto kRenderTile = render_tile_fast;
#else
constexpr auto kRenderTile = render_tile;
#endif  // __AVX512F__

}  // namespace

void render_tile_infer(const RasterCtx& ctx, int tile, const float* bg, float* out) {
  kRenderTile(ctx, tile, bg, out, nullptr, nullptr);
}

void render_tile_tracked(const RasterCtx& ctx, int tile, const float* bg, float* out, float* trans_final,
                         int32_t* n_contrib) {
  kRenderTile(ctx, tile, bg, out, trans_final, n_contrib);
}

}  // namespace stgs::splat

using namespace stgs::splat;

extern "C" {

// Bins, sorts and composites. Returns a context for the backward pass (free it
// with stgs_raster_free) and writes the (H, W, 3) image to out. Without
// for_backward the per-pixel bookkeeping the backward pass reads is skipped
// and the context only serves stgs_raster_pairs.
void* stgs_raster_forward(int64_t n, const float* xy, const float* conic, const float* opac,
                          const float* color, const float* depth, const float* extent,
                          const float* bg, int width, int height, float* out, int for_backward,
                          int nthreads) {
  RasterCtx* ctx = acquire_ctx();
  bin_gaussians(*ctx, n, xy, conic, opac, color, depth, extent, width, height, nthreads);
  const int tiles = ctx->tiles_x * ctx->tiles_y;
  ctx->for_backward = for_backward != 0;
  if (ctx->for_backward) {
    ctx->trans_final.resize(int64_t(width) * height);
    ctx->n_contrib.resize(int64_t(width) * height);
  }
  float* trans_final = ctx->for_backward ? ctx->trans_final.data() : nullptr;
  int32_t* n_contrib = ctx->for_backward ? ctx->n_contrib.data() : nullptr;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
  for (int t = 0; t < tiles; ++t) kRenderTile(*ctx, t, bg, out, trans_final, n_contrib);
  return ctx;
}

// Copies the per-pixel final transmittance and last contributor of a forward pass run
// with for_backward (nothing otherwise).
void stgs_raster_pixels(void* handle, float* trans_final, int32_t* n_contrib) {
  const auto* ctx = static_cast<const RasterCtx*>(handle);
  if (!ctx->for_backward) return;
  std::memcpy(trans_final, ctx->trans_final.data(), ctx->trans_final.size() * sizeof(float));
  std::memcpy(n_contrib, ctx->n_contrib.data(), ctx->n_contrib.size() * sizeof(int32_t));
}

}  // extern "C"
