/*
 * fbg_simd_x86.c - SSE2 and AVX2 dense-layer kernels for x86-64 (see fbg_simd.h).
 *
 * PMADDWD (_mm_madd_epi16 / _mm256_madd_epi16) multiplies int16 pairs and adds adjacent
 * products into int32 lanes; PADDD and PHADDD add lanes. All of them wrap modulo 2^32, so
 * every lane holds its share of a row's sum modulo 2^32, and so does their total; the loader
 * proved the row's true sum fits int32, which makes the modular total the true sum
 * (docs/fixed-point.md, "Host SIMD kernels"). SSE2 runs four rows together and AVX2 eight,
 * so each vector of x is loaded once per group; rows past n_out read a row of zeros.
 *
 * Rows are read as whole vectors of npad = n_in rounded up to 8 weights (int8 weights are
 * widened on load), against x copied into a buffer that is zero from n_in on: the weights
 * read past a row's end belong to the next row and meet zeros. Where such a read would leave
 * the weight array (the last rows), the row is first copied into a zero-padded buffer.
 *
 * AVX2 also requantises eight rows at once: VPMULDQ gives the exact int64 products
 * acc * mult, the rounding constant is added in int64, and a logical shift right stands for
 * the arithmetic one because a negative sum becomes 0 under the ReLU anyway (so only
 * non-negative values are shifted); the clamp at 32767 raises the saturation flag exactly
 * where fbg_sat16 does. SSE2 requantises with the scalar helpers of fbg_internal.h.
 *
 * The AVX2 functions carry __attribute__((target("avx2"))), so the file builds without
 * -mavx2 and runs on any x86-64; fbg_simd_resolve only hands them out when the CPU (and the
 * OS, which must save the YMM registers) supports AVX2.
 *
 * Integer SIMD only: no floating-point vector type or instruction is used here
 * (check-nofloat scans this file, which -mgeneral-regs-only cannot compile).
 */
#include "fbg_simd.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
#include <emmintrin.h>
#include <immintrin.h>
#include <string.h>

#define AVX2 __attribute__((target("avx2")))
#define ROW_LEN (FBG_MAX_WIDTH + FBG_SIMD_XPAD)

/* The rows past n_out of a layer's last group. */
static const int16_t zero_row16[ROW_LEN];
static const int8_t zero_row8[ROW_LEN];

/* One layer's rows: the first n_safe can be read in place for npad entries, n_in rounded up
 * to a multiple of vec (8 or 16). */
typedef struct {
    const fbg_layer *ly;
    unsigned n, npad, n_safe;
} rows_view;

static void rows_view_init(rows_view *v, const fbg_layer *ly, unsigned vec)
{
    size_t total = (size_t)ly->n_out * ly->n_in;
    v->ly = ly;
    v->n = ly->n_in;
    v->npad = (ly->n_in + vec - 1u) & ~(vec - 1u);
    /* Row r stays inside the weight array iff r * n + npad <= total; a read of npad entries
     * overruns the last ceil((npad - n) / n) rows (no division for the common n >= npad - n). */
    if (v->npad == v->n)
        v->n_safe = ly->n_out;
    else if (v->n >= v->npad - v->n)
        v->n_safe = ly->n_out - 1u;
    else
        v->n_safe = total < v->npad ? 0u : (unsigned)((total - v->npad) / v->n) + 1u;
}

/* Pointers to rows r .. r+k-1 (int16 weights), copying the ones that cannot be read in place
 * into buf. */
static inline void rows16(const rows_view *v, unsigned r, unsigned k, const int16_t **w, int16_t (*buf)[ROW_LEN])
{
    unsigned i, j;
    if (r + k <= v->n_safe) {
        const int16_t *p = v->ly->w16 + (size_t)r * v->n;
        for (i = 0; i < k; ++i, p += v->n)
            w[i] = p;
        return;
    }
    for (i = 0; i < k; ++i, ++r) {
        if (r < v->n_safe) {
            w[i] = v->ly->w16 + (size_t)r * v->n;
        } else if (r >= v->ly->n_out) {
            w[i] = zero_row16;
        } else {
            memcpy(buf[i], v->ly->w16 + (size_t)r * v->n, v->n * sizeof **buf);
            for (j = v->n; j < v->npad; ++j)
                buf[i][j] = 0;
            w[i] = buf[i];
        }
    }
}

