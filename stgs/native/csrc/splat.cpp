// Native CPU splatter: projection, tile binning, front-to-back compositing and
// its backward pass. Mirrors stgs/render/project.py and stgs/render/reference.py
// (the oracle); constants and numerics are the contract in DESIGN.md.
//
// Exposed through a C ABI and loaded with ctypes, so building it needs only a
// C++ compiler with OpenMP (no torch headers, no CUDA).

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <mutex>
#include <vector>

#include "fastmath.h"

#if defined(__AVX512F__)
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#endif

namespace {

constexpr double kNearZ = 0.01;
constexpr double kBlur = 0.3;
constexpr double kExtentMargin = 1.0 + 1e-4;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTMin = 1e-4f;
constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;

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

// One freed context is kept for the next forward pass. A frame at 640x360 with
// 65k Gaussians needs ~15 MB of buffers; fresh ones are mapped and page-faulted
// in on every call (measured: 3-4 ms of a 40 ms frame), reused ones are not.
constexpr size_t kSpareMaxBytes = size_t(256) << 20;
std::mutex spare_mutex;
RasterCtx* spare_ctx = nullptr;

RasterCtx* acquire_ctx() {
  std::lock_guard<std::mutex> lock(spare_mutex);
  RasterCtx* ctx = spare_ctx;
  spare_ctx = nullptr;
  return ctx != nullptr ? ctx : new RasterCtx();
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

// Inclusive pixel range whose centres lie within [m - h, m + h], clipped to [0, size).
void pixel_range(float m, float h, int size, int32_t& lo, int32_t& hi) {
  const double first = std::ceil(double(m) - double(h) - 0.5);
  const double last = std::floor(double(m) + double(h) - 0.5);
  lo = int32_t(std::max(0.0, std::min(first, double(size))));
  hi = int32_t(std::max(-1.0, std::min(last, double(size - 1))));
}


// -0.5 q of the Gaussian at a pixel offset; q >= 0 up to rounding, which callers clip.
inline float raw_power(const Splat& s, float dx, float dy) {
  return -0.5f * (s.a * dx * dx + 2.0f * s.b * dx * dy + s.c * dy * dy);
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

TileBox tile_box(const RasterCtx& ctx, int tile) {
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
bool refresh_live_rows(const TileState& st, bool* row_live) {
  bool any = false;
  for (int v = 0; v < kTile; ++v) {
    int live = 0;
    for (int i = 0; i < kTile; ++i) live |= st.live[v * kTile + i];
    row_live[v] = row_live[v] && live;
    any = any || row_live[v];
  }
  return any;
}

[[maybe_unused]] void render_tile(const RasterCtx& ctx, int tile, const float* bg, float* out, float* trans_final,
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

// Per-thread gradient sums for one Gaussian: xy(2) conic(3) opacity(1) colour(3).
constexpr int kGradStride = 9;

[[maybe_unused]] void backward_tile(const RasterCtx& ctx, int tile, const float* bg, const float* grad_out,
                   float* grads, double* grad_bg) {
  const TileBox box = tile_box(ctx, tile);
  // trans: transmittance after the contributions still to be undone; acc_*:
  // colour composited behind the current Gaussian (background included).
  TileState st;
  alignas(64) float d_r[kTilePixels], d_g[kTilePixels], d_b[kTilePixels];
  int32_t max_last = 0;
  for (int p = 0; p < kTilePixels; ++p) {
    const int u = p % kTile, v = p / kTile;
    const bool in = u < box.w && v < box.h;
    const int64_t pix = int64_t(box.y0 + v) * ctx.width + (box.x0 + u);
    st.trans[p] = in ? ctx.trans_final[pix] : 1.0f;
    st.last[p] = in ? ctx.n_contrib[pix] : 0;
    d_r[p] = in ? grad_out[3 * pix] : 0.0f;
    d_g[p] = in ? grad_out[3 * pix + 1] : 0.0f;
    d_b[p] = in ? grad_out[3 * pix + 2] : 0.0f;
    st.acc_r[p] = st.trans[p] * bg[0];
    st.acc_g[p] = st.trans[p] * bg[1];
    st.acc_b[p] = st.trans[p] * bg[2];
    if (in) {
      grad_bg[0] += double(st.trans[p]) * d_r[p];
      grad_bg[1] += double(st.trans[p]) * d_g[p];
      grad_bg[2] += double(st.trans[p]) * d_b[p];
    }
    max_last = std::max(max_last, st.last[p]);
  }
  const int64_t begin = ctx.tile_start[tile];
  alignas(64) float alpha[kTile], falloff[kTile], power[kTile];
  for (int32_t k = max_last - 1; k >= 0; --k) {
    const int32_t g = ctx.ids[begin + k];
    const Splat& s = ctx.splats[g];
    const Rect& r = s.rect;
    const int v0 = std::max(r.v0, box.y0), v1 = std::min(r.v1, box.y0 + box.h - 1);
    float gmx = 0, gmy = 0, ga = 0, gb = 0, gc = 0, go = 0, gr = 0, gg = 0, gbl = 0;
    for (int v = v0; v <= v1; ++v) {
      const int row = v - box.y0;
      const float dy = float(v) + 0.5f - s.my;
      row_alpha(s, box.x0, dy, r.u0, r.u1, alpha, falloff, power);
      const TileState::Row px = st.row(row);
      float *trans = px.trans, *ar = px.r, *ag = px.g, *ab = px.b;
      const int32_t* last = px.last;
      const float* dr = d_r + row * kTile;
      const float* dg = d_g + row * kTile;
      const float* db = d_b + row * kTile;
#pragma omp simd reduction(+ : gmx, gmy, ga, gb, gc, go, gr, gg, gbl)
      for (int i = 0; i < kTile; ++i) {
        const float a = alpha[i];
        const bool took = k < last[i] && a >= kAlphaMin;
        const float one_minus = 1.0f - a;
        const float t_before = took ? trans[i] / one_minus : trans[i];
        const float w = took ? a * t_before : 0.0f;
        gr += w * dr[i];
        gg += w * dg[i];
        gbl += w * db[i];
        const float g_alpha = took ? dr[i] * (s.r * t_before - ar[i] / one_minus) +
                                         dg[i] * (s.g * t_before - ag[i] / one_minus) +
                                         db[i] * (s.bl * t_before - ab[i] / one_minus)
                                   : 0.0f;
        ar[i] += s.r * w;
        ag[i] += s.g * w;
        ab[i] += s.bl * w;
        trans[i] = t_before;
        // No gradient through the 0.99 clamp, nor through the power clip at 0.
        const bool open_alpha = s.o * falloff[i] <= kAlphaMax;
        go += open_alpha ? g_alpha * falloff[i] : 0.0f;
        const float g_power = (open_alpha && power[i] <= 0.0f) ? g_alpha * s.o * falloff[i] : 0.0f;
        const float dx = float(box.x0 + i) + 0.5f - s.mx;
        gmx += g_power * (s.a * dx + s.b * dy);
        gmy += g_power * (s.b * dx + s.c * dy);
        ga += g_power * (-0.5f * dx * dx);
        gb += g_power * (-dx * dy);
        gc += g_power * (-0.5f * dy * dy);
      }
    }
    float* out = &grads[int64_t(g) * kGradStride];
    out[0] += gmx; out[1] += gmy;
    out[2] += ga; out[3] += gb; out[4] += gc;
    out[5] += go;
    out[6] += gr; out[7] += gg; out[8] += gbl;
  }
}

#if defined(__AVX512F__)
// AVX-512 versions of render_tile / backward_tile: one tile row of 16 pixels is
// one register, live pixels are a 16-bit mask per row. Same numerics as the
// portable versions above (which stay the build for CPUs without AVX-512).

// Tile-list entries ahead whose Splat is prefetched: the list visits Gaussians in
// depth order, so their records are scattered through memory.
constexpr int kPrefetch = 8;

inline void prefetch_splat(const RasterCtx& ctx, int64_t entry) {
  __builtin_prefetch(&ctx.splats[ctx.ids[entry]]);
}

// Row powers are evaluated in log2 units, so that the falloff is one 2^x: the
// conic comes pre-scaled by -0.5 log2(e) (pa, pb2, pc), which also saves the
// multiply by -0.5. The gradients keep the natural-unit conic (a, c, half).
constexpr float kLog2e = 1.44269504088896341f;

struct SplatVec {
  __m512 mx, a, c, o, r, g, bl, amin, amax, tmin, one, half, pa, pb2, pc;
  explicit SplatVec(const Splat& s)
      : mx(_mm512_set1_ps(s.mx)), a(_mm512_set1_ps(s.a)), c(_mm512_set1_ps(s.c)), o(_mm512_set1_ps(s.o)),
        r(_mm512_set1_ps(s.r)), g(_mm512_set1_ps(s.g)), bl(_mm512_set1_ps(s.bl)),
        amin(_mm512_set1_ps(kAlphaMin)), amax(_mm512_set1_ps(kAlphaMax)), tmin(_mm512_set1_ps(kTMin)),
        one(_mm512_set1_ps(1.0f)), half(_mm512_set1_ps(-0.5f)), pa(_mm512_set1_ps(-0.5f * kLog2e * s.a)),
        pb2(_mm512_set1_ps(-kLog2e * s.b)), pc(_mm512_set1_ps(-0.5f * kLog2e * s.c)) {}
};

// 2^x for x <= 0: x = n + f with n the nearest integer (f in [-0.5, 0.5], exact),
// 2^f by a degree-5 minimax polynomial (relative error 2.3e-7 in float32).
inline __m512 exp2_v(__m512 x) {
  // No clamp from below: far under -126 vscalefps underflows to 0 (n is exact for any float). Rows
  // far from the ellipse give denormals or 0 here; a clamp at 2^-64 to avoid them measured 1-4 % slower.
  const __m512 n = _mm512_roundscale_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const __m512 f = _mm512_sub_ps(x, n);
  __m512 p = _mm512_set1_ps(1.3276465062e-3f);
  p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(9.6755412793e-3f));
  p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(5.5507132949e-2f));
  p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(2.4022119725e-1f));
  p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(6.9314696705e-1f));
  p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(1.0000000717e+0f));
  return _mm512_scalef_ps(p, n);
}

