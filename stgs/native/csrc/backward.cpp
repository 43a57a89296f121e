// Stage 4, backward: gradients of the composited image with respect to the projected
// Gaussians (means2d, conics, opacities, colours) and the background, walking each tile's
// list back to front from the forward's bookkeeping. Its torch twin is autograd through
// stgs.render.stages.composite_tiles. The portable kernel; the AVX-512 and AVX2 ones are in backward_simd.h.

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "backward_simd.h"
#include "splat.h"
#include "stgs_abi.h"

namespace stgs::splat {
namespace {

// One row of one list entry, portable: undoes the entry's compositing there and, for a trainable Gaussian, adds
// the row's share of its nine running gradient sums (means, conic, opacity, colour) in sum.
template <bool Trainable>
inline void backward_row(const Splat& s, int32_t k, int x0, float dy, const float* alpha, const float* falloff,
                         const float* power, const TileState::Row& px, const float* dr, const float* dg,
                         const float* db, float* sum) {
  float *trans = px.trans, *ar = px.r, *ag = px.g, *ab = px.b;
  const int32_t* last = px.last;
  float gmx = sum[0], gmy = sum[1], ga = sum[2], gb = sum[3], gc = sum[4], go = sum[5], gr = sum[6], gg = sum[7],
        gbl = sum[8];
#pragma omp simd reduction(+ : gmx, gmy, ga, gb, gc, go, gr, gg, gbl)
  for (int i = 0; i < kTile; ++i) {
    const float a = alpha[i];
    const bool took = k < last[i] && a >= kAlphaMin;
    const float one_minus = 1.0f - a;
    const float t_before = took ? trans[i] / one_minus : trans[i];
    const float w = took ? a * t_before : 0.0f;
    if constexpr (Trainable) {
      gr += w * dr[i];
      gg += w * dg[i];
      gbl += w * db[i];
      const float g_alpha = took ? dr[i] * (s.r * t_before - ar[i] / one_minus) +
                                       dg[i] * (s.g * t_before - ag[i] / one_minus) +
                                       db[i] * (s.bl * t_before - ab[i] / one_minus)
                                 : 0.0f;
      // No gradient through the 0.99 clamp, nor through the power clip at 0.
      const bool open_alpha = s.o * falloff[i] <= kAlphaMax;
      go += open_alpha ? g_alpha * falloff[i] : 0.0f;
      const float g_power = (open_alpha && power[i] <= 0.0f) ? g_alpha * s.o * falloff[i] : 0.0f;
      const float dx = float(x0 + i) + 0.5f - s.mx;
      gmx += g_power * (s.a * dx + s.b * dy);
      gmy += g_power * (s.b * dx + s.c * dy);
      ga += g_power * (-0.5f * dx * dx);
      gb += g_power * (-dx * dy);
      gc += g_power * (-0.5f * dy * dy);
    }
    ar[i] += s.r * w;
    ag[i] += s.g * w;
    ab[i] += s.bl * w;
    trans[i] = t_before;
  }
  if constexpr (Trainable) {
    sum[0] = gmx; sum[1] = gmy;
    sum[2] = ga; sum[3] = gb; sum[4] = gc;
    sum[5] = go;
    sum[6] = gr; sum[7] = gg; sum[8] = gbl;
  }
}

[[maybe_unused]] void backward_tile(const RasterCtx& ctx, int tile, const float* bg, const float* grad_out,
                                    float* grads, double* grad_bg) {
  const TileBox box = tile_box(ctx, tile);
  // trans: transmittance after the contributions still to be undone; acc_*:
  // colour composited behind the current Gaussian (background included).
  TileState st;
  alignas(64) float d_r[kTilePixels], d_g[kTilePixels], d_b[kTilePixels];
  int32_t max_last = 0;
  for (int v = 0; v < kTile; ++v) {
    const int o = v * kTile;
    max_last = std::max(max_last, load_tile_row(ctx, box, v, grad_out, st.trans + o, st.last + o, d_r + o, d_g + o,
                                                d_b + o, grad_bg));
  }
  for (int p = 0; p < kTilePixels; ++p) {
    st.acc_r[p] = st.trans[p] * bg[0];
    st.acc_g[p] = st.trans[p] * bg[1];
    st.acc_b[p] = st.trans[p] * bg[2];
  }
  const int64_t begin = ctx.tile_start[tile];
  alignas(64) float alpha[kTile], falloff[kTile], power[kTile];
  for (int32_t k = max_last - 1; k >= 0; --k) {
    const int32_t g = ctx.ids[begin + k];
    const Splat& s = ctx.splats[g];
    const Rect& r = s.rect;
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    const bool trainable = g >= ctx.frozen;  // a kept Gaussian's compositing is only undone
    float sum[kGradStride] = {0};
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      const float dy = float(v) + 0.5f - s.my;
      row_alpha(s, box.x0, dy, r.u0, r.u1, alpha, falloff, power);
      const float *dr = d_r + row * kTile, *dg = d_g + row * kTile, *db = d_b + row * kTile;
      if (trainable)
        backward_row<true>(s, k, box.x0, dy, alpha, falloff, power, st.row(row), dr, dg, db, sum);
      else
        backward_row<false>(s, k, box.x0, dy, alpha, falloff, power, st.row(row), dr, dg, db, sum);
    }
    if (!trainable) continue;
    float* out = &grads[int64_t(g - ctx.frozen) * kGradStride];
    for (int j = 0; j < kGradStride; ++j) out[j] += sum[j];
  }
}

#if defined(__AVX512F__)
constexpr auto kBackwardTile = backward_tile_avx512;
#elif defined(__AVX2__) && defined(__FMA__)
constexpr auto kBackwardTile = backward_tile_avx2;
#else
constexpr auto kBackwardTile = backward_tile;
#endif

}  // namespace
}  // namespace stgs::splat

