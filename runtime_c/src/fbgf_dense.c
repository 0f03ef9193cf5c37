/*
 * fbgf_dense.c - dense layers of the float build: a portable C kernel and SIMD kernels
 * (SSE2 and AVX2+FMA on x86-64, NEON on aarch64); fbgf_dense.h says which one runs.
 *
 * The portable kernel is one chain of dependent adds per output, so it runs at the add
 * latency, and the compiler may not vectorise it without reassociating (under ISO C
 * floating point it must not). The SIMD kernels keep one accumulator per row and lane: the
 * weights are row-major, so lane k of row r sums the products of inputs j = k (mod lanes),
 * j ascending; each row's lanes are then added pairwise, ((l0 + l1) + (l2 + l3))
 * [+ ((l4 + l5) + (l6 + l7)) on AVX], and the bias last. On AVX2, layers with at most 16
 * inputs (each net's first) use one lane per row instead (dense_avx2_narrow). A row's
 * result never depends on which block of rows it falls in, on the other samples of a batch,
 * or on alignment. Inputs past n_in are multiplied by zero (zero-filled copies or masked
 * loads: exact, the sums never hold -0), and weights past a row are never read.
 *
 * Batches (fbgf_run) loop over samples inside each block of rows, so the block's weights are
 * read from L1 once per sample instead of from L2: a paper-size model's 65 kB of float
 * weights do not fit a 32 kB L1, and a single step is bound by that traffic.
 */
#include <string.h>

#include "fbgf_dense.h"

#if FBGF_SIMD && defined(__x86_64__)
#define FBGF_HAVE_SSE2 1
#include <emmintrin.h>
#if FBGF_HAVE_AVX2
#include <immintrin.h>
#endif
#elif FBGF_SIMD && defined(__aarch64__)
#define FBGF_HAVE_NEON 1
#include <arm_neon.h>
#endif

static void dense_portable(const fbgf_layer *ly, const float *x, float *y, int relu)
{
    unsigned r, j;
    for (r = 0; r < ly->n_out; ++r) {
        const float *w = ly->w + (size_t)r * ly->n_in;
        float a = ly->b[r];
        for (j = 0; j < ly->n_in; ++j)
            a += w[j] * x[j];
        /* a < 0 is false for NaN: an overflow inside the nets reaches the output check. */
        y[r] = (relu && a < 0.0f) ? 0.0f : a;
    }
}

#if defined(FBGF_HAVE_SSE2) || defined(FBGF_HAVE_NEON)
/* dst[0..4) = src[0..n) then zeros, n <= 4 (a loop: a memcpy call costs more than the copy). */
static void copy4(float dst[4], const float *src, unsigned n)
{
    unsigned k;
    for (k = 0; k < 4u; ++k)
        dst[k] = k < n ? src[k] : 0.0f;
}

/* The row pointers of the block of rows r0.. (`rows` of them; a short last block repeats the
 * last row) and how many of them are real. */
static unsigned block_rows(const fbgf_layer *ly, unsigned r0, unsigned rows, const float **w)
{
    unsigned k, n = ly->n_out - r0 < rows ? ly->n_out - r0 : rows;
    for (k = 0; k < rows; ++k)
        w[k] = ly->w + (size_t)(r0 + (k < n ? k : n - 1u)) * ly->n_in;
    return n;
}

/* A four-row block's set-up for the SSE2 and NEON kernels: its row pointers (block_rows), the
 * weights past the last group of four inputs zero-filled into wt (the inputs likewise, per
 * sample), its bias zero-filled into b; returns how many rows are real. */
static unsigned block4_setup(const fbgf_layer *ly, unsigned r0, const float **w, float wt[4][4],
                             float b[4])
{
    const unsigned full = ly->n_in & ~3u;
    unsigned k, n = block_rows(ly, r0, 4u, w);
    if (full < ly->n_in) {
        for (k = 0; k < 4u; ++k)
            copy4(wt[k], w[k] + full, ly->n_in - full);
    }
    copy4(b, ly->b + r0, n);
    return n;
}
#endif

#ifdef FBGF_HAVE_SSE2
/* Four rows x four lanes, samples inside row blocks (the block's weights stay in L1).
 * _mm_max_ps(0, a) is a < 0 ? 0 : a, NaN and -0 kept, as portable. */
