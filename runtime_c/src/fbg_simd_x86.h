/*
 * fbg_simd_x86.h - what the x86-64 host kernels (fbg_simd_x86*.c) share: loads, the vector
 * types, the input padding and the AVX2 requantisation, and the layer kernels' declarations.
 */
#ifndef FBG_SIMD_X86_H
#define FBG_SIMD_X86_H

#include "fbg_contract.h" /* FBG_MEMORY_KINDS */
#include "fbg_simd.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
#include <emmintrin.h>
#include <immintrin.h>
#include <stddef.h>
#include <string.h>

#define AVX2 __attribute__((target("avx2")))
#define ROW_LEN (FBG_MAX_WIDTH + FBG_SIMD_XPAD)

/* x into xp, zero from n_in for FBG_SIMD_XPAD entries (past any npad). */
static inline void pad_x(const fbg_layer *ly, const int16_t *x, int16_t *xp)
{
    unsigned j;
    for (j = 0; j < ly->n_in; ++j) /* a plain loop: the compiler vectorises it, no call */
        xp[j] = x[j];
    for (j = 0; j < FBG_SIMD_XPAD; ++j)
        xp[ly->n_in + j] = 0;
}

static inline __m128i load128(const void *p)
{
    return _mm_loadu_si128((const __m128i *)p);
}

typedef uint32_t lanes32x4 __attribute__((vector_size(16)));

AVX2 static inline __m256i load256(const void *p)
{
    return _mm256_loadu_si256((const __m256i *)p);
}

/* Accumulators as a vector of uint32 lanes (addition modulo 2^32, like VPADDD): with __m256i
 * accumulators GCC copies every one of them once per loop iteration. */
typedef uint32_t lanes32 __attribute__((vector_size(32)));


/* y = sat16(max(rshift_round(acc * mult, shift), 0)) for eight rows: t = acc * mult + round
 * (VPMULDQ: exact int64 products of the even dwords, then of the odd ones), clamped to
 * [0, top] with top = 32768 * 2^shift - 1 (or INT64_MAX if that overflows, when no row can
 * clamp), then shifted right: a logical shift is the arithmetic one on t >= 0, and
 * top >> shift = 32767. *big collects the rows that clamped at the top (fbg_sat16's flag) as
 * lanes with every bit but the sign set. */
AVX2 static inline __m128i requant8(__m256i acc, __m256i mult, __m256i round, __m256i top,
                                    __m128i shift, __m256i *big)
{
    const __m256i zero = _mm256_setzero_si256();
    __m256i t[2], out;
    int k;
    t[0] = _mm256_mul_epi32(acc, mult);
    t[1] = _mm256_mul_epi32(_mm256_srli_epi64(acc, 32), _mm256_srli_epi64(mult, 32));
    for (k = 0; k < 2; ++k) {
        __m256i v = _mm256_add_epi64(t[k], round);
        __m256i neg = _mm256_cmpgt_epi64(zero, v), over = _mm256_cmpgt_epi64(v, top);
        *big = _mm256_or_si256(*big, _mm256_srli_epi32(over, 1)); /* >= 0 for requant8_high's max */
        t[k] = _mm256_srl_epi64(_mm256_andnot_si256(neg, _mm256_blendv_epi8(v, top, over)), shift);
    }
    /* Each 64-bit lane: the even row in its low dword, the odd row in its high one. */
    out = _mm256_or_si256(t[0], _mm256_slli_epi64(t[1], 32));
    return _mm_packs_epi32(_mm256_castsi256_si128(out), _mm256_extracti128_si256(out, 1));
}

/* acc += the products of wv and xv, pairwise summed (VPMADDWD). */
#define MADD(a, wv, xv) a += (lanes32)_mm256_madd_epi16(wv, xv)

/* A sum of K rows' int32 lanes into lanes 0 .. K-1 (K = 4, 2, 1) of a 128-bit vector. */
AVX2 static inline __m128i sum4_rows(__m256i a0, __m256i a1, __m256i a2, __m256i a3)
{
    __m256i h = _mm256_hadd_epi32(_mm256_hadd_epi32(a0, a1), _mm256_hadd_epi32(a2, a3));
    return _mm_add_epi32(_mm256_castsi256_si128(h), _mm256_extracti128_si256(h, 1));
}

AVX2 static inline __m128i sum2_rows(__m256i a0, __m256i a1)
{
    __m256i h = _mm256_hadd_epi32(a0, a1);
    __m128i s = _mm_add_epi32(_mm256_castsi256_si128(h), _mm256_extracti128_si256(h, 1));
    return _mm_hadd_epi32(s, s);
}

AVX2 static inline __m128i sum1_row(__m256i a0)
{
    __m128i s = _mm_add_epi32(_mm256_castsi256_si128(a0), _mm256_extracti128_si256(a0, 1));
    s = _mm_hadd_epi32(s, s);
    return _mm_hadd_epi32(s, s);
}

/* The dense layers of one family each (fbg_simd_acc32 and fbg_simd_hidden pick one). */
void fbg_sse2_acc32(const fbg_layer *ly, const int16_t *x, int32_t *acc);
void fbg_sse2_hidden(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
AVX2 void fbg_avx2_layer(const fbg_layer *ly, const int16_t *x, int32_t *acc, int16_t *y,
                         uint32_t *sat);

#endif /* FBG_HOST_SIMD && __x86_64__ */

#endif /* FBG_SIMD_X86_H */
