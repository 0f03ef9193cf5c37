/*
 * fbg_simd_x86.c - SSE2 and AVX2 dense-layer kernels for x86-64 (see fbg_simd.h).
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
#include "fbg_contract.h" /* FBG_MEMORY_KINDS */
#include "fbg_simd.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
#include <emmintrin.h>
#include <immintrin.h>
#include <stddef.h>
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

/* acc[r] for every row of a layer of fewer than 8 inputs (int32), x padded. */
static void acc32_sse2_padded(const fbg_layer *ly, const int16_t *x, int32_t *acc)
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

/* SSE2, layers of at least 8 inputs: rows and x read in place, as AVX2 does with 16 columns
 * (wide_avx2): the last 8 columns of every row against x[n-8 .. n) with the columns of the
 * whole vectors masked to zero first, then whole vectors of 8 columns; four rows per group,
 * the last n_out mod 4 rows one by one. */
typedef uint32_t lanes32x4 __attribute__((vector_size(16)));
static const int16_t tail_lanes8[16] = {0, 0, 0, 0, 0, 0, 0, 0, -1, -1, -1, -1, -1, -1, -1, -1};
#define SSE2_IN16(i, j) load128(w16 + (size_t)(i) * n + (j))
#define SSE2_IN8(i, j) load8x8(w8 + (size_t)(i) * n + (j))
#define SSE2_MADD(a, wv, xv) a += (lanes32x4)_mm_madd_epi16(wv, xv)
#define SSE2_ROWS4(W)                                                                        \
    do {                                                                                     \
        lanes32x4 a0 = (lanes32x4)_mm_madd_epi16(W(0, n - 8u), xtail),                       \
                  a1 = (lanes32x4)_mm_madd_epi16(W(1, n - 8u), xtail),                       \
                  a2 = (lanes32x4)_mm_madd_epi16(W(2, n - 8u), xtail),                       \
                  a3 = (lanes32x4)_mm_madd_epi16(W(3, n - 8u), xtail);                       \
        for (j = 0; j < n8; j += 8u) {                                                       \
            __m128i xv = load128(x + j);                                                     \
            SSE2_MADD(a0, W(0, j), xv);                                                      \
            SSE2_MADD(a1, W(1, j), xv);                                                      \
            SSE2_MADD(a2, W(2, j), xv);                                                      \
            SSE2_MADD(a3, W(3, j), xv);                                                      \
        }                                                                                    \
        sums = sum4_lanes((__m128i)a0, (__m128i)a1, (__m128i)a2, (__m128i)a3);               \
    } while (0)
#define SSE2_ROW1(W)                                                                         \
    do {                                                                                     \
        lanes32x4 a0 = (lanes32x4)_mm_madd_epi16(W(0, n - 8u), xtail);                       \
        __m128i t;                                                                           \
        for (j = 0; j < n8; j += 8u)                                                         \
            SSE2_MADD(a0, W(0, j), load128(x + j));                                          \
        t = _mm_add_epi32((__m128i)a0, _mm_shuffle_epi32((__m128i)a0, 0x4e));                \
        t = _mm_add_epi32(t, _mm_shuffle_epi32(t, 0xb1));                                    \
        acc[r] = (int32_t)((uint32_t)_mm_cvtsi128_si32(t) + (uint32_t)ly->bias[r]);          \
    } while (0)

static void acc32_sse2(const fbg_layer *ly, const int16_t *x, int32_t *acc)
{
    const size_t n = ly->n_in;
    const unsigned n8 = ly->n_in & ~7u;
    __m128i xtail;
    unsigned r, j;
    if (ly->n_in < 8u) {
        acc32_sse2_padded(ly, x, acc);
        return;
    }
    xtail = _mm_and_si128(load128(x + n - 8u), load128(tail_lanes8 + (n & 7u)));
    for (r = 0; r + 4u <= ly->n_out; r += 4u) {
        int32_t b[4];
        __m128i sums;
        bias32(ly, r, 4u, b);
        if (ly->w_bits == 16u) {
            const int16_t *w16 = ly->w16 + (size_t)r * n;
            SSE2_ROWS4(SSE2_IN16);
        } else {
            const int8_t *w8 = ly->w8 + (size_t)r * n;
            SSE2_ROWS4(SSE2_IN8);
        }
        _mm_storeu_si128((__m128i *)(void *)(acc + r), _mm_add_epi32(sums, load128(b)));
    }
    for (; r < ly->n_out; ++r) {
        if (ly->w_bits == 16u) {
            const int16_t *w16 = ly->w16 + (size_t)r * n;
            SSE2_ROW1(SSE2_IN16);
        } else {
            const int8_t *w8 = ly->w8 + (size_t)r * n;
            SSE2_ROW1(SSE2_IN8);
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

/* What a layer's rows share in the one pass over them: the requantisation constants, and the
 * saturation flags gathered from every group. */
typedef struct {
    const fbg_layer *ly;
    int32_t *acc;
    int16_t *y;
    __m256i round, top, big;
    __m128i shift;
} layer_out;

/* Rows r .. r+k-1 (1 <= k <= 8) from their sums (lanes 0 .. k-1 of sums; the other lanes are
 * ignored): bias added, then stored as accumulators (o->acc) or requantised into o->y. Stores
 * write rows r .. r+k-1 only. */
AVX2 static inline void finish_rows(layer_out *o, unsigned r, unsigned k, __m256i sums)
{
    __m256i bias, mult;
    __m128i q;
    bias_mult8(o->ly, r, k, &bias, &mult);
    sums = _mm256_add_epi32(sums, bias);
    if (o->acc != NULL) {
        if (k == 8u)
            _mm256_storeu_si256((__m256i *)(void *)(o->acc + r), sums);
        else
            _mm256_maskstore_epi32((int *)(void *)(o->acc + r),
                                   _mm256_cmpgt_epi32(_mm256_set1_epi32((int)k),
                                                      _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7)),
                                   sums);
        return;
    }
    /* Lanes past k have mult 0 (bias_mult8): they requantise to 0 and never clamp. */
    q = requant8(sums, mult, o->round, o->top, o->shift, &o->big);
    if (k == 8u) {
        _mm_storeu_si128((__m128i *)(void *)(o->y + r), q);
        return;
    }
    if (k & 4u) {
        _mm_storel_epi64((__m128i *)(void *)(o->y + r), q);
        q = _mm_srli_si128(q, 8);
        r += 4u;
    }
    if (k & 2u) {
        _mm_storeu_si32(o->y + r, q);
        q = _mm_srli_si128(q, 4);
        r += 2u;
    }
    if (k & 1u)
        o->y[r] = (int16_t)_mm_cvtsi128_si32(q);
}

/* ---- AVX2, layers of at least 16 inputs: rows read in place ---------------------------- */

/* Row i of a group starting at row pointer w, columns j .. j+15, as int16. */
#define WIDE_W16(i, j) load256(w + (size_t)(i) * n + (j))
#define WIDE_W8(i, j) _mm256_cvtepi8_epi16(load128(w + (size_t)(i) * n + (j)))
/* Accumulators as a vector of uint32 lanes (addition modulo 2^32, like VPADDD): with __m256i
 * accumulators GCC copies every one of them once per loop iteration. */
typedef uint32_t lanes32 __attribute__((vector_size(32)));
#define MADD(a, wv, xv) a += (lanes32)_mm256_madd_epi16(wv, xv)
#define WIDE_ROW(i, W) lanes32 a##i = (lanes32)_mm256_madd_epi16(W(i, n - 16u), xtail)
#define WIDE_ROWS1(W) WIDE_ROW(0, W)
#define WIDE_ROWS2(W) WIDE_ROWS1(W); WIDE_ROW(1, W)
#define WIDE_ROWS4(W) WIDE_ROWS2(W); WIDE_ROW(2, W); WIDE_ROW(3, W)
#define WIDE_ROWS8(W) WIDE_ROWS4(W); WIDE_ROW(4, W); WIDE_ROW(5, W); WIDE_ROW(6, W); WIDE_ROW(7, W)
#define WIDE_STEP1(W, j, xv) MADD(a0, W(0, j), xv)
#define WIDE_STEP2(W, j, xv) WIDE_STEP1(W, j, xv); MADD(a1, W(1, j), xv)
#define WIDE_STEP4(W, j, xv) WIDE_STEP2(W, j, xv); MADD(a2, W(2, j), xv); MADD(a3, W(3, j), xv)
#define WIDE_STEP8(W, j, xv)                                                                 \
    WIDE_STEP4(W, j, xv); MADD(a4, W(4, j), xv); MADD(a5, W(5, j), xv); MADD(a6, W(6, j), xv); \
    MADD(a7, W(7, j), xv)

/* Declares a0 .. a(K-1) (K = 1, 2, 4, 8) and sums K rows into them: first the last 16
 * columns of every row against xtail, which is x[n-16 .. n) with the columns of the whole
 * vectors (those below n16 = n rounded down to 16) set to zero (all of it when n16 == n),
 * then the whole vectors. Every read stays inside its row and inside x[0 .. n). */
#define WIDE_DOT(K, W)                                                                       \
    WIDE_ROWS##K(W);                                                                         \
    j = 0;                                                                                   \
    do { /* n16 >= 16 */                                                                     \
        __m256i xv = load256(x + j);                                                         \
        WIDE_STEP##K(W, j, xv);                                                              \
        j += 16u;                                                                            \
    } while (j < n16)

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

/* -1 in the last t of 16 lanes read from tail_lanes + t (t = n mod 16). */
static const int16_t tail_lanes[32] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                                       -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1};

/* Every row of a layer of n >= 16 inputs: groups of eight rows, then the last n_out mod 8
 * rows as a group of 4, of 2 and of 1 (so an output layer of one or two rows multiplies only
 * those). */
#define WIDE_LAYER(T, W)                                                                     \
    do {                                                                                     \
        const T *w;                                                                          \
        unsigned k = ly->n_out & 7u, done = 0u;                                              \
        int32_t part[8] = {0, 0, 0, 0, 0, 0, 0, 0};                                          \
        for (r = 0; r + 8u <= ly->n_out; r += 8u) {                                          \
            w = base + (size_t)r * n;                                                        \
            WIDE_DOT(8, W);                                                                  \
            finish_rows(o, r, 8u, sum8_lanes((__m256i)a0, (__m256i)a1, (__m256i)a2, (__m256i)a3,     \
                                              (__m256i)a4, (__m256i)a5, (__m256i)a6, (__m256i)a7));                \
        }                                                                                    \
        if (k == 0u)                                                                         \
            break;                                                                           \
        if (k & 4u) {                                                                        \
            w = base + (size_t)r * n;                                                        \
            WIDE_DOT(4, W);                                                                  \
            _mm_storeu_si128((__m128i *)(void *)part, sum4_rows((__m256i)a0, (__m256i)a1, (__m256i)a2, (__m256i)a3));            \
            done = 4u;                                                                       \
        }                                                                                    \
        if (k & 2u) {                                                                        \
            w = base + (size_t)(r + done) * n;                                               \
            WIDE_DOT(2, W);                                                                  \
            _mm_storel_epi64((__m128i *)(void *)(part + done), sum2_rows((__m256i)a0, (__m256i)a1));           \
            done += 2u;                                                                      \
        }                                                                                    \
        if (k & 1u) {                                                                        \
            w = base + (size_t)(r + done) * n;                                               \
            WIDE_DOT(1, W);                                                                  \
            part[done] = _mm_cvtsi128_si32(sum1_row((__m256i)a0));                                    \
        }                                                                                    \
        finish_rows(o, r, k, load256(part));                                                 \
    } while (0)

AVX2 static void wide_avx2(layer_out *o, const int16_t *x)
{
    const fbg_layer *ly = o->ly;
    const size_t n = ly->n_in;
    const unsigned n16 = ly->n_in & ~15u;
    const __m256i xtail = _mm256_and_si256(load256(x + n - 16u), load256(tail_lanes + (n & 15u)));
    unsigned r, j;
    if (ly->w_bits == 16u) {
        const int16_t *base = ly->w16;
        WIDE_LAYER(int16_t, WIDE_W16);
    } else {
        const int8_t *base = ly->w8;
        WIDE_LAYER(int8_t, WIDE_W8);
    }
}

/* ---- AVX2, layers of fewer than 16 inputs: x padded, rows of 8 or 16 -------------------- */

/* Rows of 8 (n <= 8) or 16 weights read from each row's start: the weights past a row's end
 * belong to the next rows and meet the zeros of x padded into xp. The groups whose reads
 * would leave the weight array read a zero-padded copy of the array's rest instead, made
 * once (fewer than 7 n + 16 weights, read up to 7 n + 16 past a group's start, so the copy
 * holds 2 (7 * 15 + 16) < NARROW_COPY entries). Rows past n_out meet zeros in the copy and
 * finish_rows ignores them. */
#define NARROW_COPY 256u
#define NARROW_W16(i) load128(w + (size_t)(i) * n)
#define NARROW_W8(i) _mm_cvtepi8_epi16(_mm_loadl_epi64((const __m128i *)(const void *)(w + (size_t)(i) * n)))
#define NARROW_PAIR(i, W) _mm256_madd_epi16(_mm256_inserti128_si256(_mm256_castsi128_si256(W(i)), W(i + 1), 1), xv)
/* n == 8: rows i and i + 1 are one vector of 16 weights. */
#define NARROW_PAIR16(i, W) _mm256_madd_epi16(NARROW16_W##W(i), xv)
/* Two rows per vector (row 2p in the low half, 2p+1 in the high one) against x in both;
 * P(i, W) multiplies rows i and i + 1. */
#define NARROW8_SUMS(P, W)                                                                   \
    do {                                                                                     \
        __m256i h = _mm256_hadd_epi32(_mm256_hadd_epi32(P(0, W), P(2, W)),                   \
                                      _mm256_hadd_epi32(P(4, W), P(6, W)));                  \
        /* [r0 r2 r4 r6 | r1 r3 r5 r7], then in row order. */                                \
        sums = _mm256_permutevar8x32_epi32(h, _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7));    \
    } while (0)
