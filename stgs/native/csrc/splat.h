// What the splatter's stages share (internal; the C ABI is stgs_abi.h): the contract's
// constants (docs/ARCHITECTURE.md; stgs/render/project.py), the per-Gaussian record the compositor
// reads, the context a forward pass leaves for its backward pass, and the per-tile
// compositing state. Stages: project.cpp, binning.cpp, forward.cpp, backward.cpp.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "fastmath.h"

namespace stgs::splat {

constexpr double kNearZ = 0.01;
constexpr double kBlur = 0.3;
constexpr double kExtentMargin = 1.0 + 1e-4;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTMin = 1e-4f;
constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;

// The vector compositors' shared arithmetic (splat_avx512.h, splat_avx2.h): row powers in log2 units,
// so that the falloff is one 2^x, with 2^f on f in [-0.5, 0.5] by a degree-5 minimax polynomial
// (relative error 2.3e-7 in float32; coefficients from the highest degree down, evaluated by Horner).
constexpr float kLog2e = 1.44269504088896341f;
constexpr float kExp2Poly[6] = {1.3276465062e-3f, 9.6755412793e-3f, 5.5507132949e-2f,
                                2.4022119725e-1f, 6.9314696705e-1f, 1.0000000717e+0f};

// Tile-list entries ahead whose Splat record the compositors prefetch: a list visits Gaussians in
// depth order, so their records are scattered through memory.
constexpr int kPrefetch = 8;

struct Rect {
  int32_t u0, u1, v0, v1;  // inclusive pixel bounds
};

// One Gaussian as the compositor reads it: one cache line per Gaussian.
struct alignas(64) Splat {
  float mx, my, a, b, c, o, r, g, bl;
  float min_power;  // ln(1 / (255 o)) - 1e-3: below this power alpha < 1/255 everywhere
  Rect rect;        // inclusive pixel bounds of the opacity-aware extent
  float log2_o;     // log2(o), for the inference compositor's exponent
};

// Scratch space of one forward pass (sorting and binning), kept with the context so that
// a reused context reuses it too.
struct Scratch {
  std::vector<int32_t> visible, ids_tmp;          // on-screen Gaussians, depth order
  std::vector<uint32_t> keys, keys_tmp;           // radix sort keys
  std::vector<int64_t> counts, offsets;           // per thread and tile
  std::vector<std::vector<uint32_t>> columns;     // per thread: tile spans of its Gaussians
};

struct RasterCtx {
  int width = 0, height = 0, tiles_x = 0, tiles_y = 0;
  std::vector<int64_t> tile_start;  // (tiles + 1) offsets into ids
  std::vector<int32_t> ids;         // Gaussian ids, per tile, front to back
  std::vector<Splat> splats;        // per Gaussian (rect u0 > u1 when off screen)
  std::vector<float> trans_final;   // per pixel
  std::vector<int32_t> n_contrib;   // per pixel: list entries up to the last one added
  bool for_backward = false;        // trans_final and n_contrib were kept
  int32_t frozen = 0;               // ids below it get no gradients (a kept layer's Gaussians)
  Scratch scratch;

  size_t bytes() const {
    size_t total = tile_start.capacity() * 8 + ids.capacity() * 4 + splats.capacity() * sizeof(Splat) +
                   trans_final.capacity() * 4 + n_contrib.capacity() * 4 +
                   (scratch.visible.capacity() + scratch.ids_tmp.capacity() + scratch.keys.capacity() +
                    scratch.keys_tmp.capacity()) * 4 + (scratch.counts.capacity() + scratch.offsets.capacity()) * 8;
    for (const auto& c : scratch.columns) total += c.capacity() * 4;
    return total;
  }
};

inline void prefetch_splat(const RasterCtx& ctx, int64_t entry) {
  __builtin_prefetch(&ctx.splats[ctx.ids[entry]]);
}

// A context for one forward pass (reusing the last freed one's buffers) and its release.
RasterCtx* acquire_ctx();
void release_ctx(RasterCtx* ctx);

// Binning (binning.cpp): fills ctx's splats from the projected inputs (colour may be null
// when only the binning is wanted), sorts the on-screen ones by depth and fills ctx.tile_start
// and ctx.ids with each tile's Gaussians front to back.
void bin_gaussians(RasterCtx& ctx, int64_t n, const float* xy, const float* conic, const float* opac,
                   const float* color, const float* depth, const float* extent, int width, int height,
                   int nthreads);

// Composites one tile without the backward pass's bookkeeping (forward.cpp: the CPU's fastest
// inference kernel).
void render_tile_infer(const RasterCtx& ctx, int tile, const float* bg, float* out);

// Composites one tile with the bookkeeping the backward pass reads (forward.cpp: the kernel
// stgs_raster_forward runs for_backward).
void render_tile_tracked(const RasterCtx& ctx, int tile, const float* bg, float* out, float* trans_final,
                         int32_t* n_contrib);

// -0.5 q of the Gaussian at a pixel offset; q >= 0 up to rounding, which callers clip.
inline float raw_power(const Splat& s, float dx, float dy) {
  return -0.5f * (s.a * dx * dx + 2.0f * s.b * dx * dy + s.c * dy * dy);
}

// Per-tile compositing state, one lane per pixel (structure of arrays so that
// a tile row of kTile pixels is one vector).
struct TileState {
  alignas(64) float trans[kTilePixels];
  alignas(64) float acc_r[kTilePixels];
  alignas(64) float acc_g[kTilePixels];
  alignas(64) float acc_b[kTilePixels];
  alignas(64) int32_t last[kTilePixels];
  alignas(64) int32_t live[kTilePixels];  // 1 while the pixel still composites

