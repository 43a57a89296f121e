// A layer kept for the frames of one camera (a layered scene's static layer): binned and
// rendered alone once; each frame bins only the moving Gaussians and composites only the
// tiles they reach, with each such tile's two lists merged front to back. A bin of both
// layers would sort them by depth with the index as tie-break, the kept layer's indices
// first: the merge orders equal depths the same way, so every list, and so every pixel, is
// the one stgs_raster_forward makes of both layers (tests/render/test_fixed.py). A tile no
// moving Gaussian reaches holds the kept layer's list alone and is copied from its image.
// For training, the same tiles are composited with the backward pass's bookkeeping and the
// others get an empty list, so the backward pass visits only the tiles the moving Gaussians
// reach (no other tile has a gradient for them), and there it only undoes the kept
// Gaussians' compositing: their gradients are never wanted (ctx.frozen).

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include "splat.h"
#include "stgs_abi.h"

namespace stgs::splat {
namespace {

struct KeptLayer {
  int32_t count = 0;              // kept Gaussians: the moving ones' ids start here
  RasterCtx layer;                // the kept Gaussians' tile lists (their records moved into merged)
  std::vector<uint32_t> keys;     // their depths' bit patterns (the binning's sort keys)
  std::vector<float> image, bg;   // their image alone, and its background
  RasterCtx merged;               // records of both layers (the kept ones written once), merged lists
};

// Whether a moving Gaussian reaches tile t.
bool reached(const RasterCtx& moving, int t) { return moving.tile_start[t + 1] > moving.tile_start[t]; }

uint32_t key_of(const float* depth, int64_t i) {
  uint32_t key;
  std::memcpy(&key, &depth[i], 4);
  return key;
}

// Merges tile t's kept list and moving list (moving ids offset by the kept count) into out.
void merge_lists(const KeptLayer& kl, const RasterCtx& moving, const float* depth, int t, int32_t* out) {
  const int32_t offset = kl.count;
  const int32_t* a = kl.layer.ids.data() + kl.layer.tile_start[t];
  const int32_t* const a_end = kl.layer.ids.data() + kl.layer.tile_start[t + 1];
  const int32_t* b = moving.ids.data() + moving.tile_start[t];
  const int32_t* const b_end = moving.ids.data() + moving.tile_start[t + 1];
  while (a < a_end && b < b_end) {
    if (kl.keys[*a] <= key_of(depth, *b))  // equal depths: the kept layer's (lower) index first
      *out++ = *a++;
    else
      *out++ = offset + *b++;
  }
  while (a < a_end) *out++ = *a++;
  while (b < b_end) *out++ = offset + *b++;
}

// Sizes ctx's tile lists: a tile a moving Gaussian reaches gets room for both of its lists, any
// other an empty one. Returns the tiles left empty (their pixels are the kept image's).
int64_t plan_lists(const KeptLayer& kl, const RasterCtx& moving, RasterCtx& ctx) {
  const int tiles = ctx.tiles_x * ctx.tiles_y;
  ctx.tile_start.resize(tiles + 1);
  int64_t total = 0, reused = 0;
  for (int t = 0; t < tiles; ++t) {
    ctx.tile_start[t] = total;
    if (reached(moving, t))
      total += kl.layer.tile_start[t + 1] - kl.layer.tile_start[t] + moving.tile_start[t + 1] -
               moving.tile_start[t];
    else
      ++reused;
  }
  ctx.tile_start[tiles] = total;
  ctx.ids.resize(total);
  return reused;
}

void copy_tile(const RasterCtx& ctx, int tile, const float* src, float* out) {
  const TileBox box = tile_box(ctx, tile);
  for (int v = 0; v < box.h; ++v) {
    const int64_t pix = int64_t(box.y0 + v) * ctx.width + box.x0;
    std::memcpy(out + 3 * pix, src + 3 * pix, sizeof(float) * 3 * size_t(box.w));
  }
}

}  // namespace
}  // namespace stgs::splat

using namespace stgs::splat;