#define NARROW16_W16(i) load256(w + (size_t)(i) * n)
#define NARROW16_W8(i) _mm256_cvtepi8_epi16(load128(w + (size_t)(i) * n))
#define NARROW16_SUMS(W)                                                                     \
    sums = sum8_lanes(_mm256_madd_epi16(W(0), xv), _mm256_madd_epi16(W(1), xv),              \
                      _mm256_madd_epi16(W(2), xv), _mm256_madd_epi16(W(3), xv),              \
                      _mm256_madd_epi16(W(4), xv), _mm256_madd_epi16(W(5), xv),              \
                      _mm256_madd_epi16(W(6), xv), _mm256_madd_epi16(W(7), xv))

#define NARROW_SUMS(SUMS8, SUMS8J, SUMS16)                                                   \
    do {                                                                                     \
        if (n < 8u)                                                                          \
            SUMS8;                                                                           \
        else if (n == 8u)                                                                    \
            SUMS8J;                                                                          \
        else                                                                                 \
            SUMS16;                                                                          \
    } while (0)
/* The groups read in place (all of them whole: their reads reach row r + 7 and beyond),
 * then the rest from the copy. */
#define NARROW_LAYER(T, BASE, SUMS8, SUMS8J, SUMS16)                                                 \
    do {                                                                                     \
        T copy[NARROW_COPY];                                                                 \
        const T *w = BASE;                                                                   \
        const size_t total = (size_t)ly->n_out * n, reach = 7u * n + (n <= 8u ? 8u : 16u);   \
        size_t start, end, i;                                                                \
        __m256i sums;                                                                        \
        for (r = 0; (size_t)r * n + reach <= total; r += 8u, w += 8u * n) {                  \
            NARROW_SUMS(SUMS8, SUMS8J, SUMS16);                                              \
            finish_rows(o, r, 8u, sums);                                                     \
        }                                                                                    \
        if (r >= ly->n_out)                                                                  \
            break;                                                                           \
        /* The last group's reads end at end. */                                             \
        start = (size_t)r * n;                                                               \
        end = (size_t)((ly->n_out - 1u) & ~7u) * n + reach - start;                         \
        for (i = 0; i < total - start; ++i)                                                  \
            copy[i] = (BASE)[start + i];                                                     \
        for (; i < end; ++i)                                                                 \
            copy[i] = 0;                                                                     \
        for (w = copy; r < ly->n_out; r += 8u, w += 8u * n) {                                \
            NARROW_SUMS(SUMS8, SUMS8J, SUMS16);                                              \
            finish_rows(o, r, ly->n_out - r < 8u ? ly->n_out - r : 8u, sums);               \
        }                                                                                    \
    } while (0)

AVX2 static void narrow_avx2(layer_out *o, const int16_t *x)
{
    const fbg_layer *ly = o->ly;
    const size_t n = ly->n_in;
    int16_t xp[ROW_LEN];
    __m256i xv;
    unsigned r;
    pad_x(ly, x, xp);
    xv = n <= 8u ? _mm256_broadcastsi128_si256(load128(xp)) : load256(xp);
    if (ly->w_bits == 16u)
        NARROW_LAYER(int16_t, ly->w16, NARROW8_SUMS(NARROW_PAIR, NARROW_W16),
                     NARROW8_SUMS(NARROW_PAIR16, 16), NARROW16_SUMS(NARROW16_W16));
    else
        NARROW_LAYER(int8_t, ly->w8, NARROW8_SUMS(NARROW_PAIR, NARROW_W8),
                     NARROW8_SUMS(NARROW_PAIR16, 8), NARROW16_SUMS(NARROW16_W8));
}

/* The int32 accumulators (acc != NULL) or the requantised hidden outputs (y) of every row,
 * in one pass over the rows. */
AVX2 static void layer_avx2(const fbg_layer *ly, const int16_t *x, int32_t *acc, int16_t *y,
                            uint32_t *sat)
{
    layer_out o;
    o.ly = ly;
    o.acc = acc;
    o.y = y;
    o.round = _mm256_set1_epi64x((int64_t)1 << (ly->shift - 1u));
    o.top = _mm256_set1_epi64x(ly->shift < 48u ? ((int64_t)32768 << ly->shift) - 1 : INT64_MAX);
    o.shift = _mm_cvtsi32_si128((int)ly->shift);
    o.big = _mm256_setzero_si256();
    if (ly->n_in >= 16u)
        wide_avx2(&o, x);
    else
        narrow_avx2(&o, x);
    if (acc == NULL && !_mm256_testz_si256(o.big, o.big))
        *sat = 1u;
}

/* ---- Packed weights (fbg_pack): no row sums to add up across a vector ------------------- */