  // Pointers to one tile row of every per-pixel array.
  struct Row {
    float *trans, *r, *g, *b;
    int32_t *last, *live;
  };
  Row row(int v) {
    const int o = v * kTile;
    return {trans + o, acc_r + o, acc_g + o, acc_b + o, last + o, live + o};
  }
};

// The tile's pixel window (x0, y0) and its width/height clipped to the image.
struct TileBox {
  int x0, y0, w, h;
};

inline TileBox tile_box(const RasterCtx& ctx, int tile) {
  const int x0 = (tile % ctx.tiles_x) * kTile, y0 = (tile / ctx.tiles_x) * kTile;
  return {x0, y0, std::min(kTile, ctx.width - x0), std::min(kTile, ctx.height - y0)};
}

// Alpha of a Gaussian at the kTile pixel centres of one tile row (0 outside [u0, u1]).
inline void row_alpha(const Splat& s, int x0, float dy, int u0, int u1, float* __restrict alpha,
                      float* __restrict falloff, float* __restrict power_out) {
  const float base_dx = float(x0) + 0.5f - s.mx;
  const float lo = float(u0 - x0), hi = float(u1 - x0);
#pragma omp simd
  for (int i = 0; i < kTile; ++i) {
    const float fi = float(i);
    const float power = raw_power(s, base_dx + fi, dy);
    const float f = stgs::fast_exp(power < 0.0f ? power : 0.0f);
    const float a = std::min(s.o * f, kAlphaMax);
    alpha[i] = (fi >= lo && fi <= hi) ? a : 0.0f;
    falloff[i] = f;
    power_out[i] = power;
  }
}

constexpr int kScanEvery = 16;

// Recomputes which rows still composite; false once the whole tile is saturated.
inline bool refresh_live_rows(const TileState& st, bool* row_live) {
  bool any = false;
  for (int v = 0; v < kTile; ++v) {
    int live = 0;
    for (int i = 0; i < kTile; ++i) live |= st.live[v * kTile + i];
    row_live[v] = row_live[v] && live;
    any = any || row_live[v];
  }
  return any;
}

// Per-thread gradient sums for one Gaussian: xy(2) conic(3) opacity(1) colour(3).
constexpr int kGradStride = 9;

// The backward's last contributor to walk at pix: a pixel without upstream gradient adds zero to every
// sum, so its walk is skipped (taken as none); a masked loss leaves many such pixels.
inline int32_t walked_last(const RasterCtx& ctx, const float* grad_out, int64_t pix) {
  const bool any = grad_out[3 * pix] != 0.0f || grad_out[3 * pix + 1] != 0.0f || grad_out[3 * pix + 2] != 0.0f;
  return any ? ctx.n_contrib[pix] : 0;
}

// One tile row's forward bookkeeping and upstream gradient, as the backward kernels load them: final
// transmittance t (1 outside the image), last contributor to walk l, the gradient r, g, b (0 outside); adds the
// background's gradient of the row to grad_bg and returns the row's largest l.
inline int32_t load_tile_row(const RasterCtx& ctx, const TileBox& box, int v, const float* grad_out, float* t,
                             int32_t* l, float* r, float* g, float* b, double* grad_bg) {
  int32_t max_last = 0;
  for (int u = 0; u < kTile; ++u) {
    t[u] = 1.0f;
    l[u] = 0;
    r[u] = g[u] = b[u] = 0.0f;
  }
  if (v >= box.h) return 0;
  for (int u = 0; u < box.w; ++u) {
    const int64_t pix = int64_t(box.y0 + v) * ctx.width + (box.x0 + u);
    t[u] = ctx.trans_final[pix];
    l[u] = walked_last(ctx, grad_out, pix);
    r[u] = grad_out[3 * pix];
    g[u] = grad_out[3 * pix + 1];
    b[u] = grad_out[3 * pix + 2];
    grad_bg[0] += double(t[u]) * r[u];
    grad_bg[1] += double(t[u]) * g[u];
    grad_bg[2] += double(t[u]) * b[u];
    max_last = std::max(max_last, l[u]);
  }
  return max_last;
}

}  // namespace stgs::splat
