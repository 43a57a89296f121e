// The GOP stage's temporal consistency term (stgs/train/losses.py): the Huber penalty of consecutive
// feature differences f[e+1] - f[e] of (rows, cols) float32 features, summed, and its gradient with the
// frame's window gradient added in the same pass.
//
// Autograd's version writes the differences, their clamped copy and the gradient, zero-fills a second
// full-size buffer for the window's slice and adds the two: six full-size passes where these kernels read
// the features and write the gradient once (bench.temporal).
//
// Work is cut into fixed blocks of columns, each walked down the rows (the block of row e + 1, read for
// one difference, is still in cache for the next); the forward sums each block in double and adds the
// blocks in order, so the value does not depend on the thread count.

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "stgs_abi.h"

namespace {

constexpr int64_t kBlock = 1024;  // columns per work item (4 KB of a row)

inline float huber(float d, float delta) {
  const float a = std::fabs(d);
  return a < delta ? 0.5f * d * d : delta * (a - 0.5f * delta);
}

inline float slope(float d, float delta) { return std::min(std::max(d, -delta), delta); }

}  // namespace

extern "C" double stgs_temporal_huber_forward(int64_t rows, int64_t cols, const float* features, float delta,
                                              int nthreads) {
  if (rows < 2 || cols < 1) return 0.0;
  const int64_t blocks = (cols + kBlock - 1) / kBlock;
  std::vector<double> sums(blocks, 0.0);
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t b = 0; b < blocks; ++b) {
    const int64_t j0 = b * kBlock, j1 = std::min(cols, j0 + kBlock);
    double block_sum = 0.0;
    for (int64_t e = 0; e + 1 < rows; ++e) {
      const float* a = features + e * cols;
      const float* c = a + cols;
      float row_sum = 0.0f;
#pragma omp simd reduction(+ : row_sum)
      for (int64_t j = j0; j < j1; ++j) row_sum += huber(c[j] - a[j], delta);
      block_sum += row_sum;
    }
    sums[b] = block_sum;
  }
  double total = 0.0;
  for (double s : sums) total += s;
  return total;
}

extern "C" void stgs_temporal_huber_backward(int64_t rows, int64_t cols, const float* features, float delta,
                                             float scale, const float* window_grad, int64_t first,
                                             int64_t window_rows, float* grad, int nthreads) {
  if (rows < 1 || cols < 1) return;
  const int64_t blocks = (cols + kBlock - 1) / kBlock;
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t b = 0; b < blocks; ++b) {
    const int64_t j0 = b * kBlock, j1 = std::min(cols, j0 + kBlock);
    for (int64_t e = 0; e < rows; ++e) {
      const float* row = features + e * cols;
      float* out = grad + e * cols;
      // d/df[e] of the sum: slope(f[e] - f[e-1]) - slope(f[e+1] - f[e]), the missing neighbours' terms 0
      const bool before = e > 0, after = e + 1 < rows;
#pragma omp simd
      for (int64_t j = j0; j < j1; ++j) {
        float g = 0.0f;
        if (before) g += slope(row[j] - row[j - cols], delta);
        if (after) g -= slope(row[j + cols] - row[j], delta);
        out[j] = scale * g;
      }
      if (window_grad != nullptr && e >= first && e < first + window_rows) {
        const float* w = window_grad + (e - first) * cols;
#pragma omp simd
        for (int64_t j = j0; j < j1; ++j) out[j] += w[j];
      }
    }
  }
}
