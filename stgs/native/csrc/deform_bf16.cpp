// bf16 deformation field (inference only): the layers of deform.cpp with bf16
// inputs and weights and float32 accumulation, an accuracy knob
// (docs/BENCHMARKS.md measures what it costs). Two back ends run the same
// block loop: AMX tiles (Intel Sapphire Rapids and later, where the kernel
// grants AMX state) and AVX512-BF16 vectors (`vdpbf16ps`: AMD Zen 4/5, Intel
// Cooper Lake). Both take the weights packed by stgs/model/native_deform.py
// (`_bf16_tiles`): per K chunk of 32 and 16-column tile, 16 rows of (column,
// pair of consecutive K) bf16 values. One such row is an AMX B-tile row and
// also, as it stands, the second operand of one `vdpbf16ps`.
//
// Built only where the compiler targets AVX512-BF16 (AMX additionally needs
// AMX-TILE/AMX-BF16); elsewhere stgs_deform_bf16_backends returns 0 and
// stgs_deform_bf16 returns -1.

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <cstring>

#include "deform.h"
#include "stgs_abi.h"
#include "fastmath.h"

#if defined(__AVX512F__) && defined(__AVX512BF16__)
#define STGS_HAVE_BF16 1
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#if defined(__AMX_TILE__) && defined(__AMX_BF16__)
#define STGS_HAVE_AMX 1
#include <sys/syscall.h>
#include <unistd.h>
#else
#define STGS_HAVE_AMX 0
#endif
#else
#define STGS_HAVE_BF16 0
#define STGS_HAVE_AMX 0
#endif

namespace {

constexpr int kVectorBackend = 1;  // stgs_abi.h: AVX512-BF16 vectors
constexpr int kAmxBackend = 2;     // stgs_abi.h: AMX tiles

#if STGS_HAVE_BF16
using bf16 = uint16_t;
using stgs::kFeat;
using stgs::kHidden;
using stgs::kOut;

constexpr int kRows = 16;         // Gaussians per block: the rows of one tile
constexpr int kChunk = 32;        // bf16 values of K in one A-tile row
constexpr int kPairs = kChunk / 2;  // rows of one packed B tile
constexpr int kTileValues = 512;  // bf16 values in one packed B tile (16 pairs x 16 columns x 2)
constexpr int kMaxIn = 4 * kChunk;     // D_t's input (W·16 <= 128), padded
constexpr int kAppIn = 3 * kChunk;     // [h(64), view direction(3)] padded to 96
constexpr int kWide = 2 * kHidden;     // the two first decoder layers side by side

// The matrix products of one block on AVX512-BF16 vectors. vdpbf16ps adds, in each of 16
// float32 lanes, the products of one pair of bf16 values: lane m gets x[r, 2j] w[2j, m] +
// x[r, 2j+1] w[2j+1, m] from a broadcast pair of row r and one packed weight row.
struct VectorMatmul {
  static void begin() {}
  static void end() {}

  static __m512bh pair(const bf16* a) {
    uint32_t bits;
    std::memcpy(&bits, a, sizeof(bits));
    return (__m512bh)_mm512_set1_epi32(int(bits));
  }

  // c (16 x 64, row stride ldc floats) = a (16 x k bf16, row stride lda) @ column tiles ct0 …
  // ct0+3 of a packed weight that has ct_total column tiles per K chunk; 4 rows at a time, so
  // each weight row loaded feeds 4 products (16 accumulators). Only the pairs that hold some of
  // the k inputs are summed: the rest of the last chunk is zero padding.
  static void m16x64(const bf16* a, int lda, int k, const bf16* w, int ct_total, int ct0, float* c, int ldc) {
    const int pairs = (k + 1) / 2;
    for (int r0 = 0; r0 < kRows; r0 += 4) {
      __m512 acc[4][4];
      for (auto& row : acc)
        for (auto& v : row) v = _mm512_setzero_ps();
      for (int p = 0; p < pairs; ++p) {
        const bf16* wp = w + ((size_t(p / kPairs) * ct_total + ct0) * kTileValues) + (p % kPairs) * kChunk;
        __m512bh wv[4];
        for (int t = 0; t < 4; ++t) wv[t] = (__m512bh)_mm512_loadu_si512(wp + t * kTileValues);
        for (int r = 0; r < 4; ++r) {
          const __m512bh av = pair(a + (r0 + r) * lda + 2 * p);
          for (int t = 0; t < 4; ++t) acc[r][t] = _mm512_dpbf16_ps(acc[r][t], av, wv[t]);
        }
      }
      for (int r = 0; r < 4; ++r)
        for (int t = 0; t < 4; ++t) _mm512_storeu_ps(c + (r0 + r) * ldc + 16 * t, acc[r][t]);
    }
  }

