/*
 * fbg_simd.h - host SIMD kernels of the fixed-point dense layers (not installed).
 *
 * x86-64: SSE2 (every x86-64 CPU has it) and AVX2 (chosen at run time when the CPU has it);
 * aarch64: NEON (every AArch64 CPU has it). Each kernel computes the int32 accumulators of
 * an acc32 layer, acc[r] = bias[r] + sum_j w[r][j] * x[j], with int16 or int8 weights, and
 * a hidden layer's outputs from them by the one rounding and saturation rule
 * (docs/fixed-point.md) on whole vectors of rows. Why the sums
 * are the portable C's bits in any summation order: docs/fixed-point.md, "Host SIMD
 * kernels". int64-accumulator layers run the portable C.
 *
 * This header has no intrinsics, so fbg_fixed.c stays a general-register translation unit
 * (check-nofloat). FBG_HOST_SIMD=0 builds the portable C only.
 */
#ifndef FBG_SIMD_H
#define FBG_SIMD_H

#include "fbg_internal.h"

#ifndef FBG_HOST_SIMD
#if (defined(__x86_64__) || defined(__aarch64__)) && defined(__GNUC__) && \
    !(defined(FBG_USE_DSP) && FBG_USE_DSP)
#define FBG_HOST_SIMD 1
#else
#define FBG_HOST_SIMD 0
#endif
#endif

#if FBG_HOST_SIMD
#if !(defined(__x86_64__) || defined(__aarch64__)) || !defined(__GNUC__)
#error "FBG_HOST_SIMD=1 needs GCC or Clang on x86-64 or aarch64"
#endif

/* Inputs are copied into a zero-padded buffer of this many int16 beyond FBG_MAX_WIDTH, so a
 * kernel reads whole vectors of x (the widest vector holds 16 int16). */
#define FBG_SIMD_XPAD 16u

/* The kernel fbg_init stores for a requested FBG_OPT_KERNEL_* value: AUTO becomes the best
 * kernel this CPU runs, any other value itself if this CPU runs it; 0 if it cannot run. The
 * CPU is asked once (the answer is cached; asking again gives the same answer). */
uint32_t fbg_simd_resolve(uint32_t requested);

/* acc[r] = bias[r] + sum_j w[r][j] * x[j] for every row of an acc32 layer (ly->acc32 == 1),
 * with a resolved kernel other than FBG_OPT_KERNEL_PORTABLE. x has ly->n_in entries. */
void fbg_simd_acc32(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int32_t *acc);

/* A hidden acc32 layer: y[r] = sat16(max(rshift_round(acc[r] * mult[r], shift), 0)) with
 * acc as above; *sat = 1 if any row clamped at 32767 (the rule of fbg_fixed.c). */
void fbg_simd_hidden(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
#endif

#endif /* FBG_SIMD_H */
