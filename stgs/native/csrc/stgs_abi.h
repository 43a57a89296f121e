// The C ABI of the native library: every function Python calls, and nothing else.
//
// Each kernel source includes this header, so a definition whose signature drifts from
// its declaration here does not compile ("conflicting declaration of C function"); the
// Python bindings (stgs/native/abi.py) hand the text between the ABI markers to cffi,
// which checks every call's argument count and pointer types against it. Pointers are
// C-contiguous arrays; shapes are in the comments; nthreads is the OpenMP team size.
#pragma once

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

// Built with -fvisibility=hidden: these declarations are the library's only exports.
#pragma GCC visibility push(default)

// STGS_ABI_BEGIN

// --- splatter (project.cpp, binning.cpp, forward.cpp, backward.cpp) ---

// Projection of n Gaussians in double precision: means (n,3), quats (n,4) wxyz,
// scales (n,3), opac (n); viewmat 4x4 and K 3x3 row-major. Writes means2d (n,2),
// conics (n,3), depths (n) (-1: culled), extents (n,2) (-1: culled).
void stgs_project(int64_t n, const float* means, const float* quats, const float* scales,
                  const float* opac, const double* viewmat, const double* K, float* means2d,
                  float* conics, float* depths, float* extents, int nthreads);

// Gradients of stgs_project's means2d and conics (grad_means2d (n,2), grad_conics (n,3)) in
// means (n,3), quats (n,4) and scales (n,3), written to grad_means, grad_quats, grad_scales;
// the forward is recomputed in double. Culled Gaussians get zero.
void stgs_project_backward(int64_t n, const float* means, const float* quats, const float* scales,
                           const double* viewmat, const double* K, const float* grad_means2d,
                           const float* grad_conics, float* grad_means, float* grad_quats, float* grad_scales,
                           int nthreads);

// Binning alone: returns a context (free it with stgs_raster_free) whose tile lists
// stgs_raster_tiles copies out.
void* stgs_raster_bin(int64_t n, const float* xy, const float* conic, const float* opac,
                      const float* depth, const float* extent, int width, int height, int nthreads);

// A context's tile offsets, tile_start (tiles + 1), and tile lists, ids (stgs_raster_pairs).
void stgs_raster_tiles(void* handle, int64_t* tile_start, int32_t* ids);

// Bins and composites into out (height, width, 3); returns the context. With
// for_backward the context keeps what stgs_raster_backward and stgs_raster_pixels read.
void* stgs_raster_forward(int64_t n, const float* xy, const float* conic, const float* opac,
                          const float* color, const float* depth, const float* extent,
                          const float* bg, int width, int height, float* out, int for_backward,
                          int nthreads);

// Per pixel (height * width): final transmittance and the 1-based rank, in its tile's
// list, of the last Gaussian composited (0: none). Only after a for_backward forward.
void stgs_raster_pixels(void* handle, float* trans_final, int32_t* n_contrib);

// Gradients of the image with respect to the forward's xy (n,2), conic (n,3), opac (n),
// color (n,3) and bg (3), given grad_out (height, width, 3).
void stgs_raster_backward(void* handle, int64_t n, const float* bg, const float* grad_out,
                          float* grad_xy, float* grad_conic, float* grad_opac, float* grad_color,
                          float* grad_bg, int nthreads);

// (tile, Gaussian) pairs the context binned: a cost statistic.
int64_t stgs_raster_pairs(void* handle);

// A layer kept for the frames of one camera (kept.cpp): bins n Gaussians and renders them
// alone into out (height, width, 3) over bg, as stgs_raster_forward does, and returns what
// stgs_raster_over reuses (free it with stgs_raster_kept_free). Not for two threads at once.
void* stgs_raster_keep(int64_t n, const float* xy, const float* conic, const float* opac,
                       const float* color, const float* depth, const float* extent, const float* bg,
                       int width, int height, float* out, int nthreads);

// The image stgs_raster_forward makes of the kept layer's Gaussians followed by these n, into
// out: only these are binned; each tile one of them reaches gets both lists merged front to
// back and is composited, the others are copied from the kept image. Returns the tiles copied.
int64_t stgs_raster_over(void* kept, int64_t n, const float* xy, const float* conic, const float* opac,
                         const float* color, const float* depth, const float* extent, float* out,
                         int nthreads);

// stgs_raster_over for training: the image (reached tiles composited by the tracked kernel, the
// others copied from the kept image), and a context for stgs_raster_backward (free it with
// stgs_raster_free) over the kept layer's Gaussians followed by these n. Unreached tiles get empty
// lists, so the backward pass gives the moving Gaussians their whole gradients and the background's
// covers the reached tiles only; it leaves the kept ones' rows of its outputs as they were (it only
// undoes their compositing). Reads the kept layer only: several such calls may
// share it (not with stgs_raster_over, which writes it).
void* stgs_raster_over_train(void* kept, int64_t n, const float* xy, const float* conic, const float* opac,
                             const float* color, const float* depth, const float* extent, float* out,
                             int nthreads);

