// Stage 2, binning: each projected Gaussian's pixel rect, the on-screen ones sorted by
// depth (stable radix sort on the float32 keys, index tie-break), and each 16x16 tile's list
// of the Gaussians whose ellipse can reach alpha >= 1/255 at one of its pixel centres, front
// to back. Its torch twin is stgs.render.stages.bin_tiles (the same lists, id for id).

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <mutex>
#include <vector>

#include "splat.h"
#include "stgs_abi.h"
#include "tile_reach.h"

namespace stgs::splat {
namespace {

// One freed context is kept for the next forward pass. A frame at 640x360 with
// 65k Gaussians needs ~15 MB of buffers; fresh ones are mapped and page-faulted
// in on every call (measured: 3-4 ms of a 40 ms frame), reused ones are not.
constexpr size_t kSpareMaxBytes = size_t(256) << 20;
std::mutex spare_mutex;
RasterCtx* spare_ctx = nullptr;

}  // namespace

RasterCtx* acquire_ctx() {
  std::lock_guard<std::mutex> lock(spare_mutex);
  RasterCtx* ctx = spare_ctx;
  spare_ctx = nullptr;
  if (ctx == nullptr) return new RasterCtx();
  ctx->frozen = 0;
  return ctx;
}

void release_ctx(RasterCtx* ctx) {
  if (ctx->bytes() <= kSpareMaxBytes) {
    std::lock_guard<std::mutex> lock(spare_mutex);
    if (spare_ctx == nullptr) {
      spare_ctx = ctx;
      return;
    }
  }
  delete ctx;
}

namespace {

// Stable LSD radix sort of ids by non-negative float keys (bit patterns are monotone), 8-bit
// digits. Each thread histograms and scatters a contiguous run of the input; the offsets put
// thread t's entries of a bucket after those of the threads before it, so the sort stays stable.
void radix_sort_by_depth(std::vector<int32_t>& ids, const float* depth, Scratch& scratch, int nthreads) {
  const int64_t n = int64_t(ids.size());
  nthreads = int(std::max<int64_t>(1, std::min<int64_t>(nthreads, n / 16384 + 1)));
  scratch.ids_tmp.resize(n);
  scratch.keys.resize(n);
  scratch.keys_tmp.resize(n);
  scratch.counts.assign(size_t(nthreads) * 256, 0);
  int32_t* id_src = ids.data();
  int32_t* id_dst = scratch.ids_tmp.data();
  uint32_t* key_src = scratch.keys.data();
  uint32_t* key_dst = scratch.keys_tmp.data();
  int64_t* const counts = scratch.counts.data();
#pragma omp parallel num_threads(nthreads) firstprivate(id_src, id_dst, key_src, key_dst)
  {
    const int t = omp_get_thread_num();
    const int64_t lo = n * t / nthreads, hi = n * (t + 1) / nthreads;
    for (int64_t i = lo; i < hi; ++i) std::memcpy(&key_src[i], &depth[id_src[i]], 4);
    for (int shift = 0; shift < 32; shift += 8) {
      int64_t* mine = counts + 256 * t;
      std::fill(mine, mine + 256, 0);
      for (int64_t i = lo; i < hi; ++i) ++mine[(key_src[i] >> shift) & 255u];
#pragma omp barrier
#pragma omp single
      {
        int64_t total = 0;
        for (int bucket = 0; bucket < 256; ++bucket)
          for (int u = 0; u < nthreads; ++u) {
            const int64_t c = counts[256 * u + bucket];
            counts[256 * u + bucket] = total;
            total += c;
          }
      }  // implicit barrier
      for (int64_t i = lo; i < hi; ++i) {
        const int64_t dst = mine[(key_src[i] >> shift) & 255u]++;
        id_dst[dst] = id_src[i];
        key_dst[dst] = key_src[i];
      }
#pragma omp barrier
      std::swap(id_src, id_dst);  // firstprivate: each thread swaps its own copies
      std::swap(key_src, key_dst);
    }
  }
  // Four passes: the sorted ids are back in ids.
}

// Fills ctx.tile_start / ctx.ids from Gaussians in depth order. Each thread bins
// a contiguous run of the depth order, and its entries go after those of the
// threads before it, so every tile's list stays front to back. The counting
// pass records each Gaussian's tile rows and each row's columns, so the
// filling pass reads them in order instead of the scattered Splat records.
void bin_by_tile(RasterCtx& ctx, const std::vector<int32_t>& ordered, int nthreads) {
  const int tiles = ctx.tiles_x * ctx.tiles_y;
  const int64_t n = int64_t(ordered.size());
  nthreads = int(std::max<int64_t>(1, std::min<int64_t>(nthreads, n / 4096 + 1)));
  // Per thread, each tile row's counts as differences (+1 at a span's first column, -1 past its
  // last): two stores per row instead of a loop over its columns, whose varying trip counts
  // mispredicted.
  const int stride = ctx.tiles_x + 1;
  std::vector<int64_t>& diffs = ctx.scratch.counts;
  diffs.assign(size_t(nthreads) * ctx.tiles_y * stride, 0);
  std::vector<std::vector<uint32_t>>& columns = ctx.scratch.columns;
  columns.resize(nthreads);
#pragma omp parallel num_threads(nthreads)
  {
    const int t = omp_get_thread_num();
    int64_t* mine = &diffs[size_t(t) * ctx.tiles_y * stride];
    // A local vector: the vector objects of columns share a cache line, which updating them from
    // both threads on every Gaussian bounced between the cores.
    std::vector<uint32_t> spans = std::move(columns[t]);
    spans.clear();
    spans.reserve(size_t(2 * (n / nthreads + 1)));
    const int64_t end = n * (t + 1) / nthreads;
    for (int64_t i = n * t / nthreads; i < end; ++i) {
      if (i + 8 < end) __builtin_prefetch(&ctx.splats[ordered[i + 8]]);
      const size_t at = spans.size();
      append_spans(ctx.splats[ordered[i]], spans);
      const uint32_t rows = spans[at];
      const uint32_t* cols = &spans[at + 1];
      for (int ty = int(rows & 0xffffu); ty <= int(rows >> 16); ++ty, ++cols) {
        ++mine[ty * stride + int(*cols & 0xffffu)];  // an empty row (1, 0) adds and removes at 1
        --mine[ty * stride + int(*cols >> 16) + 1];
      }
    }
    columns[t] = std::move(spans);
  }
  ctx.tile_start.assign(tiles + 1, 0);
  std::vector<int64_t>& offsets = ctx.scratch.offsets;
  offsets.resize(size_t(nthreads) * tiles);
  std::vector<int64_t> running(nthreads);
  int64_t total = 0;
  for (int tile = 0; tile < tiles; ++tile) {
    ctx.tile_start[tile] = total;
    const int ty = tile / ctx.tiles_x, tx = tile % ctx.tiles_x;
    for (int t = 0; t < nthreads; ++t) {
      running[t] = (tx == 0 ? 0 : running[t]) + diffs[(size_t(t) * ctx.tiles_y + ty) * stride + tx];
      offsets[size_t(t) * tiles + tile] = total;
      total += running[t];
    }
  }
  ctx.tile_start[tiles] = total;
  ctx.ids.resize(total);
#pragma omp parallel num_threads(nthreads)
  {
    const int t = omp_get_thread_num();
    int64_t* next = &offsets[size_t(t) * tiles];
    const uint32_t* span = columns[t].data();
    // Locals, so that the stores into ids (which may alias them as far as the compiler knows) do
    // not force a reload of the span and the list pointer on every entry.
    int32_t* const ids = ctx.ids.data();
    const int tiles_x = ctx.tiles_x;
    for (int64_t i = n * t / nthreads; i < n * (t + 1) / nthreads; ++i) {
      const int32_t g = ordered[i];
      const uint32_t rows = *span++;
      const int ty0 = int(rows & 0xffffu), ty1 = int(rows >> 16);
      for (int ty = ty0; ty <= ty1; ++ty) {
        const uint32_t cols = *span++;
        int64_t* const row_next = next + ty * tiles_x;
        for (int tx = int(cols & 0xffffu), tx1 = int(cols >> 16); tx <= tx1; ++tx) ids[row_next[tx]++] = g;
      }
    }
  }
}

}  // namespace

void bin_gaussians(RasterCtx& ctx, int64_t n, const float* xy, const float* conic, const float* opac,
                   const float* color, const float* depth, const float* extent, int width, int height,
                   int nthreads) {
  ctx.width = width;
  ctx.height = height;
  ctx.tiles_x = (width + kTile - 1) / kTile;
  ctx.tiles_y = (height + kTile - 1) / kTile;
  ctx.splats.resize(n);
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    Splat& s = ctx.splats[i];
    const bool coloured = color != nullptr;
    s = {xy[2 * i], xy[2 * i + 1], conic[3 * i], conic[3 * i + 1], conic[3 * i + 2], opac[i],
         coloured ? color[3 * i] : 0.0f, coloured ? color[3 * i + 1] : 0.0f, coloured ? color[3 * i + 2] : 0.0f,
         0.0f, {0, -1, 0, -1}, 0.0f};
    if (!(extent[2 * i] >= 0.0f)) continue;
    s.min_power = -std::log(255.0f * opac[i]) - 1e-3f;
    s.log2_o = std::log2(opac[i]);
    pixel_range(xy[2 * i], extent[2 * i], width, s.rect.u0, s.rect.u1);
    pixel_range(xy[2 * i + 1], extent[2 * i + 1], height, s.rect.v0, s.rect.v1);
  }
  std::vector<int32_t>& visible = ctx.scratch.visible;
  visible.clear();
  visible.reserve(n);
  for (int64_t i = 0; i < n; ++i) {
    const Rect& r = ctx.splats[i].rect;
    if (r.u0 <= r.u1 && r.v0 <= r.v1) visible.push_back(int32_t(i));
  }
  radix_sort_by_depth(visible, depth, ctx.scratch, nthreads);
  bin_by_tile(ctx, visible, nthreads);
}

}  // namespace stgs::splat