static void dense_sse2(const fbgf_layer *ly, const float *xs, size_t x_stride, float *ys,
                       size_t y_stride, size_t n_samples, int relu)
{
    float wt[4][4], xt[4], b[4], out[4];
    const unsigned n_in = ly->n_in, full = n_in & ~3u;
    const __m128 zero = _mm_setzero_ps();
    unsigned r0, j, n;
    size_t i;
    for (r0 = 0; r0 < ly->n_out; r0 += 4u) {
        const float *w[4];
        __m128 bias;
        n = block4_setup(ly, r0, w, wt, b);
        bias = _mm_loadu_ps(b);
        for (i = 0; i < n_samples; ++i) {
            const float *x = xs + i * x_stride;
            float *y = ys + i * y_stride;
            __m128 a0 = zero, a1 = zero, a2 = zero, a3 = zero, t0, t1, t2, t3, s;
            for (j = 0; j < full; j += 4u) {
                const __m128 xv = _mm_loadu_ps(x + j);
                a0 = _mm_add_ps(a0, _mm_mul_ps(_mm_loadu_ps(w[0] + j), xv));
                a1 = _mm_add_ps(a1, _mm_mul_ps(_mm_loadu_ps(w[1] + j), xv));
                a2 = _mm_add_ps(a2, _mm_mul_ps(_mm_loadu_ps(w[2] + j), xv));
                a3 = _mm_add_ps(a3, _mm_mul_ps(_mm_loadu_ps(w[3] + j), xv));
            }
            if (full < n_in) {
                __m128 xv;
                copy4(xt, x + full, n_in - full);
                xv = _mm_loadu_ps(xt);
                a0 = _mm_add_ps(a0, _mm_mul_ps(_mm_loadu_ps(wt[0]), xv));
                a1 = _mm_add_ps(a1, _mm_mul_ps(_mm_loadu_ps(wt[1]), xv));
                a2 = _mm_add_ps(a2, _mm_mul_ps(_mm_loadu_ps(wt[2]), xv));
                a3 = _mm_add_ps(a3, _mm_mul_ps(_mm_loadu_ps(wt[3]), xv));
            }
            /* Transpose so that t_k holds lane k of every row, then (l0 + l1) + (l2 + l3). */
            t0 = _mm_unpacklo_ps(a0, a1);   /* a0[0] a1[0] a0[1] a1[1] */
            t1 = _mm_unpackhi_ps(a0, a1);   /* a0[2] a1[2] a0[3] a1[3] */
            t2 = _mm_unpacklo_ps(a2, a3);
            t3 = _mm_unpackhi_ps(a2, a3);
            a0 = _mm_movelh_ps(t0, t2);     /* lane 0 of rows 0..3 */
            a1 = _mm_movehl_ps(t2, t0);     /* lane 1 */
            a2 = _mm_movelh_ps(t1, t3);     /* lane 2 */
            a3 = _mm_movehl_ps(t3, t1);     /* lane 3 */
            s = _mm_add_ps(_mm_add_ps(_mm_add_ps(a0, a1), _mm_add_ps(a2, a3)), bias);
            if (relu)
                s = _mm_max_ps(zero, s);
            if (n == 4u) {
                _mm_storeu_ps(y + r0, s);
            } else {
                _mm_storeu_ps(out, s);
                memcpy(y + r0, out, n * sizeof *out);
            }
        }
    }
}
#endif

#if FBGF_HAVE_AVX2
#define FBGF_AVX2 __attribute__((target("avx2,fma")))

/* Lanes 0 .. n - full - 1 on: the inputs of the last, partial group of eight (maskload reads
 * nothing past a row or past x), or with full = 0 the first n lanes. */
FBGF_AVX2 static __m256i tail_mask(unsigned n, unsigned full)
{
    static const int32_t ones[16] = {-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0};
    return _mm256_loadu_si256((const __m256i *)(ones + 8u - (n - full)));
}

/* The lane sums of rows 0..7 (a0..a7) added as ((l0 + l1) + (l2 + l3)) + ((l4 + l5) + (l6 + l7))
 * per row, rows in order; _mm256_hadd_ps adds neighbours within each 128-bit half. The four-
 * and one-row forms below use the same tree, so a row's bits do not depend on its block. */