// Power (-0.5 q log2 e, unclipped), falloff 2^min(power, 0) and clamped alpha along a row.
struct RowEval {
  __m512 dx, power, falloff, alpha;
};

inline __m512 row_power(const SplatVec& v, __m512 px, float dy) {
  const __m512 dx = _mm512_sub_ps(px, v.mx);
  const __m512 dyv = _mm512_set1_ps(dy);
  const __m512 cdy2 = _mm512_mul_ps(_mm512_mul_ps(v.pc, dyv), dyv);
  return _mm512_fmadd_ps(_mm512_mul_ps(v.pa, dx), dx, _mm512_fmadd_ps(_mm512_mul_ps(v.pb2, dyv), dx, cdy2));
}

// `power` is row_power(v, px, dy), which callers already need for their early exits.
inline RowEval eval_row(const SplatVec& v, __m512 px, __m512 power, __mmask16 inside) {
  RowEval e;
  e.dx = _mm512_sub_ps(px, v.mx);
  e.power = power;
  e.falloff = exp2_v(_mm512_min_ps(e.power, _mm512_setzero_ps()));
  e.alpha = _mm512_maskz_min_ps(inside, _mm512_mul_ps(v.o, e.falloff), v.amax);
  return e;
}

inline __mmask16 span_mask(int x0, int u0, int u1) {
  const int lo = std::max(0, u0 - x0), hi = std::min(kTile - 1, u1 - x0);
  if (lo > hi) return 0;
  return __mmask16(((1u << (hi - lo + 1)) - 1u) << lo);
}