/* A packed layer: this head, then its output rows in groups of `rows` (8 for AVX2, 4 for
 * SSE2; the rows past n_out are zeros), the groups in passes of up to PACK_PASS (nine
 * groups, then the rest: the kernel's passes over the inputs; nine, so that a layer of 70
 * rows runs in one pass). A pass of K groups holds the K
 * groups' biases as int32 (|bias| <= INT32_MAX in an acc32 layer), then their multipliers,
 * then for each input pair p the K groups' vectors of 2 * rows int16, (w[r][2p], w[r][2p+1])
 * for the group's rows r (the odd last column's partner is 0; int8 weights are widened, the
 * same values). A pair's vector against x[2p], x[2p+1] broadcast to every lane gives, through
 * (V)PMADDWD, each row's share of that pair in the row's own int32 lane: a group's
 * accumulator holds its rows' sums once every pair is added, with no horizontal sums, and
 * the pass reads its vectors in order. Every block is a multiple of 32 bytes long, so with the
 * buffer FBG_PACK_ALIGN-aligned every vector lies aligned. */
#define PACK_PASS 9u
typedef struct {
    int64_t round;      /* 2^(shift - 1) */
    int64_t top;        /* 32768 * 2^shift - 1, INT64_MAX when that overflows (requant8) */
    uint32_t shift;
    uint16_t n_in, n_out, n_groups;
    uint16_t high_word; /* 1: multipliers stored at shift 32 for requant8_high (high_word_requant) */
    uint16_t dot;       /* 1: an output layer in the dot-product form (dot_layer) */
    uint16_t reserved;
} packed_head;

typedef char packed_head_is_32_bytes[sizeof(packed_head) == 32u ? 1 : -1];

/* One field of the head at the start of a block, read where it lies (memcpy: the buffer's
 * declared type is the caller's), so that a kernel loads only the fields it uses. */
static inline unsigned head_u16(const unsigned char *block, size_t off)
{
    uint16_t v;
    memcpy(&v, block + off, sizeof v);
    return v;
}

static inline unsigned head_u32(const unsigned char *block, size_t off)
{
    uint32_t v;
    memcpy(&v, block + off, sizeof v);
    return v;
}

static inline int64_t head_i64(const unsigned char *block, size_t off)
{
    int64_t v;
    memcpy(&v, block + off, sizeof v);
    return v;
}
#define HEAD_U16(block, field) head_u16(block, offsetof(packed_head, field))
#define HEAD_I64(block, field) head_i64(block, offsetof(packed_head, field))
#define HEAD_U32(block, field) head_u32(block, offsetof(packed_head, field))

#define PACK_HEADER_BYTES ((sizeof(fbg_pack_header) + 31u) & ~(size_t)31u)

/* Rows per group of a kernel's packed form; 0: no packed form. */
static unsigned pack_rows(uint32_t kernel)
{
    return kernel == FBG_OPT_KERNEL_AVX2 ? 8u : kernel == FBG_OPT_KERNEL_SSE2 ? 4u : 0u;
}

/* Bytes of one group: biases and multipliers (4 bytes a row each), then 2 int16 a row per pair. */
static size_t packed_group_bytes(unsigned n_in, unsigned rows)
{
    return (size_t)rows * (8u + 4u * ((n_in + 1u) / 2u));
}

/* AVX2 packs an output layer of up to DOT_ROWS rows that reads a hidden layer's output
 * (l >= 1: the activation buffer, FBG_MAX_WIDTH long) in the dot-product form instead of
 * groups: a group of 8 rows would spend a broadcast and a multiply-add of 8 lanes on each
 * input pair for one or two rows. The block: the head, the rows' biases as int32 (32 bytes),
 * then each row's weights as int16, zero from n_in up to DOT_WIDTH(n_in) (whole vectors of
 * 16). The kernel multiplies whole vectors of x, so it reads x up to DOT_WIDTH(n_in) <=
 * FBG_MAX_WIDTH; the activations there past n_in meet those zero weights. */
#define DOT_ROWS 2u
#define DOT_WIDTH(n_in) (((unsigned)(n_in) + 15u) & ~15u)
typedef char dot_reads_inside_act[(FBG_MAX_WIDTH % 16) == 0 ? 1 : -1];

static int dot_layer(const fbg_net *net, unsigned l, unsigned rows)
{
    return rows == 8u && l >= 1u && l + 1u == net->n_layers && net->layers[l].n_out <= DOT_ROWS;
}

/* The nets the packed form holds: those with only acc32 layers. */
static int packed_net(const fbg_net *net)
{
    unsigned l;
    for (l = 0; l < net->n_layers; ++l)
        if (!net->layers[l].acc32)
            return 0;
    return 1;
}

/* Weight w[r][j] of a layer as int16 (int8 weights widened: the same value). */
static int16_t weight16(const fbg_layer *ly, unsigned r, unsigned j)
{
    return ly->w_bits == 16u ? ly->w16[(size_t)r * ly->n_in + j] : (int16_t)ly->w8[(size_t)r * ly->n_in + j];
}

/* Whether row r of hidden layer l (not the last) may be left out of the packed form: the next
 * layer's column r is all zeros, so the row's output adds nothing anywhere, and the row can
 * never clamp, so it never raises the saturation flag either. Its accumulator lies in
 * [lo, hi]: the bias plus the weights against inputs in [-32767, 32767] (a first layer: sat16
 * inputs) or [0, 32767] (ReLU outputs), within int32 by the acc32 proof; the requantised
 * value rshift_round(acc * mult, shift) is monotonic in acc, so its largest value is at lo or
 * hi, and the row clamps (ReLU, then sat16) only if that exceeds 32767. Weight decay leaves
 * such units (all-zero rows and columns) in trained nets. */
static int row_unused(const fbg_net *net, unsigned l, unsigned r)
{
    const fbg_layer *ly = &net->layers[l], *next = &net->layers[l + 1u];
    int64_t pos = 0, neg = 0, lo, hi;
    unsigned i, j;
    for (i = 0; i < next->n_out; ++i)
        if (weight16(next, i, r) != 0)
            return 0;
    for (j = 0; j < ly->n_in; ++j) {
        const int64_t w = weight16(ly, r, j);
        if (w > 0)
            pos += w;
        else
            neg += w;
    }
    if (l == 0u) {
        hi = ly->bias[r] + FBG_SAT16 * (pos - neg);
        lo = ly->bias[r] - FBG_SAT16 * (pos - neg);
    } else {
        hi = ly->bias[r] + FBG_SAT16 * pos;
        lo = ly->bias[r] + FBG_SAT16 * neg;
    }
    return fbg_rshift_round(hi * ly->mult[r], ly->shift) <= FBG_SAT16 &&
           fbg_rshift_round(lo * ly->mult[r], ly->shift) <= FBG_SAT16;
}

/* Which rows and columns of a layer a packed net keeps: row[0 .. n_rows) and col[0 .. n_cols)
 * in order, the rows of row_unused left out, and with them the next layer's columns (the
 * activations of the kept rows are stored back to back). A first layer keeps every column
 * (the net inputs), an output layer every row. */
typedef struct {
    unsigned n_rows, n_cols;
    uint8_t row[FBG_MAX_WIDTH], col[FBG_MAX_WIDTH];
} pack_shape;

typedef char pack_shape_indices_fit[FBG_MAX_WIDTH <= 256 ? 1 : -1];

static unsigned kept_rows(const fbg_net *net, unsigned l, uint8_t *row)
{
    unsigned r, n = 0;
    for (r = 0; r < net->layers[l].n_out; ++r)
        if (l + 1u == net->n_layers || !row_unused(net, l, r))
            row[n++] = (uint8_t)r;
    return n;
}

static void pack_shape_of(const fbg_net *net, unsigned l, pack_shape *sh)
{
    unsigned j;
    sh->n_rows = kept_rows(net, l, sh->row);
    if (l > 0u) {
        sh->n_cols = kept_rows(net, l - 1u, sh->col);
    } else {
        sh->n_cols = net->layers[0].n_in;
        for (j = 0; j < sh->n_cols; ++j)
            sh->col[j] = (uint8_t)j;
    }
}

/* At least one vector, so that the kernel's first multiply-add reads weights of the block
 * (every column of the layer may have gone with the rows before). */
static unsigned dot_width(unsigned n_in)
{
    return n_in == 0u ? 16u : DOT_WIDTH(n_in);
}

static size_t packed_layer_bytes(const pack_shape *sh, unsigned rows, int dot)
{
    if (dot)
        return sizeof(packed_head) + 32u + (size_t)sh->n_rows * dot_width(sh->n_cols) * 2u;
    return sizeof(packed_head) + (size_t)((sh->n_rows + rows - 1u) / rows) * packed_group_bytes(sh->n_cols, rows);
}

size_t fbg_simd_pack_bytes(uint32_t kernel, const fbg_model *m)
{
    const unsigned rows = pack_rows(kernel);
    size_t total = PACK_HEADER_BYTES;
    pack_shape sh;
    unsigned n, l;
    if (rows == 0u)
        return 0u;
    for (n = 0; n < FBG_N_NETS; ++n)
        if (packed_net(&m->nets[n]))
            for (l = 0; l < m->nets[n].n_layers; ++l) {
                pack_shape_of(&m->nets[n], l, &sh);
                total += packed_layer_bytes(&sh, rows, dot_layer(&m->nets[n], l, rows));
            }
    return total;
}