FBGF_AVX2 static __m256 sum8(__m256 a0, __m256 a1, __m256 a2, __m256 a3, __m256 a4, __m256 a5,
                             __m256 a6, __m256 a7)
{
    /* h01 = [r0: l0+l1, l2+l3, r1: l0+l1, l2+l3 | r0: l4+l5, l6+l7, r1: l4+l5, l6+l7] */
    __m256 h01 = _mm256_hadd_ps(a0, a1), h23 = _mm256_hadd_ps(a2, a3);
    __m256 h45 = _mm256_hadd_ps(a4, a5), h67 = _mm256_hadd_ps(a6, a7);
    /* q0 = [r0..r3: (l0+l1)+(l2+l3) | r0..r3: (l4+l5)+(l6+l7)] */
    __m256 q0 = _mm256_hadd_ps(h01, h23), q1 = _mm256_hadd_ps(h45, h67);
    return _mm256_add_ps(_mm256_permute2f128_ps(q0, q1, 0x20), _mm256_permute2f128_ps(q0, q1, 0x31));
}

FBGF_AVX2 static __m128 sum4(__m256 a0, __m256 a1, __m256 a2, __m256 a3)
{
    __m256 q = _mm256_hadd_ps(_mm256_hadd_ps(a0, a1), _mm256_hadd_ps(a2, a3));
    return _mm_add_ps(_mm256_castps256_ps128(q), _mm256_extractf128_ps(q, 1));
}

FBGF_AVX2 static float sum1(__m256 a)
{
    __m256 q = _mm256_hadd_ps(a, a);
    q = _mm256_hadd_ps(q, q);
    return _mm_cvtss_f32(_mm_add_ss(_mm256_castps256_ps128(q), _mm256_extractf128_ps(q, 1)));
}

/* c[k] = row k of an 8 x 8 block -> col[j] = column j. */
FBGF_AVX2 static inline void transpose8(const __m256 c[8], __m256 col[8])
{
    __m256 t[8], u[8];
    t[0] = _mm256_unpacklo_ps(c[0], c[1]);
    t[1] = _mm256_unpackhi_ps(c[0], c[1]);
    t[2] = _mm256_unpacklo_ps(c[2], c[3]);
    t[3] = _mm256_unpackhi_ps(c[2], c[3]);
    t[4] = _mm256_unpacklo_ps(c[4], c[5]);
    t[5] = _mm256_unpackhi_ps(c[4], c[5]);
    t[6] = _mm256_unpacklo_ps(c[6], c[7]);
    t[7] = _mm256_unpackhi_ps(c[6], c[7]);
    u[0] = _mm256_shuffle_ps(t[0], t[2], 0x44);
    u[1] = _mm256_shuffle_ps(t[0], t[2], 0xEE);
    u[2] = _mm256_shuffle_ps(t[1], t[3], 0x44);
    u[3] = _mm256_shuffle_ps(t[1], t[3], 0xEE);
    u[4] = _mm256_shuffle_ps(t[4], t[6], 0x44);
    u[5] = _mm256_shuffle_ps(t[4], t[6], 0xEE);
    u[6] = _mm256_shuffle_ps(t[5], t[7], 0x44);
    u[7] = _mm256_shuffle_ps(t[5], t[7], 0xEE);
    col[0] = _mm256_permute2f128_ps(u[0], u[4], 0x20);
    col[1] = _mm256_permute2f128_ps(u[1], u[5], 0x20);
    col[2] = _mm256_permute2f128_ps(u[2], u[6], 0x20);
    col[3] = _mm256_permute2f128_ps(u[3], u[7], 0x20);
    col[4] = _mm256_permute2f128_ps(u[0], u[4], 0x31);
    col[5] = _mm256_permute2f128_ps(u[1], u[5], 0x31);
    col[6] = _mm256_permute2f128_ps(u[2], u[6], 0x31);
    col[7] = _mm256_permute2f128_ps(u[3], u[7], 0x31);
}

/* Layers with at most FBGF_NARROW inputs (each net's first: FBG_MAX_INPUTS): one lane per
 * row instead. Eight rows are loaded once per block and transposed, so that column j (the
 * weights of input j in rows r..r+7) is one vector; each sample then needs n_in fused
 * multiply-adds with its broadcast input and no horizontal sums: output r is b[r] followed
 * by fma(w[r][j], x[j], .) for j ascending, the portable order with fused steps. */
#define FBGF_NARROW 16u
typedef char fbgf_require_narrow_first_layers[FBG_MAX_INPUTS <= FBGF_NARROW ? 1 : -1];