void stgs_raster_kept_free(void* kept);

void stgs_raster_free(void* handle);

// --- SSIM (ssim.cpp) ---

// SSIM of (height, width, 3) image against reference with the 11 window taps (stgs/metrics.py):
// writes the channel-mean map ssim (height, width) and, unless NULL, partials (9, height, width),
// what stgs_ssim_backward reads.
void stgs_ssim_forward(int height, int width, const float* image, const float* reference,
                       const float* taps, float* ssim, float* partials, int nthreads);

// The gradient grad_image (height, width, 3) of the map's inner product with grad_ssim
// (height, width), from the forward's partials.
void stgs_ssim_backward(int height, int width, const float* image, const float* reference,
                        const float* taps, const float* partials, const float* grad_ssim,
                        float* grad_image, int nthreads);

// --- temporal consistency (temporal.cpp) ---

// The sum over e < rows - 1 and j < cols of Huber_delta(features[e+1][j] - features[e][j]) for
// (rows, cols) float32 features (torch's huber_loss terms); 0 when rows < 2. Does not depend on nthreads.
double stgs_temporal_huber_forward(int64_t rows, int64_t cols, const float* features, float delta,
                                   int nthreads);

// grad (rows, cols) = scale * the gradient of that sum in features, plus window_grad (window_rows, cols)
// added at rows first ... first + window_rows - 1 (unless window_grad is NULL).
void stgs_temporal_huber_backward(int64_t rows, int64_t cols, const float* features, float delta,
                                  float scale, const float* window_grad, int64_t first,
                                  int64_t window_rows, float* grad, int nthreads);

// --- deformation (deform.cpp, deform_bf16.cpp, deform_int16.cpp) ---

// The deformation field of one frame in float32 for n Gaussians (docs/MODEL_FORMAT.md; weights packed
// by stgs/model/native_deform.py). window_feats holds `window` pointers, to the frame's
// features e_i ... e_{i+W-1} (n x 16 floats each). With viewmat, Gaussians that cannot
// reach the image (or, with guard, lie outside the guard band) get opacity 0.
void stgs_deform(int64_t n, int window, const float* const* window_feats, const float* xyz,
                 const float* log_scale, const float* rotation, const float* opacity_logit,
                 const float* color, const float* temporal_t, const float* pe_bias,
                 const float* geo1_t, const float* geo2_t, const float* app1_t,
                 const float* app2_t, const float* camera_center, const double* viewmat,
                 const double* K, int width, int height, float* out_means, float* out_quats,
                 float* out_scales, float* out_opac, float* out_colors, const double* guard,
                 int nthreads);

// The back ends of stgs_deform_bf16 that can run in this process, as a bit mask: 1 AVX512-BF16
// vectors (built for such a CPU), 2 AMX tiles (built for AMX, and Linux grants AMX state).
int stgs_deform_bf16_backends(void);

// stgs_deform in bf16 on `backend` (1 or 2, as above), the five weights packed as bf16 tiles
// (stgs/model/native_deform.py); 0, or -1 (nothing written) when that back end cannot run here.
int stgs_deform_bf16(int64_t n, int window, const float* const* window_feats, const float* xyz,
                     const float* log_scale, const float* rotation, const float* opacity_logit,
                     const float* color, const void* temporal_w, int t_chunks, const float* pe_bias,
                     const void* geo1_w, const void* geo2_w, const void* app1_w, const void* app2_w,
                     const float* camera_center, const double* viewmat, const double* K, int width,
                     int height, float* out_means, float* out_quats, float* out_scales, float* out_opac,
                     float* out_colors, const double* guard, int backend, int nthreads);

// The kernel stgs_deform_int16 runs: 0 not built (the compiler does not target AVX2), 1 AVX2 (vpmaddwd),
// 2 AVX512BW (vpmaddwd on 512-bit registers), 3 AVX512-VNNI (vpdpwssd). All give the same bits.
int stgs_deform_int16_available(void);

// stgs_deform with int16 products and exact int32 sums (deform_int16.cpp): layer_weights holds the
// five layers (temporal, geo1, geo2, app1, app2) as (K/2) x M x 2 int16, col_scales their column
// scales, qx their input bounds (stgs/model/native_deform.py packs them). 0, or -1 (nothing
// written) where it was not built or the window is out of range.
int stgs_deform_int16(int64_t n, int window, const float* const* window_feats, const float* xyz,
                      const float* log_scale, const float* rotation, const float* opacity_logit,
                      const float* color, const int16_t* const* layer_weights, const float* const* col_scales,
                      const float* qx, const float* pe_bias, const float* camera_center, const double* viewmat,
                      const double* K, int width, int height, float* out_means, float* out_quats,
                      float* out_scales, float* out_opac, float* out_colors, const double* guard, int nthreads);

// STGS_ABI_END

#pragma GCC visibility pop

#ifdef __cplusplus
}  // extern "C"
#endif