/* Whether AVX2 can requantise the layer at shift 32 (requant8_high): shift <= 32 and every
 * multiplier times 2^(32 - shift) an int32, which the pack then stores. Then
 * acc * mult * 2^(32-shift) + 2^31 is the rounding sum times 2^(32-shift), exact in int64
 * (|acc| <= 2^31 in an acc32 layer), and its floor over 2^32, the high dword, is the
 * quotient floor((acc * mult + 2^(shift-1)) / 2^shift) (docs/fixed-point.md, "Host SIMD
 * kernels"). */
static int high_word_requant(const fbg_layer *ly)
{
    unsigned r;
    if (ly->shift > 32u)
        return 0;
    for (r = 0; r < ly->n_out; ++r) {
        const int64_t m = (int64_t)ly->mult[r] * ((int64_t)1 << (32u - ly->shift));
        if (m > INT32_MAX || m < INT32_MIN)
            return 0;
    }
    return 1;
}

/* The dot-product form's block after the head (dot_layer). */
static void pack_dot(const fbg_layer *ly, const pack_shape *sh, unsigned char *dst)
{
    const unsigned width = dot_width(sh->n_cols);
    unsigned r, j;
    memset(dst, 0, 32u);
    for (r = 0; r < sh->n_rows; ++r) {
        const int32_t bias = (int32_t)ly->bias[sh->row[r]];
        memcpy(dst + 4u * r, &bias, sizeof bias);
    }
    dst += 32u;
    for (r = 0; r < sh->n_rows; ++r)
        for (j = 0; j < width; ++j, dst += 2u) {
            const int16_t w = j < sh->n_cols ? weight16(ly, sh->row[r], sh->col[j]) : 0;
            memcpy(dst, &w, sizeof w);
        }
}

/* One layer's block at dst (its kept rows and columns, sh). Plain stores through memcpy: the
 * buffer's declared type is the caller's. */
static void pack_layer(const fbg_layer *ly, const pack_shape *sh, unsigned rows, int dot, unsigned char *dst)
{
    const unsigned pairs = (sh->n_cols + 1u) / 2u;
    packed_head h;
    unsigned g0, k, g, i, p, c;
    memset(&h, 0, sizeof h);
    h.shift = ly->shift;
    h.round = (int64_t)1 << (ly->shift - 1u);
    h.top = ly->shift < 48u ? ((int64_t)32768 << ly->shift) - 1 : INT64_MAX;
    h.n_in = (uint16_t)sh->n_cols;
    h.n_out = (uint16_t)sh->n_rows;
    h.n_groups = (uint16_t)((sh->n_rows + rows - 1u) / rows);
    /* SSE2 requantises from the multipliers as they are. */
    h.high_word = (uint16_t)(rows == 8u && high_word_requant(ly));
    h.dot = (uint16_t)dot;
    memcpy(dst, &h, sizeof h);
    dst += sizeof h;
    if (dot) {
        pack_dot(ly, sh, dst);
        return;
    }
    for (g0 = 0; g0 < h.n_groups; g0 += k) {
        k = h.n_groups - g0 < PACK_PASS ? h.n_groups - g0 : PACK_PASS;
        for (g = g0; g < g0 + k; ++g)
            for (i = 0; i < rows; ++i) {
                const unsigned r = g * rows + i, src = r < sh->n_rows ? sh->row[r] : 0u;
                const int32_t bias = r < sh->n_rows ? (int32_t)ly->bias[src] : 0;
                const int32_t mult = r >= sh->n_rows ? 0
                                     : h.high_word ? (int32_t)((int64_t)ly->mult[src] * ((int64_t)1 << (32u - h.shift)))
                                                   : ly->mult[src];
                memcpy(dst + 4u * ((g - g0) * rows + i), &bias, sizeof bias);
                memcpy(dst + 4u * ((k + g - g0) * rows + i), &mult, sizeof mult);
            }
        dst += 8u * k * rows;
        for (p = 0; p < pairs; ++p)
            for (g = g0; g < g0 + k; ++g)
                for (i = 0; i < rows; ++i)
                    for (c = 0; c < 2u; ++c) {
                        const unsigned r = g * rows + i, j = 2u * p + c;
                        const int16_t w = r < sh->n_rows && j < sh->n_cols ? weight16(ly, sh->row[r], sh->col[j]) : 0;
                        memcpy(dst, &w, sizeof w);
                        dst += sizeof w;
                    }
    }
}

void fbg_simd_pack(uint32_t kernel, const fbg_model *m, void *buf)
{
    const unsigned rows = pack_rows(kernel);
    unsigned char *base = (unsigned char *)buf;
    fbg_pack_header hd;
    pack_shape sh;
    size_t off = PACK_HEADER_BYTES;
    unsigned n, l;
    memset(&hd, 0, sizeof hd);
    memset(base, 0, PACK_HEADER_BYTES);
    for (n = 0; n < FBG_N_NETS; ++n) {
        if (!packed_net(&m->nets[n]))
            continue;
        hd.net_off[n] = (uint32_t)off;
        for (l = 0; l < m->nets[n].n_layers; ++l) {
            const int dot = dot_layer(&m->nets[n], l, rows);
            pack_shape_of(&m->nets[n], l, &sh);
            pack_layer(&m->nets[n].layers[l], &sh, rows, dot, base + off);
            off += packed_layer_bytes(&sh, rows, dot);
        }
    }
    hd.magic = FBG_PACK_MAGIC;
    hd.kernel = kernel;
    hd.model = m;
    hd.bytes = off;
    memcpy(base, &hd, sizeof hd);
}

/* The passes over the input pairs of a packed layer: K groups (1 <= K <= PACK_PASS) per
 * pass, so each broadcast pair serves K groups (all the groups of a layer of up to 72 rows
 * in one pass), two pairs per loop iteration (four where K <= 2). In a pass at b (VB bytes a vector): the biases
 * at b, the multipliers at b + K VB, the vector of group i for pair p at
 * w + (p K + i) VB with w = b + 2 K VB. PK_LISTK(M, A, B) is M(0, A, B); ...; M(K-1, A, B). */
#define PK_LIST1(M, A, B) M(0, A, B)
#define PK_LIST2(M, A, B) PK_LIST1(M, A, B); M(1, A, B)
#define PK_LIST3(M, A, B) PK_LIST2(M, A, B); M(2, A, B)
#define PK_LIST4(M, A, B) PK_LIST3(M, A, B); M(3, A, B)
#define PK_LIST5(M, A, B) PK_LIST4(M, A, B); M(4, A, B)
#define PK_LIST6(M, A, B) PK_LIST5(M, A, B); M(5, A, B)
#define PK_LIST7(M, A, B) PK_LIST6(M, A, B); M(6, A, B)
#define PK_LIST8(M, A, B) PK_LIST7(M, A, B); M(7, A, B)
#define PK_LIST9(M, A, B) PK_LIST8(M, A, B); M(8, A, B)
/* One pass of K groups: T the vector type, BCAST(p) the broadcast pair p (BCAST##_LAST the
 * odd last column with a zero partner); ACC(i) declares
 * accumulator a##i from its bias, MADD(i, w, xb) adds the products of the vector at w + i VB,
 * OUT(i, K, 0) finishes group i of the K. */
#define PK_PASS(K, T, VB, BCAST, ACC, MADD, OUT)                                             \
    do {                                                                                     \
        const size_t kb = (size_t)(K) * (VB);                                                \
        const unsigned char *w = b + 2u * kb;                                                \
        PK_LIST##K(ACC, 0, 0);                                                               \
        p = 0;                                                                               \
        if ((K) <= 2) /* four broadcasts: wider passes spill accumulators */              \
            for (; p + 4u <= full; p += 4u, w += 4u * kb) {                                  \
                const T xb0 = BCAST(p), xb1 = BCAST(p + 1u), xb2 = BCAST(p + 2u), xb3 = BCAST(p + 3u); \
                PK_LIST##K(MADD, w, xb0);                                                    \
                PK_LIST##K(MADD, w + kb, xb1);                                               \
                PK_LIST##K(MADD, w + 2u * kb, xb2);                                          \
                PK_LIST##K(MADD, w + 3u * kb, xb3);                                          \
            }                                                                                \
        for (; p + 2u <= full; p += 2u, w += 2u * kb) {                                      \
            const T xb0 = BCAST(p), xb1 = BCAST(p + 1u);                                     \
            PK_LIST##K(MADD, w, xb0);                                                        \
            PK_LIST##K(MADD, w + kb, xb1);                                                   \
        }                                                                                    \
        if (p < full) {                                                                      \
            const T xb = BCAST(p);                                                           \
            PK_LIST##K(MADD, w, xb);                                                         \
            w += kb;                                                                         \
        }                                                                                    \
        if (n_in & 1u) { /* the odd last column, paired with 0 */                            \
            const T xlast = BCAST##_LAST;                                                    \
            PK_LIST##K(MADD, w, xlast);                                                      \
            w += kb;                                                                         \
        }                                                                                    \
        PK_LIST##K(OUT, K, 0);                                                               \
        b = w;                                                                               \
        grp += (K);                                                                          \
    } while (0)