FBGF_AVX2 static void dense_avx2_narrow(const fbgf_layer *ly, const float *xs, size_t x_stride, float *ys,
                                        size_t y_stride, size_t n, int relu)
{
    const unsigned n_in = ly->n_in, n_out = ly->n_out;
    const __m256 zero = _mm256_setzero_ps();
    unsigned r, j, k, j0;
    size_t i;
    for (r = 0; r < n_out; r += 8u) {
        const unsigned rows = n_out - r < 8u ? n_out - r : 8u;
        const __m256i row_mask = tail_mask(rows, 0u);
        __m256 c[8], col[FBGF_NARROW], bias;
        if (n_in <= 8u) {
            /* One block of columns: the common case kept free of the loop below. */
            const __m256i in_mask = tail_mask(n_in, 0u);
            for (k = 0; k < 8u; ++k)
                c[k] = k < rows ? _mm256_maskload_ps(ly->w + (size_t)(r + k) * n_in, in_mask) : zero;
            transpose8(c, col);
        } else {
            for (j0 = 0; j0 < n_in; j0 += 8u) {
                const __m256i in_mask = tail_mask(n_in - j0 < 8u ? n_in - j0 : 8u, 0u);
                for (k = 0; k < 8u; ++k)
                    c[k] = k < rows ? _mm256_maskload_ps(ly->w + (size_t)(r + k) * n_in + j0, in_mask)
                                    : zero;
                transpose8(c, col + j0);
            }
        }
        bias = _mm256_maskload_ps(ly->b + r, row_mask);
        for (i = 0; i < n; ++i) {
            const float *x = xs + i * x_stride;
            __m256 a = bias;
            for (j = 0; j < n_in; ++j)
                a = _mm256_fmadd_ps(col[j], _mm256_broadcast_ss(x + j), a);
            if (relu)
                a = _mm256_max_ps(zero, a);
            if (rows == 8u)
                _mm256_storeu_ps(ys + i * y_stride + r, a);
            else
                _mm256_maskstore_ps(ys + i * y_stride + r, row_mask, a);
        }
    }
}

/* The kernels below give row r of one sample the lanes a[k] = sum of w[r][j] x[j] over
 * j = k (mod 8), fused, j ascending, the inputs past the last full group of eight through
 * masked loads (`mask`, `full` = n_in rounded down to 8), then sum8/sum4/sum1, then b[r]. They
 * differ only in how many rows share the loop, not in the arithmetic. _mm256_max_ps(0, a) is
 * a < 0 ? 0 : a with NaN and -0 kept, as portable. */
typedef struct {
    size_t stride;      /* floats from one row of weights to the next (n_in) */
    unsigned n_in, full;
    __m256i mask;
    int relu;
} dense_shape;

/* Eight rows, one sample: eight independent accumulators. */
FBGF_AVX2 static void rows8x1(const dense_shape *d, const float *w, const float *b, const float *x,
                              float *y)
{
    const size_t st = d->stride;
    const __m256 zero = _mm256_setzero_ps(), xt = _mm256_maskload_ps(x + d->full, d->mask);
    __m256 a0 = zero, a1 = zero, a2 = zero, a3 = zero, a4 = zero, a5 = zero, a6 = zero, a7 = zero, s;
    unsigned j;
    for (j = 0; j < d->full; j += 8u) {
        const __m256 xv = _mm256_loadu_ps(x + j);
        a0 = _mm256_fmadd_ps(_mm256_loadu_ps(w + j), xv, a0);
        a1 = _mm256_fmadd_ps(_mm256_loadu_ps(w + st + j), xv, a1);
        a2 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 2u * st + j), xv, a2);
        a3 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 3u * st + j), xv, a3);
        a4 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 4u * st + j), xv, a4);
        a5 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 5u * st + j), xv, a5);
        a6 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 6u * st + j), xv, a6);
        a7 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 7u * st + j), xv, a7);
    }
    if (d->full < d->n_in) {
        const float *wt = w + d->full;
        a0 = _mm256_fmadd_ps(_mm256_maskload_ps(wt, d->mask), xt, a0);
        a1 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + st, d->mask), xt, a1);
        a2 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 2u * st, d->mask), xt, a2);
        a3 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 3u * st, d->mask), xt, a3);
        a4 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 4u * st, d->mask), xt, a4);
        a5 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 5u * st, d->mask), xt, a5);
        a6 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 6u * st, d->mask), xt, a6);
        a7 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 7u * st, d->mask), xt, a7);
    }
    s = _mm256_add_ps(sum8(a0, a1, a2, a3, a4, a5, a6, a7), _mm256_loadu_ps(b));
    _mm256_storeu_ps(y, d->relu ? _mm256_max_ps(zero, s) : s);
}

