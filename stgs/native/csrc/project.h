// Stage 1's inputs and outputs (stgs_project), shared by the portable kernel (project.cpp) and the AVX-512
// one (project_avx512.h).
#pragma once

namespace stgs::splat {
namespace {

// Inputs and outputs of stgs_project.
struct ProjectIO {
  const float *means, *quats, *scales, *opac;
  const double *viewmat, *K;
  float *means2d, *conics, *depths, *extents;
};

}  // namespace
}  // namespace stgs::splat