/* Every group of a layer: passes of PACK_PASS groups, then one of the rest. */
#define PK_LAYER(T, VB, BCAST, ACC, MADD, OUT)                                               \
    do {                                                                                     \
        while (n_groups - grp >= PACK_PASS)                                                \
            PK_PASS(9, T, VB, BCAST, ACC, MADD, OUT);                                        \
        switch (n_groups - grp) {                                                          \
        case 1: PK_PASS(1, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 2: PK_PASS(2, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 3: PK_PASS(3, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 4: PK_PASS(4, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 5: PK_PASS(5, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 6: PK_PASS(6, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 7: PK_PASS(7, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 8: PK_PASS(8, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        default: break;                                                                      \
        }                                                                                    \
    } while (0)
typedef char pack_pass_is_9[PACK_PASS == 9u ? 1 : -1]; /* PK_LAYER's passes */

/* Input pair p (x[2p] in the low half) as one int32; memcpy: x is int16 storage. */
static inline int32_t x_pair(const int16_t *x, unsigned p)
{
    int32_t v;
    memcpy(&v, x + 2u * p, sizeof v);
    return v;
}

/* The common start of a packed kernel: the head's counts and the whole input pairs (a pass
 * broadcasts an odd last column, with a zero partner, only where there is one). */
#define PK_BEGIN                                                                             \
    const unsigned char *b = block + sizeof(packed_head);                                    \
    const unsigned n_in = HEAD_U16(block, n_in), n_groups = HEAD_U16(block, n_groups);       \
    const unsigned full = n_in / 2u;                                                         \
    unsigned grp = 0u, p

/* SSE2: groups of four rows, 16-byte vectors; the sums requantised by the scalar rule. */
#define PK4_BCAST(p) _mm_set1_epi32(x_pair(x, p))
#define PK4_BCAST_LAST _mm_set1_epi32((int32_t)(uint16_t)x[n_in - 1u])
#define PK4_ACC(i, p_, xb_) lanes32x4 a##i = (lanes32x4)load128(b + 16u * (i))
#define PK4_MADD(i, w, xb) a##i += (lanes32x4)_mm_madd_epi16(load128((w) + 16u * (i)), xb)
#define PK4_ACC_OUT(i, p_, xb_) _mm_storeu_si128((__m128i *)(void *)(acc + 4u * (grp + (i))), (__m128i)a##i)
#define PK4_HIDDEN_OUT(i, p_, xb_)                                                           \
    do {                                                                                     \
        int32_t t[4], m[4];                                                                  \
        unsigned q;                                                                          \
        _mm_storeu_si128((__m128i *)(void *)t, (__m128i)a##i);                               \
        memcpy(m, b + kb + 16u * (i), sizeof m);                                             \
        for (q = 0; q < 4u; ++q) {                                                           \
            int64_t v = fbg_rshift_round((int64_t)t[q] * m[q], shift);                       \
            y[4u * (grp + (i)) + q] = fbg_sat16(v < 0 ? 0 : v, sat);                         \
        }                                                                                    \
    } while (0)

/* One hidden layer; returns the next layer's block. */
static inline const unsigned char *hidden_packed_sse2(const unsigned char *block, const int16_t *x,
                                                      int16_t *y, uint32_t *sat)
{
    PK_BEGIN;
    const unsigned shift = HEAD_U32(block, shift);
    PK_LAYER(__m128i, 16u, PK4_BCAST, PK4_ACC, PK4_MADD, PK4_HIDDEN_OUT);
    return b;
}

/* The output layer: its rows' accumulators into acc (n_out rounded up to 4); returns n_out. */
static inline unsigned acc32_packed_sse2(const unsigned char *block, const int16_t *x, int32_t *acc)
{
    PK_BEGIN;
    PK_LAYER(__m128i, 16u, PK4_BCAST, PK4_ACC, PK4_MADD, PK4_ACC_OUT);
    return HEAD_U16(block, n_out);
}

/* Every layer of a packed net (n_layers blocks from block on). */
static unsigned net_packed_sse2(const unsigned char *block, unsigned n_layers, const int16_t *x,
                                int16_t (*act)[FBG_MAX_WIDTH], int32_t *acc, uint32_t *sat)
{
    unsigned l;
    for (l = 0; l + 1u < n_layers; ++l) {
        block = hidden_packed_sse2(block, x, act[l & 1u], sat);
        x = act[l & 1u];
    }
    return acc32_packed_sse2(block, x, acc);
}

/* AVX2: groups of eight rows, 32-byte vectors; eight rows requantised at once (requant8). */
#define PK8_BCAST(p) _mm256_set1_epi32(x_pair(x, p))
#define PK8_BCAST_LAST _mm256_set1_epi32((int32_t)(uint16_t)x[n_in - 1u])
#define PK8_ACC(i, p_, xb_) lanes32 a##i = (lanes32)load256(b + 32u * (i))
#define PK8_MADD(i, w, xb) a##i += (lanes32)_mm256_madd_epi16(load256((w) + 32u * (i)), xb)
#define PK8_ACC_OUT(i, p_, xb_) _mm256_storeu_si256((__m256i *)(void *)(acc + 8u * (grp + (i))), (__m256i)a##i)
#define PK8_HIDDEN_OUT(i, p_, xb_)                                                           \
    _mm_storeu_si128((__m128i *)(void *)(y + 8u * (grp + (i))),                              \
                     requant8((__m256i)a##i, load256(b + kb + 32u * (i)), round, top, shift, &big))

/* requant8 where high_word_requant holds, from multipliers stored at shift 32 (m' = mult *
 * 2^(32-shift)) at mult: t = acc * m' + 2^31 exactly in int64 (VPMULDQ of the even rows, then
 * of the odd ones against the multipliers read 4 bytes on, whose low dwords are the odd
 * rows'), and the quotient is t's high dword (for the even rows shifted down, the odd ones'
 * already in place: one blend puts the eight in row order), returned before ReLU.
 * *peak keeps each lane's largest value (VPMAXSD; it starts at 0, so it stays >= 0): a bit
 * above bit 14 in some lane is a row that clamped (fbg_sat16's flag). */
AVX2 static inline __m256i requant8_high(__m256i acc, const unsigned char *mult, __m256i *peak)
{
    const __m256i round = _mm256_set1_epi64x((int64_t)1 << 31);
    const __m256i t0 = _mm256_add_epi64(_mm256_mul_epi32(acc, load256(mult)), round);
    const __m256i t1 = _mm256_add_epi64(_mm256_mul_epi32(_mm256_srli_epi64(acc, 32), load256(mult + 4)), round);
    const __m256i q = _mm256_blend_epi32(_mm256_srli_epi64(t0, 32), t1, 0xAA);
    *peak = _mm256_max_epi32(*peak, q);
    return q;
}

/* requant8_high's int32 quotients of group i into rq[i]; then, at each odd i, groups i-1 and
 * i narrowed to int16 together (VPACKSSDW of the two interleaves them by 64 bits and
 * saturates at 32767, the clamp; VPMAXSW with 0 is the ReLU, which commutes with that
 * narrowing: a negative value stays negative; VPERMQ puts the rows back in order) and stored
 * as one vector of 16 rows, and the pass's last group alone when K is odd. The multipliers
 * of the pass's last group are followed by its first weights: the read 4 bytes on stays
 * inside the block. */
#define PK8_HIGH_OUT(i, K, xb_)                                                              \
    do {                                                                                     \
        rq[i] = requant8_high((__m256i)a##i, b + kb + 32u * (i), &big);                      \
        if ((i) & 1u)                                                                        \
            _mm256_storeu_si256((__m256i *)(void *)(y + 8u * (grp + (i) - 1u)),              \
                                _mm256_permute4x64_epi64(_mm256_max_epi16(_mm256_packs_epi32(rq[(i) - ((i) & 1u)], rq[i]), \
                                                                          _mm256_setzero_si256()), 0xD8)); \
        else if ((i) + 1u == (K))                                                            \
            _mm_storeu_si128((__m128i *)(void *)(y + 8u * (grp + (i))),                      \
                             _mm_max_epi16(_mm_packs_epi32(_mm256_castsi256_si128(rq[i]), _mm256_extracti128_si256(rq[i], 1)), \
                                           _mm_setzero_si128()));                            \
    } while (0)

/* One hidden layer; big collects the rows that clamped (a bit above bit 14 in a lane, which
 * stays >= 0: requant8 sets all but the sign bit of a clamped lane, requant8_high keeps the
 * lane's largest value there); returns the next layer's block. */
AVX2 __attribute__((always_inline)) static inline const unsigned char *hidden_packed_avx2(const unsigned char *block, const int16_t *x,
                                                           int16_t *y, __m256i *bigp)
{
    PK_BEGIN;
    __m256i big = *bigp;
    if (HEAD_U16(block, high_word)) {
        __m256i rq[PACK_PASS];
        PK_LAYER(__m256i, 32u, PK8_BCAST, PK8_ACC, PK8_MADD, PK8_HIGH_OUT);
    } else {
        const __m256i round = _mm256_set1_epi64x(HEAD_I64(block, round));
        const __m256i top = _mm256_set1_epi64x(HEAD_I64(block, top));
        const __m128i shift = _mm_cvtsi32_si128((int)HEAD_U32(block, shift));
        PK_LAYER(__m256i, 32u, PK8_BCAST, PK8_ACC, PK8_MADD, PK8_HIDDEN_OUT);
    }
    *bigp = big;
    return b;
}

/* The output layer in groups: its rows' accumulators into acc (n_out rounded up to 8). */
AVX2 __attribute__((always_inline)) static inline void acc32_packed_avx2(const unsigned char *block, const int16_t *x, int32_t *acc)
{
    PK_BEGIN;
    PK_LAYER(__m256i, 32u, PK8_BCAST, PK8_ACC, PK8_MADD, PK8_ACC_OUT);
}

/* The output layer in the dot-product form (dot_layer): each row's whole vectors of 16
 * weights against x's, one multiply-add and one add a vector, the lanes added up at the end
 * (any order: the int32 proof), the bias added, sign-extended into acc. */
AVX2 __attribute__((always_inline)) static inline void acc_dot_avx2(const unsigned char *block, const int16_t *x, int64_t *acc)
{
    const unsigned char *w = block + sizeof(packed_head) + 32u;
    const unsigned width = dot_width(HEAD_U16(block, n_in));
    unsigned j;
    int32_t bias;
    lanes32 a0, a1;
    __m128i s;
    a0 = (lanes32)_mm256_madd_epi16(load256(w), load256(x));
    if (HEAD_U16(block, n_out) == 1u) {
        for (j = 16u; j < width; j += 16u)
            MADD(a0, load256(w + 2u * j), load256(x + j));
        s = sum1_row((__m256i)a0);
        memcpy(&bias, block + sizeof(packed_head), sizeof bias);
        acc[0] = (int32_t)((uint32_t)_mm_cvtsi128_si32(s) + (uint32_t)bias);
        return;
    }
    a1 = (lanes32)_mm256_madd_epi16(load256(w + 2u * width), load256(x));
    for (j = 16u; j < width; j += 16u) {
        const __m256i xv = load256(x + j);
        MADD(a0, load256(w + 2u * j), xv);
        MADD(a1, load256(w + 2u * (width + j)), xv);
    }
    s = sum2_rows((__m256i)a0, (__m256i)a1);
    s = _mm_add_epi32(s, _mm_loadl_epi64((const __m128i *)(const void *)(block + sizeof(packed_head))));
    _mm_storeu_si128((__m128i *)(void *)acc, _mm_cvtepi32_epi64(s));
}

AVX2 static void net_packed_avx2(const unsigned char *block, unsigned n_layers, const int16_t *x,
                                 int16_t (*act)[FBG_MAX_WIDTH], int64_t *acc, uint32_t *sat)
{
    /* Every bit but the low 15 of a lane: a clamped row. */
    const __m256i clamped = _mm256_set1_epi32(~0x7FFF);
    __m256i big = _mm256_setzero_si256();
    int32_t acc32[FBG_MAX_WIDTH];
    unsigned l, r, n_out;
    for (l = 0; l + 1u < n_layers; ++l) {
        block = hidden_packed_avx2(block, x, act[l & 1u], &big);
        x = act[l & 1u];
    }
    /* Rows past n_out have multiplier 0: they requantise to 0 and never clamp. */
    if (!_mm256_testz_si256(big, clamped))
        *sat = 1u;
    if (HEAD_U16(block, dot)) {
        acc_dot_avx2(block, x, acc);
        return;
    }
    acc32_packed_avx2(block, x, acc32);
    n_out = HEAD_U16(block, n_out);
    for (r = 0; r < n_out; ++r)
        acc[r] = acc32[r];
}

/* SSE2's packed net and the copy of its int32 accumulators: kept out of line, so that the
 * AVX2 path through fbg_simd_net_packed needs no frame (a call every net of every step). */
__attribute__((noinline)) static void net_packed_sse2_acc64(const unsigned char *block, unsigned n_layers,
                                                            const int16_t *x, int16_t (*act)[FBG_MAX_WIDTH],
                                                            int64_t *acc, uint32_t *sat)
{
    int32_t acc32[FBG_MAX_WIDTH];
    unsigned r, n_out = net_packed_sse2(block, n_layers, x, act, acc32, sat);
    for (r = 0; r < n_out; ++r)
        acc[r] = acc32[r];
}

int fbg_simd_net_packed(uint32_t kernel, const void *packed, unsigned n, unsigned n_layers,
                        const int16_t *x, int16_t (*act)[FBG_MAX_WIDTH], int64_t *acc, uint32_t *sat)
{
    uint32_t off;
    /* memcpy: the caller's buffer may have any declared type. */
    memcpy(&off, (const unsigned char *)packed + offsetof(fbg_pack_header, net_off) + n * sizeof off,
           sizeof off);
    if (off == 0u)
        return 0;
    if (kernel == FBG_OPT_KERNEL_AVX2)
        net_packed_avx2((const unsigned char *)packed + off, n_layers, x, act, acc, sat);
    else
        net_packed_sse2_acc64((const unsigned char *)packed + off, n_layers, x, act, acc, sat);
    return 1;
}

/* ---- AVX2 filter: the four channels in one vector of int64 --------------------------- */

/* Each tap: the four int32 history values sign-extended to int64 (VPMOVSXDQ), times the tap
 * (VPMULDQ multiplies the low dwords as signed: int32 by int16, exact in int64), added in
 * int64; the ring read as its two runs, newest first, so no index wraps. Within a run, four
 * taps at a time are widened to int32 in one vector whose two halves both hold them, so that
 * VPSHUFD puts tap j in the low dword of every 64-bit lane (all VPMULDQ reads); the run's
 * last len mod 4 taps one by one. The sum is the portable loop's sum of the same integers,
 * in another order, which fbg_model_check bounds within int64 whatever the order (every
 * partial sum is a sum of a subset of the terms). */
#define FIR_TAP(j) _mm256_mul_epi32(_mm256_cvtepi32_epi64(load128(hist[idx - (j)])), _mm256_shuffle_epi32(t4, (j) * 0x55))
AVX2 static inline __m256i fir_run(__m256i acc, const int16_t *taps, const int32_t (*hist)[FBG_N_STRAIN],
                                   size_t idx, unsigned len)
{
    unsigned k; /* idx a size_t: the four reads of a block take one address and offsets */
    for (k = 0; k + 4u <= len; k += 4u, idx -= 4u) {
        const __m256i t4 = _mm256_broadcastsi128_si256(
            _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)(taps + k))));
        acc = _mm256_add_epi64(acc, _mm256_add_epi64(_mm256_add_epi64(FIR_TAP(0), FIR_TAP(1)),
                                                     _mm256_add_epi64(FIR_TAP(2), FIR_TAP(3))));
    }
    for (; k < len; ++k, --idx)
        acc = _mm256_add_epi64(acc, _mm256_mul_epi32(_mm256_cvtepi32_epi64(load128(hist[idx])),
                                                     _mm256_set1_epi32(taps[k])));
    return acc;
}

/* The first run: taps 0 .. pos against hist[pos] down to hist[0]; the second: taps pos+1 ..
 * n_taps-1 against hist[n_taps-1] down to hist[pos+1]. idx - 3 stays >= 0 within a run's
 * blocks of four (idx counts down to the run's last entry). */
AVX2 static inline __m256i fir4_avx2(const int16_t *taps, unsigned n_taps, const int32_t (*hist)[FBG_N_STRAIN],
                                     unsigned pos)
{
    const __m256i acc = fir_run(_mm256_setzero_si256(), taps, hist, pos, pos + 1u);
    return fir_run(acc, taps + pos + 1u, hist, n_taps - 1u, n_taps - 1u - pos);
}

/* floor(v / 2^s) of int64 lanes (AVX2 has no 64-bit arithmetic shift): with m = -1 in the
 * negative lanes, v ^ m is -v - 1 >= 0 there, whose logical shift is floor((-v - 1) / 2^s),
 * and ^ m again gives -floor((-v - 1) / 2^s) - 1 = floor(v / 2^s). */
AVX2 static inline __m256i sra64(__m256i v, __m128i s)
{
    const __m256i m = _mm256_cmpgt_epi64(_mm256_setzero_si256(), v);
    return _mm256_xor_si256(_mm256_srl_epi64(_mm256_xor_si256(v, m), s), m);
}

/* clamp(v, -lim, lim) of int64 lanes, *flag gathering the lanes that clamped (fbg_sat32's or
 * fbg_sat16's flag). */
AVX2 static inline __m256i clamp64(__m256i v, int64_t lim, __m256i *flag)
{
    const __m256i hi = _mm256_set1_epi64x(lim), lo = _mm256_set1_epi64x(-lim);
    const __m256i over = _mm256_cmpgt_epi64(v, hi), under = _mm256_cmpgt_epi64(lo, v);
    *flag = _mm256_or_si256(*flag, _mm256_or_si256(over, under));
    return _mm256_blendv_epi8(_mm256_blendv_epi8(v, hi, over), lo, under);
}

/* Steps 2 and 3 of fbg_step in lanes of int64, one channel each, the same operations as its
 * loop: filt = sat32(rshift_round(fir, tap_q)), d = sat32(filt - mean), in =
 * sat16(rshift_round(d * z_mult, z_shift)) (VPMULDQ: filt and d are int32 after their clamps,
 * the low dwords it reads; the products are exact in int64), and the load proxy's terms
 * filt * load_coeff added up. The rounding sums stay inside int64 as in the scalar code
 * (|fir| < 2^52, |d * z_mult| < 2^62, 2^(z_shift-1) <= 2^61). */
AVX2 static int filter4_avx2(const fbg_model *m, const int32_t (*hist)[FBG_N_STRAIN], unsigned pos,
                             int16_t *in, int32_t *held, int64_t *load)
{
    __m256i flag = _mm256_setzero_si256(), t;
    __m128i l, z;
    const __m256i fir = fir4_avx2(m->taps, m->n_taps, hist, pos);
    const __m256i filt = clamp64(sra64(_mm256_add_epi64(fir, _mm256_set1_epi64x((int64_t)1 << (m->tap_q - 1u))),
                                       _mm_cvtsi32_si128(m->tap_q)), FBG_SAT32, &flag);
    const __m256i d = clamp64(_mm256_sub_epi64(filt, _mm256_cvtepi32_epi64(load128(m->mean_fm))), FBG_SAT32, &flag);
    _mm_storeu_si128((__m128i *)(void *)held, _mm256_castsi256_si128(
        _mm256_permutevar8x32_epi32(filt, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6))));
    t = _mm256_add_epi64(_mm256_mul_epi32(d, _mm256_cvtepi32_epi64(load128(m->z_mult))),
                         _mm256_set1_epi64x((int64_t)1 << (m->z_shift - 1u)));
    t = clamp64(sra64(t, _mm_cvtsi32_si128(m->z_shift)), FBG_SAT16, &flag);
    /* The four values' low dwords (each an int16 value) into the low half, narrowed. */
    t = _mm256_permutevar8x32_epi32(t, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6));
    z = _mm256_castsi256_si128(t);
    _mm_storel_epi64((__m128i *)(void *)in, _mm_packs_epi32(z, z));
    t = _mm256_mul_epi32(filt, _mm256_cvtepi32_epi64(load128(m->load_coeff)));
    l = _mm_add_epi64(_mm256_castsi256_si128(t), _mm256_extracti128_si256(t, 1));
    l = _mm_add_epi64(l, _mm_unpackhi_epi64(l, l));
    *load = _mm_cvtsi128_si64(l);
    return !_mm256_testz_si256(flag, flag);
}

/* The location averages of memory_features (fbg_fixed.c) from z = in[0..3] as int32 lanes,
 * the same operations lane by lane: r = sat16(z - z0) (VPMINSD/VPMAXSD; a lane that moved
 * clamped), target = r * 2^15, the state primed at the target on the first sample, state +=
 * rshift_round(target - state, shift) with the arithmetic shift VPSRAD (the scalar loop's
 * bounds keep every lane's sum in int32), loc = rshift_round(state, 15), which lies within
 * int16, so VPACKSSDW narrows it unchanged. Returns 1 where a lane clamped. The constants
 * are loaded from memory (one instruction each, where building them takes three). */
static const int32_t loc_consts[3][4] = {{FBG_SAT16, FBG_SAT16, FBG_SAT16, FBG_SAT16},
                                          {-FBG_SAT16, -FBG_SAT16, -FBG_SAT16, -FBG_SAT16},
                                          {1 << (FBG_EMA_FRAC - 1), 1 << (FBG_EMA_FRAC - 1),
                                           1 << (FBG_EMA_FRAC - 1), 1 << (FBG_EMA_FRAC - 1)}};
AVX2 static int loc4_avx2(fbg_state *s, unsigned shift, __m128i z, int16_t *loc)
{
    const __m128i d = _mm_sub_epi32(z, _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)s->loc_z0)));
    const __m128i r = _mm_max_epi32(_mm_min_epi32(d, load128(loc_consts[0])), load128(loc_consts[1]));
    const __m128i target = _mm_slli_epi32(r, FBG_EMA_FRAC);
    __m128i e = s->mem_primed ? load128(s->loc) : target;
    e = _mm_add_epi32(e, _mm_sra_epi32(_mm_add_epi32(_mm_sub_epi32(target, e), _mm_set1_epi32((int32_t)1 << (shift - 1u))),
                                       _mm_cvtsi32_si128((int)shift)));
    _mm_storeu_si128((__m128i *)(void *)s->loc, e);
    e = _mm_srai_epi32(_mm_add_epi32(e, load128(loc_consts[2])), FBG_EMA_FRAC);
    _mm_storel_epi64((__m128i *)(void *)loc, _mm_packs_epi32(e, e));
    return !_mm_testc_si128(_mm_cmpeq_epi32(d, r), _mm_cmpeq_epi32(d, d));
}

/* Step 1's fault rule (fbg_fault_check of fbg_internal.h) for the five channels in lanes 0-4
 * of int32 (lanes 5-7 hold 0 and are masked off by lanes5; load5 and store5 touch only the
 * five), the same tests lane
 * by lane: a lane out of the window [FBG_WL_MIN_FM, FBG_WL_MAX_FM] is faulty and its run
 * restarts, prev and its valid bit unchanged; an in-window lane whose prev holds a sample is
 * faulty past jump_max_fm either way (the difference is exact in int32: both in the window)
 * and counts a repeat of the identical value (saturating at 0xFFFF, VPMINUD), faulty at
 * stuck_max repeats when that is not 0; an in-window lane becomes prev, valid. Returns 1 for
 * a faulty sample; *w = the sample's lanes (lanes 5-7: 0, never stored). */
static const int32_t lanes5[8] = {-1, -1, -1, -1, -1, 0, 0, 0};
/* Five int32 into lanes 0-4 (the rest 0), and lanes 0-4 back: plain loads and stores, not
 * VPMASKMOVD (its store is microcoded and slow on AMD cores). */
AVX2 static inline __m256i load5(const int32_t *p)
{
    return _mm256_inserti128_si256(_mm256_castsi128_si256(load128(p)), _mm_cvtsi32_si128(p[4]), 1);
}

AVX2 static inline void store5(int32_t *p, __m256i v)
{
    _mm_storeu_si128((__m128i *)(void *)p, _mm256_castsi256_si128(v));
    p[4] = _mm_cvtsi128_si32(_mm256_extracti128_si256(v, 1));
}

static const int32_t lane_bits[8] = {1, 2, 4, 8, 16, 32, 64, 128};
AVX2 static int fault5_avx2(fbg_state *s, const int32_t *wl, __m256i *w)
{
    const fbg_model *m = s->model;
    const __m256i zero = _mm256_setzero_si256(), m5 = load256(lanes5), bits = load256(lane_bits);
    const __m256i jmax = _mm256_set1_epi32(m->jump_max_fm);
    const unsigned valid = s->prev_valid;
    uint16_t run16[8] = {0};
    __m256i out, in_window, active, d, jump, n, faulty;
    __m128i packed;
    const __m256i prev = load5(s->prev_fm);
    *w = load5(wl);
    out = _mm256_and_si256(m5, _mm256_or_si256(_mm256_cmpgt_epi32(_mm256_set1_epi32(FBG_WL_MIN_FM), *w),
                                                _mm256_cmpgt_epi32(*w, _mm256_set1_epi32(FBG_WL_MAX_FM))));
    in_window = _mm256_andnot_si256(out, m5);
    active = _mm256_and_si256(in_window, _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32((int)valid), bits), bits));
    d = _mm256_sub_epi32(*w, prev);
    jump = _mm256_or_si256(_mm256_cmpgt_epi32(d, jmax), _mm256_cmpgt_epi32(_mm256_sub_epi32(zero, jmax), d));
    memcpy(run16, s->same_run, sizeof s->same_run);
    n = _mm256_add_epi32(_mm256_cvtepu16_epi32(load128(run16)), _mm256_srli_epi32(m5, 31));
    n = _mm256_and_si256(_mm256_and_si256(active, _mm256_cmpeq_epi32(d, zero)),
                         _mm256_min_epu32(n, _mm256_set1_epi32(0xFFFF)));
    faulty = _mm256_or_si256(out, _mm256_and_si256(jump, active));
    if (m->stuck_max != 0u)
        faulty = _mm256_or_si256(faulty, _mm256_cmpgt_epi32(n, _mm256_set1_epi32((int)m->stuck_max - 1)));
    packed = _mm_packus_epi32(_mm256_castsi256_si128(n), _mm256_extracti128_si256(n, 1));
    _mm_storeu_si128((__m128i *)(void *)run16, packed);
    memcpy(s->same_run, run16, sizeof s->same_run);
    store5(s->prev_fm, _mm256_blendv_epi8(prev, *w, in_window));
    if (valid != 0x1Fu) { /* until every channel has had an in-window sample */
        int32_t lanes[8];
        unsigned c, v = valid;
        _mm256_storeu_si256((__m256i *)(void *)lanes, in_window);
        for (c = 0; c < FBG_N_CHANNELS; ++c)
            if (lanes[c])
                v |= 1u << c;
        s->prev_valid = (uint8_t)v;
    }
    return !_mm256_testz_si256(faulty, faulty);
}

/* Step 1's temperature compensation of fbg_step in lanes of int64, one channel each, the
 * same operations as its loop: comp = sat32(shift_c - rshift_round(ref * coeff_c, 24))
 * (VPMULDQ of ref, the reference's average that fbg_ref_update gave for this sample,
 * broadcast, by the sign-extended coefficients: exact in int64, |.| < 2^30 * 2^31), stored
 * where the loop's values go: the ring at pos. Returns 1 where a lane clamped. */
AVX2 static int comp4_avx2(fbg_state *s, __m256i shift, int32_t ref)
{
    __m256i flag = _mm256_setzero_si256();
    const __m256i p = _mm256_mul_epi32(_mm256_set1_epi32(ref),
                                       _mm256_cvtepi32_epi64(load128(s->model->temp_coeff_q24)));
    const __m256i t = sra64(_mm256_add_epi64(p, _mm256_set1_epi64x((int64_t)1 << (FBG_TEMP_COEFF_SHIFT - 1))),
                            _mm_cvtsi32_si128(FBG_TEMP_COEFF_SHIFT));
    const __m256i c = clamp64(_mm256_sub_epi64(_mm256_cvtepi32_epi64(_mm256_castsi256_si128(shift)), t), FBG_SAT32, &flag);
    const __m128i comp = _mm256_castsi256_si128(_mm256_permutevar8x32_epi32(c, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6)));
    _mm_storeu_si128((__m128i *)(void *)s->hist[s->pos], comp);
    return !_mm256_testz_si256(flag, flag);
}

/* The memory kinds' update rules of fbg_fixed.c (<kind>_features, FBG_MEMORY_KINDS), the
 * states of a kind in the lanes of one vector, the same operations: the scalar loop's bounds
 * hold in every lane. The states of lanes k >= n stay as they are (blended back); the features
 * go to f[0 ..] as a whole vector of four, the entries past the kind's last being overwritten
 * by the next kind's or ones no net reads. Each returns the number of features of its kind
 * and sets *clamped where an in-use feature clamped. */
static const int32_t lane_index4[4] = {0, 1, 2, 3};

/* All ones in the lanes k < n. */
AVX2 static __m128i lanes_in_use(unsigned n)
{
    return _mm_cmpgt_epi32(_mm_set1_epi32((int)n), load128(lane_index4));
}

/* sat16 of the features f into out[0..3]; 1 where a lane in use clamped. */
AVX2 static int store_features4(__m128i f, __m128i used, int16_t *out)
{
    const __m128i lim = load128(loc_consts[0]), nlim = load128(loc_consts[1]);
    const __m128i flag = _mm_and_si128(used, _mm_or_si128(_mm_cmpgt_epi32(f, lim), _mm_cmpgt_epi32(nlim, f)));
    f = _mm_max_epi32(_mm_min_epi32(f, lim), nlim);
    _mm_storel_epi64((__m128i *)(void *)out, _mm_packs_epi32(f, f));
    return !_mm_testz_si128(flag, flag);
}

/* The exponential averages: e += (target - e + 2^(shift-1)) >> shift (VPSRAVD: each lane its
 * own shift), feature = sat16((u - rshift_round(e, 15)) << gain) (VPSLLVD). */
AVX2 static unsigned ema_features_avx2(fbg_state *s, __m128i u, int primed, int16_t *f, int *clamped)
{
    const fbg_model *m = s->model;
    const __m128i used = lanes_in_use(m->n_ema), target = _mm_slli_epi32(u, FBG_EMA_FRAC);
    __m128i e = primed ? load128(s->ema) : target, shift, fe;
    int32_t word;
    memcpy(&word, m->ema_shift, sizeof word);
    shift = _mm_cvtepu8_epi32(_mm_cvtsi32_si128(word));
    e = _mm_add_epi32(e, _mm_srav_epi32(_mm_add_epi32(_mm_sub_epi32(target, e),
                                                      _mm_srli_epi32(_mm_sllv_epi32(_mm_set1_epi32(1), shift), 1)),
                                       shift));
    _mm_storeu_si128((__m128i *)(void *)s->ema, _mm_blendv_epi8(load128(s->ema), e, used));
    memcpy(&word, m->ema_gain, sizeof word);
    fe = _mm_sllv_epi32(_mm_sub_epi32(u, _mm_srai_epi32(_mm_add_epi32(e, load128(loc_consts[2])), FBG_EMA_FRAC)),
                        _mm_cvtepu8_epi32(_mm_cvtsi32_si128(word)));
    *clamped |= store_features4(fe, used, f);
    return m->n_ema;
}

/* The play operators: p = clamp(p, u - width, u + width), feature = sat16((u - p) << gain). */
AVX2 static unsigned play_features_avx2(fbg_state *s, __m128i u, int primed, int16_t *f, int *clamped)
{
    const fbg_model *m = s->model;
    const __m128i used = lanes_in_use(m->n_play);
    const __m128i width = _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)m->play_width));
    __m128i p = primed ? load128(s->play) : _mm_add_epi32(u, width);
    int32_t word;
    p = _mm_min_epi32(_mm_max_epi32(p, _mm_sub_epi32(u, width)), _mm_add_epi32(u, width));
    _mm_storeu_si128((__m128i *)(void *)s->play, _mm_blendv_epi8(load128(s->play), p, used));
    memcpy(&word, m->play_gain, sizeof word);
    *clamped |= store_features4(_mm_sllv_epi32(_mm_sub_epi32(u, p), _mm_cvtepu8_epi32(_mm_cvtsi32_si128(word))),
                                used, f);
    return m->n_play;
}

