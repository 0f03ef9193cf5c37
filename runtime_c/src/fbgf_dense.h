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
 *   FBGF_RUN_LANES=0     x86-64 with AVX2+FMA: fbgf_run passes the samples of a batch to
 *                        fbgf_dense in rows instead of to fbgf_dense_lanes in lanes (the same
 *                        bits, slower), e.g. to compare the two
 *
 * Every kernel sums in an order fixed by the layer's shape alone (never by data alignment,
 * by the other samples of a batch or by earlier calls), so a given build on a given CPU gives
 * the same bits for the same inputs, and fbgf_run the bits of fbgf_step. The SIMD kernels
 * reassociate the sums (lanes, then a fixed tree; fbgf_dense.c) and, on AVX2 and NEON, fuse
 * multiply and add, so their results differ from the portable kernel's by float32 rounding
 * (tests/test_float_simd.py bounds it; docs/runtime.md, "Float build: speed").
 */
#ifndef FBGF_DENSE_H
#define FBGF_DENSE_H

#include "fbgforce.h"

#ifndef FBGF_SIMD
#if (defined(__x86_64__) || defined(__aarch64__)) && (defined(__GNUC__) || defined(__clang__))
#define FBGF_SIMD 1
#else
#define FBGF_SIMD 0
#endif
#endif

/* fbgf_run runs the nets of several samples together (about 18 kB of stack) only where a SIMD
 * kernel can reuse the weights; elsewhere (Cortex-M4F) it stays a loop of fbgf_step. */
#if FBGF_SIMD && (defined(__x86_64__) || defined(__aarch64__))
#define FBGF_RUN_BATCHED 1
#else
#define FBGF_RUN_BATCHED 0
#endif

/* Samples whose nets fbgf_run runs together: on AVX2, two vectors of eight (fbgf_dense_lanes). */
#define FBGF_RUN_CHUNK 16u

/* x86-64 builds that may pick AVX2+FMA at run time; these also have fbgf_dense_lanes. */
#if FBGF_SIMD && defined(__x86_64__) && (!defined(FBGF_NO_AVX2) || !FBGF_NO_AVX2)
#define FBGF_HAVE_AVX2 1
#else
#define FBGF_HAVE_AVX2 0
#endif

/* The kernel the build and this CPU use. */
typedef enum { FBGF_KERNEL_PORTABLE = 0, FBGF_KERNEL_SSE2, FBGF_KERNEL_AVX2_FMA, FBGF_KERNEL_NEON } fbgf_kernel;

fbgf_kernel fbgf_dense_kernel(void);

/* For each of n samples i: y_i[0..n_out) = W x_i + b, then max(0, .) when relu, where x_i =
 * x + i * x_stride holds n_in values and y_i = y + i * y_stride; y does not alias x. A sample's
 * result does not depend on n or on the other samples: kernels that reuse a block of weights
 * across samples (while it is in L1) compute each sample exactly as alone. */
void fbgf_dense(fbgf_kernel kernel, const fbgf_layer *ly, const float *x, size_t x_stride, float *y,
                size_t y_stride, size_t n, int relu);

#ifndef FBGF_RUN_LANES
#define FBGF_RUN_LANES FBGF_HAVE_AVX2
#endif

#if FBGF_HAVE_AVX2
/* The AVX2+FMA kernel (only when fbgf_dense_kernel() says so) on samples in lanes: input j of
 * sample s is x[j * FBGF_RUN_CHUNK + s], output r goes to y[r * FBGF_RUN_CHUNK + s], for the
 * samples s < 8 * n_vec (n_vec = 1 or 2; lanes past the real samples are computed too, and
 * zeros there keep that cheap). Each sample gets the bits fbgf_dense gives it alone, whatever
 * its lane and the other lanes; y does not alias x. */
void fbgf_dense_lanes(const fbgf_layer *ly, const float *x, float *y, unsigned n_vec, int relu);
#endif

#endif /* FBGF_DENSE_H */