static inline void rows8(const rows_view *v, unsigned r, unsigned k, const int8_t **w, int8_t (*buf)[ROW_LEN])
{
    unsigned i, j;
    if (r + k <= v->n_safe) {
        const int8_t *p = v->ly->w8 + (size_t)r * v->n;
        for (i = 0; i < k; ++i, p += v->n)
            w[i] = p;
        return;
    }
    for (i = 0; i < k; ++i, ++r) {
        if (r < v->n_safe) {
            w[i] = v->ly->w8 + (size_t)r * v->n;
        } else if (r >= v->ly->n_out) {
            w[i] = zero_row8;
        } else {
            memcpy(buf[i], v->ly->w8 + (size_t)r * v->n, v->n);
            for (j = v->n; j < v->npad; ++j)
                buf[i][j] = 0;
            w[i] = buf[i];
        }
    }
}

/* x into xp, zero from n_in for FBG_SIMD_XPAD entries (past any npad). */
static inline void pad_x(const fbg_layer *ly, const int16_t *x, int16_t *xp)
{
    unsigned j;
    for (j = 0; j < ly->n_in; ++j) /* a plain loop: the compiler vectorises it, no call */
        xp[j] = x[j];
    for (j = 0; j < FBG_SIMD_XPAD; ++j)
        xp[ly->n_in + j] = 0;
}

/* bias[r .. r+k-1] as int32 (|bias| <= INT32_MAX in an acc32 layer), 0 beyond k. */
static void bias32(const fbg_layer *ly, unsigned r, unsigned k, int32_t *b)
{
    unsigned i;
    for (i = 0; i < k; ++i)
        b[i] = r + i < ly->n_out ? (int32_t)ly->bias[r + i] : 0;
}

/* ---- SSE2: four rows per group ------------------------------------------------------- */

static inline __m128i load128(const void *p)
{
    return _mm_loadu_si128((const __m128i *)p);
}

/* 8 int8 weights sign-extended to int16 (each byte doubled, then shifted down arithmetically). */
static inline __m128i load8x8(const int8_t *p)
{
    __m128i b = _mm_loadl_epi64((const __m128i *)(const void *)p);
    return _mm_srai_epi16(_mm_unpacklo_epi8(b, b), 8);
}

/* [sum of a's lanes, sum of b's, sum of c's, sum of d's]. */
static inline __m128i sum4_lanes(__m128i a, __m128i b, __m128i c, __m128i d)
{
    __m128i ab = _mm_add_epi32(_mm_unpacklo_epi32(a, b), _mm_unpackhi_epi32(a, b));
    __m128i cd = _mm_add_epi32(_mm_unpacklo_epi32(c, d), _mm_unpackhi_epi32(c, d));
    return _mm_add_epi32(_mm_unpacklo_epi64(ab, cd), _mm_unpackhi_epi64(ab, cd));
}

/* The MACs of four rows; W(i, j) loads 8 weights of row i at column j as int16. */
#define SSE2_DOT4(W)                                                                 \
    do {                                                                             \
        __m128i a0 = _mm_setzero_si128(), a1 = a0, a2 = a0, a3 = a0;                \
        for (j = 0; j < v.npad; j += 8u) {                                           \
            __m128i xv = load128(xp + j);                                           \
            a0 = _mm_add_epi32(a0, _mm_madd_epi16(W(0, j), xv));                    \
            a1 = _mm_add_epi32(a1, _mm_madd_epi16(W(1, j), xv));                    \
            a2 = _mm_add_epi32(a2, _mm_madd_epi16(W(2, j), xv));                    \
            a3 = _mm_add_epi32(a3, _mm_madd_epi16(W(3, j), xv));                    \
        }                                                                            \
        sums = _mm_add_epi32(sum4_lanes(a0, a1, a2, a3), load128(b));                \
    } while (0)
