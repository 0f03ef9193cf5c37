/*
 * fbgf_dense.h - the dense layer of the float build (not installed): y = W x + b, ReLU on
 * hidden layers. fbgf_dense.c holds a portable C kernel and SIMD kernels; which one runs is
 * fixed by the build and the CPU (docs/runtime.md, "Float build: speed"):
 *
 *   FBGF_SIMD=0          portable C everywhere: each output sums its products in index order,
 *                        one multiply and one add each (the order of fbgforce.model)
 *   FBGF_SIMD=1          (the default where available) x86-64: SSE2, or AVX2+FMA when the CPU
 *                        has both (asked at run time); aarch64: NEON with FMA
 *   FBGF_NO_AVX2=1       x86-64: never pick AVX2+FMA (SSE2 only), e.g. to compare the paths
 *
 * Every kernel sums in an order fixed by the layer's shape alone (never by data alignment or
 * earlier calls), so a given build on a given CPU gives the same bits for the same inputs.
 * The SIMD kernels reassociate the sums (lanes, then a fixed tree) and, on AVX2 and NEON,
 * fuse multiply and add, so their results differ from the portable kernel's by float32
 * rounding only (tests/test_float_simd.py bounds it).
 */
#ifndef FBGF_DENSE_H
#define FBGF_DENSE_H

#include "fbgforce.h"

/* The kernel the build and this CPU use. */
typedef enum { FBGF_KERNEL_PORTABLE = 0, FBGF_KERNEL_SSE2, FBGF_KERNEL_AVX2_FMA, FBGF_KERNEL_NEON } fbgf_kernel;

fbgf_kernel fbgf_dense_kernel(void);

/* y[0..n_out) = W x + b, then max(0, .) when relu; x holds n_in values, y does not alias x. */
void fbgf_dense(fbgf_kernel kernel, const fbgf_layer *ly, const float *x, float *y, int relu);

#endif /* FBGF_DENSE_H */
