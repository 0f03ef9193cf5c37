/*
 * fbg_simd_x86_sse2.c - SSE2 dense layers, four rows per group (fbg_simd_acc32, fbg_simd_hidden).
 * How the kernels stay exact: fbg_simd_x86.c.
 */
#include "fbg_simd_x86.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
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

/* bias[r .. r+k-1] as int32 (|bias| <= INT32_MAX in an acc32 layer), 0 beyond k. */
static void bias32(const fbg_layer *ly, unsigned r, unsigned k, int32_t *b)
{
    unsigned i;
    for (i = 0; i < k; ++i)
        b[i] = r + i < ly->n_out ? (int32_t)ly->bias[r + i] : 0;
}

/* ---- SSE2: four rows per group ------------------------------------------------------- */

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

void fbg_sse2_acc32(const fbg_layer *ly, const int16_t *x, int32_t *acc)
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

void fbg_sse2_hidden(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    int32_t acc[FBG_MAX_WIDTH];
    unsigned r;
    fbg_sse2_acc32(ly, x, acc);
    for (r = 0; r < ly->n_out; ++r) {
        int64_t v = fbg_rshift_round((int64_t)acc[r] * ly->mult[r], ly->shift);
        y[r] = fbg_sat16(v < 0 ? 0 : v, sat);
    }
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_sse2_unused;
#endif
