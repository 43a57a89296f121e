// SSIM of two (height, width, 3) float32 images and its gradient in the first, fused (stgs/metrics.py's
// formula: 11-tap separable Gaussian window, zero padding, the map averaged over the channels).
//
// The forward blurs the fifteen windowed moments (x, y, x², y², xy per channel) row by row and
// writes, beside the map, the nine partial derivatives of the map in the image's windowed mean,
// mean square and product with the reference. The backward multiplies them by the upstream
// gradient, blurs them with the same window (a symmetric, zero-padded window is its own adjoint)
// and applies the chain rule through x² and xy. Autograd's graph of the same formula also blurs
// the reference's six channels backwards and writes every intermediate (bench.loss_terms).

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <memory>

#include "stgs_abi.h"

namespace {

constexpr int kTaps = 11;
constexpr int kPad = kTaps / 2;
constexpr float kC1 = 0.01f * 0.01f;
constexpr float kC2 = 0.03f * 0.03f;

// One plane's row of the window: dst[x] = sum over k of taps[k] * src[x + k - kPad], zero padded.
inline void row_pass(int width, const float* taps, const float* __restrict src, float* __restrict dst) {
  auto edge = [&](int x) {
    float sum = 0.0f;
    for (int k = 0; k < kTaps; ++k) {
      const int at = x + k - kPad;
      if (at >= 0 && at < width) sum += taps[k] * src[at];
    }
    dst[x] = sum;
  };
  const int lo = std::min(kPad, width), hi = std::max(lo, width - kPad);
  for (int x = 0; x < lo; ++x) edge(x);
  for (int x = lo; x < hi; ++x) {
    float sum = 0.0f;
    for (int k = 0; k < kTaps; ++k) sum += taps[k] * src[x + k - kPad];
    dst[x] = sum;
  }
  for (int x = hi; x < width; ++x) edge(x);
}

// The separable window over the rows of C planes that `fill(y, row)` makes row by row (row[c * width + x]),
// each blurred row handed to `use(y, row)` in the same layout, whose loops over x vectorise. Each thread
// takes a band of rows and keeps the row pass of the kTaps rows around the one it finishes in a ring (a
// few hundred KB, in cache), so no full-size intermediate is written: the rows at a band's edges are made
// twice, by both bands.
template <int C, typename Fill, typename Use>
void blur_rows(int height, int width, const float* taps, Fill fill, Use use, int nthreads) {
  const int64_t stride = (int64_t)width * C;
#pragma omp parallel num_threads(nthreads)
  {
    const int team = omp_get_num_threads(), me = omp_get_thread_num();
    const int y0 = (int)((int64_t)height * me / team), y1 = (int)((int64_t)height * (me + 1) / team);
    std::unique_ptr<float[]> raw(new float[stride]), ring(new float[stride * kTaps]), out(new float[stride]);
    int next = std::max(0, y0 - kPad);  // the next row whose row pass goes into the ring
    for (int y = y0; y < y1; ++y) {
      for (; next <= std::min(height - 1, y + kPad); ++next) {
        fill(next, raw.get());
        float* __restrict dst = ring.get() + (int64_t)(next % kTaps) * stride;
        for (int c = 0; c < C; ++c) row_pass(width, taps, raw.get() + (int64_t)c * width, dst + (int64_t)c * width);
      }
      const float* rows[kTaps];  // the ring's rows y - kPad ... y + kPad; zero padding beyond the image
      for (int k = 0; k < kTaps; ++k) {
        const int r = y + k - kPad;
        rows[k] = r < 0 || r >= height ? nullptr : ring.get() + (int64_t)(r % kTaps) * stride;
      }
      float* __restrict acc = out.get();
      if (y >= kPad && y + kPad < height) {
        for (int64_t i = 0; i < stride; ++i) {
          float sum = 0.0f;
          for (int k = 0; k < kTaps; ++k) sum += taps[k] * rows[k][i];
          acc[i] = sum;
        }
      } else {
        for (int64_t i = 0; i < stride; ++i) acc[i] = 0.0f;
        for (int k = 0; k < kTaps; ++k)
          if (rows[k] != nullptr)
            for (int64_t i = 0; i < stride; ++i) acc[i] += taps[k] * rows[k][i];
      }
      use(y, (const float*)acc);
    }
  }
}

}  // namespace