#define SSE2_W16(i, j) load128(w16[i] + (j))
#define SSE2_W8(i, j) load8x8(w8[i] + (j))

/* acc[r] for every row of the layer (int32). */
static void acc32_sse2(const fbg_layer *ly, const int16_t *x, int32_t *acc)
{
    int16_t xp[ROW_LEN];
    int16_t buf16[4][ROW_LEN];
    int8_t buf8[4][ROW_LEN];
    int32_t b[4], t[4];
    rows_view v;
    unsigned r, j;
    pad_x(ly, x, xp);
    rows_view_init(&v, ly, 8u);
    for (r = 0; r < ly->n_out; r += 4u) {
        __m128i sums;
        bias32(ly, r, 4u, b);
        if (ly->w_bits == 16u) {
            const int16_t *w16[4];
            rows16(&v, r, 4u, w16, buf16);
            SSE2_DOT4(SSE2_W16);
        } else {
            const int8_t *w8[4];
            rows8(&v, r, 4u, w8, buf8);
            SSE2_DOT4(SSE2_W8);
        }
        if (r + 4u <= ly->n_out) {
            _mm_storeu_si128((__m128i *)(void *)(acc + r), sums);
        } else {
            _mm_storeu_si128((__m128i *)(void *)t, sums);
            memcpy(acc + r, t, (ly->n_out - r) * sizeof *acc);
        }
    }
}

static void hidden_sse2(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    int32_t acc[FBG_MAX_WIDTH];
    unsigned r;
    acc32_sse2(ly, x, acc);
    for (r = 0; r < ly->n_out; ++r) {
        int64_t v = fbg_rshift_round((int64_t)acc[r] * ly->mult[r], ly->shift);
        y[r] = fbg_sat16(v < 0 ? 0 : v, sat);
    }
}

/* ---- AVX2: eight rows per group, vector requantisation -------------------------------- */

AVX2 static inline __m256i load256(const void *p)
{
    return _mm256_loadu_si256((const __m256i *)p);
}

/* [sum of a0's lanes, ..., sum of a7's lanes]. */
AVX2 static inline __m256i sum8_lanes(__m256i a0, __m256i a1, __m256i a2, __m256i a3, __m256i a4,
                                      __m256i a5, __m256i a6, __m256i a7)
{
    /* Within each 128-bit half: [a0 a1 a2 a3] and [a4 a5 a6 a7] partial sums. */
    __m256i h0123 = _mm256_hadd_epi32(_mm256_hadd_epi32(a0, a1), _mm256_hadd_epi32(a2, a3));
    __m256i h4567 = _mm256_hadd_epi32(_mm256_hadd_epi32(a4, a5), _mm256_hadd_epi32(a6, a7));
    return _mm256_add_epi32(_mm256_permute2x128_si256(h0123, h4567, 0x20),
                            _mm256_permute2x128_si256(h0123, h4567, 0x31));
}

/* The MACs of eight rows: W(i, j) loads 16 weights of row i at column j as int16. */
#define AVX2_DOT8(W)                                                                         \
    do {                                                                                     \
        __m256i a0 = _mm256_setzero_si256(), a1 = a0, a2 = a0, a3 = a0, a4 = a0, a5 = a0,   \
                a6 = a0, a7 = a0, xv;                                                        \
        for (j = 0; j < v.npad; j += 16u) {                                                  \
            xv = load256(xp + j);                                                            \
            a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(W(0, j), xv));                       \
            a1 = _mm256_add_epi32(a1, _mm256_madd_epi16(W(1, j), xv));                       \
            a2 = _mm256_add_epi32(a2, _mm256_madd_epi16(W(2, j), xv));                       \
            a3 = _mm256_add_epi32(a3, _mm256_madd_epi16(W(3, j), xv));                       \
            a4 = _mm256_add_epi32(a4, _mm256_madd_epi16(W(4, j), xv));                       \
            a5 = _mm256_add_epi32(a5, _mm256_madd_epi16(W(5, j), xv));                       \
            a6 = _mm256_add_epi32(a6, _mm256_madd_epi16(W(6, j), xv));                       \
            a7 = _mm256_add_epi32(a7, _mm256_madd_epi16(W(7, j), xv));                       \
        }                                                                                    \
        sums = sum8_lanes(a0, a1, a2, a3, a4, a5, a6, a7);                                   \
    } while (0)
