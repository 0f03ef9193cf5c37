/*
 * fbg_simd_x86.c - the x86-64 host kernels (fbg_simd.h): which one runs, and why they are exact.
 *
 * The kernels, one file per family: fbg_simd_x86_sse2.c and fbg_simd_x86_avx2.c (dense layers),
 * fbg_simd_x86_pack.c (packed weights), fbg_simd_x86_stages.c (AVX2 front, filter, memory);
 * what they share is in fbg_simd_x86.h.
 *
 * PMADDWD (_mm_madd_epi16 / _mm256_madd_epi16) multiplies int16 pairs and adds adjacent
 * products into int32 lanes; PADDD and PHADDD add lanes. All of them wrap modulo 2^32, so
 * every lane holds its share of a row's sum modulo 2^32, and so does their total; the loader
 * proved the row's true sum fits int32, which makes the modular total the true sum
 * (docs/fixed-point.md, "Host SIMD kernels"); a column counted twice meets a zero of x the
 * second time. SSE2 runs four rows together and AVX2 eight, so each vector of x is loaded
 * once per group.
 *
 * SSE2 reads a layer of n_in >= 8 in place as AVX2 does (below) with vectors of 8 columns.
 * Narrower layers are read as whole vectors of npad = 8 weights (int8 weights are widened on
 * load), against x copied into a buffer that is zero from n_in on: the weights read past a
 * row's end belong to the next row and meet zeros. Where such a read would leave the weight
 * array (the last rows), the row is first copied into a zero-padded buffer; rows past n_out
 * read a row of zeros.
 *
 * AVX2 reads a layer of n_in >= 16 in place: rows at a stride of n_in from the weight array,
 * x where it is, whole vectors of 16 columns, and the last 16 columns of every row once more
 * against x with the columns already counted masked to zero, so no read leaves a row or x;
 * eight rows per group, then groups of 4, 2 and 1 for the rest (an output layer of one or two
 * rows multiplies only those). Narrower layers pad x and read 8 (two rows per vector) or 16
 * weights from each row's start; the last groups read a zero-padded copy of the array's
 * rest. Each group's sums get their bias and requantisation at once (one pass).
 *
 * AVX2 also requantises eight rows at once: VPMULDQ gives the exact int64 products
 * acc * mult, the rounding constant is added in int64, and a logical shift right stands for
 * the arithmetic one because a negative sum becomes 0 under the ReLU anyway (so only
 * non-negative values are shifted); the clamp at 32767 raises the saturation flag exactly
 * where fbg_sat16 does. SSE2 requantises with the scalar helpers of fbg_internal.h.
 *
 * From packed weights (fbg_pack; below, "Packed weights") SSE2 and AVX2 need no horizontal
 * sums: each pair of inputs is broadcast and multiplied against four or eight rows' weights
 * interleaved for it, and a whole net runs in one call. AVX2 also has its own variants of
 * fbg_step's front stages (fbg_avx2_front, fbg_avx2_filter, fbg_avx2_memory): the fault rule
 * of the five channels in one vector of int32, the temperature compensation, FIR and
 * standardisation of the four strain channels as vectors of int64, the location averages and
 * the load signal's memory states in vectors of int32.
 *
 * The AVX2 functions carry __attribute__((target("avx2"))), so the file builds without
 * -mavx2 and runs on any x86-64; fbg_simd_resolve only hands them out when the CPU (and the
 * OS, which must save the YMM registers) supports AVX2.
 *
 * Integer SIMD only: no floating-point vector type or instruction is used here
 * (check-nofloat scans this file, which -mgeneral-regs-only cannot compile).
 */
#include "fbg_simd_x86.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
uint32_t fbg_simd_resolve(uint32_t requested)
{
    int avx2;
    __builtin_cpu_init();
    /* GCC's and Clang's runtimes report AVX2 only if the OS saves the YMM state (XGETBV). */
    avx2 = __builtin_cpu_supports("avx2") != 0;
    switch (requested) {
    case FBG_OPT_KERNEL_AUTO:
        return avx2 ? FBG_OPT_KERNEL_AVX2 : FBG_OPT_KERNEL_SSE2;
    case FBG_OPT_KERNEL_PORTABLE:
    case FBG_OPT_KERNEL_SSE2:
        return requested;
    case FBG_OPT_KERNEL_AVX2:
        return avx2 ? requested : 0u;
    default:
        return 0u;
    }
}

void fbg_simd_acc32(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int32_t *acc)
{
    if (kernel == FBG_OPT_KERNEL_AVX2)
        fbg_avx2_layer(ly, x, acc, NULL, NULL);
    else
        fbg_sse2_acc32(ly, x, acc);
}

void fbg_simd_hidden(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    if (kernel == FBG_OPT_KERNEL_AVX2)
        fbg_avx2_layer(ly, x, NULL, y, sat);
    else
        fbg_sse2_hidden(ly, x, y, sat);
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_unused;
#endif
