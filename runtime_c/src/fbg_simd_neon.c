/*
 * fbg_simd_neon.c - NEON dense-layer kernels for aarch64 (see fbg_simd.h).
 *
 * SMLAL/SMLAL2 (vmlal_s16 / vmlal_high_s16) multiply int16 pairs exactly and add the products
 * into int32 lanes, and ADDP (vpaddq_s32) adds lanes; all wrap modulo 2^32, so every lane
 * holds its share of a row's sum modulo 2^32, and so does their total; the loader proved the
 * row's true sum fits int32, which makes the modular total the true sum (docs/fixed-point.md,
 * "Host SIMD kernels"). Four rows run together so each vector of x is loaded once per four
 * rows; rows past n_out read a row of zeros. NEON is part of every AArch64 CPU, so there is
 * no run-time check.
 *
 * Rows are read as whole vectors of npad = n_in rounded up to 8 weights (int8 weights are
 * widened on load), against x copied into a buffer that is zero from n_in on: the weights
 * read past a row's end belong to the next row and meet zeros. Where such a read would leave
 * the weight array (the last rows), the row is first copied into a zero-padded buffer.
 *
 * Requantisation, four rows at once: SMULL/SMULL2 give the exact int64 products acc * mult;
 * SRSHL by -shift (vrshlq_s64) is (t + 2^(shift-1)) >> shift, the rounding rule, computed
 * without overflow; SQXTN narrows to int32 saturating (any value beyond int32 is beyond
 * 32767 too), then max(., 0) and min(., 32767), the comparison with 32767 feeding the
 * saturation flag exactly where fbg_sat16 raises it.
 *
 * Integer SIMD only: no floating-point vector type or instruction is used here
 * (check-nofloat scans this file and its aarch64 object).
 */
#include "fbg_simd.h"

#if FBG_HOST_SIMD && defined(__aarch64__)
#include <arm_neon.h>
#include <string.h>

#define ROW_LEN (FBG_MAX_WIDTH + FBG_SIMD_XPAD)

/* The rows past n_out of a layer's last group. */
static const int16_t zero_row16[ROW_LEN];
static const int8_t zero_row8[ROW_LEN];

/* Where row r of the layer is read for npad entries: in place if r * n + npad stays inside the
 * weight array, else a zero-padded copy in buf; past n_out, the zero row. */
static const int16_t *row16(const fbg_layer *ly, unsigned r, unsigned npad, int16_t *buf)
{
    size_t start = (size_t)r * ly->n_in;
    if (r >= ly->n_out)
        return zero_row16;
    if (start + npad <= (size_t)ly->n_out * ly->n_in)
        return ly->w16 + start;
    memset(buf, 0, npad * sizeof *buf);
    memcpy(buf, ly->w16 + start, ly->n_in * sizeof *buf);
    return buf;
}

static const int8_t *row8(const fbg_layer *ly, unsigned r, unsigned npad, int8_t *buf)
{
    size_t start = (size_t)r * ly->n_in;
    if (r >= ly->n_out)
        return zero_row8;
    if (start + npad <= (size_t)ly->n_out * ly->n_in)
        return ly->w8 + start;
    memset(buf, 0, npad);
    memcpy(buf, ly->w8 + start, ly->n_in);
    return buf;
}

/* acc += w . x over 8 entries (exact products, int32 lanes). */
static inline int32x4_t mac8(int32x4_t acc, int16x8_t w, int16x8_t x)
{
    return vmlal_high_s16(vmlal_s16(acc, vget_low_s16(w), vget_low_s16(x)), w, x);
}

/* The MACs of four rows; W(i, j) loads 8 weights of row i at column j as int16. */
#define NEON_DOT4(W)                                                                 \
    do {                                                                             \
        int32x4_t a0 = vdupq_n_s32(0), a1 = a0, a2 = a0, a3 = a0;                    \
        for (j = 0; j < npad; j += 8u) {                                             \
            int16x8_t xv = vld1q_s16(xp + j);                                        \
            a0 = mac8(a0, W(0, j), xv);                                              \
            a1 = mac8(a1, W(1, j), xv);                                              \
            a2 = mac8(a2, W(2, j), xv);                                              \
            a3 = mac8(a3, W(3, j), xv);                                              \
        }                                                                            \
        sums = vpaddq_s32(vpaddq_s32(a0, a1), vpaddq_s32(a2, a3));                   \
    } while (0)