#define AVX2_W16(i, j) load256(w16[i] + (j))
#define AVX2_W8(i, j) _mm256_cvtepi8_epi16(load128(w8[i] + (j)))

/* A layer of at most 8 inputs: two rows per vector (row 2p in the low half, 2p+1 in the
 * high half) against x in both halves; W(i) loads row i's 8 weights as int16. */
#define AVX2_NARROW8(W)                                                                      \
    do {                                                                                     \
        __m256i xv = _mm256_broadcastsi128_si256(load128(xp));                               \
        __m256i m0 = _mm256_madd_epi16(_mm256_inserti128_si256(_mm256_castsi128_si256(W(0)), W(1), 1), xv); \
        __m256i m1 = _mm256_madd_epi16(_mm256_inserti128_si256(_mm256_castsi128_si256(W(2)), W(3), 1), xv); \
        __m256i m2 = _mm256_madd_epi16(_mm256_inserti128_si256(_mm256_castsi128_si256(W(4)), W(5), 1), xv); \
        __m256i m3 = _mm256_madd_epi16(_mm256_inserti128_si256(_mm256_castsi128_si256(W(6)), W(7), 1), xv); \
        /* [r0 r2 r4 r6 | r1 r3 r5 r7], then in row order. */                                \
        __m256i h = _mm256_hadd_epi32(_mm256_hadd_epi32(m0, m1), _mm256_hadd_epi32(m2, m3)); \
        sums = _mm256_permutevar8x32_epi32(h, _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7));    \
    } while (0)
#define NARROW_W16(i) load128(w16[i])
#define NARROW_W8(i) _mm_cvtepi8_epi16(_mm_loadl_epi64((const __m128i *)(const void *)w8[i]))

/* y = sat16(max(rshift_round(acc * mult, shift), 0)) for eight rows: t = acc * mult + round
 * (VPMULDQ: exact int64 products of the even dwords, then of the odd ones), clamped to
 * [0, top] with top = 32768 * 2^shift - 1 (or INT64_MAX if that overflows, when no row can
 * clamp), then shifted right: a logical shift is the arithmetic one on t >= 0, and
 * top >> shift = 32767. *big collects the rows that clamped at the top (fbg_sat16's flag). */
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
        *big = _mm256_or_si256(*big, over);
        t[k] = _mm256_srl_epi64(_mm256_andnot_si256(neg, _mm256_blendv_epi8(v, top, over)), shift);
    }
    /* Each 64-bit lane: the even row in its low dword, the odd row in its high one. */
    out = _mm256_or_si256(t[0], _mm256_slli_epi64(t[1], 32));
    return _mm_packs_epi32(_mm256_castsi256_si128(out), _mm256_extracti128_si256(out, 1));
}

/* Rows r .. r+k-1 (k <= 8) of a layer's bias, as int32 (|bias| <= INT32_MAX in an acc32
 * layer: the low dwords of the int64 values), and of its mult; 0 beyond k. Masked loads read
 * nothing past the arrays. */