/* Four rows, one sample. */
FBGF_AVX2 static void rows4x1(const dense_shape *d, const float *w, const float *b, const float *x,
                              float *y)
{
    const size_t st = d->stride;
    const __m256 zero = _mm256_setzero_ps();
    __m256 a0 = zero, a1 = zero, a2 = zero, a3 = zero;
    __m128 s;
    unsigned j;
    for (j = 0; j < d->full; j += 8u) {
        const __m256 xv = _mm256_loadu_ps(x + j);
        a0 = _mm256_fmadd_ps(_mm256_loadu_ps(w + j), xv, a0);
        a1 = _mm256_fmadd_ps(_mm256_loadu_ps(w + st + j), xv, a1);
        a2 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 2u * st + j), xv, a2);
        a3 = _mm256_fmadd_ps(_mm256_loadu_ps(w + 3u * st + j), xv, a3);
    }
    if (d->full < d->n_in) {
        const float *wt = w + d->full;
        const __m256 xt = _mm256_maskload_ps(x + d->full, d->mask);
        a0 = _mm256_fmadd_ps(_mm256_maskload_ps(wt, d->mask), xt, a0);
        a1 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + st, d->mask), xt, a1);
        a2 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 2u * st, d->mask), xt, a2);
        a3 = _mm256_fmadd_ps(_mm256_maskload_ps(wt + 3u * st, d->mask), xt, a3);
    }
    s = _mm_add_ps(sum4(a0, a1, a2, a3), _mm_loadu_ps(b));
    _mm_storeu_ps(y, d->relu ? _mm_max_ps(_mm_setzero_ps(), s) : s);
}

/* One row, one sample. */
FBGF_AVX2 static void rows1x1(const dense_shape *d, const float *w, const float *b, const float *x,
                              float *y)
{
    __m256 a = _mm256_setzero_ps();
    float s;
    unsigned j;
    for (j = 0; j < d->full; j += 8u)
        a = _mm256_fmadd_ps(_mm256_loadu_ps(w + j), _mm256_loadu_ps(x + j), a);
    if (d->full < d->n_in)
        a = _mm256_fmadd_ps(_mm256_maskload_ps(w + d->full, d->mask),
                            _mm256_maskload_ps(x + d->full, d->mask), a);
    s = sum1(a) + *b;
    *y = (d->relu && s < 0.0f) ? 0.0f : s;
}

/* Blocks of eight rows, then four, then single rows, samples inside each block. */
FBGF_AVX2 static void dense_avx2(const fbgf_layer *ly, const float *xs, size_t x_stride, float *ys,
                                size_t y_stride, size_t n, int relu)
{
    dense_shape d;
    unsigned r = 0;
    size_t i;
    d.stride = ly->n_in;
    d.n_in = ly->n_in;
    d.full = ly->n_in & ~7u;
    d.mask = tail_mask(d.n_in, d.full);
    d.relu = relu;
    for (; r + 8u <= ly->n_out; r += 8u) {
        const float *w = ly->w + r * d.stride, *b = ly->b + r;
        for (i = 0; i < n; ++i)
            rows8x1(&d, w, b, xs + i * x_stride, ys + i * y_stride + r);
    }
    if (r + 4u <= ly->n_out) {
        const float *w = ly->w + r * d.stride, *b = ly->b + r;
        for (i = 0; i < n; ++i)
            rows4x1(&d, w, b, xs + i * x_stride, ys + i * y_stride + r);
        r += 4u;
    }
    for (; r < ly->n_out; ++r)
        for (i = 0; i < n; ++i)
            rows1x1(&d, ly->w + r * d.stride, ly->b + r, xs + i * x_stride, ys + i * y_stride + r);
}
/* Samples in lanes (fbgf_dense_lanes): a block of up to six rows times n_vec (1 or 2) vectors
 * of eight samples, one accumulator each (at most twelve of the sixteen vector registers), so
 * that every weight is broadcast once for 8 * n_vec samples and no sum crosses lanes. Sample
 * by sample the sums are those of the kernels above:
 *
 *   narrow (n_in <= FBGF_NARROW, as dense_avx2_narrow): b[r], then fused w[r][j] x[j] for j
 *     ascending;
 *   otherwise (as rows8x1, rows4x1, rows1x1): eight phases, phase k the fused sum from zero of
 *     w[r][j] x[j] over j = k (mod 8) ascending (lane k of those kernels; their zero products
 *     past n_in change no sum, which never holds -0), then ((p0 + p1) + (p2 + p3)) +
 *     ((p4 + p5) + (p6 + p7)), then + b[r]. The tree is built as the phases end (t0 = p0, then
 *     p0 + p1, then (p0 + p1) + (p2 + p3); t1 = p2, then p4, then p4 + p5; t2 = p6; after
 *     phase 7, t0 + (t1 + (t2 + p7)), which is the same tree), so that the phase sums wait in
 *     three slots instead of eight and the last phase ends the block.
 *
 * rows, n_vec and narrow are constants where this is inlined, so that the accumulators stay in
 * registers: they are named, not an array, because GCC keeps an array of vectors in memory. */
