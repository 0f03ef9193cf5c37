/*
 * fbg_dsp_fir.c - the filter stage on the Cortex-M4 DSP extension: the FIR of the four strain
 * channels (SMLAL, fir4_asm) and the standardisation after it on 32-bit words.
 * See fbg_dsp_kernels.h for why the results equal the portable C bit for bit.
 */
#include "fbg_dsp_kernels.h"

#if FBG_USE_DSP
typedef char fbg_dsp_fir_four[FBG_N_STRAIN == 4 ? 1 : -1]; /* rows of 16 bytes in fir4_asm */

#if FBG_DSP_ASM
/* One tap of fir4_asm: the tap (LDRSH) times the four history words below P, into the four sums. */
#define FBG_FIR4_TAP(p)                          \
        "ldrsh   r12, [r0], #2\n\t"              \
        "ldmdb   " p "!, {r2, r3}\n\t"           \
        "smlal   r8, r9, r2, r12\n\t"            \
        "smlal   r10, r11, r3, r12\n\t"          \
        "ldmdb   " p "!, {r2, r3}\n\t"           \
        "smlal   r4, r5, r2, r12\n\t"            \
        "smlal   r6, r7, r3, r12\n\t"

/* fir4_asm: fbg_dsp_fir4 with the four int64 sums in registers (r4:r5 ... r10:r11): per tap
 * one LDRSH of the tap, two LDMDB of two history words (walking the ring down from the
 * newest sample) and four SMLAL (32 x 32 -> 64, exact: the same int64 products as the C),
 * 9 instructions with the loop test; the ring is walked as two contiguous runs, rows pos..0
 * then n_taps-1..pos+1. */
__attribute__((naked, noinline)) static void fir4_asm(const int16_t *taps, unsigned n_taps,
                                                      const int32_t (*hist)[FBG_N_STRAIN],
                                                      unsigned pos, int64_t f[FBG_N_STRAIN])
{
    (void)taps;
    (void)n_taps;
    (void)hist;
    (void)pos;
    (void)f;
    __asm__ volatile(
        "push    {r4-r11, lr}\n\t"
        "add     r12, r2, r1, lsl #4\n\t"
        "add     r1, r2, r3, lsl #4\n\t"
        "add     r1, r1, #16\n\t"
        "push    {r1, r12}\n\t"
        "mov     lr, r2\n\t"
        "movs    r4, #0\n\t"
        "movs    r5, #0\n\t"
        "movs    r6, #0\n\t"
        "movs    r7, #0\n\t"
        "mov     r8, #0\n\t"
        "mov     r9, #0\n\t"
        "mov     r10, #0\n\t"
        "mov     r11, #0\n\t"
        "1:\n\t"
        FBG_FIR4_TAP("r1")
        "cmp     r1, lr\n\t"
        "bne     1b\n\t"
        "pop     {r1, lr}\n\t"
        "cmp     lr, r1\n\t"
        "beq     3f\n\t"
        "2:\n\t"
        FBG_FIR4_TAP("lr")
        "cmp     lr, r1\n\t"
        "bne     2b\n\t"
        "3:\n\t"
        "ldr     r0, [sp, #36]\n\t"
        "stmia   r0, {r4-r11}\n\t"
        "pop     {r4-r11, pc}\n\t");
}

#undef FBG_FIR4_TAP
#endif /* FBG_DSP_ASM */

/* sat32 of a 64-bit value given as its two words (|hi:lo| any); *clamped != 0 if it clamps. */
static inline int32_t sat32_words(int32_t hi, uint32_t lo, uint32_t *clamped)
{
    /* Fits int32 iff hi is lo's sign extension; INT32_MIN itself clamps (symmetric rule). */
    if (hi != ((int32_t)lo >> 31) || lo == 0x80000000u) {
        *clamped = 1u;
        return hi < 0 ? -FBG_SAT32 : FBG_SAT32;
    }
    return (int32_t)lo;
}

/* sat16 of an int32 with the flag of fbg_sat16 (*clamped != 0 iff it clamped): SSAT to
 * [-32768, 32767], then -32768 up to -32767. */
static inline int32_t sat16_32(int32_t v, uint32_t *clamped)
{
    int32_t y = __ssat(v, 16);
    y = y < -FBG_SAT16 ? -FBG_SAT16 : y;
    *clamped |= (uint32_t)(v ^ y);
    return y;
}