using namespace stgs::splat;

extern "C" {

// Binning alone (no compositing): a context whose tile lists stgs_raster_tiles copies out.
void* stgs_raster_bin(int64_t n, const float* xy, const float* conic, const float* opac, const float* depth,
                      const float* extent, int width, int height, int nthreads) {
  RasterCtx* ctx = acquire_ctx();
  bin_gaussians(*ctx, n, xy, conic, opac, nullptr, depth, extent, width, height, nthreads);
  ctx->for_backward = false;
  return ctx;
}

// Copies a context's tile offsets (tiles + 1) and tile lists (stgs_raster_pairs entries).
void stgs_raster_tiles(void* handle, int64_t* tile_start, int32_t* ids) {
  const auto* ctx = static_cast<const RasterCtx*>(handle);
  std::memcpy(tile_start, ctx->tile_start.data(), ctx->tile_start.size() * sizeof(int64_t));
  std::memcpy(ids, ctx->ids.data(), ctx->ids.size() * sizeof(int32_t));
}

// Number of (tile, Gaussian) pairs the last forward binned: a cost statistic.
int64_t stgs_raster_pairs(void* handle) {
  return int64_t(static_cast<RasterCtx*>(handle)->ids.size());
}

void stgs_raster_free(void* handle) { release_ctx(static_cast<RasterCtx*>(handle)); }

}  // extern "C"