extern "C" void stgs_ssim_forward(int height, int width, const float* image, const float* reference,
                                  const float* taps, float* ssim, float* partials, int nthreads) {
  auto fill = [&](int y, float* row) {  // the fifteen moments: x, y, x², y², xy per channel
    const float* a = image + (int64_t)y * width * 3;
    const float* b = reference + (int64_t)y * width * 3;
    for (int c = 0; c < 3; ++c) {
      float* mx = row + (int64_t)c * width;
      float* my = mx + 3 * width;
      float* xx = my + 3 * width;
      float* yy = xx + 3 * width;
      float* xy = yy + 3 * width;
      for (int x = 0; x < width; ++x) {
        const float u = a[x * 3 + c], v = b[x * 3 + c];
        mx[x] = u, my[x] = v, xx[x] = u * u, yy[x] = v * v, xy[x] = u * v;
      }
    }
  };
  const int64_t plane = (int64_t)height * width;
  auto use = [&](int y, const float* m) {
    float* __restrict out = ssim + (int64_t)y * width;
    for (int x = 0; x < width; ++x) out[x] = 0.0f;
    for (int c = 0; c < 3; ++c) {
      const float* __restrict mu_x = m + (int64_t)c * width;
      const float* __restrict mu_y = mu_x + 3 * width;
      const float* __restrict sq_x = mu_y + 3 * width;
      const float* __restrict sq_y = sq_x + 3 * width;
      const float* __restrict prod = sq_y + 3 * width;
      float* d_mu = partials != nullptr ? partials + c * plane + (int64_t)y * width : nullptr;
      float* d_xx = partials != nullptr ? d_mu + 3 * plane : nullptr;
      float* d_xy = partials != nullptr ? d_xx + 3 * plane : nullptr;
      for (int x = 0; x < width; ++x) {
        const float mx = mu_x[x], my = mu_y[x];
        const float a1 = 2.0f * mx * my + kC1;
        const float a2 = 2.0f * (prod[x] - mx * my) + kC2;
        const float b1 = mx * mx + my * my + kC1;
        const float b2 = (sq_x[x] - mx * mx) + (sq_y[x] - my * my) + kC2;
        const float inv_b1 = 1.0f / b1, inv_b2 = 1.0f / b2, inv_den = inv_b1 * inv_b2;
        const float s = a1 * a2 * inv_den;
        out[x] += s;
        if (d_mu != nullptr) {
          d_mu[x] = 2.0f * my * (a2 - a1) * inv_den + 2.0f * mx * s * (inv_b2 - inv_b1);
          d_xx[x] = -s * inv_b2;
          d_xy[x] = 2.0f * a1 * inv_den;
        }
      }
    }
    for (int x = 0; x < width; ++x) out[x] /= 3.0f;
  };
  blur_rows<15>(height, width, taps, fill, use, nthreads);
}

extern "C" void stgs_ssim_backward(int height, int width, const float* image, const float* reference,
                                   const float* taps, const float* partials, const float* grad_ssim,
                                   float* grad_image, int nthreads) {
  const int64_t plane = (int64_t)height * width;
  auto fill = [&](int y, float* row) {  // the partials times the upstream gradient
    const float* g = grad_ssim + (int64_t)y * width;
    for (int c = 0; c < 9; ++c) {
      const float* d = partials + c * plane + (int64_t)y * width;
      float* r = row + (int64_t)c * width;
      for (int x = 0; x < width; ++x) r[x] = d[x] * (g[x] / 3.0f);  // the map is the mean over the channels
    }
  };
  auto use = [&](int y, const float* b) {
    for (int c = 0; c < 3; ++c) {
      const float* d_mu = b + (int64_t)c * width;
      const float* d_xx = d_mu + 3 * width;
      const float* d_xy = d_xx + 3 * width;
      for (int x = 0; x < width; ++x) {
        const int64_t i = ((int64_t)y * width + x) * 3 + c;
        grad_image[i] = d_mu[x] + 2.0f * image[i] * d_xx[x] + reference[i] * d_xy[x];
      }
    }
  };
  blur_rows<9>(height, width, taps, fill, use, nthreads);
}