#define NEON_W16(i, j) vld1q_s16(w16[i] + (j))
#define NEON_W8(i, j) vmovl_s8(vld1_s8(w8[i] + (j)))

/* acc[r] for every row of the layer (int32), four rows of padding room past n_out. */
static void acc32_neon(const fbg_layer *ly, const int16_t *x, int32_t *acc)
{
    int16_t xp[ROW_LEN];
    int16_t buf16[4][ROW_LEN];
    int8_t buf8[4][ROW_LEN];
    int32_t b[4];
    unsigned r, j, i, npad = (ly->n_in + 7u) & ~7u;
    /* Rows r < n_fast read in place: r * n + npad stays inside the weight array. */
    size_t total = (size_t)ly->n_out * ly->n_in;
    unsigned n_fast = total < npad ? 0u : (unsigned)((total - npad) / ly->n_in) + 1u;
    for (j = 0; j < ly->n_in; ++j)
        xp[j] = x[j];
    for (j = 0; j < FBG_SIMD_XPAD; ++j)
        xp[ly->n_in + j] = 0;
    for (r = 0; r < ly->n_out; r += 4u) {
        int32x4_t sums;
        int fast = r + 4u <= n_fast;
        for (i = 0; i < 4u; ++i) /* |bias| <= INT32_MAX in an acc32 layer */
            b[i] = r + i < ly->n_out ? (int32_t)ly->bias[r + i] : 0;
        if (ly->w_bits == 16u) {
            const int16_t *w16[4];
            for (i = 0; i < 4u; ++i)
                w16[i] = fast ? ly->w16 + (size_t)(r + i) * ly->n_in : row16(ly, r + i, npad, buf16[i]);
            NEON_DOT4(NEON_W16);
        } else {
            const int8_t *w8[4];
            for (i = 0; i < 4u; ++i)
                w8[i] = fast ? ly->w8 + (size_t)(r + i) * ly->n_in : row8(ly, r + i, npad, buf8[i]);
            NEON_DOT4(NEON_W8);
        }
        vst1q_s32(acc + r, vaddq_s32(sums, vld1q_s32(b)));
    }
}

uint32_t fbg_simd_resolve(uint32_t requested)
{
    switch (requested) {
    case FBG_OPT_KERNEL_AUTO:
        return FBG_OPT_KERNEL_NEON;
    case FBG_OPT_KERNEL_PORTABLE:
    case FBG_OPT_KERNEL_NEON:
        return requested;
    default:
        return 0u;
    }
}

void fbg_simd_acc32(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int32_t *acc)
{
    int32_t a[FBG_MAX_WIDTH + 4u];
    (void)kernel; /* NEON is the only SIMD kernel here */
    acc32_neon(ly, x, a);
    memcpy(acc, a, ly->n_out * sizeof *acc);
}

void fbg_simd_hidden(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    int32_t acc[FBG_MAX_WIDTH + 4u], mult[4];
    int16_t out[4];
    unsigned r, k;
    const int64x2_t shift = vdupq_n_s64(-(int64_t)ly->shift);
    const int32x4_t zero = vdupq_n_s32(0), top = vdupq_n_s32(FBG_SAT16);
    uint32x4_t big = vdupq_n_u32(0);
    (void)kernel;
    acc32_neon(ly, x, acc);
    for (r = 0; r < ly->n_out; r += 4u) {
        int32x4_t a = vld1q_s32(acc + r), m, v;
        k = ly->n_out - r < 4u ? ly->n_out - r : 4u;
        if (k == 4u) {
            m = vld1q_s32(ly->mult + r);
        } else {
            memset(mult, 0, sizeof mult);
            memcpy(mult, ly->mult + r, k * sizeof *mult);
            m = vld1q_s32(mult);
        }
        v = vqmovn_high_s64(vqmovn_s64(vrshlq_s64(vmull_s32(vget_low_s32(a), vget_low_s32(m)), shift)),
                            vrshlq_s64(vmull_high_s32(a, m), shift));
        v = vmaxq_s32(v, zero);
        big = vorrq_u32(big, vcgtq_s32(v, top));
        v = vminq_s32(v, top);
        if (k == 4u) {
            vst1_s16(y + r, vmovn_s32(v));
        } else {
            vst1_s16(out, vmovn_s32(v));
            memcpy(y + r, out, k * sizeof *y);
        }
    }
    if (vmaxvq_u32(big) != 0u)
        *sat = 1u;
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_neon_unused;
#endif
