// bf16 deformation field on AMX tiles (inference only). The layers of
// deform.cpp with bf16 inputs and weights and float32 accumulation: an
// accuracy knob (docs/BENCHMARKS.md measures what it costs). Weights arrive
// packed as AMX B tiles by stgs/model/native_deform.py (`_amx_tiles`).
//
// Built only where the compiler targets AMX-BF16; elsewhere, and where the
// kernel refuses AMX to this process, stgs_deform_bf16 returns -1.

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <cstring>

#include "deform.h"
#include "stgs_abi.h"
#include "fastmath.h"

#if defined(__AMX_TILE__) && defined(__AMX_BF16__) && defined(__AVX512BF16__)
#define STGS_HAVE_AMX 1
// GCC 12's AVX-512 headers trip -Wmaybe-uninitialized on their own internals.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>
#else
#define STGS_HAVE_AMX 0
#endif

namespace {

#if STGS_HAVE_AMX
using bf16 = uint16_t;
using stgs::kFeat;
using stgs::kHidden;
using stgs::kOut;

constexpr int kRows = 16;         // Gaussians per block: the rows of one tile
constexpr int kChunk = 32;        // bf16 values of K in one A-tile row
constexpr int kTileValues = 512;  // bf16 values in one packed B tile (16 pairs x 16 columns x 2)
constexpr int kMaxIn = 4 * kChunk;     // D_t's input (W·16 <= 128), padded
constexpr int kAppIn = 3 * kChunk;     // [h(64), view direction(3)] padded to 96
constexpr int kWide = 2 * kHidden;     // the two first decoder layers side by side

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

void configure_tiles() {
  TileConfig cfg;
  for (int t = 0; t < 8; ++t) {
    cfg.colsb[t] = 64;
    cfg.rows[t] = kRows;
  }
  _tile_loadconfig(&cfg);
}

// c (16 x 64, row stride ldc floats) = a (16 x 32·chunks bf16, row stride lda) @ column tiles
// ct0 … ct0+3 of a packed weight that has ct_total column tiles per K chunk.
void matmul_16x64(const bf16* a, int lda, int chunks, const bf16* w, int ct_total, int ct0, float* c,
                  int ldc) {
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

// c (16 x 16) = a (16 x 32·chunks) @ w (one column tile per chunk).
void matmul_16x16(const bf16* a, int lda, int chunks, const bf16* w, float* c) {
  _tile_zero(0);
  for (int kc = 0; kc < chunks; ++kc) {
    _tile_loadd(4, a + kc * kChunk, lda * 2);
    _tile_loadd(5, w + size_t(kc) * kTileValues, 64);
    _tile_dpbf16ps(0, 4, 5);
  }
  _tile_stored(0, c, kOut * 4);
}

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
#endif  // STGS_HAVE_AMX

}  // namespace

extern "C" {

// 1 when stgs_deform_bf16 can run in this process.
int stgs_deform_bf16_available() {
#if STGS_HAVE_AMX
  return amx_permitted() ? 1 : 0;
#else
  return 0;
#endif
}

// stgs_deform (deform.cpp) in bf16: same inputs and outputs, except that the
// five weights are AMX tiles (temporal: t_chunks K chunks x 4 column tiles;
// geo1/app1: 2/3 chunks x 8; geo2/app2: 4 chunks x 1). Returns 0, or -1 when
// AMX is not available (nothing is written then).
int stgs_deform_bf16(int64_t n, int window, const float* const* window_feats, const float* xyz,
                     const float* log_scale, const float* rotation, const float* opacity_logit,
                     const float* color, const void* temporal_w, int t_chunks, const float* pe_bias,
                     const void* geo1_w, const void* geo2_w, const void* app1_w, const void* app2_w,
                     const float* camera_center, const double* viewmat, const double* K, int width,
                     int height, float* out_means, float* out_quats, float* out_scales, float* out_opac,
                     float* out_colors, const double* guard, int nthreads) {
#if STGS_HAVE_AMX
  if (!amx_permitted() || t_chunks < 1 || t_chunks * kChunk > kMaxIn || window * kFeat > t_chunks * kChunk)
    return -1;
  const auto* w_t = static_cast<const bf16*>(temporal_w);
  const auto* w_geo1 = static_cast<const bf16*>(geo1_w);
  const auto* w_geo2 = static_cast<const bf16*>(geo2_w);
  const auto* w_app1 = static_cast<const bf16*>(app1_w);
  const auto* w_app2 = static_cast<const bf16*>(app2_w);
  const stgs::DeformIO io{xyz, log_scale, rotation, opacity_logit, color, camera_center, viewmat, K, width,
                          height, out_means, out_quats, out_scales, out_opac, out_colors, guard};
  const int lt = t_chunks * kChunk;
  const int64_t blocks = (n + kRows - 1) / kRows;
#pragma omp parallel num_threads(nthreads)
  {
    configure_tiles();
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
        for (int w = 0; w < window; ++w)
          store_bf16(&a_t[b * lt + w * kFeat], _mm512_loadu_ps(window_feats[w] + (first + b) * kFeat));
      matmul_16x64(a_t, lt, t_chunks, w_t, 4, 0, c, kHidden);
      for (int b = 0; b < kRows; ++b)
        for (int m = 0; m < kHidden; m += 16)
          store_bf16(&a_h[b * kHidden + m],
                     stgs::fast_tanh_v(_mm512_add_ps(_mm512_load_ps(&c[b * kHidden + m]), _mm512_loadu_ps(pe_bias + m))));
      // D_v and D_cov: [dx(3) ds(3) dq(4)] in out2.
      matmul_16x64(a_h, kHidden, 2, w_geo1, 8, 0, c, kWide);
      matmul_16x64(a_h, kHidden, 2, w_geo1, 8, 4, c + 64, kWide);
      relu_to_bf16(c, a_wide);
      matmul_16x16(a_wide, kWide, 4, w_geo2, out2);
      stgs::deformed_scales(io, first, rows, out2, kOut);
      bool keep[kRows];
      int kept = 0;
      for (int b0 = 0; b0 < rows; b0 += stgs::kGeometryLanes) {
        float dirs[3 * stgs::kGeometryLanes];
        const int count = std::min(stgs::kGeometryLanes, rows - b0);
        const unsigned lanes = stgs::block_geometry(io, first + b0, count, &out2[b0 * kOut], kOut, dirs);
        for (int i = 0; i < count; ++i) {
          const int b = b0 + i;
          keep[b] = (lanes >> i) & 1u;
          if (!keep[b]) continue;
          std::memcpy(&a_app[b * kAppIn], &a_h[b * kHidden], kHidden * sizeof(bf16));
          for (int k = 0; k < 3; ++k) a_app[b * kAppIn + kHidden + k] = scalar_bf16(dirs[3 * i + k]);
          ++kept;
        }
      }
      if (kept == 0) continue;
      // D_o and D_c on [h, view direction]: [do(1) dc(3)] in out2.
      matmul_16x64(a_app, kAppIn, 3, w_app1, 8, 0, c, kWide);
      matmul_16x64(a_app, kAppIn, 3, w_app1, 8, 4, c + 64, kWide);
      relu_to_bf16(c, a_wide);
      matmul_16x16(a_wide, kWide, 4, w_app2, out2);
      for (int b = 0; b < rows; ++b)
        if (keep[b])
          stgs::deformed_appearance(io, first + b, &out2[b * kOut]);
    }
    _tile_release();
  }
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
