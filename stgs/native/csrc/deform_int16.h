// The int16 deformation's build switches (which kernel the compiler's target allows) and its row scaling modes,
// shared by deform_int16.cpp and its two ISA files, deform_int16_avx512.h and deform_int16_avx2.h.
#pragma once

#if defined(__AVX2__)
#define STGS_HAVE_INT16 1
#include <immintrin.h>
#else
#define STGS_HAVE_INT16 0
#endif

// The kernel stgs_deform_int16_available reports (its values: stgs_abi.h).
#if defined(__AVX512BW__) && defined(__AVX512VNNI__)
#define STGS_INT16_KERNEL 3
#elif defined(__AVX512BW__)
#define STGS_INT16_KERNEL 2
#elif STGS_HAVE_INT16
#define STGS_INT16_KERNEL 1
#else
#define STGS_INT16_KERNEL 0
#endif

#if STGS_HAVE_INT16
namespace {

// How a layer's input rows are scaled to integers of at most qx (the layer's q).
enum class Scale {
  kRow,      // by the row's own max |x|
  kReluRow,  // max(0, x) (NaN kept, as torch.relu), then by the row's own max
  kUnit,     // by 1: inputs within [-1, 1] (tanh outputs, unit view directions)
};

}  // namespace
#endif
