/*
 * fbg_simd_x86.c - SSE2 and AVX2 dense-layer kernels for x86-64 (see fbg_simd.h).
 *
 * PMADDWD (_mm_madd_epi16 / _mm256_madd_epi16) multiplies int16 pairs and adds adjacent
 * products into int32 lanes; PADDD adds lanes. Both wrap modulo 2^32, so every lane holds its
 * share of the row's sum modulo 2^32, and so does their total; the loader proved the row's
 * true sum fits int32, which makes the modular total the true sum (docs/fixed-point.md, "Host
 * SIMD kernels"). Four rows run together so each vector of x is loaded once per four rows.
 *
 * Rows are read as whole vectors of npad = n_in rounded up to 8 weights, against x copied
 * into a buffer that is zero from n_in to npad: the weights read past a row's end belong to
 * the next row and meet zeros. Where such a read would leave the weight array (the last
 * rows), the row is first copied into a zero-padded buffer instead. int8 rows are widened to
 * int16 in such a buffer. The AVX2 functions carry __attribute__((target("avx2"))), so the
 * file builds without -mavx2 and runs on any x86-64; fbg_simd_resolve only hands them out
 * when the CPU (and the OS, which must save the YMM registers) supports AVX2.
 *
 * Integer SIMD only: no floating-point vector type or instruction is used here (check-nofloat scans
 * this file, which -mgeneral-regs-only cannot compile).
 */
#include "fbg_simd.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
#include <emmintrin.h>
#include <immintrin.h>
#include <string.h>

#define ROWS 4u

/* The rows past n_out of the last group of four. */
static const int16_t zero_row[FBG_MAX_WIDTH + FBG_SIMD_XPAD];

/* Sum of each argument's four lanes: [sum a, sum b, sum c, sum d]. */
static inline __m128i sum4_lanes(__m128i a, __m128i b, __m128i c, __m128i d)
{
    __m128i ab = _mm_add_epi32(_mm_unpacklo_epi32(a, b), _mm_unpackhi_epi32(a, b));
    __m128i cd = _mm_add_epi32(_mm_unpacklo_epi32(c, d), _mm_unpackhi_epi32(c, d));
    return _mm_add_epi32(_mm_unpacklo_epi64(ab, cd), _mm_unpackhi_epi64(ab, cd));
}

static inline __m128i load128(const int16_t *p)
{
    return _mm_loadu_si128((const __m128i *)(const void *)p);
}

/* Where the rows of a layer are read: n_safe leading int16 rows in place, the rest copied. */
typedef struct {
    const fbg_layer *ly;
    unsigned n, npad, n_safe;
} row_source;

static void row_source_init(row_source *src, const fbg_layer *ly)
{
    size_t total = (size_t)ly->n_out * ly->n_in;
    src->ly = ly;
    src->n = ly->n_in;
    src->npad = (ly->n_in + 7u) & ~7u;
    /* Row r can be read in place iff r * n + npad <= total (int16 weights only). */
    if (ly->w_bits != 16u || total < src->npad)
        src->n_safe = 0u;
    else
        src->n_safe = (unsigned)((total - src->npad) / src->n) + 1u;
    if (src->n_safe > ly->n_out)
        src->n_safe = ly->n_out;
}

/* Row r as int16, readable for npad entries: in place, or copied (widened) into buf. */
static const int16_t *row_at(const row_source *src, unsigned r, int16_t *buf)
{
    unsigned j;
    if (r >= src->ly->n_out)
        return zero_row;
    if (r < src->n_safe)
        return src->ly->w16 + (size_t)r * src->n;
    if (src->ly->w_bits == 16u) {
        memcpy(buf, src->ly->w16 + (size_t)r * src->n, src->n * sizeof *buf);
    } else {
        const int8_t *w = src->ly->w8 + (size_t)r * src->n;
        for (j = 0; j < src->n; ++j)
            buf[j] = w[j];
    }
    for (j = src->n; j < src->npad; ++j)
        buf[j] = 0;
    return buf;
}

/* Rows r..r+3 of the bias (0 beyond n_out), as int32: |bias| <= INT32_MAX in an acc32 layer. */
static inline __m128i bias4(const fbg_layer *ly, unsigned r)
{
    int32_t b[ROWS];
    unsigned k;
    for (k = 0; k < ROWS; ++k)
        b[k] = r + k < ly->n_out ? (int32_t)ly->bias[r + k] : 0;
    return _mm_loadu_si128((const __m128i *)(const void *)b);
}

static inline void store4(const fbg_layer *ly, unsigned r, __m128i sums, int32_t *acc)
{
    if (r + ROWS <= ly->n_out) {
        _mm_storeu_si128((__m128i *)(void *)(acc + r), sums);
    } else {
        int32_t t[ROWS];
        _mm_storeu_si128((__m128i *)(void *)t, sums);
        memcpy(acc + r, t, (ly->n_out - r) * sizeof *acc);
    }
}