/* Every kind's states fill the four lanes of one vector, and its four features stored from
 * its offset (at most FBG_N_STRAIN plus the earlier kinds' limits) stay inside in[]. */
#define FBG_KIND_LANES(kind, KIND) typedef char kind##_lanes_avx2[FBG_MAX_##KIND == 4 ? 1 : -1];
FBG_MEMORY_KINDS(FBG_KIND_LANES)
#undef FBG_KIND_LANES
#define FBG_KIND_LIMIT(kind, KIND) + FBG_MAX_##KIND
typedef char memory4_stores_inside_in[FBG_N_STRAIN FBG_MEMORY_KINDS(FBG_KIND_LIMIT) <= FBG_MAX_INPUTS ? 1 : -1];
#undef FBG_KIND_LIMIT

/* The load signal's memory features of memory_features (fbg_fixed.c) from z (int32 lanes):
 * u = sat16(rshift_round(sum_c z_c * mem_mult_c, mem_shift)) (VPMULDQ: exact int64 products,
 * their sum < 2^48, then the scalar rule), then every kind's states, primed on the first
 * sample, and features to in[4 ..] in the order of FBG_MEMORY_KINDS. Returns 1 where a clamp
 * happened. */
AVX2 static int memory4_avx2(fbg_state *s, __m128i z, int16_t *in)
{
    const fbg_model *m = s->model;
    const __m256i prod = _mm256_mul_epi32(_mm256_cvtepi32_epi64(z), _mm256_cvtepi32_epi64(load128(m->mem_mult)));
    __m128i l = _mm_add_epi64(_mm256_castsi256_si128(prod), _mm256_extracti128_si256(prod, 1));
    const int primed = s->mem_primed;
    uint32_t sat = 0u;
    int clamped;
    int16_t *f = in + FBG_N_STRAIN;
    __m128i u;
    l = _mm_add_epi64(l, _mm_unpackhi_epi64(l, l));
    u = _mm_set1_epi32(fbg_sat16_rshift_round(_mm_cvtsi128_si64(l), m->mem_shift, &sat));
    clamped = sat != 0u;
#define FBG_KIND_FEATURES(kind, KIND) f += kind##_features_avx2(s, u, primed, f, &clamped);
    FBG_MEMORY_KINDS(FBG_KIND_FEATURES)
#undef FBG_KIND_FEATURES
    return clamped;
}