inline __m512 pixel_centres(int x0) {
  return _mm512_add_ps(_mm512_set1_ps(float(x0) + 0.5f),
                       _mm512_setr_ps(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
}

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

inline float hsum(__m512 v) { return _mm512_reduce_add_ps(v); }

void backward_tile_avx512(const RasterCtx& ctx, int tile, const float* bg, const float* grad_out,
                          float* grads, double* grad_bg) {
  const TileBox box = tile_box(ctx, tile);
  __m512 trans[kTile], ar[kTile], ag[kTile], ab[kTile], dr[kTile], dg[kTile], db[kTile];
  __m512i last[kTile];
  int32_t max_last = 0;
  for (int v = 0; v < kTile; ++v) {
    alignas(64) float t[kTile] = {0}, r[kTile] = {0}, g[kTile] = {0}, b[kTile] = {0};
    alignas(64) int32_t l[kTile] = {0};
    for (int u = 0; u < kTile; ++u) t[u] = 1.0f;
    if (v < box.h) {
      for (int u = 0; u < box.w; ++u) {
        const int64_t pix = int64_t(box.y0 + v) * ctx.width + (box.x0 + u);
        t[u] = ctx.trans_final[pix];
        l[u] = ctx.n_contrib[pix];
        r[u] = grad_out[3 * pix];
        g[u] = grad_out[3 * pix + 1];
        b[u] = grad_out[3 * pix + 2];
        grad_bg[0] += double(t[u]) * r[u];
        grad_bg[1] += double(t[u]) * g[u];
        grad_bg[2] += double(t[u]) * b[u];
        max_last = std::max(max_last, l[u]);
      }
    }
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
  const int64_t begin = ctx.tile_start[tile];
  for (int32_t k = max_last - 1; k >= 0; --k) {
    if (k >= kPrefetch) prefetch_splat(ctx, begin + k - kPrefetch);
    const int32_t g = ctx.ids[begin + k];
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
      gr = _mm512_fmadd_ps(w, dr[row], gr);
      gg = _mm512_fmadd_ps(w, dg[row], gg);
      gbl = _mm512_fmadd_ps(w, db[row], gbl);
      __m512 g_alpha = _mm512_mul_ps(dr[row], _mm512_fmsub_ps(sv.r, t_before, _mm512_mul_ps(ar[row], inv)));
      g_alpha = _mm512_fmadd_ps(dg[row], _mm512_fmsub_ps(sv.g, t_before, _mm512_mul_ps(ag[row], inv)), g_alpha);
      g_alpha = _mm512_fmadd_ps(db[row], _mm512_fmsub_ps(sv.bl, t_before, _mm512_mul_ps(ab[row], inv)), g_alpha);
      g_alpha = _mm512_maskz_mov_ps(took, g_alpha);
      ar[row] = _mm512_fmadd_ps(sv.r, w, ar[row]);
      ag[row] = _mm512_fmadd_ps(sv.g, w, ag[row]);
      ab[row] = _mm512_fmadd_ps(sv.bl, w, ab[row]);
      trans[row] = t_before;
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
    float* o = &grads[int64_t(g) * kGradStride];
    o[0] += hsum(gmx); o[1] += hsum(gmy);
    o[2] += hsum(ga); o[3] += hsum(gb); o[4] += hsum(gc);
    o[5] += hsum(go);
    o[6] += hsum(gr); o[7] += hsum(gg); o[8] += hsum(gbl);
  }
}
constexpr auto kRenderTile = render_tile_fast;
constexpr auto kBackwardTile = backward_tile_avx512;
#else
constexpr auto kRenderTile = render_tile;
constexpr auto kBackwardTile = backward_tile;
#endif  // __AVX512F__

// Inputs and outputs of stgs_project.
struct ProjectIO {
  const float *means, *quats, *scales, *opac;
  const double *viewmat, *K;
  float *means2d, *conics, *depths, *extents;
};

// Projection of Gaussian i (stgs_project's outputs for one Gaussian).
inline void project_one(int64_t i, const ProjectIO& io) {
  const float *means = io.means, *quats = io.quats, *scales = io.scales, *opac = io.opac;
  const double *viewmat = io.viewmat, *K = io.K;
  float *means2d = io.means2d, *conics = io.conics, *depths = io.depths, *extents = io.extents;
  const double px = means[3 * i], py = means[3 * i + 1], pz = means[3 * i + 2];
  const double x = viewmat[0] * px + viewmat[1] * py + viewmat[2] * pz + viewmat[3];
  const double y = viewmat[4] * px + viewmat[5] * py + viewmat[6] * pz + viewmat[7];
  const double z = viewmat[8] * px + viewmat[9] * py + viewmat[10] * pz + viewmat[11];
  const bool valid = z >= kNearZ;
  const double zs = valid ? z : 1.0;
  const double xn = x / zs, yn = y / zs;
  means2d[2 * i] = float(K[0] * xn + K[1] * yn + K[2]);
  means2d[2 * i + 1] = float(K[4] * yn + K[5]);
  depths[i] = valid ? float(z) : -1.0f;
  // Rotation from the overflow-safe normalised quaternion (zero -> identity).
  double q[4] = {quats[4 * i], quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3]};
  double peak = std::max(std::max(std::fabs(q[0]), std::fabs(q[1])),
                         std::max(std::fabs(q[2]), std::fabs(q[3])));
  if (peak > 0) {
    for (double& c : q) c /= peak;
    const double nrm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (double& c : q) c /= nrm;
  } else {
    q[0] = 1; q[1] = q[2] = q[3] = 0;
  }
  const double w = q[0], qx = q[1], qy = q[2], qz = q[3];
  const double R[9] = {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
                       2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx),
                       2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)};
  // jac = K[:2,:2] @ d(xn,yn)/d(p_cam); M = jac @ Rcw @ R @ diag(s).
  const double dn[6] = {1 / zs, 0, -xn / zs, 0, 1 / zs, -yn / zs};
  double jac[6];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      jac[3 * r + c] = K[3 * r] * dn[c] + K[3 * r + 1] * dn[3 + c];
  double jw[6];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      jw[3 * r + c] = jac[3 * r] * viewmat[c] + jac[3 * r + 1] * viewmat[4 + c] +
                      jac[3 * r + 2] * viewmat[8 + c];
  double M[6];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      M[3 * r + c] = (jw[3 * r] * R[c] + jw[3 * r + 1] * R[3 + c] + jw[3 * r + 2] * R[6 + c]) *
                     double(scales[3 * i + c]);
  const double a0 = M[0] * M[0] + M[1] * M[1] + M[2] * M[2];
  const double b0 = M[0] * M[3] + M[1] * M[4] + M[2] * M[5];
  const double c0 = M[3] * M[3] + M[4] * M[4] + M[5] * M[5];
  const double m01 = M[0] * M[4] - M[1] * M[3], m02 = M[0] * M[5] - M[2] * M[3],
               m12 = M[1] * M[5] - M[2] * M[4];
  const double det = m01 * m01 + m02 * m02 + m12 * m12 + kBlur * (a0 + c0) + kBlur * kBlur;
  conics[3 * i] = float((c0 + kBlur) / det);
  conics[3 * i + 1] = float(-b0 / det);
  conics[3 * i + 2] = float((a0 + kBlur) / det);
  const double level = 255.0 * double(opac[i]);
  if (valid && level >= 1.0) {
    const double quad = 2.0 * std::log(level);
    extents[2 * i] = float(std::sqrt(quad * (a0 + kBlur)) * kExtentMargin + 1e-3);
    extents[2 * i + 1] = float(std::sqrt(quad * (c0 + kBlur)) * kExtentMargin + 1e-3);
  } else {
    extents[2 * i] = extents[2 * i + 1] = -1.0f;
  }
}