#define FBGF_LANE_ROWS 6u

FBGF_AVX2 static inline __attribute__((always_inline)) void
lanes_block(const float *w, unsigned n_in, const float *b, const float *x, float *y,
            const unsigned rows, const unsigned n_vec, const int narrow, int relu)
{
    const __m256 zero = _mm256_setzero_ps();
    const float *w1 = w + n_in, *w2 = w1 + n_in, *w3 = w2 + n_in, *w4 = w3 + n_in, *w5 = w4 + n_in;
    __m256 a00 = zero, a01 = zero, a10 = zero, a11 = zero, a20 = zero, a21 = zero;
    __m256 a30 = zero, a31 = zero, a40 = zero, a41 = zero, a50 = zero, a51 = zero;
    __m256 t[FBGF_LANE_ROWS][2][3];
    unsigned j;
#define FBGF_LANES_EACH(DO) DO(0) DO(1) DO(2) DO(3) DO(4) DO(5)
#define FBGF_LANES_FMA(K, WK)                                                       \
        if (rows > K##u) {                                                          \
            const __m256 wk = _mm256_broadcast_ss(WK + j);                          \
            a##K##0 = _mm256_fmadd_ps(wk, x0, a##K##0);                             \
            if (n_vec > 1u)                                                         \
                a##K##1 = _mm256_fmadd_ps(wk, x1, a##K##1);                         \
        }
#define FBGF_LANES_LOOP(J0, STEP)                                                   \
    for (j = (J0); j < n_in; j += (STEP)) {                                         \
        const float *xj = x + (size_t)j * FBGF_RUN_CHUNK;                           \
        const __m256 x0 = _mm256_loadu_ps(xj);                                      \
        const __m256 x1 = n_vec > 1u ? _mm256_loadu_ps(xj + 8) : zero;              \
        FBGF_LANES_FMA(0, w) FBGF_LANES_FMA(1, w1) FBGF_LANES_FMA(2, w2)            \
        FBGF_LANES_FMA(3, w3) FBGF_LANES_FMA(4, w4) FBGF_LANES_FMA(5, w5)           \
    }
    /* y row K, vector V gets A + b[K] (narrow: A), then ReLU on hidden layers. */
#define FBGF_LANES_PUT(A, K, V)                                                     \
    _mm256_storeu_ps(y + K * FBGF_RUN_CHUNK + 8 * V, relu ? _mm256_max_ps(zero, A) : A);
    if (narrow) {
#define FBGF_LANES_BIAS(K)                                                          \
        if (rows > K##u)                                                            \
            a##K##0 = a##K##1 = _mm256_broadcast_ss(b + K);
#define FBGF_LANES_STORE(K)                                                         \
        if (rows > K##u) {                                                          \
            FBGF_LANES_PUT(a##K##0, K, 0)                                           \
            if (n_vec > 1u)                                                         \
                FBGF_LANES_PUT(a##K##1, K, 1)                                       \
        }
        FBGF_LANES_EACH(FBGF_LANES_BIAS)
        FBGF_LANES_LOOP(0u, 1u)
        FBGF_LANES_EACH(FBGF_LANES_STORE)
        return;
    }
#define FBGF_LANES_FOLD(P, A, K, V)                                                 \
        switch (P) {                                                                \
        case 0u: t[K][V][0] = A; break;                                             \
        case 1u: t[K][V][0] = _mm256_add_ps(t[K][V][0], A); break;                  \
        case 2u: t[K][V][1] = A; break;                                             \
        case 3u: t[K][V][0] = _mm256_add_ps(t[K][V][0], _mm256_add_ps(t[K][V][1], A)); break; \
        case 4u: t[K][V][1] = A; break;                                             \
        case 5u: t[K][V][1] = _mm256_add_ps(t[K][V][1], A); break;                  \
        case 6u: t[K][V][2] = A; break;                                             \
        default:                                                                    \
            A = _mm256_add_ps(t[K][V][1], _mm256_add_ps(t[K][V][2], A));            \
            A = _mm256_add_ps(_mm256_add_ps(t[K][V][0], A), _mm256_broadcast_ss(b + K)); \
            FBGF_LANES_PUT(A, K, V)                                                 \
        }
#define FBGF_LANES_KEEP(K)                                                          \
        if (rows > K##u) {                                                          \
            FBGF_LANES_FOLD(phase, a##K##0, K, 0)                                   \
            if (n_vec > 1u)                                                         \
                FBGF_LANES_FOLD(phase, a##K##1, K, 1)                               \
        }
#define FBGF_LANES_ZERO(K) a##K##0 = a##K##1 = zero;
    /* The phases written out, so that each one's tree step is fixed where it is compiled. */
#define FBGF_LANES_PHASE(P)                                                         \
    {                                                                               \
        const unsigned phase = P;                                                   \
        FBGF_LANES_EACH(FBGF_LANES_ZERO)                                            \
        FBGF_LANES_LOOP(phase, 8u)                                                  \
        FBGF_LANES_EACH(FBGF_LANES_KEEP)                                            \
    }
    FBGF_LANES_PHASE(0u) FBGF_LANES_PHASE(1u) FBGF_LANES_PHASE(2u) FBGF_LANES_PHASE(3u)
    FBGF_LANES_PHASE(4u) FBGF_LANES_PHASE(5u) FBGF_LANES_PHASE(6u) FBGF_LANES_PHASE(7u)
#undef FBGF_LANES_PHASE
#undef FBGF_LANES_ZERO
#undef FBGF_LANES_KEEP
#undef FBGF_LANES_FOLD
#undef FBGF_LANES_STORE
#undef FBGF_LANES_BIAS
#undef FBGF_LANES_PUT
#undef FBGF_LANES_LOOP
#undef FBGF_LANES_FMA
#undef FBGF_LANES_EACH
}

FBGF_AVX2 static void lanes_rows(const float *w, unsigned n_in, const float *b, const float *x, float *y,
                                 unsigned rows, unsigned n_vec, int relu)
{
#define FBGF_LANES_CASE(R)                                                          \
    case R:                                                                         \
        if (n_in <= FBGF_NARROW) {                                                  \
            if (n_vec > 1u)                                                         \
                lanes_block(w, n_in, b, x, y, R, 2u, 1, relu);                      \
            else                                                                    \
                lanes_block(w, n_in, b, x, y, R, 1u, 1, relu);                      \
        } else if (n_vec > 1u) {                                                    \
            lanes_block(w, n_in, b, x, y, R, 2u, 0, relu);                          \
        } else {                                                                    \
            lanes_block(w, n_in, b, x, y, R, 1u, 0, relu);                          \
        }                                                                           \
        return;
    switch (rows) {
        FBGF_LANES_CASE(6u)
        FBGF_LANES_CASE(5u)
        FBGF_LANES_CASE(4u)
        FBGF_LANES_CASE(3u)
        FBGF_LANES_CASE(2u)
    default:
        FBGF_LANES_CASE(1u)
    }
#undef FBGF_LANES_CASE
}

/* The rows go in blocks of as equal a size as FBGF_LANE_ROWS allows (50 rows: 5 x 6 + 4 x 5),
 * so that no block is left with too few accumulators to hide the fused multiply-add latency. */
FBGF_AVX2 void fbgf_dense_lanes(const fbgf_layer *ly, const float *x, float *y, unsigned n_vec, int relu)
{
    const unsigned n_out = ly->n_out, blocks = (n_out + FBGF_LANE_ROWS - 1u) / FBGF_LANE_ROWS;
    unsigned blk, r = 0;
    for (blk = 0; blk < blocks; ++blk) {
        const unsigned rows = (n_out - r) / (blocks - blk) + ((n_out - r) % (blocks - blk) != 0u);
        lanes_rows(ly->w + (size_t)r * ly->n_in, ly->n_in, ly->b + r, x, y + (size_t)r * FBGF_RUN_CHUNK,
                   rows, n_vec, relu);
        r += rows;
    }
}
#endif

#ifdef FBGF_HAVE_NEON
/* Four rows x four lanes, fused multiply-add, samples inside row blocks as on SSE2; vpaddq
 * adds neighbours, which gives the same (l0 + l1) + (l2 + l3) per row as the SSE2 transpose. */
static void dense_neon(const fbgf_layer *ly, const float *xs, size_t x_stride, float *ys,
                       size_t y_stride, size_t n_samples, int relu)
{
    float wt[4][4], xt[4], b[4], out[4];
    const unsigned n_in = ly->n_in, full = n_in & ~3u;
    const float32x4_t zero = vdupq_n_f32(0.0f);
    unsigned r0, j, n;
    size_t i;
    for (r0 = 0; r0 < ly->n_out; r0 += 4u) {
        const float *w[4];
        float32x4_t bias;
        n = block4_setup(ly, r0, w, wt, b);
        bias = vld1q_f32(b);
        for (i = 0; i < n_samples; ++i) {
            const float *x = xs + i * x_stride;
            float *y = ys + i * y_stride;
            float32x4_t a0 = zero, a1 = zero, a2 = zero, a3 = zero, s;
            for (j = 0; j < full; j += 4u) {
                const float32x4_t xv = vld1q_f32(x + j);
                a0 = vfmaq_f32(a0, vld1q_f32(w[0] + j), xv);
                a1 = vfmaq_f32(a1, vld1q_f32(w[1] + j), xv);
                a2 = vfmaq_f32(a2, vld1q_f32(w[2] + j), xv);
                a3 = vfmaq_f32(a3, vld1q_f32(w[3] + j), xv);
            }
            if (full < n_in) {
                float32x4_t xv;
                copy4(xt, x + full, n_in - full);
                xv = vld1q_f32(xt);
                a0 = vfmaq_f32(a0, vld1q_f32(wt[0]), xv);
                a1 = vfmaq_f32(a1, vld1q_f32(wt[1]), xv);
                a2 = vfmaq_f32(a2, vld1q_f32(wt[2]), xv);
                a3 = vfmaq_f32(a3, vld1q_f32(wt[3]), xv);
            }
            s = vaddq_f32(vpaddq_f32(vpaddq_f32(a0, a1), vpaddq_f32(a2, a3)), bias);
            if (relu)   /* a < 0 ? 0 : a, NaN and -0 kept, as portable */
                s = vbslq_f32(vcltq_f32(s, zero), zero, s);
            if (n == 4u) {
                vst1q_f32(y + r0, s);
            } else {
                vst1q_f32(out, s);
                memcpy(y + r0, out, n * sizeof *out);
            }
        }
    }
}
#endif

fbgf_kernel fbgf_dense_kernel(void)
{
#if FBGF_HAVE_AVX2
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
        return FBGF_KERNEL_AVX2_FMA;
    return FBGF_KERNEL_SSE2;
#elif defined(FBGF_HAVE_SSE2)
    return FBGF_KERNEL_SSE2;
#elif defined(FBGF_HAVE_NEON)
    return FBGF_KERNEL_NEON;
#else
    return FBGF_KERNEL_PORTABLE;
#endif
}

void fbgf_dense(fbgf_kernel kernel, const fbgf_layer *ly, const float *x, size_t x_stride, float *y,
                size_t y_stride, size_t n, int relu)
{
    size_t i;
    switch (kernel) {
#if FBGF_HAVE_AVX2
    case FBGF_KERNEL_AVX2_FMA:
        if (ly->n_in <= FBGF_NARROW)
            dense_avx2_narrow(ly, x, x_stride, y, y_stride, n, relu);
        else
            dense_avx2(ly, x, x_stride, y, y_stride, n, relu);
        return;
#endif
#ifdef FBGF_HAVE_SSE2
    case FBGF_KERNEL_SSE2:
        dense_sse2(ly, x, x_stride, y, y_stride, n, relu);
        return;
#endif
#ifdef FBGF_HAVE_NEON
    case FBGF_KERNEL_NEON:
        dense_neon(ly, x, x_stride, y, y_stride, n, relu);
        return;
#endif
    default:
        for (i = 0; i < n; ++i)
            dense_portable(ly, x + i * x_stride, y + i * y_stride, relu);
        return;
    }
}