  // c (16 x 16) = a (16 x k) @ w (one column tile per K chunk).
  static void m16x16(const bf16* a, int lda, int k, const bf16* w, float* c) {
    __m512 acc[kRows];
    for (auto& v : acc) v = _mm512_setzero_ps();
    for (int p = 0; p < (k + 1) / 2; ++p) {
      const __m512bh wv = (__m512bh)_mm512_loadu_si512(w + size_t(p / kPairs) * kTileValues + (p % kPairs) * kChunk);
      for (int r = 0; r < kRows; ++r) acc[r] = _mm512_dpbf16_ps(acc[r], pair(a + r * lda + 2 * p), wv);
    }
    for (int r = 0; r < kRows; ++r) _mm512_storeu_ps(c + r * kOut, acc[r]);
  }
};

#if STGS_HAVE_AMX
struct alignas(64) TileConfig {
  uint8_t palette = 1;
  uint8_t start_row = 0;
  uint8_t reserved[14] = {};
  uint16_t colsb[16] = {};
  uint8_t rows[16] = {};
};

bool amx_permitted() {
  // Linux hands out AMX state per process on request (arch_prctl ARCH_REQ_XCOMP_PERM, XTILEDATA).
  static const bool ok = syscall(SYS_arch_prctl, 0x1023, 18) == 0;
  return ok;
}

// The same products on AMX tiles (each thread configures its tiles once per call).
struct AmxMatmul {
  static void begin() {
    TileConfig cfg;
    for (int t = 0; t < 8; ++t) {
      cfg.colsb[t] = 64;
      cfg.rows[t] = kRows;
    }
    _tile_loadconfig(&cfg);
  }
  static void end() { _tile_release(); }

  // Whole K chunks: the tiles' zero padding is summed.
  static void m16x64(const bf16* a, int lda, int k, const bf16* w, int ct_total, int ct0, float* c, int ldc) {
    const int chunks = (k + kChunk - 1) / kChunk;
    _tile_zero(0);
    _tile_zero(1);
    _tile_zero(2);
    _tile_zero(3);
    for (int kc = 0; kc < chunks; ++kc) {
      const bf16* wk = w + (size_t(kc) * ct_total + ct0) * kTileValues;
      _tile_loadd(4, a + kc * kChunk, lda * 2);
      _tile_loadd(5, wk, 64);
      _tile_loadd(6, wk + kTileValues, 64);
      _tile_dpbf16ps(0, 4, 5);
      _tile_loadd(7, wk + 2 * kTileValues, 64);
      _tile_dpbf16ps(1, 4, 6);
      _tile_loadd(5, wk + 3 * kTileValues, 64);
      _tile_dpbf16ps(2, 4, 7);
      _tile_dpbf16ps(3, 4, 5);
    }
    _tile_stored(0, c, ldc * 4);
    _tile_stored(1, c + 16, ldc * 4);
    _tile_stored(2, c + 32, ldc * 4);
    _tile_stored(3, c + 48, ldc * 4);
  }

  static void m16x16(const bf16* a, int lda, int k, const bf16* w, float* c) {
    const int chunks = (k + kChunk - 1) / kChunk;
    _tile_zero(0);
    for (int kc = 0; kc < chunks; ++kc) {
      _tile_loadd(4, a + kc * kChunk, lda * 2);
      _tile_loadd(5, w + size_t(kc) * kTileValues, 64);
      _tile_dpbf16ps(0, 4, 5);
    }
    _tile_stored(0, c, kOut * 4);
  }
};
#endif  // STGS_HAVE_AMX

// 16 floats -> 16 bf16 (round to nearest even).
inline void store_bf16(bf16* dst, __m512 v) {
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(dst), (__m256i)_mm512_cvtneps_pbh(v));
}

inline bf16 scalar_bf16(float v) {
  uint32_t bits;
  std::memcpy(&bits, &v, 4);
  bits += 0x7fffu + ((bits >> 16) & 1u);
  return bf16(bits >> 16);
}

// relu(c) of a (16 x 128) float block into bf16 (c second: max returns it when it is NaN, as torch.relu does).
void relu_to_bf16(const float* c, bf16* a) {
  const __m512 zero = _mm512_setzero_ps();
  for (int i = 0; i < kRows * kWide; i += 16) store_bf16(a + i, _mm512_max_ps(zero, _mm512_load_ps(c + i)));
}

// The packed bf16 weights of the five layers (see stgs_deform_bf16).
struct Bf16Weights {
  const bf16 *temporal, *geo1, *geo2, *app1, *app2;
  int t_chunks;
};