extern "C" {

void* stgs_raster_keep(int64_t n, const float* xy, const float* conic, const float* opac,
                       const float* color, const float* depth, const float* extent, const float* bg,
                       int width, int height, float* out, int nthreads) {
  auto* kl = new KeptLayer();
  RasterCtx& layer = kl->layer;
  bin_gaussians(layer, n, xy, conic, opac, color, depth, extent, width, height, nthreads);
  layer.scratch = Scratch{};  // the sort's buffers: not needed again
  const int tiles = layer.tiles_x * layer.tiles_y;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
  for (int t = 0; t < tiles; ++t) render_tile_infer(layer, t, bg, out);
  kl->keys.resize(n);
  for (int64_t i = 0; i < n; ++i) kl->keys[i] = key_of(depth, i);
  kl->image.assign(out, out + int64_t(width) * height * 3);
  kl->bg.assign(bg, bg + 3);
  RasterCtx& merged = kl->merged;
  merged.width = width;
  merged.height = height;
  merged.tiles_x = layer.tiles_x;
  merged.tiles_y = layer.tiles_y;
  merged.splats = std::move(layer.splats);
  merged.tile_start.assign(tiles + 1, 0);
  kl->count = int32_t(n);
  return kl;
}

int64_t stgs_raster_over(void* kept, int64_t n, const float* xy, const float* conic, const float* opac,
                         const float* color, const float* depth, const float* extent, float* out,
                         int nthreads) {
  auto* kl = static_cast<KeptLayer*>(kept);
  RasterCtx& merged = kl->merged;
  RasterCtx* moving = acquire_ctx();
  bin_gaussians(*moving, n, xy, conic, opac, color, depth, extent, merged.width, merged.height, nthreads);
  merged.splats.resize(kl->count + n);
  std::copy(moving->splats.begin(), moving->splats.end(), merged.splats.begin() + kl->count);
  const int64_t reused = plan_lists(*kl, *moving, merged);
  const int tiles = merged.tiles_x * merged.tiles_y;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
  for (int t = 0; t < tiles; ++t) {
    if (reached(*moving, t)) {
      merge_lists(*kl, *moving, depth, t, merged.ids.data() + merged.tile_start[t]);
      render_tile_infer(merged, t, kl->bg.data(), out);
    } else {
      copy_tile(merged, t, kl->image.data(), out);
    }
  }
  release_ctx(moving);
  return reused;
}

void* stgs_raster_over_train(void* kept, int64_t n, const float* xy, const float* conic, const float* opac,
                             const float* color, const float* depth, const float* extent, float* out,
                             int nthreads) {
  const auto* kl = static_cast<const KeptLayer*>(kept);
  const RasterCtx& shape = kl->merged;
  RasterCtx* moving = acquire_ctx();
  bin_gaussians(*moving, n, xy, conic, opac, color, depth, extent, shape.width, shape.height, nthreads);
  RasterCtx* ctx = acquire_ctx();
  ctx->width = shape.width;
  ctx->height = shape.height;
  ctx->tiles_x = shape.tiles_x;
  ctx->tiles_y = shape.tiles_y;
  ctx->splats.assign(shape.splats.begin(), shape.splats.begin() + kl->count);
  ctx->splats.insert(ctx->splats.end(), moving->splats.begin(), moving->splats.end());
  plan_lists(*kl, *moving, *ctx);
  ctx->for_backward = true;
  ctx->frozen = kl->count;  // the backward pass only undoes their compositing
  const int64_t pixels = int64_t(shape.width) * shape.height;
  ctx->trans_final.resize(pixels);
  ctx->n_contrib.resize(pixels);
  const int tiles = ctx->tiles_x * ctx->tiles_y;
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1)
  for (int t = 0; t < tiles; ++t) {
    if (reached(*moving, t)) {
      merge_lists(*kl, *moving, depth, t, ctx->ids.data() + ctx->tile_start[t]);
      render_tile_tracked(*ctx, t, kl->bg.data(), out, ctx->trans_final.data(), ctx->n_contrib.data());
    } else {  // an empty list: the backward pass finds nothing to differentiate there
      copy_tile(*ctx, t, kl->image.data(), out);
      const TileBox box = tile_box(*ctx, t);
      for (int v = 0; v < box.h; ++v) {
        const int64_t pix = int64_t(box.y0 + v) * ctx->width + box.x0;
        std::fill_n(ctx->trans_final.data() + pix, box.w, 0.0f);
        std::fill_n(ctx->n_contrib.data() + pix, box.w, 0);
      }
    }
  }
  release_ctx(moving);
  return ctx;
}

void stgs_raster_kept_free(void* kept) { delete static_cast<KeptLayer*>(kept); }

}  // extern "C"
