/*
 * fbg_simd_x86_avx2.c - AVX2 dense layers, eight rows per group, vector requantisation.
 * How the kernels stay exact: fbg_simd_x86.c.
 */
#include "fbg_simd_x86.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
/* ---- AVX2: eight rows per group, vector requantisation -------------------------------- */

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
AVX2 void fbg_avx2_layer(const fbg_layer *ly, const int16_t *x, int32_t *acc, int16_t *y,
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

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_avx2_unused;
#endif