AVX2 static inline void bias_mult8(const fbg_layer *ly, unsigned r, unsigned k, __m256i *bias,
                                   __m256i *mult)
{
    const __m256i low_dwords = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
    __m256i lo, hi;
    if (k == 8u) {
        lo = load256(ly->bias + r);
        hi = load256(ly->bias + r + 4u);
        *mult = load256(ly->mult + r);
    } else {
        __m256i keep = _mm256_cmpgt_epi32(_mm256_set1_epi32((int)k), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
        *mult = _mm256_maskload_epi32((const int *)(const void *)(ly->mult + r), keep);
        lo = _mm256_maskload_epi64((const long long *)(const void *)(ly->bias + r),
                                   _mm256_cvtepi32_epi64(_mm256_castsi256_si128(keep)));
        hi = k > 4u ? _mm256_maskload_epi64((const long long *)(const void *)(ly->bias + r + 4u),
                                            _mm256_cvtepi32_epi64(_mm256_extracti128_si256(keep, 1)))
                    : _mm256_setzero_si256();
    }
    *bias = _mm256_inserti128_si256(_mm256_permutevar8x32_epi32(lo, low_dwords),
                                    _mm256_castsi256_si128(_mm256_permutevar8x32_epi32(hi, low_dwords)), 1);
}

/* The int32 accumulators (acc != NULL) or the requantised hidden outputs (y) of every row.
 * Two passes: the sums of all row groups first, then bias and requantisation eight rows at
 * a time, so that no group's long chain (reduction, then requantisation) holds up the next. */
AVX2 static void layer_avx2(const fbg_layer *ly, const int16_t *x, int32_t *acc, int16_t *y,
                            uint32_t *sat)
{
    int16_t xp[ROW_LEN];
    int16_t buf16[8][ROW_LEN];
    int8_t buf8[8][ROW_LEN];
    int32_t sum[FBG_MAX_WIDTH + 8u];
    rows_view v;
    unsigned r, j;
    const __m256i round = _mm256_set1_epi64x((int64_t)1 << (ly->shift - 1u));
    const __m256i top = _mm256_set1_epi64x(ly->shift < 48u ? ((int64_t)32768 << ly->shift) - 1 : INT64_MAX);
    const __m128i shift = _mm_cvtsi32_si128((int)ly->shift);
    __m256i big = _mm256_setzero_si256();
    pad_x(ly, x, xp);
    rows_view_init(&v, ly, ly->n_in <= 8u ? 8u : 16u);
    for (r = 0; r < ly->n_out; r += 8u) {
        __m256i sums;
        if (ly->w_bits == 16u) {
            const int16_t *w16[8];
            rows16(&v, r, 8u, w16, buf16);
            if (v.npad == 8u)
                AVX2_NARROW8(NARROW_W16);
            else
                AVX2_DOT8(AVX2_W16);
        } else {
            const int8_t *w8[8];
            rows8(&v, r, 8u, w8, buf8);
            if (v.npad == 8u)
                AVX2_NARROW8(NARROW_W8);
            else
                AVX2_DOT8(AVX2_W8);
        }
        _mm256_storeu_si256((__m256i *)(void *)(sum + r), sums);
    }
    for (r = 0; r < ly->n_out; r += 8u) {
        unsigned k = ly->n_out - r < 8u ? ly->n_out - r : 8u;
        __m256i bias, mult, sums;
        bias_mult8(ly, r, k, &bias, &mult);
        sums = _mm256_add_epi32(load256(sum + r), bias);
        if (acc != NULL) {
            _mm256_storeu_si256((__m256i *)(void *)(sum + r), sums);
            memcpy(acc + r, sum + r, k * sizeof *acc);
        } else if (k == 8u) {
            _mm_storeu_si128((__m128i *)(void *)(y + r), requant8(sums, mult, round, top, shift, &big));
        } else {
            int16_t t[8];
            _mm_storeu_si128((__m128i *)(void *)t, requant8(sums, mult, round, top, shift, &big));
            memcpy(y + r, t, k * sizeof *y);
        }
    }
    if (!_mm256_testz_si256(big, big))
        *sat = 1u;
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
        layer_avx2(ly, x, acc, NULL, NULL);
    else
        acc32_sse2(ly, x, acc);
}

void fbg_simd_hidden(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    if (kernel == FBG_OPT_KERNEL_AVX2)
        layer_avx2(ly, x, NULL, y, sat);
    else
        hidden_sse2(ly, x, y, sat);
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_unused;
#endif