/* x into xp, zero from n_in up to the padded width. */
static void pad_x(const fbg_layer *ly, const int16_t *x, int16_t *xp)
{
    memcpy(xp, x, ly->n_in * sizeof *xp);
    memset(xp + ly->n_in, 0, FBG_SIMD_XPAD * sizeof *xp);
}

static void acc32_sse2(const fbg_layer *ly, const int16_t *x, int32_t *acc)
{
    int16_t xp[FBG_MAX_WIDTH + FBG_SIMD_XPAD];
    int16_t buf[ROWS][FBG_MAX_WIDTH + FBG_SIMD_XPAD];
    row_source src;
    unsigned r, j;
    pad_x(ly, x, xp);
    row_source_init(&src, ly);
    for (r = 0; r < ly->n_out; r += ROWS) {
        const int16_t *w0 = row_at(&src, r, buf[0]), *w1 = row_at(&src, r + 1u, buf[1]);
        const int16_t *w2 = row_at(&src, r + 2u, buf[2]), *w3 = row_at(&src, r + 3u, buf[3]);
        __m128i a0 = _mm_setzero_si128(), a1 = a0, a2 = a0, a3 = a0;
        for (j = 0; j < src.npad; j += 8u) {
            __m128i xv = load128(xp + j);
            a0 = _mm_add_epi32(a0, _mm_madd_epi16(load128(w0 + j), xv));
            a1 = _mm_add_epi32(a1, _mm_madd_epi16(load128(w1 + j), xv));
            a2 = _mm_add_epi32(a2, _mm_madd_epi16(load128(w2 + j), xv));
            a3 = _mm_add_epi32(a3, _mm_madd_epi16(load128(w3 + j), xv));
        }
        store4(ly, r, _mm_add_epi32(sum4_lanes(a0, a1, a2, a3), bias4(ly, r)), acc);
    }
}

__attribute__((target("avx2"))) static inline __m256i load256(const int16_t *p)
{
    return _mm256_loadu_si256((const __m256i *)(const void *)p);
}

/* The two 128-bit halves of a added lane by lane (the lanes' total is unchanged). */
__attribute__((target("avx2"))) static inline __m128i fold256(__m256i a)
{
    return _mm_add_epi32(_mm256_castsi256_si128(a), _mm256_extracti128_si256(a, 1));
}

__attribute__((target("avx2"))) static void acc32_avx2(const fbg_layer *ly, const int16_t *x,
                                                       int32_t *acc)
{
    int16_t xp[FBG_MAX_WIDTH + FBG_SIMD_XPAD];
    int16_t buf[ROWS][FBG_MAX_WIDTH + FBG_SIMD_XPAD];
    row_source src;
    unsigned r, j;
    pad_x(ly, x, xp);
    row_source_init(&src, ly);
    for (r = 0; r < ly->n_out; r += ROWS) {
        const int16_t *w0 = row_at(&src, r, buf[0]), *w1 = row_at(&src, r + 1u, buf[1]);
        const int16_t *w2 = row_at(&src, r + 2u, buf[2]), *w3 = row_at(&src, r + 3u, buf[3]);
        __m256i a0 = _mm256_setzero_si256(), a1 = a0, a2 = a0, a3 = a0;
        __m128i b0, b1, b2, b3;
        for (j = 0; j + 16u <= src.npad; j += 16u) {
            __m256i xv = load256(xp + j);
            a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(load256(w0 + j), xv));
            a1 = _mm256_add_epi32(a1, _mm256_madd_epi16(load256(w1 + j), xv));
            a2 = _mm256_add_epi32(a2, _mm256_madd_epi16(load256(w2 + j), xv));
            a3 = _mm256_add_epi32(a3, _mm256_madd_epi16(load256(w3 + j), xv));
        }
        b0 = fold256(a0);
        b1 = fold256(a1);
        b2 = fold256(a2);
        b3 = fold256(a3);
        if (j < src.npad) { /* npad is a multiple of 8: one half vector left */
            __m128i xv = load128(xp + j);
            b0 = _mm_add_epi32(b0, _mm_madd_epi16(load128(w0 + j), xv));
            b1 = _mm_add_epi32(b1, _mm_madd_epi16(load128(w1 + j), xv));
            b2 = _mm_add_epi32(b2, _mm_madd_epi16(load128(w2 + j), xv));
            b3 = _mm_add_epi32(b3, _mm_madd_epi16(load128(w3 + j), xv));
        }
        store4(ly, r, _mm_add_epi32(sum4_lanes(b0, b1, b2, b3), bias4(ly, r)), acc);
    }
}

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
        acc32_avx2(ly, x, acc);
    else
        acc32_sse2(ly, x, acc);
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_unused;
#endif