using namespace stgs::splat;

extern "C" {

// Gradients of the composited image with respect to the forward's inputs.
// The forward's inputs are read from the copies the context keeps (ctx.splats).
void stgs_raster_backward(void* handle, int64_t n, const float* bg, const float* grad_out,
                          float* grad_xy, float* grad_conic, float* grad_opac, float* grad_color,
                          float* grad_bg, int nthreads) {
  const auto* ctx = static_cast<const RasterCtx*>(handle);
  if (!ctx->for_backward) return;  // the forward kept nothing to differentiate (bindings never ask)
  const int tiles = ctx->tiles_x * ctx->tiles_y;
  const int64_t first = std::min<int64_t>(ctx->frozen, n), m = n - first;  // the kernels' rows: first + row
  std::vector<float> partial(size_t(nthreads) * m * kGradStride, 0.0f);
  std::vector<double> partial_bg(size_t(nthreads) * 3, 0.0);
#pragma omp parallel num_threads(nthreads)
  {
    const int tid = omp_get_thread_num();
    float* mine = partial.data() + size_t(tid) * m * kGradStride;
    // static: which thread sums which tile must not vary between runs, or seeded training is not reproducible
#pragma omp for schedule(static, 1)
    for (int t = 0; t < tiles; ++t)
      kBackwardTile(*ctx, t, bg, grad_out, mine, &partial_bg[3 * tid]);
  }
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = first; i < n; ++i) {
    float sum[kGradStride] = {0};
    for (int t = 0; t < nthreads; ++t)
      for (int j = 0; j < kGradStride; ++j) sum[j] += partial[(size_t(t) * m + i - first) * kGradStride + j];
    grad_xy[2 * i] = sum[0]; grad_xy[2 * i + 1] = sum[1];
    grad_conic[3 * i] = sum[2]; grad_conic[3 * i + 1] = sum[3]; grad_conic[3 * i + 2] = sum[4];
    grad_opac[i] = sum[5];
    grad_color[3 * i] = sum[6]; grad_color[3 * i + 1] = sum[7]; grad_color[3 * i + 2] = sum[8];
  }
  for (int ch = 0; ch < 3; ++ch) {
    double s = 0;
    for (int t = 0; t < nthreads; ++t) s += partial_bg[3 * t + ch];
    grad_bg[ch] = float(s);
  }
}

}  // extern "C"