#if defined(__AVX512F__)
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
#endif

}  // namespace

extern "C" {

// Projection in double precision; mirrors stgs.render.project.project.
// viewmat: 4x4 row-major world-to-camera; K: 3x3 row-major.
void stgs_project(int64_t n, const float* means, const float* quats, const float* scales,
                  const float* opac, const double* viewmat, const double* K, float* means2d,
                  float* conics, float* depths, float* extents, int nthreads) {
  const ProjectIO io{means, quats, scales, opac, viewmat, K, means2d, conics, depths, extents};
#if defined(__AVX512F__)
  const int64_t blocks = n / 8;
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t blk = 0; blk < blocks; ++blk) project_x8(8 * blk, io);
  for (int64_t i = 8 * blocks; i < n; ++i) project_one(i, io);
#else
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < n; ++i) project_one(i, io);
#endif
}

// Bins, sorts and composites. Returns a context for the backward pass (free it
// with stgs_raster_free) and writes the (H, W, 3) image to out. Without
// for_backward the per-pixel bookkeeping the backward pass reads is skipped
// and the context only serves stgs_raster_pairs.
void* stgs_raster_forward(int64_t n, const float* xy, const float* conic, const float* opac,
                          const float* color, const float* depth, const float* extent,
                          const float* bg, int width, int height, float* out, int for_backward,
                          int nthreads) {
  RasterCtx* ctx = acquire_ctx();
  ctx->width = width;
  ctx->height = height;
  ctx->tiles_x = (width + kTile - 1) / kTile;
  ctx->tiles_y = (height + kTile - 1) / kTile;
  const int tiles = ctx->tiles_x * ctx->tiles_y;
  ctx->splats.resize(n);
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    Splat& s = ctx->splats[i];
    s = {xy[2 * i], xy[2 * i + 1], conic[3 * i], conic[3 * i + 1], conic[3 * i + 2], opac[i],
         color[3 * i], color[3 * i + 1], color[3 * i + 2], 0.0f, {0, -1, 0, -1}, 0.0f};
    if (!(extent[2 * i] >= 0.0f)) continue;
    s.min_power = -std::log(255.0f * opac[i]) - 1e-3f;
    s.log2_o = std::log2(opac[i]);
    pixel_range(xy[2 * i], extent[2 * i], width, s.rect.u0, s.rect.u1);
    pixel_range(xy[2 * i + 1], extent[2 * i + 1], height, s.rect.v0, s.rect.v1);
  }
  std::vector<int32_t>& visible = ctx->scratch.visible;
  visible.clear();
  visible.reserve(n);
  for (int64_t i = 0; i < n; ++i) {
    const Rect& r = ctx->splats[i].rect;
    if (r.u0 <= r.u1 && r.v0 <= r.v1) visible.push_back(int32_t(i));
  }
  radix_sort_by_depth(visible, depth, ctx->scratch, nthreads);
  bin_by_tile(*ctx, visible, nthreads);
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