// All blocks of 16 Gaussians on back end MM (VectorMatmul or AmxMatmul).
template <class MM>
void deform_blocks(const stgs::DeformIO& io, int64_t n, int window, const float* const* window_feats,
                   const Bf16Weights& w, const float* pe_bias, int nthreads) {
  const int lt = w.t_chunks * kChunk;
  const int64_t blocks = (n + kRows - 1) / kRows;
#pragma omp parallel num_threads(nthreads)
  {
    MM::begin();
    // Padding columns (and rows past n) must hold finite values: they meet zero weights.
    alignas(64) bf16 a_t[kRows * kMaxIn] = {};
    alignas(64) bf16 a_h[kRows * kHidden];
    alignas(64) bf16 a_wide[kRows * kWide];
    alignas(64) bf16 a_app[kRows * kAppIn] = {};
    alignas(64) float c[kRows * kWide];
    alignas(64) float out2[kRows * kOut];
#pragma omp for schedule(dynamic, 16)
    for (int64_t blk = 0; blk < blocks; ++blk) {
      const int64_t first = blk * kRows;
      const int rows = int(std::min<int64_t>(kRows, n - first));
      for (int b = 0; b < rows; ++b)
        for (int f = 0; f < window; ++f)
          store_bf16(&a_t[b * lt + f * kFeat], _mm512_loadu_ps(window_feats[f] + (first + b) * kFeat));
      MM::m16x64(a_t, lt, window * kFeat, w.temporal, 4, 0, c, kHidden);
      for (int b = 0; b < kRows; ++b)
        for (int m = 0; m < kHidden; m += 16)
          store_bf16(&a_h[b * kHidden + m],
                     stgs::fast_tanh_v(_mm512_add_ps(_mm512_load_ps(&c[b * kHidden + m]), _mm512_loadu_ps(pe_bias + m))));
      // D_v and D_cov: [dx(3) ds(3) dq(4)] in out2.
      MM::m16x64(a_h, kHidden, kHidden, w.geo1, 8, 0, c, kWide);
      MM::m16x64(a_h, kHidden, kHidden, w.geo1, 8, 4, c + 64, kWide);
      relu_to_bf16(c, a_wide);
      MM::m16x16(a_wide, kWide, kWide, w.geo2, out2);
      stgs::deformed_scales(io, first, rows, out2, kOut);
      bool keep[kRows];
      const int kept = stgs::cull_block(io, first, rows, out2, kOut, keep, [&](int b, const float* dir) {
        std::memcpy(&a_app[b * kAppIn], &a_h[b * kHidden], kHidden * sizeof(bf16));
        for (int k = 0; k < 3; ++k) a_app[b * kAppIn + kHidden + k] = scalar_bf16(dir[k]);
      });
      if (kept == 0) continue;
      // D_o and D_c on [h, view direction]: [do(1) dc(3)] in out2.
      MM::m16x64(a_app, kAppIn, kHidden + 3, w.app1, 8, 0, c, kWide);
      MM::m16x64(a_app, kAppIn, kHidden + 3, w.app1, 8, 4, c + 64, kWide);
      relu_to_bf16(c, a_wide);
      MM::m16x16(a_wide, kWide, kWide, w.app2, out2);
      for (int b = 0; b < rows; ++b)
        if (keep[b])
          stgs::deformed_appearance(io, first + b, &out2[b * kOut]);
    }
    MM::end();
  }
}
#endif  // STGS_HAVE_BF16

int runnable_backends() {
  int mask = STGS_HAVE_BF16 ? kVectorBackend : 0;
#if STGS_HAVE_AMX
  if (amx_permitted()) mask |= kAmxBackend;
#endif
  return mask;
}

}  // namespace

extern "C" {

int stgs_deform_bf16_backends() { return runnable_backends(); }

int stgs_deform_bf16(int64_t n, int window, const float* const* window_feats, const float* xyz,
                     const float* log_scale, const float* rotation, const float* opacity_logit,
                     const float* color, const void* temporal_w, int t_chunks, const float* pe_bias,
                     const void* geo1_w, const void* geo2_w, const void* app1_w, const void* app2_w,
                     const float* camera_center, const double* viewmat, const double* K, int width,
                     int height, float* out_means, float* out_quats, float* out_scales, float* out_opac,
                     float* out_colors, const double* guard, int backend, int nthreads) {
  if ((backend != kVectorBackend && backend != kAmxBackend) || !(runnable_backends() & backend)) return -1;
#if STGS_HAVE_BF16
  if (t_chunks < 1 || t_chunks * kChunk > kMaxIn || window * kFeat > t_chunks * kChunk) return -1;
  const Bf16Weights weights{static_cast<const bf16*>(temporal_w), static_cast<const bf16*>(geo1_w),
                            static_cast<const bf16*>(geo2_w),     static_cast<const bf16*>(app1_w),
                            static_cast<const bf16*>(app2_w),     t_chunks};
  const stgs::DeformIO io{xyz, log_scale, rotation, opacity_logit, color, camera_center, viewmat, K, width,
                          height, out_means, out_quats, out_scales, out_opac, out_colors, guard};
#if STGS_HAVE_AMX
  if (backend == kAmxBackend) {
    deform_blocks<AmxMatmul>(io, n, window, window_feats, weights, pe_bias, nthreads);
    return 0;
  }
#endif
  deform_blocks<VectorMatmul>(io, n, window, window_feats, weights, pe_bias, nthreads);
  return 0;
#else
  (void)n, (void)window, (void)window_feats, (void)xyz, (void)log_scale, (void)rotation;
  (void)opacity_logit, (void)color, (void)temporal_w, (void)t_chunks, (void)pe_bias, (void)geo1_w;
  (void)geo2_w, (void)app1_w, (void)app2_w, (void)camera_center, (void)viewmat, (void)K, (void)width;
  (void)height, (void)out_means, (void)out_quats, (void)out_scales, (void)out_opac, (void)out_colors;
  (void)guard, (void)nthreads;
  return -1;
#endif
}

}  // extern "C"