int fbg_dsp_standardise(const fbg_model *m, const int64_t f[FBG_N_STRAIN], int16_t z[FBG_N_STRAIN],
                        uint32_t *sat)
{
    const unsigned tq = m->tap_q, zs = m->z_shift;
    const uint32_t fround = 1u << (tq - 1u);
    /* 2^(zs-1), zs <= 62, built so that one of its words is visibly zero. */
    const int64_t zround = zs > 32u ? (int64_t)((uint64_t)(1u << (zs - 33u)) << 32)
                                    : (int64_t)(uint32_t)(1u << (zs - 1u));
    uint32_t clamped = 0u;
    int64_t load = 0;
    unsigned c;
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        /* filt = sat32(rshift_round(f, tq)) with 1 <= tq <= 15 (fbg_params_check): |f| < 2^53
         * (64 taps of |int16| * |int32|), so f + 2^(tq-1) is exact, and with tq < 32 the
         * arithmetic shift of the 64-bit sum is two words shifted and joined. */
        const int64_t g = f[c] + (int64_t)fround;
        const uint32_t glo = (uint32_t)g;
        const int32_t ghi = (int32_t)(g >> 32);
        int32_t filt = sat32_words(ghi >> tq, (glo >> tq) | ((uint32_t)ghi << (32u - tq)), &clamped);
        int32_t d, v;
        int64_t p;
        /* d = sat32(filt - mean): on int32 overflow the true difference has filt's sign. */
        if (__builtin_sub_overflow(filt, m->mean_fm[c], &d)) {
            clamped = 1u;
            d = filt < 0 ? -FBG_SAT32 : FBG_SAT32;
        } else if (d == INT32_MIN) {
            clamped = 1u;
            d = -FBG_SAT32;
        }
        /* |d * z_mult| < 2^62 and 2^(zs-1) <= 2^61: p is exact in int64. */
        p = smlal(zround, d, m->z_mult[c]);
        if (zs >= 32u) {
            v = (int32_t)(p >> 32) >> (zs - 32u); /* floor(p / 2^zs), |.| < 2^31 */
        } else {
            int64_t q = p >> zs;
            /* Beyond int32 the outcome of sat16 is already decided; keep the sign. */
            v = q > INT32_MAX ? INT32_MAX : (q < -INT32_MAX ? -INT32_MAX : (int32_t)q);
        }
        z[c] = (int16_t)sat16_32(v, &clamped);
        load = smlal(load, filt, m->load_coeff[c]); /* |.| < 2^59 each (fbg_model_check) */
    }
    if (clamped != 0u)
        *sat = 1u;
    return fbg_rshift_round(load, m->load_shift) > m->load_max_mN;
}

void fbg_dsp_fir4(const int16_t *taps, unsigned n_taps, const int32_t (*hist)[FBG_N_STRAIN],
                  unsigned pos, int64_t f[FBG_N_STRAIN])
{
#if FBG_DSP_ASM
    fir4_asm(taps, n_taps, hist, pos, f);
#else
    int64_t f0 = 0, f1 = 0, f2 = 0, f3 = 0;
    unsigned k = 0, i;
    /* Newest first: ring index pos, pos-1, ..., 0 (taps 0..pos), then n_taps-1, ..., pos+1. */
#define FBG_FIR_TAP(row)                 \
    do {                                 \
        const int32_t *h_ = (row);       \
        int32_t t_ = taps[k++];          \
        f0 += (int64_t)t_ * h_[0];       \
        f1 += (int64_t)t_ * h_[1];       \
        f2 += (int64_t)t_ * h_[2];       \
        f3 += (int64_t)t_ * h_[3];       \
    } while (0)
    for (i = pos + 1u; i-- > 0u;)
        FBG_FIR_TAP(hist[i]);
    for (i = n_taps; i-- > pos + 1u;)
        FBG_FIR_TAP(hist[i]);
#undef FBG_FIR_TAP
    f[0] = f0;
    f[1] = f1;
    f[2] = f2;
    f[3] = f3;
#endif
}

#else
/* ISO C forbids an empty translation unit: the portable build compiles this file to nothing. */
typedef int fbg_dsp_fir_unused;
#endif