// Gradients of the composited image with respect to the forward's inputs.
// The forward's inputs are read from the copies the context keeps (ctx.splats).
void stgs_raster_backward(void* handle, int64_t n, const float* bg, const float* grad_out,
                          float* grad_xy, float* grad_conic, float* grad_opac, float* grad_color,
                          float* grad_bg, int nthreads) {
  const auto* ctx = static_cast<const RasterCtx*>(handle);
  if (!ctx->for_backward) return;  // the forward kept nothing to differentiate (bindings never ask)
  const int tiles = ctx->tiles_x * ctx->tiles_y;
  std::vector<float> partial(size_t(nthreads) * n * kGradStride, 0.0f);
  std::vector<double> partial_bg(size_t(nthreads) * 3, 0.0);
#pragma omp parallel num_threads(nthreads)
  {
    const int tid = omp_get_thread_num();
    float* mine = partial.data() + size_t(tid) * n * kGradStride;
    // static: which thread sums which tile must not vary between runs, or seeded training is not reproducible
#pragma omp for schedule(static, 1)
    for (int t = 0; t < tiles; ++t)
      kBackwardTile(*ctx, t, bg, grad_out, mine, &partial_bg[3 * tid]);
  }
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    float sum[kGradStride] = {0};
    for (int t = 0; t < nthreads; ++t)
      for (int j = 0; j < kGradStride; ++j) sum[j] += partial[(size_t(t) * n + i) * kGradStride + j];
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

// Number of (tile, Gaussian) pairs the last forward binned: a cost statistic.
int64_t stgs_raster_pairs(void* handle) {
  return int64_t(static_cast<RasterCtx*>(handle)->ids.size());
}

void stgs_raster_free(void* handle) { release_ctx(static_cast<RasterCtx*>(handle)); }

}  // extern "C"