/* The stages of fbg_step in AVX2 (fbg_simd.h). The front: the fault rule; for a clean sample
 * the tare difference (within +-1e9 for in-window values: fbg_front_sample) and the
 * compensation into the ring; for a faulty one last_comp (the last filtered shifts, which
 * filter4_avx2 keeps) into the ring. */
AVX2 void fbg_avx2_front(fbg_state *s, const int32_t *wl_fm, uint32_t *status, uint32_t *sat)
{
    __m256i w, shift;
    int32_t ref;
    if (fault5_avx2(s, wl_fm, &w)) {
        *status |= FBG_STATUS_SENSOR_FAULT;
        _mm_storeu_si128((__m128i *)(void *)s->hist[s->pos], load128(s->last_comp));
        return;
    }
    shift = _mm256_sub_epi32(w, load5(s->baseline_fm));
    /* The reference's average is one scalar recursion: it runs before the vector part. */
    ref = fbg_ref_update(&s->ref_acc, &s->ref_primed, _mm256_extract_epi32(shift, FBG_N_STRAIN),
                         s->model->ref_shift);
    if (comp4_avx2(s, shift, ref))
        *sat = 1u;
}

AVX2 int fbg_avx2_filter(fbg_state *s, int16_t *in, uint32_t *sat)
{
    const fbg_model *m = s->model;
    int64_t load;
    if (filter4_avx2(m, (const int32_t(*)[FBG_N_STRAIN])s->hist, s->pos, in, s->last_comp, &load))
        *sat = 1u;
    return fbg_rshift_round(load, m->load_shift) > m->load_max_mN;
}

/* The memory features from z = in[0..3] (int16 values, widened to int32 lanes): the location
 * averages, then the load signal's, and the flags of the clamps in each and of
 * memory_features' loc_z0_clamped. */
AVX2 void fbg_avx2_memory(fbg_state *s, int16_t *in, int16_t *loc, uint32_t *sat)
{
    const fbg_model *m = s->model;
    const __m128i z = _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)in));
    int clamped = 0;
    if (m->loc_shift)
        clamped |= loc4_avx2(s, m->loc_shift, z, loc) | s->loc_z0_clamped;
    if (FBG_N_MEMORY_FEATURES(m) != 0u)
        clamped |= memory4_avx2(s, z, in);
    s->mem_primed = 1u;
    if (clamped)
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
