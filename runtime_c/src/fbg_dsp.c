/*
 * fbg_dsp.c - Cortex-M4 DSP-extension inner loops (FBG_USE_DSP=1); see fbg_dsp.h.
 *
 * Why the results are bit-identical to the portable C of fbg_fixed.c:
 * - SMLALD adds two exact 16x16 products to a 64-bit accumulator; int64 addition is exact
 *   and associative as long as nothing overflows, and fbg_model_check proved
 *   |acc| <= sum|w| * 32767 + |bias| with acc * mult + 2^(shift-1) inside int64 (every partial
 *   sum obeys the same bound). So summing in pairs, three rows at a time, gives the same int64
 *   as the portable row-by-row loop.
 * - Requantisation needs p = acc * mult + 2^(shift-1), exact in int64 by the same proof; for
 *   shift >= 32 only floor(p / 2^32) matters (rounded_product_hi: one SMULL/SMLAL and one MLA
 *   instead of a 64x64 multiply), then >> (shift - 32) gives floor(p / 2^shift), which fits
 *   int32 because |p| < 2^63. ReLU is v & ~(v >> 31); USAT #15 clamps to [0, 32767] = sat16
 *   of a non-negative value and saturates exactly when the portable sat16 raises its flag
 *   (seen as v - usat(v) != 0 in C, as the sticky Q flag in the assembly).
 * - Everything is C with ACLE intrinsics (__smlad, __smlald, __sxtb16 for int8 weights,
 *   __usat) except the hand-written assembly kernels (FBG_DSP_ASM, below; docs/firmware.md
 *   has the instructions per step): for int64 layers with shift >= 32, rows3d_asm
 *   (word-aligned, LDRD), rows3_asm (any alignment) and first_asm (2, 4 or 6 inputs held in
 *   registers); for int32 layers (fbg_layer.acc32, proven by the loader: every partial sum
 *   fits int32; SMLAD and SMMULR instead) at shift 32, two rows per pass: rows2d32_asm (LDM-fed,
 *   fully unrolled body entered at a computed offset), first2d32_asm (n <= 12, inputs in
 *   registers), and with int8 weights rows2b32_asm and first2b32_asm (SXTB16); dot32_asm for
 *   the output layers' rows and fir4_asm for the FIR. The int16 kernels have ACLE C versions
 *   (rows3_c, first_c, rows2_32_c; the FIR and row loops in C) that FBG_DSP_ASM=0 builds
 *   instead; with int8 weights that build runs the C pairs of hidden8.
 * - The assembly kernels share their recurring fragments as string-literal macros (the Q-flag
 *   entry and exit, a pair or quad of MACs, a row's or a pair's requantisation): the compiler
 *   pastes them back, so the object code is what the written-out instructions gave.
 * - The FIR uses SMLAL (32x16 -> 64-bit accumulate; the history is int32, too wide for the
 *   16-bit dual MACs) and walks the ring buffer as two contiguous runs instead of wrapping the
 *   index per tap; the sum is the same set of exact int64 products.
 * - The standardisation after it (fbg_dsp_standardise) computes the same int64 values on
 *   32-bit words; the comments at each step give the bound that makes the narrower
 *   arithmetic exact.
 */
#include "fbg_dsp.h"

#if FBG_USE_DSP
#include <arm_acle.h>
#include <stddef.h>
#include <string.h>

/* FBG_DSP_ASM=1 (the default with GCC): the hand-written assembly kernels, kept where
 * they measurably beat the ACLE C (instructions per step, docs/firmware.md); 0: ACLE C only,
 * for any compiler with arm_acle.h, clang included (the kernel test runs both). */
#ifndef FBG_DSP_ASM
#if defined(__GNUC__) && !defined(__clang__) /* naked functions of GNU assembly */
#define FBG_DSP_ASM 1
#else
#define FBG_DSP_ASM 0
#endif
#endif

/* Blocks of 8 inputs in the unrolled MAC body of rows2d32_asm (its .rept count): room for
 * the widest layer the loader accepts. */
#define FBG_DSP_BODY_BLOCKS 16u
/* Most inputs first2d32_asm holds in registers (six words: r4-r9): every first layer. */
#define FBG_DSP_FIRST_MAX_IN 12u
typedef char fbg_dsp_body_fits[FBG_MAX_WIDTH <= 8 * 16 ? 1 : -1];

/* Two adjacent int16 as one word: a single LDR (ARMv7E-M allows unaligned LDR; LDRD/LDM
 * would fault on the 2-byte-aligned rows of an odd-width layer, hence rows3d_asm only after
 * an alignment check). */
static inline int16x2_t ld2(const int16_t *p)
{
    int16x2_t v;
    memcpy(&v, p, sizeof v);
    return v;
}

/* floor((acc * mult + 2^(shift-1)) / 2^32) for shift >= 32, i.e. the high word of the
 * rounded product, without a 64x64-bit multiply: with acc = H * 2^32 + (int32)lo, where
 * H = hi + bit 31 of lo, p = (int32)lo * mult + round (one SMLAL, exact in int64 since
 * |lo * mult| < 2^62 and round <= 2^61) plus H * mult * 2^32. Only the high word of p is
 * needed and p fits int64 (the model's bound proof), so adding H * mult to it modulo 2^32
 * (one MLA) gives exactly floor(p / 2^32). */
static inline int32_t rounded_product_hi(int64_t acc, int32_t mult, int64_t round)
{
    uint32_t lo = (uint32_t)acc;
    uint32_t big = (uint32_t)(acc >> 32) + (lo >> 31);
    int64_t t = (int64_t)(int32_t)lo * mult + round;
    /* Unsigned arithmetic wraps as intended; the conversion back is the identity on the
     * two's-complement targets this file compiles for (the DSP extension implies ARM). */
    return (int32_t)((uint32_t)(t >> 32) + big * (uint32_t)mult);
}

/* sat16(max(rshift_round(acc * mult, shift), 0)) of fbg_fixed.c; *clamped != 0 iff it clamped.
 * round = 2^(shift-1). */
static inline int32_t relu_sat16(int64_t acc, int32_t mult, unsigned shift, int64_t round,
                                 uint32_t *clamped)
{
    int32_t v, y;
    if (shift >= 32u) {
        /* floor(p / 2^shift) = floor(floor(p / 2^32) / 2^(shift-32)); fits int32 as |p| < 2^63. */
        v = rounded_product_hi(acc, mult, round) >> (shift - 32u);
    } else {
        int64_t q = fbg_rshift_round(acc * mult, shift);
        /* Beyond int32 the outcome of relu + sat16 is already decided; keep the sign. */
        v = q > INT32_MAX ? INT32_MAX : (q < -INT32_MAX ? -INT32_MAX : (int32_t)q);
    }
    v &= ~(v >> 31);
    y = __usat(v, 15);
    *clamped |= (uint32_t)(v - y);
    return y;
}

/* rshift_round(acc * mult, 32) for int32 acc and mult: SMMULR, the high word of
 * acc * mult + 2^31, exactly the rounding rule at shift 32. */
static inline int32_t smmulr(int32_t acc, int32_t mult)
{
#if FBG_DSP_ASM /* ACLE has no SMMULR; the C below costs three instructions (SMLAL) */
    int32_t r;
    __asm__("smmulr %0, %1, %2" : "=r"(r) : "r"(acc), "r"(mult));
    return r;
#else
    return (int32_t)(((int64_t)acc * mult + ((int64_t)1 << 31)) >> 32);
#endif
}

/* acc + a * b, exact (the caller bounds the sum inside int64). SMLAL in assembly: GCC folds
 * an int32 chosen by a branch (a saturated value) into a 64-bit phi and then multiplies
 * 64 x 64 bits (MUL, MLA, UMULL and the carries) where one SMLAL does. */
static inline int64_t smlal(int64_t acc, int32_t a, int32_t b)
{
#if FBG_DSP_ASM
    __asm__("smlal %Q0, %R0, %1, %2" : "+r"(acc) : "r"(a), "r"(b));
    return acc;
#else
    return acc + (int64_t)a * b;
#endif
}

/* sat16(max(v, 0)) with the flag of fbg_fixed.c (USAT after the ReLU, as the assembly). */
static inline int32_t relu_usat15(int32_t v, uint32_t *clamped)
{
    int32_t y;
    v &= ~(v >> 31);
    y = __usat(v, 15);
    *clamped |= (uint32_t)(v - y);
    return y;
}

int64_t fbg_dsp_dot16(const int16_t *w, const int16_t *x, unsigned n, int64_t acc)
{
    int64_t acc2 = 0;
    unsigned j = 0;
    for (; j + 4u <= n; j += 4u) {
        acc = __smlald(ld2(w + j), ld2(x + j), acc);
        acc2 = __smlald(ld2(w + j + 2u), ld2(x + j + 2u), acc2);
    }
    if (j + 2u <= n) {
        acc = __smlald(ld2(w + j), ld2(x + j), acc);
        j += 2u;
    }
    if (j < n)
        acc += (int32_t)w[j] * (int32_t)x[j];
    return acc + acc2;
}

/* Work order of rows3_asm (field offsets are used by the assembly; checked below). */
typedef struct {
    const int16_t *w;     /*  0: first weight row of the next group of three rows */
    const int16_t *x;     /*  4: layer input */
    const int64_t *bias;  /*  8: bias of the next group */
    const int32_t *mult;  /* 12: multiplier of the next group */
    int16_t *y;           /* 16: output of the next group */
    uint32_t n;           /* 20: n_in */
    uint32_t groups;      /* 24: groups of three rows left, >= 1 */
    uint32_t round_lo;    /* 28: 2^(shift-1), low word */
    uint32_t round_hi;    /* 32: and high word */
    uint32_t s32;         /* 36: shift - 32 (shift >= 32) */
    uint32_t clamped;     /* 40: out: 1 iff a row clamped at 32767 (the Q flag) */
} fbg_dsp_job;

typedef char fbg_dsp_job_layout[(offsetof(fbg_dsp_job, x) == 4 && offsetof(fbg_dsp_job, bias) == 8 &&
                                  offsetof(fbg_dsp_job, mult) == 12 && offsetof(fbg_dsp_job, y) == 16 &&
                                  offsetof(fbg_dsp_job, n) == 20 && offsetof(fbg_dsp_job, groups) == 24 &&
                                  offsetof(fbg_dsp_job, round_lo) == 28 &&
                                  offsetof(fbg_dsp_job, s32) == 36 &&
                                  offsetof(fbg_dsp_job, clamped) == 40) ? 1 : -1];


/* Field offsets of fbg_layer read by the pair kernels' assembly. */
typedef char fbg_dsp_layer_layout[(offsetof(fbg_layer, n_out) == 2 && offsetof(fbg_layer, w16) == 8 &&
                                   offsetof(fbg_layer, bias) == 16 && offsetof(fbg_layer, mult) == 20) ? 1 : -1];

/* ---- The kernels in C with ACLE intrinsics: the FBG_DSP_ASM=0 versions of the assembly
 * further down, same jobs, same bits (any alignment: LDR may be unaligned on ARMv7E-M). With
 * GCC 12 they cost more instructions per step than the assembly, which therefore stays the
 * default (docs/firmware.md has the figures): GCC forms no LDRD from two word loads, advances
 * every row pointer with its own ADD and keeps ReLU as ASR + BIC. ---- */
#if !FBG_DSP_ASM

/* Requantise an int64 row with shift >= 32 (rounded_product_hi), ReLU, USAT #15. */
static inline int32_t requant64(int64_t acc, int32_t mult, int64_t round, unsigned s32,
                                uint32_t *clamped)
{
    return relu_usat15(rounded_product_hi(acc, mult, round) >> s32, clamped);
}

static inline int64_t job_round(const fbg_dsp_job *job)
{
    return (int64_t)(((uint64_t)job->round_hi << 32) | job->round_lo);
}

/* Three int64 rows per pass (rows3_asm, rows3d_asm). */
__attribute__((noinline)) static void rows3_c(fbg_dsp_job *job)
{
    const unsigned n = job->n, s32 = job->s32;
    const int64_t round = job_round(job);
    const int16_t *w = job->w, *x = job->x;
    const int64_t *bias = job->bias;
    const int32_t *mult = job->mult;
    int16_t *y = job->y;
    uint32_t clamped = 0u, g;
    for (g = job->groups; g > 0u; --g, w += 3u * n, bias += 3, mult += 3, y += 3) {
        const int16_t *w0 = w, *w1 = w0 + n, *w2 = w1 + n;
        int64_t a0 = bias[0], a1 = bias[1], a2 = bias[2];
        unsigned j = 0;
        for (; j + 2u <= n; j += 2u) {
            int16x2_t xv = ld2(x + j);
            a0 = __smlald(ld2(w0 + j), xv, a0);
            a1 = __smlald(ld2(w1 + j), xv, a1);
            a2 = __smlald(ld2(w2 + j), xv, a2);
        }
        if (j < n) {
            a0 += (int32_t)w0[j] * (int32_t)x[j];
            a1 += (int32_t)w1[j] * (int32_t)x[j];
            a2 += (int32_t)w2[j] * (int32_t)x[j];
        }
        y[0] = (int16_t)requant64(a0, mult[0], round, s32, &clamped);
        y[1] = (int16_t)requant64(a1, mult[1], round, s32, &clamped);
        y[2] = (int16_t)requant64(a2, mult[2], round, s32, &clamped);
    }
    job->clamped = clamped != 0u;
}

/* A first layer of n = 2, 4 or 6 inputs held in registers, int64 rows (first_asm); n is a
 * constant at each call, so the row loop carries no test on it. */
static inline void first_n(fbg_dsp_job *job, unsigned n)
{
    const int64_t round = job_round(job);
    const unsigned s32 = job->s32;
    const int16_t *w = job->w;
    const int64_t *bias = job->bias;
    const int32_t *mult = job->mult;
    int16_t *y = job->y, *end = job->y + job->groups;
    const int16x2_t x0 = ld2(job->x), x1 = n > 2u ? ld2(job->x + 2) : 0,
                    x2 = n > 4u ? ld2(job->x + 4) : 0;
    uint32_t clamped = 0u;
    while (y != end) {
        int64_t a = __smlald(ld2(w), x0, *bias++);
        w += 2;
        if (n > 2u) {
            a = __smlald(ld2(w), x1, a);
            w += 2;
        }
        if (n > 4u) {
            a = __smlald(ld2(w), x2, a);
            w += 2;
        }
        *y++ = (int16_t)requant64(a, *mult++, round, s32, &clamped);
    }
    job->clamped = clamped != 0u;
}

__attribute__((noinline)) static void first_c(fbg_dsp_job *job)
{
    if (job->n == 2u)
        first_n(job, 2u);
    else if (job->n == 4u)
        first_n(job, 4u);
    else
        first_n(job, 6u);
}

/* Two int32 rows per pass, SMLAD and SMMULR (rows2d32_asm, first2d32_asm): every pair of
 * rows of the layer (n_out & ~1 rows), n even, y word-aligned; *sat |= 1 iff a row clamped. */
__attribute__((noinline)) static void rows2_32_c(const fbg_layer *ly, const int16_t *x,
                                                 int16_t *y, uint32_t *sat)
{
    const unsigned n = ly->n_in, m2 = ly->n_out & ~1u;
    const int16_t *w = ly->w16;
    uint32_t clamped = 0u;
    unsigned r;
    for (r = 0; r < m2; r += 2u, w += 2u * n) {
        const int16_t *w1 = w + n;
        int32_t a0 = (int32_t)ly->bias[r], a1 = (int32_t)ly->bias[r + 1u];
        unsigned j;
        for (j = 0; j < n; j += 2u) {
            int16x2_t xv = ld2(x + j);
            a0 = __smlad(ld2(w + j), xv, a0);
            a1 = __smlad(ld2(w1 + j), xv, a1);
        }
        y[r] = (int16_t)relu_usat15(smmulr(a0, ly->mult[r]), &clamped);
        y[r + 1u] = (int16_t)relu_usat15(smmulr(a1, ly->mult[r + 1u]), &clamped);
    }
    *sat |= clamped != 0u;
}
#endif /* !FBG_DSP_ASM */

#if FBG_DSP_ASM
/* The sticky Q flag (set by a USAT that clamped) into r12. */
#define FBG_Q_READ                               \
        "mrs     r12, apsr\n\t"                  \
        "ubfx    r12, r12, #27, #1\n\t"

/* Entry of the int64 kernels: the caller's APSR saved with r4-r12 and lr, then Q cleared. */
#define FBG_Q_SAVE_CLEAR                         \
        "mrs     r12, apsr\n\t"                  \
        "push    {r4-r12, lr}\n\t"               \
        "bic     r12, r12, #0x08000000\n\t"      \
        "msr     APSR_nzcvq, r12\n\t"

/* Their exit before the return: Q into job->clamped (JOB names the register holding job), the
 * caller's APSR back. */
#define FBG_Q_RESTORE(job)                       \
        FBG_Q_READ                               \
        "str     r12, [" job ", #40]\n\t"        \
        "pop     {r4-r12, lr}\n\t"               \
        "msr     APSR_nzcvq, r12\n\t"

/* Entry of the int32 kernels: r4-r11 and lr saved, Q cleared (the AAPCS leaves the caller's Q
 * undefined across a call). */
#define FBG_Q_CLEAR_PUSH                         \
        "push    {r4-r11, lr}\n\t"               \
        "mov     r12, #0\n\t"                    \
        "msr     APSR_nzcvq, r12\n\t"

/* Their exit, with Q in r12 (FBG_Q_READ) and the sat pointer in r3: *sat |= Q. */
#define FBG_SAT_OR_Q                             \
        "ldr     r0, [r3]\n\t"                   \
        "orr     r0, r0, r12\n\t"                \
        "str     r0, [r3]\n\t"

/* rows3_asm: one input pair of three rows (r1: x, r0/r10/r11: the rows) into r5:r4, r7:r6, r9:r8;
 * FBG_ROWS3_PAIR_LOADS leaves out the last SMLALD, for a loop test to go before it. */
#define FBG_ROWS3_PAIR_LOADS                     \
        "ldr     r12, [r1], #4\n\t"              \
        "ldr     r2, [r0], #4\n\t"               \
        "smlald  r4, r5, r2, r12\n\t"            \
        "ldr     r2, [r10], #4\n\t"              \
        "smlald  r6, r7, r2, r12\n\t"            \
        "ldr     r2, [r11], #4\n\t"

/* The whole pair. */
#define FBG_ROWS3_PAIR                           \
        FBG_ROWS3_PAIR_LOADS                     \
        "smlald  r8, r9, r2, r12\n\t"

/* rows3d_asm: four inputs of three rows, each read with one LDRD. */
#define FBG_ROWS3_QUAD                           \
        "ldrd    r2, r3, [r1], #8\n\t"           \
        "ldrd    r12, lr, [r0], #8\n\t"          \
        "smlald  r4, r5, r12, r2\n\t"            \
        "smlald  r4, r5, lr, r3\n\t"             \
        "ldrd    r12, lr, [r10], #8\n\t"         \
        "smlald  r6, r7, r12, r2\n\t"            \
        "smlald  r6, r7, lr, r3\n\t"             \
        "ldrd    r12, lr, [r11], #8\n\t"         \
        "smlald  r8, r9, r12, r2\n\t"            \
        "smlald  r8, r9, lr, r3\n\t"

/* The requantisation and store of one row of rows3_asm and rows3d_asm (accumulator hi:lo). */
#define FBG_ROWS3_REQUANT(lo, hi)                \
        "ldr     r11, [r0], #4\n\t"              \
        "add     " hi ", " hi ", " lo ", lsr #31\n\t" \
        "smull   r12, " lo ", " lo ", r11\n\t"   \
        "adds    r12, r12, r1\n\t"               \
        "adc     " lo ", " lo ", r2\n\t"         \
        "mla     " lo ", " hi ", r11, " lo "\n\t" \
        "asr     " lo ", " lo ", lr\n\t"         \
        "bic     " lo ", " lo ", " lo ", asr #31\n\t" \
        "usat    r12, #15, " lo "\n\t"           \
        "strh    r12, [r10], #2\n\t"

/* The end of a group of three rows (job in r3): the next x, the three rows requantised and stored,
 * the multiplier and output pointers written back. */
#define FBG_ROWS3_OUT                            \
        "str     r11, [r3]\n\t"                  \
        "ldr     r0, [r3, #12]\n\t"              \
        "ldrd    r1, r2, [r3, #28]\n\t"          \
        "ldr     lr, [r3, #36]\n\t"              \
        "ldr     r10, [r3, #16]\n\t"             \
        FBG_ROWS3_REQUANT("r4", "r5")            \
        FBG_ROWS3_REQUANT("r6", "r7")            \
        FBG_ROWS3_REQUANT("r8", "r9")            \
        "str     r0, [r3, #12]\n\t"              \
        "str     r10, [r3, #16]\n\t"

/* A hidden layer with shift >= 32, three rows per pass, everything in registers:
 *   MACs: r5:r4, r7:r6, r9:r8 = the three int64 accumulators (from the bias); per input pair
 *         one LDR of x, three LDR of weights (post-increment), three SMLALD; unrolled by four
 *         pairs: 30 instructions per 24 MACs; then 2, 1 pairs and 1 element for n % 8.
 *   requantisation per row (10 instructions): H = hi + bit31(lo); SMULL lo * mult, add
 *         2^(shift-1) (ADDS/ADC), MLA H * mult into the high word = floor(p / 2^32) (see
 *         rounded_product_hi), ASR by shift - 32, ReLU (BIC with ASR #31), USAT #15, STRH.
 *         USAT sets the sticky Q flag exactly when a (non-negative) value exceeds 32767, i.e.
 *         when the portable sat16 raises its flag: Q is cleared on entry, read into
 *         job->clamped on exit, and the caller's APSR restored.
 * GCC's own code for this spilled the accumulators around every row group (about 30
 * instructions per row against 10 here), hence hand-allocated registers in a naked function. */
__attribute__((naked, noinline)) static void rows3_asm(fbg_dsp_job *job)
{
    (void)job;
    __asm__ volatile(
        FBG_Q_SAVE_CLEAR
        "mov     r3, r0\n\t"
        "0:\n\t"
        "ldr     r12, [r3, #8]\n\t"
        "ldrd    r4, r5, [r12]\n\t"
        "ldrd    r6, r7, [r12, #8]\n\t"
        "ldrd    r8, r9, [r12, #16]\n\t"
        "add     r12, r12, #24\n\t"
        "str     r12, [r3, #8]\n\t"
        "ldr     r0, [r3]\n\t"
        "ldr     r12, [r3, #20]\n\t"
        "add     r10, r0, r12, lsl #1\n\t"
        "add     r11, r10, r12, lsl #1\n\t"
        "ldr     r1, [r3, #4]\n\t"
        "bic     lr, r12, #7\n\t"
        "add     lr, r1, lr, lsl #1\n\t"
        "cmp     r1, lr\n\t"
        "beq     2f\n\t"
        "1:\n\t"
        FBG_ROWS3_PAIR
        FBG_ROWS3_PAIR
        FBG_ROWS3_PAIR
        FBG_ROWS3_PAIR_LOADS
        "cmp     r1, lr\n\t"
        "smlald  r8, r9, r2, r12\n\t"
        "bne     1b\n\t"
        "2:\n\t"
        "ldr     lr, [r3, #20]\n\t"
        "tst     lr, #4\n\t"
        "beq     3f\n\t"
        FBG_ROWS3_PAIR
        FBG_ROWS3_PAIR
        "3:\n\t"
        "tst     lr, #2\n\t"
        "beq     4f\n\t"
        FBG_ROWS3_PAIR
        "4:\n\t"
        "tst     lr, #1\n\t"
        "beq     5f\n\t"
        "ldrsh   r12, [r1]\n\t"
        "ldrsh   r2, [r0]\n\t"
        "smlalbb r4, r5, r2, r12\n\t"
        "ldrsh   r2, [r10]\n\t"
        "smlalbb r6, r7, r2, r12\n\t"
        "ldrsh   r2, [r11], #2\n\t"
        "smlalbb r8, r9, r2, r12\n\t"
        "5:\n\t"
        FBG_ROWS3_OUT
        "ldr     r12, [r3, #24]\n\t"
        "subs    r12, r12, #1\n\t"
        "str     r12, [r3, #24]\n\t"
        "bne     0b\n\t"
        FBG_Q_RESTORE("r3")
        "bx      lr\n\t");
}

/* rows3_asm for word-aligned inputs and rows (x and w 4-byte aligned, n even), the usual case
 * (activation buffers in fbg_state, generated arrays and blob arrays are word-aligned): LDRD
 * fetches four inputs or four weights of a row in one instruction, so sixteen inputs of
 * three rows cost 4 x (1 + 3 x 3) + 3 = 43 instructions per 48 MACs (0.90) instead of 60;
 * with all four temporaries in use, the job pointer, the loop end, n and the end of the
 * output live on the stack (computed once per layer; the group loop ends at the last output). Then 8, 4 and 2 inputs for n % 16. Same
 * arithmetic, same requantisation as rows3_asm. (LDRD needs word alignment: the caller
 * checks it, the unaligned case stays with rows3_asm.) */
__attribute__((naked, noinline)) static void rows3d_asm(fbg_dsp_job *job)
{
    (void)job;
    __asm__ volatile(
        FBG_Q_SAVE_CLEAR
        "sub     sp, sp, #16\n\t"
        "str     r0, [sp]\n\t"
        "ldr     r12, [r0, #24]\n\t"
        "ldr     r1, [r0, #16]\n\t"
        "add     r12, r12, r12, lsl #1\n\t"
        "add     r12, r1, r12, lsl #1\n\t"
        "str     r12, [sp, #12]\n\t"
        "ldr     r12, [r0, #20]\n\t"
        "str     r12, [sp, #8]\n\t"
        "ldr     r1, [r0, #4]\n\t"
        "bic     r12, r12, #15\n\t"
        "add     r12, r1, r12, lsl #1\n\t"
        "str     r12, [sp, #4]\n\t"
        "0:\n\t"
        "ldr     r3, [sp]\n\t"
        "ldr     r12, [r3, #8]\n\t"
        "ldrd    r4, r5, [r12], #8\n\t"
        "ldrd    r6, r7, [r12], #8\n\t"
        "ldrd    r8, r9, [r12], #8\n\t"
        "str     r12, [r3, #8]\n\t"
        "ldr     r0, [r3]\n\t"
        "ldr     r12, [sp, #8]\n\t"
        "add     r10, r0, r12, lsl #1\n\t"
        "add     r11, r10, r12, lsl #1\n\t"
        "ldr     r1, [r3, #4]\n\t"
        "ldr     lr, [sp, #4]\n\t"
        "cmp     r1, lr\n\t"
        "beq     2f\n\t"
        "1:\n\t"
        FBG_ROWS3_QUAD
        FBG_ROWS3_QUAD
        FBG_ROWS3_QUAD
        FBG_ROWS3_QUAD
        "ldr     r12, [sp, #4]\n\t"
        "cmp     r1, r12\n\t"
        "bne     1b\n\t"
        "2:\n\t"
        "ldr     r12, [sp, #8]\n\t"
        "tst     r12, #8\n\t"
        "beq     3f\n\t"
        FBG_ROWS3_QUAD
        FBG_ROWS3_QUAD
        "3:\n\t"
        "ldr     r12, [sp, #8]\n\t"
        "lsls    r12, r12, #30\n\t"
        "bcc     4f\n\t"
        FBG_ROWS3_QUAD
        "4:\n\t"
        "bpl     5f\n\t"
        "ldr     r2, [r1], #4\n\t"
        "ldr     r12, [r0], #4\n\t"
        "smlald  r4, r5, r12, r2\n\t"
        "ldr     r12, [r10], #4\n\t"
        "smlald  r6, r7, r12, r2\n\t"
        "ldr     r12, [r11], #4\n\t"
        "smlald  r8, r9, r12, r2\n\t"
        "5:\n\t"
        "ldr     r3, [sp]\n\t"
        FBG_ROWS3_OUT
        "ldr     r12, [sp, #12]\n\t"
        "cmp     r10, r12\n\t"
        "bne     0b\n\t"
        "add     sp, sp, #16\n\t"
        FBG_Q_RESTORE("r3")
        "bx      lr\n\t");
}

/* first_asm: the requantisation and store of one row (accumulator r9:r8, the rounding constant
 * on the stack, shift - 32 in r7), then the loop test against the output end r12. */
#define FBG_FIRST_ROW_OUT                        \
        "ldr     lr, [r2], #4\n\t"               \
        "add     r9, r9, r8, lsr #31\n\t"        \
        "ldrd    r10, r11, [sp]\n\t"             \
        "smlal   r10, r11, r8, lr\n\t"           \
        "mla     r11, r9, lr, r11\n\t"           \
        "asr     r11, r11, r7\n\t"               \
        "bic     r11, r11, r11, asr #31\n\t"     \
        "usat    r11, #15, r11\n\t"              \
        "strh    r11, [r3], #2\n\t"              \
        "cmp     r3, r12\n\t"

/* A first layer (2, 4 or 6 inputs: the nets' z1..z4 and the location net's six inputs) with
 * shift >= 32: the inputs stay in registers (r4-r6 as int16 pairs) and each row costs one
 * LDRD of its bias, one LDR + SMLALD per input pair, the requantisation of rows3_asm (with
 * the rounding constant kept on the stack, read with one LDRD: 9 instructions) and the loop
 * test: 16 instructions per row for 4 inputs against about 27 through rows3_asm, whose
 * bookkeeping per three rows is written for long rows. Same arithmetic, same Q-flag saturation report; job->groups holds
 * the number of ROWS here. */
__attribute__((naked, noinline)) static void first_asm(fbg_dsp_job *job)
{
    (void)job;
    __asm__ volatile(
        FBG_Q_SAVE_CLEAR
        "sub     sp, sp, #16\n\t"
        "ldrd    r10, r11, [r0, #28]\n\t"
        "strd    r10, r11, [sp]\n\t"
        "str     r0, [sp, #8]\n\t"
        "ldr     r7, [r0, #36]\n\t"
        "ldr     r3, [r0, #16]\n\t"
        "ldr     r12, [r0, #24]\n\t"
        "add     r12, r3, r12, lsl #1\n\t"
        "ldr     r1, [r0, #8]\n\t"
        "ldr     r2, [r0, #12]\n\t"
        "ldr     lr, [r0, #20]\n\t"
        "ldr     r10, [r0, #4]\n\t"
        "ldr     r0, [r0]\n\t"
        "ldr     r4, [r10]\n\t"
        "cmp     lr, #4\n\t"
        "blo     2f\n\t"
        "ldr     r5, [r10, #4]\n\t"
        "beq     4f\n\t"
        "ldr     r6, [r10, #8]\n\t"
        "b       6f\n\t"
        "2:\n\t"
        "ldrd    r8, r9, [r1], #8\n\t"
        "ldr     r10, [r0], #4\n\t"
        "smlald  r8, r9, r10, r4\n\t"
        FBG_FIRST_ROW_OUT
        "bne     2b\n\t"
        "b       9f\n\t"
        "4:\n\t"
        "ldrd    r8, r9, [r1], #8\n\t"
        "ldr     r10, [r0], #4\n\t"
        "smlald  r8, r9, r10, r4\n\t"
        "ldr     r10, [r0], #4\n\t"
        "smlald  r8, r9, r10, r5\n\t"
        FBG_FIRST_ROW_OUT
        "bne     4b\n\t"
        "b       9f\n\t"
        "6:\n\t"
        "ldrd    r8, r9, [r1], #8\n\t"
        "ldr     r10, [r0], #4\n\t"
        "smlald  r8, r9, r10, r4\n\t"
        "ldr     r10, [r0], #4\n\t"
        "smlald  r8, r9, r10, r5\n\t"
        "ldr     r10, [r0], #4\n\t"
        "smlald  r8, r9, r10, r6\n\t"
        FBG_FIRST_ROW_OUT
        "bne     6b\n\t"
        "b       9f\n\t"
        "9:\n\t"
        "ldr     r0, [sp, #8]\n\t"
        "add     sp, sp, #16\n\t"
        FBG_Q_RESTORE("r0")
        "bx      lr\n\t");
}


/* The requantisation and store of a pair of rows of the int32 kernels: accumulators A and B,
 * their multipliers read from MULT (post-incremented) into MA and MB, SMMULR, ReLU as BIC with
 * ASR #31, USAT #15, both outputs packed into one word and stored at OUT (post-incremented). */
#define FBG_PAIR_REQUANT(mult, ma, mb, a, b, out)                \
        "ldrd    " ma ", " mb ", [" mult "], #8\n\t"             \
        "smmulr  " a ", " a ", " ma "\n\t"                       \
        "smmulr  " b ", " b ", " mb "\n\t"                       \
        "bic     " a ", " a ", " a ", asr #31\n\t"               \
        "bic     " b ", " b ", " b ", asr #31\n\t"               \
        "usat    " a ", #15, " a "\n\t"                          \
        "usat    " b ", #15, " b "\n\t"                          \
        "pkhbt   " a ", " a ", " b ", lsl #16\n\t"               \
        "str     " a ", [" out "], #4\n\t"

/* The end of a pass of rows2d32_asm and rows2b32_asm ("8:"): the requantisation and store of the
 * pair (LDRD of both multipliers, SMMULR, ReLU, USAT, PKHBT, STR), the next pair's biases and
 * rows and the jump to where a pass starts; after the last pair ("9:") the sat pointer into r3. */
#define FBG_ROWS2_PASS_END                       \
        "8:\n\t"                                 \
        "ldm     sp, {r3, r4, r5, r6, r8, lr}\n\t" \
        FBG_PAIR_REQUANT("r4", "r7", "r10", "r9", "r11", "r5") \
        "cmp     r5, r6\n\t"                     \
        "beq     9f\n\t"                         \
        "ldmia   r3!, {r9-r12}\n\t"              \
        "stmia   sp, {r3, r4, r5}\n\t"           \
        "mov     r0, r1\n\t"                     \
        "add     r1, r1, r8\n\t"                 \
        "ldr     pc, [sp, #24]\n\t"              \
        "9:\n\t"                                 \
        "ldr     r3, [sp, #28]\n\t"

/* int32 layers (fbg_layer.acc32, shift 32): the exporter proved that every partial sum of a
 * row fits int32 (fbg_model_check re-proves it: sum|w| * 32767 + |bias| <= INT32_MAX bounds
 * the bias plus ANY subset of the products, so the order of summation is free), so SMLAD (two
 * 16x16 products added to a 32-bit accumulator, which cannot overflow here and so never sets
 * Q) gives the same number as the int64 sum, in ONE register per row; and
 * rshift_round(acc * mult, 32) is exactly SMMULR (the high word of acc * mult + 2^31).
 *
 * Both kernels below take the layer itself (fbg_layer offsets checked above), run TWO rows
 * per pass over every pair of rows (n_out & ~1; the caller runs the last row of an odd layer)
 * and finish a pass with the same 9-instruction requantisation of the pair: LDRD of the two
 * multipliers, SMMULR x 2, ReLU as BIC with ASR #31 x 2, USAT #15 x 2 (Q set exactly when a
 * non-negative value exceeds 32767, i.e. when the portable sat16 raises its flag), PKHBT and
 * one STR of both outputs (y word-aligned, row r in the low half: little-endian). The pair's
 * two int32 biases come with one LDM of the int64 pair {lo, hi, lo, hi} (the high words land
 * in scratch registers). Q is cleared on entry and ORed into *sat on exit (1 iff a row
 * clamped); the AAPCS leaves Q and the condition flags undefined across calls, so the
 * caller's are not restored.
 *
 * rows2d32_asm (n even, w, x and y word-aligned): the MAC body is sixteen copies of an
 * 8-input block, fully unrolled,
 *     LDM x!, {4 words}; LDM rowA!, {4 words}; SMLAD x 4; LDM rowB!, {4 words}; SMLAD x 4
 * = 11 instructions per 16 MACs (0.69) with no loop test: every block is 44 bytes, so a layer
 * of n inputs enters the body n / 8 blocks before its end (computed once per layer, kept in
 * r2), after a tail of n % 8 = 2, 4 or 6 inputs (5, 7 or 9 instructions + BX r2) when there
 * is one. Fourteen registers are live in the body (two row pointers, x in lr, four inputs,
 * four weights, two accumulators, the entry); the bias, multiplier and output pointers, the
 * output end, the row length and the start of x live in a stack frame, read with one LDM
 * (which also rewinds x) and written back with one STM per pair. Per pair beyond the MACs:
 * 9 (requantisation) + 8 (frame, loop test, biases, next rows, dispatch) + 1 (a tail's BX)
 * instructions. */
__attribute__((naked, noinline)) static void rows2d32_asm(const fbg_layer *ly, const int16_t *x,
                                                          int16_t *y, uint32_t *sat)
{
    (void)ly;
    (void)x;
    (void)y;
    (void)sat;
    __asm__ volatile(
        FBG_Q_CLEAR_PUSH
        /* frame: [sp] bias, [4] mult, [8] out, [12] out end (after the last pair),
         * [16] row bytes, [20] x, [24] where a pass starts (tail or body entry, Thumb bit),
         * [28] sat; written with one STM */
        "sub     sp, sp, #32\n\t"
        "mov     r10, r3\n\t"
        "ldr     r11, [r0]\n\t"
        "ldrd    r3, r4, [r0, #16]\n\t"
        "ldr     r0, [r0, #8]\n\t"
        "mov     r5, r2\n\t"
        "lsr     r6, r11, #16\n\t"
        "bic     r6, r6, #1\n\t"
        "add     r6, r2, r6, lsl #1\n\t"
        "uxth    r11, r11\n\t"
        "lsl     r7, r11, #1\n\t"
        "mov     r8, r1\n\t"
        "mov     lr, r1\n\t"
        "add     r1, r0, r7\n\t"
        "adr.w   r2, 8f\n\t"
        "lsr     r12, r11, #3\n\t"
        "mov     r9, #44\n\t"
        "mls     r2, r12, r9, r2\n\t"
        "orr     r2, r2, #1\n\t"
        "mov     r9, r2\n\t"
        "ands    r12, r11, #6\n\t"
        "beq     1f\n\t"
        "adr.w   r9, 72f\n\t"
        "cmp     r12, #2\n\t"
        "beq     0f\n\t"
        "adr.w   r9, 74f\n\t"
        "cmp     r12, #4\n\t"
        "beq     0f\n\t"
        "adr.w   r9, 76f\n\t"
        "0:\n\t"
        "orr     r9, r9, #1\n\t"
        "1:\n\t"
        "add     r3, r3, #16\n\t"
        "stm     sp, {r3-r10}\n\t"
        "ldmdb   r3, {r9-r12}\n\t"
        "ldr     pc, [sp, #24]\n\t"
        /* tails: 2, 4, 6 inputs, then into the body */
        "72:\n\t"
        "ldr     r3, [lr], #4\n\t"
        "ldr     r7, [r0], #4\n\t"
        "smlad   r9, r7, r3, r9\n\t"
        "ldr     r7, [r1], #4\n\t"
        "smlad   r11, r7, r3, r11\n\t"
        "bx      r2\n\t"
        "74:\n\t"
        "ldrd    r3, r4, [lr], #8\n\t"
        "ldrd    r7, r8, [r0], #8\n\t"
        "smlad   r9, r7, r3, r9\n\t"
        "smlad   r9, r8, r4, r9\n\t"
        "ldrd    r7, r8, [r1], #8\n\t"
        "smlad   r11, r7, r3, r11\n\t"
        "smlad   r11, r8, r4, r11\n\t"
        "bx      r2\n\t"
        "76:\n\t"
        "ldmia.w lr!, {r3-r5}\n\t"
        "ldmia.w r0!, {r7, r8, r10}\n\t"
        "smlad   r9, r7, r3, r9\n\t"
        "smlad   r9, r8, r4, r9\n\t"
        "smlad   r9, r10, r5, r9\n\t"
        "ldmia.w r1!, {r7, r8, r10}\n\t"
        "smlad   r11, r7, r3, r11\n\t"
        "smlad   r11, r8, r4, r11\n\t"
        "smlad   r11, r10, r5, r11\n\t"
        "bx      r2\n\t"
        /* the body: 16 blocks of 8 inputs, 44 bytes each (every instruction 32-bit) */
        ".rept   16\n\t"
        "ldmia.w lr!, {r3-r6}\n\t"
        "ldmia.w r0!, {r7, r8, r10, r12}\n\t"
        "smlad   r9, r7, r3, r9\n\t"
        "smlad   r9, r8, r4, r9\n\t"
        "smlad   r9, r10, r5, r9\n\t"
        "smlad   r9, r12, r6, r9\n\t"
        "ldmia.w r1!, {r7, r8, r10, r12}\n\t"
        "smlad   r11, r7, r3, r11\n\t"
        "smlad   r11, r8, r4, r11\n\t"
        "smlad   r11, r10, r5, r11\n\t"
        "smlad   r11, r12, r6, r11\n\t"
        ".endr\n\t"
        FBG_ROWS2_PASS_END
        "add     sp, sp, #32\n\t"
        FBG_Q_READ
        FBG_SAT_OR_Q
        "pop     {r4-r11, pc}\n\t");
}

/* The requantisation and store of a pair in first2d32_asm. */
#define FBG_PAIR_OUT FBG_PAIR_REQUANT("r2", "r8", "r10", "r9", "r11", "r3")

/* One pair of a 6-input first layer (inputs in r4-r6). */
#define FBG_PAIR6                                \
        "ldmia   r1!, {r9-r12}\n\t"              \
        "ldmia.w r0!, {r8, r10, r12}\n\t"        \
        "smlad   r9, r8, r4, r9\n\t"             \
        "smlad   r9, r10, r5, r9\n\t"            \
        "smlad   r9, r12, r6, r9\n\t"            \
        "ldmia.w r0!, {r8, r10, r12}\n\t"        \
        "smlad   r11, r8, r4, r11\n\t"           \
        "smlad   r11, r10, r5, r11\n\t"          \
        "smlad   r11, r12, r6, r11\n\t"          \
        FBG_PAIR_OUT

/* One pair of an 8-input first layer (all four input registers r4-r7 in use). */
#define FBG_PAIR8                                \
        "ldmia   r1!, {r9-r12}\n\t"              \
        "ldmia.w r0!, {r8, r10, r12, lr}\n\t"    \
        "smlad   r9, r8, r4, r9\n\t"             \
        "smlad   r9, r10, r5, r9\n\t"            \
        "smlad   r9, r12, r6, r9\n\t"            \
        "smlad   r9, lr, r7, r9\n\t"             \
        "ldmia.w r0!, {r8, r10, r12, lr}\n\t"    \
        "smlad   r11, r8, r4, r11\n\t"           \
        "smlad   r11, r10, r5, r11\n\t"          \
        "smlad   r11, r12, r6, r11\n\t"          \
        "smlad   r11, lr, r7, r11\n\t"           \
        FBG_PAIR_OUT

/* One pair of a 10-input first layer: inputs in r4-r8, accumulators r9 and r11, three
 * registers left for the weights (an LDM of 3 and one of 2 words per row). */
#define FBG_PAIR10                               \
        "ldmia   r1!, {r9-r12}\n\t"              \
        "ldmia.w r0!, {r10, r12, lr}\n\t"        \
        "smlad   r9, r10, r4, r9\n\t"            \
        "smlad   r9, r12, r5, r9\n\t"            \
        "smlad   r9, lr, r6, r9\n\t"             \
        "ldrd    r10, r12, [r0], #8\n\t"         \
        "smlad   r9, r10, r7, r9\n\t"            \
        "smlad   r9, r12, r8, r9\n\t"            \
        "ldmia.w r0!, {r10, r12, lr}\n\t"        \
        "smlad   r11, r10, r4, r11\n\t"          \
        "smlad   r11, r12, r5, r11\n\t"          \
        "smlad   r11, lr, r6, r11\n\t"           \
        "ldrd    r10, r12, [r0], #8\n\t"         \
        "smlad   r11, r10, r7, r11\n\t"          \
        "smlad   r11, r12, r8, r11\n\t"          \
        FBG_PAIR_REQUANT("r2", "r10", "r12", "r9", "r11", "r3")

/* One pair of a 12-input first layer: inputs in r4-r9, the biases' low words (r10, r12) are
 * the accumulators, their high words' registers (r11, lr) take the weights two at a time. */
#define FBG_PAIR12                               \
        "ldmia   r1!, {r10-r12, lr}\n\t"         \
        "ldrd    r11, lr, [r0], #8\n\t"          \
        "smlad   r10, r11, r4, r10\n\t"          \
        "smlad   r10, lr, r5, r10\n\t"           \
        "ldrd    r11, lr, [r0], #8\n\t"          \
        "smlad   r10, r11, r6, r10\n\t"          \
        "smlad   r10, lr, r7, r10\n\t"           \
        "ldrd    r11, lr, [r0], #8\n\t"          \
        "smlad   r10, r11, r8, r10\n\t"          \
        "smlad   r10, lr, r9, r10\n\t"           \
        "ldrd    r11, lr, [r0], #8\n\t"          \
        "smlad   r12, r11, r4, r12\n\t"          \
        "smlad   r12, lr, r5, r12\n\t"           \
        "ldrd    r11, lr, [r0], #8\n\t"          \
        "smlad   r12, r11, r6, r12\n\t"          \
        "smlad   r12, lr, r7, r12\n\t"           \
        "ldrd    r11, lr, [r0], #8\n\t"          \
        "smlad   r12, r11, r8, r12\n\t"          \
        "smlad   r12, lr, r9, r12\n\t"           \
        FBG_PAIR_REQUANT("r2", "r11", "lr", "r10", "r12", "r3")

/* first2d32_asm: a first layer of n = 2, 4, 6, 8, 10 or 12 inputs (the nets' inputs with or without
 * the memory features and location averages), two rows per pass: the inputs stay in registers
 * (r4-r9 as int16 pairs, read once with LDR, which may be unaligned); the two rows are
 * adjacent in memory, so one pointer walks both (one LDRD or LDM per row, or one LDM for both
 * at n = 4). Per pair: LDM of the biases, the weights, n SMLAD, the 9-instruction
 * requantisation and the loop test (CMP with the output end, held in r7 for n <= 6): 15 and 17
 * instructions for 4 and 8 MACs. The n = 6, 8 and 10 loops run two pairs per test (entered at
 * their second pair for an odd number of pairs): 38 instructions per 24 MACs, and from n = 8
 * on, where the end is read from the stack, 43 per 32 and 51 per 40 (two loads per row at
 * n = 10: three registers are left for weights). n = 12 runs one pair per test, 31
 * instructions per 24 MACs. Weights and y word-aligned (the caller checks). */
__attribute__((naked, noinline)) static void first2d32_asm(const fbg_layer *ly, const int16_t *x,
                                                           int16_t *y, uint32_t *sat)
{
    (void)ly;
    (void)x;
    (void)y;
    (void)sat;
    __asm__ volatile(
        FBG_Q_CLEAR_PUSH
        "sub     sp, sp, #8\n\t"
        "str     r3, [sp, #4]\n\t"
        "mov     r3, r2\n\t"
        "ldrh    r9, [r0, #2]\n\t"
        "bic     r7, r9, #1\n\t"
        "add     r7, r3, r7, lsl #1\n\t"
        "str     r7, [sp]\n\t"
        "mov     r10, r1\n\t"
        "ldr     r1, [r0, #16]\n\t"
        "ldr     r2, [r0, #20]\n\t"
        "ldrh    r12, [r0]\n\t"
        "ldr     r0, [r0, #8]\n\t"
        "ldr     r4, [r10]\n\t"
        "cmp     r12, #4\n\t"
        "blo     2f\n\t"
        "ldr     r5, [r10, #4]\n\t"
        "beq     4f\n\t"
        "ldr     r6, [r10, #8]\n\t"
        "cmp     r12, #6\n\t"
        "bne     7f\n\t"
        "tst     r9, #2\n\t"
        "bne     61f\n\t"
        "b       6f\n\t"
        "7:\n\t"
        "ldr     r7, [r10, #12]\n\t"
        "ubfx    r11, r9, #1, #2\n\t"
        "cmp     r12, #8\n\t"
        "bne     10f\n\t"
        "cmp     r11, #2\n\t"
        "beq     83f\n\t"
        "bhi     82f\n\t"
        "cmp     r11, #1\n\t"
        "beq     84f\n\t"
        "b       8f\n\t"
        "2:\n\t"
        "ldmia   r1!, {r9-r12}\n\t"
        "ldrd    r8, r10, [r0], #8\n\t"
        "smlad   r9, r8, r4, r9\n\t"
        "smlad   r11, r10, r4, r11\n\t"
        FBG_PAIR_OUT
        "cmp     r3, r7\n\t"
        "bne     2b\n\t"
        "b       9f\n\t"
        "4:\n\t"
        "ldmia   r1!, {r9-r12}\n\t"
        "ldmia.w r0!, {r6, r8, r10, r12}\n\t"
        "smlad   r9, r6, r4, r9\n\t"
        "smlad   r9, r8, r5, r9\n\t"
        "smlad   r11, r10, r4, r11\n\t"
        "smlad   r11, r12, r5, r11\n\t"
        FBG_PAIR_OUT
        "cmp     r3, r7\n\t"
        "bne     4b\n\t"
        "b       9f\n\t"
        "6:\n\t"
        FBG_PAIR6
        "61:\n\t"
        FBG_PAIR6
        "cmp     r3, r7\n\t"
        "bne     6b\n\t"
        "b       9f\n\t"
        "8:\n\t"
        FBG_PAIR8
        "82:\n\t"
        FBG_PAIR8
        "83:\n\t"
        FBG_PAIR8
        "84:\n\t"
        FBG_PAIR8
        "ldr     r8, [sp]\n\t"
        "cmp     r3, r8\n\t"
        "bne     8b\n\t"
        "b       9f\n\t"
        "10:\n\t"
        "ldr     r8, [r10, #16]\n\t"
        "cmp     r12, #10\n\t"
        "bne     12f\n\t"
        "cmp     r11, #2\n\t"
        "beq     103f\n\t"
        "bhi     102f\n\t"
        "cmp     r11, #1\n\t"
        "beq     104f\n\t"
        "100:\n\t"
        FBG_PAIR10
        "102:\n\t"
        FBG_PAIR10
        "103:\n\t"
        FBG_PAIR10
        "104:\n\t"
        FBG_PAIR10
        "ldr     r12, [sp]\n\t"
        "cmp     r3, r12\n\t"
        "bne     100b\n\t"
        "b       9f\n\t"
        "12:\n\t"
        "ldr     r9, [r10, #20]\n\t"
        "120:\n\t"
        FBG_PAIR12
        "ldr     r11, [sp]\n\t"
        "cmp     r3, r11\n\t"
        "bne     120b\n\t"
        "9:\n\t"
        "ldr     r3, [sp, #4]\n\t"
        "add     sp, sp, #8\n\t"
        FBG_Q_READ
        FBG_SAT_OR_Q
        "pop     {r4-r11, pc}\n\t");
}
#undef FBG_PAIR12
#undef FBG_PAIR10
#undef FBG_PAIR8
#undef FBG_PAIR6
#undef FBG_PAIR_OUT

/* dot32_asm: acc + sum_j w[j] * x[j] for one row of an int32 layer (the output layers' rows,
 * fbg_dsp_row_acc), w and x word-aligned, n even: 8 inputs per LDM pair and four SMLAD
 * (8 instructions per 8 MACs with the loop test), then the n % 8 inputs two at a time. */
__attribute__((naked, noinline)) static int32_t dot32_asm(const int16_t *w, const int16_t *x,
                                                          unsigned n, int32_t acc)
{
    (void)w;
    (void)x;
    (void)n;
    (void)acc;
    __asm__ volatile(
        "push    {r4-r11}\n\t"
        "bic     r12, r2, #7\n\t"
        "add     r12, r0, r12, lsl #1\n\t"
        "cmp     r0, r12\n\t"
        "beq     2f\n\t"
        "1:\n\t"
        "ldmia   r1!, {r4-r7}\n\t"
        "ldmia   r0!, {r8-r11}\n\t"
        "smlad   r3, r8, r4, r3\n\t"
        "smlad   r3, r9, r5, r3\n\t"
        "smlad   r3, r10, r6, r3\n\t"
        "smlad   r3, r11, r7, r3\n\t"
        "cmp     r0, r12\n\t"
        "bne     1b\n\t"
        "2:\n\t"
        "ands    r2, r2, #7\n\t"
        "beq     4f\n\t"
        "3:\n\t"
        "ldr     r4, [r1], #4\n\t"
        "ldr     r8, [r0], #4\n\t"
        "smlad   r3, r8, r4, r3\n\t"
        "subs    r2, r2, #2\n\t"
        "bne     3b\n\t"
        "4:\n\t"
        "mov     r0, r3\n\t"
        "pop     {r4-r11}\n\t"
        "bx      lr\n\t");
}

/* One group of rows2b32_asm's loop: 8 inputs (x words in r3-r6) of rows r0 and r1, int8
 * weights widened by SXTB16 into the accumulators r9 and r11. */
#define ROWS2B32_GROUP \
        "ldmia.w lr!, {r3-r6}\n\t" \
        "ldr     r7, [r0], #4\n\t" \
        "ldr     r8, [r0], #4\n\t" \
        "sxtb16  r10, r7\n\t" \
        "smlad   r9, r10, r3, r9\n\t" \
        "sxtb16  r10, r7, ror #8\n\t" \
        "smlad   r9, r10, r4, r9\n\t" \
        "sxtb16  r10, r8\n\t" \
        "smlad   r9, r10, r5, r9\n\t" \
        "sxtb16  r10, r8, ror #8\n\t" \
        "smlad   r9, r10, r6, r9\n\t" \
        "ldr     r7, [r1], #4\n\t" \
        "ldr     r8, [r1], #4\n\t" \
        "sxtb16  r10, r7\n\t" \
        "smlad   r11, r10, r3, r11\n\t" \
        "sxtb16  r10, r7, ror #8\n\t" \
        "smlad   r11, r10, r4, r11\n\t" \
        "sxtb16  r10, r8\n\t" \
        "smlad   r11, r10, r5, r11\n\t" \
        "sxtb16  r10, r8, ror #8\n\t" \
        "smlad   r11, r10, r6, r11\n\t"

/* Four inputs of the tail of rows2b32_asm (x words in r3, r4) of rows r0 and r1. */
#define ROWS2B32_TAIL4                           \
        "ldrd    r3, r4, [lr], #8\n\t"           \
        "ldr     r7, [r0], #4\n\t"               \
        "sxtb16  r10, r7\n\t"                    \
        "smlad   r9, r10, r3, r9\n\t"            \
        "sxtb16  r10, r7, ror #8\n\t"            \
        "smlad   r9, r10, r4, r9\n\t"            \
        "ldr     r7, [r1], #4\n\t"               \
        "sxtb16  r10, r7\n\t"                    \
        "smlad   r11, r10, r3, r11\n\t"          \
        "sxtb16  r10, r7, ror #8\n\t"            \
        "smlad   r11, r10, r4, r11\n\t"

/* rows2b32_asm: the pairs of rows of an int32 layer at shift 32 with int8 weights (int8
 * weights always prove int32) and n even; any alignment of the rows (single LDR, which may be
 * unaligned), x and y word-aligned. First x is re-paired for SXTB16 into xp on the stack
 * (as hidden8 does, 8 inputs per LDM, two PKHBT, two PKHTB, STM): per group of four
 * (x0, x2), (x1, x3); then, when n % 4 == 2, the last two as (x[n-2], x[n-1]).
 * SXTB16 splits a word of four weights into the int16 pairs (w0, w2) and, rotated by 8,
 * (w1, w3), each one SMLAD with its input pair: per 8 inputs and two rows
 *     LDM xp!, {4 words}; 2 x (2 LDR, 4 SXTB16, 4 SMLAD)
 * = 21 instructions per 16 MACs, two such groups per loop test (CMP, BNE; an odd number of
 * groups enters the loop at its second). The n % 8 inputs after the loop: four (LDRD of two input
 * words, per row LDR + 2 SXTB16 + 2 SMLAD) and/or two (per row two LDRSB and SMLABB, SMLATB
 * with the natural pair), entered through a per-layer address in the frame. Requantisation,
 * frame and flag as rows2d32_asm (SMLAD, SMLABB and SMLATB never overflow here, so Q only
 * comes from USAT). */
__attribute__((naked, noinline)) static void rows2b32_asm(const fbg_layer *ly, const int16_t *x,
                                                          int16_t *y, uint32_t *sat)
{
    (void)ly;
    (void)x;
    (void)y;
    (void)sat;
    __asm__ volatile(
        FBG_Q_CLEAR_PUSH
        /* frame: [sp] bias, [4] mult, [8] out, [12] out end, [16] row bytes (n), [20] xp,
         * [24] where a pass starts (loop or tail), [28] sat, [32] the tail after the loop;
         * [40..] xp (FBG_MAX_WIDTH / 2 words); r2 = end of the 8-input groups of xp in the
         * MAC loop */
        "sub     sp, sp, #296\n\t"
        "str     r3, [sp, #28]\n\t"
        "ldrh    r8, [r0]\n\t"
        /* x (word-aligned) re-paired into xp: LDM of 8 inputs, PKHBT/PKHTB, STM */
        "add     r12, sp, #40\n\t"
        "bic     r7, r8, #7\n\t"
        "add     r7, r1, r7, lsl #1\n\t"
        "cmp     r1, r7\n\t"
        "beq     2f\n\t"
        "1:\n\t"
        "ldmia   r1!, {r3-r6}\n\t"
        "pkhbt   r9, r3, r4, lsl #16\n\t"
        "pkhtb   r10, r4, r3, asr #16\n\t"
        "pkhbt   r11, r5, r6, lsl #16\n\t"
        "pkhtb   lr, r6, r5, asr #16\n\t"
        "stmia   r12!, {r9, r10, r11, lr}\n\t"
        "cmp     r1, r7\n\t"
        "bne     1b\n\t"
        "2:\n\t"
        "tst     r8, #4\n\t"
        "beq     3f\n\t"
        "ldmia   r1!, {r3, r4}\n\t"
        "pkhbt   r9, r3, r4, lsl #16\n\t"
        "pkhtb   r10, r4, r3, asr #16\n\t"
        "stmia   r12!, {r9, r10}\n\t"
        "3:\n\t"
        "tst     r8, #2\n\t"
        "itt     ne\n\t"
        "ldrne   r3, [r1]\n\t"
        "strne   r3, [r12]\n\t"
        "add     r1, sp, #40\n\t"
        "ldrh    r6, [r0, #2]\n\t"
        "str     r8, [sp, #16]\n\t"
        "str     r1, [sp, #20]\n\t"
        "mov     lr, r1\n\t"
        "str     r2, [sp, #8]\n\t"
        "bic     r6, r6, #1\n\t"
        "add     r6, r2, r6, lsl #1\n\t"
        "str     r6, [sp, #12]\n\t"
        "bic     r7, r8, #7\n\t"
        "add     r2, r1, r7, lsl #1\n\t"
        "ldr     r3, [r0, #16]\n\t"
        "ldmia   r3!, {r9-r12}\n\t"
        "str     r3, [sp]\n\t"
        "ldr     r3, [r0, #20]\n\t"
        "str     r3, [sp, #4]\n\t"
        "ldr     r0, [r0, #12]\n\t"
        "add     r1, r0, r8\n\t"
        /* the tail: none, 2, 4 or 4 + 2 inputs */
        "and     r7, r8, #6\n\t"
        "adr.w   r3, 8f\n\t"
        "cmp     r7, #2\n\t"
        "it      eq\n\t"
        "adreq.w r3, 72f\n\t"
        "cmp     r7, #4\n\t"
        "it      eq\n\t"
        "adreq.w r3, 74f\n\t"
        "cmp     r7, #6\n\t"
        "it      eq\n\t"
        "adreq.w r3, 76f\n\t"
        "orr     r3, r3, #1\n\t"
        "str     r3, [sp, #32]\n\t"
        /* 8-input groups: two per loop test, entered at the second for an odd count */
        "cmp     r8, #8\n\t"
        "blo     0f\n\t"
        "tst     r8, #8\n\t"
        "ite     ne\n\t"
        "adrne.w r3, 10f\n\t"
        "adreq.w r3, 1f\n\t"
        "orr     r3, r3, #1\n\t"
        "0:\n\t"
        "str     r3, [sp, #24]\n\t"
        "bx      r3\n\t"
        "1:\n\t"
        ROWS2B32_GROUP
        "10:\n\t"
        ROWS2B32_GROUP
        "cmp     lr, r2\n\t"
        "bne     1b\n\t"
        "ldr     pc, [sp, #32]\n\t"
        /* 4 inputs, then to the epilogue */
        "74:\n\t"
        ROWS2B32_TAIL4
        "b       8f\n\t"
        /* 4 + 2 inputs */
        "76:\n\t"
        ROWS2B32_TAIL4
        /* 2 inputs: (x[n-2], x[n-1]) */
        "72:\n\t"
        "ldr     r3, [lr], #4\n\t"
        "ldrsb   r7, [r0], #1\n\t"
        "ldrsb   r8, [r0], #1\n\t"
        "smlabb  r9, r3, r7, r9\n\t"
        "smlatb  r9, r3, r8, r9\n\t"
        "ldrsb   r7, [r1], #1\n\t"
        "ldrsb   r8, [r1], #1\n\t"
        "smlabb  r11, r3, r7, r11\n\t"
        "smlatb  r11, r3, r8, r11\n\t"
        FBG_ROWS2_PASS_END
        "add     sp, sp, #296\n\t"
        FBG_Q_READ
        FBG_SAT_OR_Q
        "pop     {r4-r11, pc}\n\t");
}

/* The requantisation and store of a pair in first2b32_asm, then the loop test against lr. */
#define FBG_PAIR_OUT8                            \
        FBG_PAIR_REQUANT("r2", "r8", "r10", "r9", "r11", "r3") \
        "cmp     r3, lr\n\t"

/* Four int8 weights (one LDR into r10) against two re-paired input words, into ACC. */
#define FBG_W4(acc, xa, xb)                      \
        "sxtb16  r8, r10\n\t"                    \
        "smlad   " acc ", r8, " xa ", " acc "\n\t" \
        "sxtb16  r8, r10, ror #8\n\t"            \
        "smlad   " acc ", r8, " xb ", " acc "\n\t"

/* Two int8 weights (two LDRSB) against the natural input pair XW, into ACC. */
#define FBG_W2(acc, xw)                          \
        "ldrsb   r10, [r0], #1\n\t"              \
        "ldrsb   r12, [r0], #1\n\t"              \
        "smlabb  " acc ", " xw ", r10, " acc "\n\t" \
        "smlatb  " acc ", " xw ", r12, " acc "\n\t"

/* first2b32_asm: an int8-weight int32 first layer (shift 32) of n = 2, 4, 6 or 8 inputs, two
 * rows per pass, the inputs re-paired once into registers (r4-r7: (x0, x2), (x1, x3) per four,
 * the natural pair for the last two when n % 4 == 2; LDR, which may be unaligned, and
 * PKHBT/PKHTB); the rows are adjacent, one pointer walks both (single LDR/LDRSB, any
 * alignment). Per pair: LDM of the biases, per row one LDR + 2 SXTB16 + 2 SMLAD per four
 * weights and 2 LDRSB + SMLABB + SMLATB per two, the requantisation of first2d32_asm and the
 * loop test (output end in lr): 20, 22, 30 and 32 instructions for 4, 8, 12 and 16 MACs.
 * y word-aligned (the caller checks). */
__attribute__((naked, noinline)) static void first2b32_asm(const fbg_layer *ly, const int16_t *x,
                                                           int16_t *y, uint32_t *sat)
{
    (void)ly;
    (void)x;
    (void)y;
    (void)sat;
    __asm__ volatile(
        "push    {r3-r11, lr}\n\t"
        "mov     r12, #0\n\t"
        "msr     APSR_nzcvq, r12\n\t"
        "mov     r3, r2\n\t"
        "ldrh    r9, [r0, #2]\n\t"
        "bic     lr, r9, #1\n\t"
        "add     lr, r3, lr, lsl #1\n\t"
        "ldr     r2, [r0, #20]\n\t"
        "ldrh    r12, [r0]\n\t"
        "mov     r10, r1\n\t"
        "ldr     r1, [r0, #16]\n\t"
        "ldr     r0, [r0, #12]\n\t"
        "ldr     r4, [r10]\n\t"
        "cmp     r12, #4\n\t"
        "blo     2f\n\t"
        "ldr     r5, [r10, #4]\n\t"
        "pkhbt   r8, r4, r5, lsl #16\n\t"
        "pkhtb   r5, r5, r4, asr #16\n\t"
        "mov     r4, r8\n\t"
        "beq     4f\n\t"
        "ldr     r6, [r10, #8]\n\t"
        "cmp     r12, #6\n\t"
        "beq     6f\n\t"
        "ldr     r7, [r10, #12]\n\t"
        "pkhbt   r8, r6, r7, lsl #16\n\t"
        "pkhtb   r7, r7, r6, asr #16\n\t"
        "mov     r6, r8\n\t"
        "b       8f\n\t"
        "2:\n\t"
        "ldmia   r1!, {r9-r12}\n\t"
        FBG_W2("r9", "r4")
        FBG_W2("r11", "r4")
        FBG_PAIR_OUT8
        "bne     2b\n\t"
        "b       9f\n\t"
        "4:\n\t"
        "ldmia   r1!, {r9-r12}\n\t"
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r9", "r4", "r5")
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r11", "r4", "r5")
        FBG_PAIR_OUT8
        "bne     4b\n\t"
        "b       9f\n\t"
        "6:\n\t"
        "ldmia   r1!, {r9-r12}\n\t"
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r9", "r4", "r5")
        FBG_W2("r9", "r6")
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r11", "r4", "r5")
        FBG_W2("r11", "r6")
        FBG_PAIR_OUT8
        "bne     6b\n\t"
        "b       9f\n\t"
        "8:\n\t"
        "ldmia   r1!, {r9-r12}\n\t"
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r9", "r4", "r5")
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r9", "r6", "r7")
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r11", "r4", "r5")
        "ldr     r10, [r0], #4\n\t"
        FBG_W4("r11", "r6", "r7")
        FBG_PAIR_OUT8
        "bne     8b\n\t"
        "9:\n\t"
        FBG_Q_READ
        "pop     {r3}\n\t"
        FBG_SAT_OR_Q
        "pop     {r4-r11, pc}\n\t");
}
#undef FBG_W2
#undef FBG_W4
#undef FBG_PAIR_OUT8

typedef char fbg_dsp_xp_fits[FBG_MAX_WIDTH * 2 <= 256 ? 1 : -1]; /* xp in rows2b32_asm's frame */
typedef char fbg_dsp_fir_four[FBG_N_STRAIN == 4 ? 1 : -1]; /* rows of 16 bytes in fir4_asm */

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
#undef ROWS2B32_TAIL4
#undef ROWS2B32_GROUP
#undef FBG_PAIR_REQUANT
#undef FBG_ROWS2_PASS_END
#undef FBG_FIRST_ROW_OUT
#undef FBG_ROWS3_OUT
#undef FBG_ROWS3_REQUANT
#undef FBG_ROWS3_QUAD
#undef FBG_ROWS3_PAIR
#undef FBG_ROWS3_PAIR_LOADS
#undef FBG_SAT_OR_Q
#undef FBG_Q_RESTORE
#undef FBG_Q_SAVE_CLEAR
#undef FBG_Q_CLEAR_PUSH
#undef FBG_Q_READ
#endif /* FBG_DSP_ASM */

/* The kernels hidden16 and hidden16_32 call: the assembly (FBG_DSP_ASM) or its ACLE C. */
static void run_rows3(fbg_dsp_job *job, int aligned)
{
#if FBG_DSP_ASM
    if (aligned)
        rows3d_asm(job);
    else
        rows3_asm(job);
#else
    (void)aligned;
    rows3_c(job);
#endif
}

static void run_first(fbg_dsp_job *job)
{
#if FBG_DSP_ASM
    first_asm(job);
#else
    first_c(job);
#endif
}

/* The pairs of rows of an int32 layer at shift 32: the first-layer kernel (inputs in
 * registers) for n <= FBG_DSP_FIRST_MAX_IN, else the unrolled one (x word-aligned); *sat |= 1
 * iff a row clamped. */
static void run_pairs32(const fbg_layer *ly, const int16_t *x, int16_t *y, unsigned n,
                        uint32_t *sat)
{
#if FBG_DSP_ASM
    if (n <= FBG_DSP_FIRST_MAX_IN)
        first2d32_asm(ly, x, y, sat);
    else
        rows2d32_asm(ly, x, y, sat);
#else
    (void)n;
    rows2_32_c(ly, x, y, sat);
#endif
}

/* acc + sum_j w[j] * x[j] with SMLAD (an int32 layer: no partial sum overflows). */
static int32_t dot16_32(const int16_t *w, const int16_t *x, unsigned n, int32_t acc)
{
    unsigned j = 0;
    for (; j + 2u <= n; j += 2u)
        acc = __smlad(ld2(w + j), ld2(x + j), acc);
    if (j < n)
        acc += (int32_t)w[j] * (int32_t)x[j];
    return acc;
}

/* An int32 int16-weight hidden layer that the pair kernels do not take (see
 * fbg_dsp_hidden): SMLAD rows with C requantisation, any shift and alignment; from row r0 on. */
static void hidden16_32(const fbg_layer *ly, const int16_t *x, int16_t *y, unsigned r0,
                        uint32_t *sat)
{
    const unsigned n = ly->n_in, m = ly->n_out, shift = ly->shift;
    const int64_t round = (int64_t)1 << (shift - 1u);
    uint32_t clamped = 0u;
    unsigned r;
    for (r = r0; r < m; ++r)
        y[r] = (int16_t)relu_sat16(dot16_32(ly->w16 + (size_t)r * n, x, n, (int32_t)ly->bias[r]),
                                   ly->mult[r], shift, round, &clamped);
    if (clamped)
        *sat = 1u;
}

static void hidden16(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    const unsigned n = ly->n_in, m = ly->n_out, shift = ly->shift;
    const int16_t *w = ly->w16;
    const int64_t round = (int64_t)1 << (shift - 1u);
    uint32_t clamped = 0u;
    unsigned r = 0;

    if (shift >= 32u && (n == 2u || n == 4u || n == 6u)) {
        fbg_dsp_job job;
        job.w = w;
        job.x = x;
        job.bias = ly->bias;
        job.mult = ly->mult;
        job.y = y;
        job.n = n;
        job.groups = m;
        job.round_lo = (uint32_t)round;
        job.round_hi = (uint32_t)(round >> 32);
        job.s32 = shift - 32u;
        job.clamped = 0u;
        run_first(&job);
        if (job.clamped)
            *sat = 1u;
        return;
    }
    if (shift >= 32u && m >= 3u) {
        /* rows3d_asm needs word-aligned rows and inputs. Generated models and blobs give
         * 8-byte-aligned weights; the input (an activation buffer inside fbg_state, whose
         * layout may change) is copied to an aligned buffer when it is not: n/2 word moves
         * against about a quarter of the MAC loop saved. */
        union {
            int16_t v[FBG_MAX_WIDTH];
            int64_t align;
        } xbuf;
        int aligned = ((uintptr_t)w & 3u) == 0u && (n & 1u) == 0u;
        fbg_dsp_job job;
        if (aligned && ((uintptr_t)x & 3u) != 0u) {
            memcpy(xbuf.v, x, n * sizeof *x); /* the libc's word-wise copy */
            x = xbuf.v;
        }
        job.w = w;
        job.x = x;
        job.bias = ly->bias;
        job.mult = ly->mult;
        job.y = y;
        job.n = n;
        job.groups = m / 3u;
        job.round_lo = (uint32_t)round;
        job.round_hi = (uint32_t)(round >> 32);
        job.s32 = shift - 32u;
        job.clamped = 0u;
        run_rows3(&job, aligned);
        clamped = job.clamped;
        r = 3u * (m / 3u);
        if (m - r == 2u) {
            /* Two rows left: one more pass over the LAST three rows (the first of them is
             * recomputed, to the same value) is cheaper than two rows in C. */
            job.w = ly->w16 + (size_t)(m - 3u) * n;
            job.bias = ly->bias + (m - 3u);
            job.mult = ly->mult + (m - 3u);
            job.y = y + (m - 3u);
            job.groups = 1u;
            job.clamped = 0u;
            run_rows3(&job, aligned);
            clamped |= job.clamped;
            r = m;
        }
        w += (size_t)r * n;
    }
    /* The last one or two rows, and layers whose shift is below 32 (not chosen by the
     * exporter for int16 layers in practice, but valid): SMLALD per row, C requantisation. */
    for (; r < m; ++r, w += n)
        y[r] = (int16_t)relu_sat16(fbg_dsp_dot16(w, x, n, ly->bias[r]), ly->mult[r], shift, round,
                                   &clamped);
    if (clamped)
        *sat = 1u;
}

/* The inputs re-paired for int8 weights: SXTB16 splits a word of four int8 weights
 * (w0, w1, w2, w3) into the int16 pairs (w0, w2) and, rotated by 8, (w1, w3); so the inputs
 * are stored once per layer as (x0, x2), (x1, x3) for every group of four. */
static inline uint32_t ror8(uint32_t v) { return (v >> 8) | (v << 24); }

static inline int16x2_t pair16(int16_t lo, int16_t hi)
{
    return (int16x2_t)((uint32_t)(uint16_t)lo | ((uint32_t)(uint16_t)hi << 16));
}

static inline int8x4_t ld4_8(const int8_t *p)
{
    int8x4_t v;
    memcpy(&v, p, sizeof v);
    return v;
}

/* Two adjacent int16 inputs as one unsigned word. */
static inline uint32_t ld2u(const int16_t *p)
{
    uint32_t v;
    memcpy(&v, p, sizeof v);
    return v;
}

/* xp[] = x re-paired for SXTB16 over the first n4 inputs (n4 % 4 == 0): (x0, x2), (x1, x3)
 * per group of four, two word loads and two packs (PKHBT, PKHTB) per group. */
static inline void repair8(const int16_t *x, unsigned n4, int16x2_t *xp)
{
    unsigned j;
    for (j = 0; j < n4; j += 4u, xp += 2) {
        uint32_t a = ld2u(x + j), b = ld2u(x + j + 2u);
        xp[0] = (int16x2_t)((a & 0xFFFFu) | (b << 16));
        xp[1] = (int16x2_t)((a >> 16) | (b & 0xFFFF0000u));
    }
}

/* One row of an int32 layer with int8 weights (the output layers' rows): no re-paired copy
 * of x; the two SXTB16 halves (w0, w2), (w1, w3) are re-packed into (w0, w1), (w2, w3) to meet
 * the inputs as they lie (two PKH per four weights). */
static int32_t dot8_32(const int8_t *w, const int16_t *x, unsigned n, int32_t acc)
{
    unsigned j;
    for (j = 0; j + 4u <= n; j += 4u) {
        uint32_t v;
        uint32_t e, o;
        memcpy(&v, w + j, sizeof v);
        e = (uint32_t)__sxtb16((int8x4_t)v);
        o = (uint32_t)__sxtb16((int8x4_t)ror8(v));
        acc = __smlad((int16x2_t)((e & 0xFFFFu) | (o << 16)), ld2(x + j), acc);
        acc = __smlad((int16x2_t)((o & 0xFFFF0000u) | (e >> 16)), ld2(x + j + 2u), acc);
    }
    for (; j < n; ++j)
        acc += (int32_t)w[j] * (int32_t)x[j];
    return acc;
}

/* One row of int8 weights: acc = bias + sum_j w[j] x[j]; xp = the re-paired inputs. */
static int64_t dot8(const int8_t *w, const int16_t *x, const int16x2_t *xp, unsigned n, int64_t acc)
{
    unsigned j, n4 = n & ~3u;
    for (j = 0; j < n4; j += 4u, xp += 2) {
        int8x4_t v = ld4_8(w + j);
        acc = __smlald(__sxtb16(v), xp[0], acc);
        acc = __smlald(__sxtb16((int8x4_t)ror8((uint32_t)v)), xp[1], acc);
    }
    for (; j < n; ++j)
        acc += (int32_t)w[j] * (int32_t)x[j];
    return acc;
}

/* A hidden layer with int8 weights: two rows per pass share the re-paired inputs; per four
 * inputs and row one LDR, two SXTB16, two SMLALD. Requantisation in C: relu_sat16, or for an
 * int32 layer at shift 32 (int8 weights always prove int32: 128 * 127 * 32767 < 2^29) one
 * SMMULR; SMLALD costs what SMLAD does, so the MAC loop is shared. */
static __attribute__((noinline)) void hidden8(const fbg_layer *ly, const int16_t *x, int16_t *y,
                                              uint32_t *sat)
{
    const unsigned n = ly->n_in, m = ly->n_out, shift = ly->shift, n4 = n & ~3u;
    const int64_t round = (int64_t)1 << (shift - 1u);
    const int fast32 = ly->acc32 && shift == 32u;
    int16x2_t xp[FBG_MAX_WIDTH / 2];
    uint32_t clamped = 0u;
    unsigned j, r = 0;
    repair8(x, n4, xp);
    for (; r + 2u <= m; r += 2u) {
        const int8_t *w0 = ly->w8 + (size_t)r * n, *w1 = w0 + n;
        const int16x2_t *pp = xp;
        int64_t a0 = ly->bias[r], a1 = ly->bias[r + 1u];
        for (j = 0; j < n4; j += 4u, pp += 2) {
            int8x4_t v0 = ld4_8(w0 + j), v1 = ld4_8(w1 + j);
            a0 = __smlald(__sxtb16(v0), pp[0], a0);
            a1 = __smlald(__sxtb16(v1), pp[0], a1);
            a0 = __smlald(__sxtb16((int8x4_t)ror8((uint32_t)v0)), pp[1], a0);
            a1 = __smlald(__sxtb16((int8x4_t)ror8((uint32_t)v1)), pp[1], a1);
        }
        for (; j < n; ++j) {
            a0 += (int32_t)w0[j] * (int32_t)x[j];
            a1 += (int32_t)w1[j] * (int32_t)x[j];
        }
        if (fast32) {
            /* An int32 layer: a0, a1 fit int32 (the proof), so SMMULR is the rounding rule. */
            y[r] = (int16_t)relu_usat15(smmulr((int32_t)a0, ly->mult[r]), &clamped);
            y[r + 1u] = (int16_t)relu_usat15(smmulr((int32_t)a1, ly->mult[r + 1u]), &clamped);
        } else {
            y[r] = (int16_t)relu_sat16(a0, ly->mult[r], shift, round, &clamped);
            y[r + 1u] = (int16_t)relu_sat16(a1, ly->mult[r + 1u], shift, round, &clamped);
        }
    }
    if (r < m)
        y[r] = (int16_t)relu_sat16(dot8(ly->w8 + (size_t)r * n, x, xp, n, ly->bias[r]),
                                   ly->mult[r], shift, round, &clamped);
    if (clamped)
        *sat = 1u;
}

/* w_bits, shift, acc32 of an fbg_layer read as one little-endian word (bytes 4..6): the layers
 * the pair kernels take (16-bit weights, shift 32, int32 accumulators). */
#define FBG_DSP_PAIRS_KIND (16u | (32u << 8) | (1u << 16))
typedef char fbg_dsp_kind_layout[(offsetof(fbg_layer, w_bits) == 4 && offsetof(fbg_layer, shift) == 5 &&
                                  offsetof(fbg_layer, acc32) == 6 && offsetof(fbg_layer, n_in) == 0) ? 1 : -1];

/* Whether the pair kernels take this layer: an int32 layer at shift 32 (what the exporter
 * writes) with n even, at least two rows, the weights and y word-aligned and, beyond
 * FBG_DSP_FIRST_MAX_IN inputs (read with LDM), x too - as generated models, blobs and the activation buffers of fbg_state
 * give. The fields are read two words at a time: this runs for every layer of every step. */
static inline int pairs32_ok(const fbg_layer *ly, const int16_t *x, const int16_t *y,
                             unsigned *n_out)
{
    uint32_t dims, kind;
    unsigned n;
    memcpy(&dims, &ly->n_in, sizeof dims);
    memcpy(&kind, &ly->w_bits, sizeof kind);
    n = dims & 0xFFFFu;
    *n_out = dims >> 16;
    return (kind & 0xFFFFFFu) == FBG_DSP_PAIRS_KIND && *n_out >= 2u && n <= 8u * FBG_DSP_BODY_BLOCKS &&
           ((((uintptr_t)ly->w16 | (uintptr_t)y | (n > FBG_DSP_FIRST_MAX_IN ? (uintptr_t)x : 0u)) & 3u) | (n & 1u)) == 0u;
}

/* Every layer the even-height fast path of fbg_dsp_hidden does not take. */
static __attribute__((noinline)) void hidden_other(const fbg_layer *ly, const int16_t *x, int16_t *y,
                                                   uint32_t *sat)
{
    unsigned m;
    if (pairs32_ok(ly, x, y, &m)) { /* an odd number of rows: the last one in C */
        run_pairs32(ly, x, y, ly->n_in, sat);
        hidden16_32(ly, x, y, m - 1u, sat);
    }
#if FBG_DSP_ASM
    else if (ly->w_bits == 8u && ly->acc32 && ly->shift == 32u && (m = ly->n_out) >= 2u &&
             (ly->n_in & 1u) == 0u && ((uintptr_t)y & 3u) == 0u &&
             (ly->n_in <= 8u || ((uintptr_t)x & 3u) == 0u)) {
        /* int8 weights (int32 by construction), shift 32: the pairs in first2b32_asm (n <= 8)
         * or rows2b32_asm, the last row of an odd layer with dot8_32. */
        if (ly->n_in <= 8u)
            first2b32_asm(ly, x, y, sat);
        else
            rows2b32_asm(ly, x, y, sat);
        if (m & 1u) {
            uint32_t clamped = 0u;
            y[m - 1u] = (int16_t)relu_usat15(
                smmulr(dot8_32(ly->w8 + (size_t)(m - 1u) * ly->n_in, x, ly->n_in,
                               (int32_t)ly->bias[m - 1u]), ly->mult[m - 1u]), &clamped);
            *sat |= clamped != 0u;
        }
    }
#endif
    else if (ly->w_bits == 16u && ly->acc32)
        hidden16_32(ly, x, y, 0u, sat);
    else if (ly->w_bits == 16u)
        hidden16(ly, x, y, sat);
    else
        hidden8(ly, x, y, sat);
}

static inline void hidden_layer(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    unsigned m;
    if (pairs32_ok(ly, x, y, &m) && (m & 1u) == 0u)
        run_pairs32(ly, x, y, ly->n_in, sat);
    else
        hidden_other(ly, x, y, sat);
}

void fbg_dsp_hidden(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    hidden_layer(ly, x, y, sat);
}

/* Rows of FBG_MAX_WIDTH int16 keep act[1] word-aligned when act[0] is. */
typedef char fbg_dsp_act_rows_aligned[(FBG_MAX_WIDTH % 2) == 0 ? 1 : -1];

const int16_t *fbg_dsp_run_hidden(const fbg_net *net, const int16_t *x,
                                  int16_t (*act)[FBG_MAX_WIDTH], uint32_t *sat)
{
    /* The layer test of fbg_dsp_hidden, less what holds by construction here: y and every
     * input after the first are rows of act (word-aligned), n_in <= FBG_MAX_WIDTH <= the
     * unrolled body and n_out >= 1 (fbg_model_check), so an even n_out is at least 2. */
    const fbg_layer *ly = net->layers, *end = ly + net->n_layers - 1u;
    uintptr_t x_odd = (uintptr_t)x & 3u;
    unsigned buf = 0u;
    for (; ly != end; ++ly, buf ^= 1u) {
        int16_t *const y = act[buf];
        uint32_t dims, kind;
        unsigned n;
        memcpy(&dims, &ly->n_in, sizeof dims);  /* n_in, n_out */
        memcpy(&kind, &ly->w_bits, sizeof kind); /* w_bits, shift, acc32 */
        n = dims & 0xFFFFu;
        /* (kind ^ FBG_DSP_PAIRS_KIND) << 8 is zero iff the low three bytes match */
        if ((((kind ^ FBG_DSP_PAIRS_KIND) << 8) | (dims & 0x10001u) | ((uintptr_t)ly->w16 & 3u)) == 0u &&
            (n <= FBG_DSP_FIRST_MAX_IN || x_odd == 0u))
            run_pairs32(ly, x, y, n, sat);
        else
            hidden_other(ly, x, y, sat);
        x = y;
        x_odd = 0u;
    }
    return x;
}

/* Separate (noinline) so that the int16 path does not carry its 256-byte buffer on the stack. */
static __attribute__((noinline)) int64_t row_acc8(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    const unsigned n = ly->n_in;
    int16x2_t xp[FBG_MAX_WIDTH / 2];
    repair8(x, n & ~3u, xp);
    return dot8(ly->w8 + (size_t)r * n, x, xp, n, ly->bias[r]);
}

/* Row r's accumulator of an int32 layer (ly->acc32: every partial sum fits int32). */
static inline int32_t row_acc32(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    const unsigned n = ly->n_in;
    if (ly->w_bits == 16u) {
        const int16_t *w = ly->w16 + (size_t)r * n;
#if FBG_DSP_ASM
        if (((((uintptr_t)w | (uintptr_t)x) & 3u) | (n & 1u)) == 0u)
            return dot32_asm(w, x, n, (int32_t)ly->bias[r]);
#endif
        return dot16_32(w, x, n, (int32_t)ly->bias[r]);
    }
    return dot8_32(ly->w8 + (size_t)r * n, x, n, (int32_t)ly->bias[r]);
}

static inline int64_t row_acc(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    if (ly->acc32)
        return row_acc32(ly, r, x);
    if (ly->w_bits == 16u)
        return fbg_dsp_dot16(ly->w16 + (size_t)r * ly->n_in, x, ly->n_in, ly->bias[r]);
    return row_acc8(ly, r, x);
}

int64_t fbg_dsp_row_acc(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    return row_acc(ly, r, x);
}

void fbg_dsp_output_accs(const fbg_layer *ly, const int16_t *x, int64_t *acc)
{
    unsigned r;
#if FBG_DSP_ASM
    const unsigned n = ly->n_in;
    if (ly->acc32 && ly->w_bits == 16u &&
        ((((uintptr_t)ly->w16 | (uintptr_t)x) & 3u) | (n & 1u)) == 0u) {
        /* The test of row_acc32 once for the layer: with n even every row is word-aligned. */
        const int16_t *w = ly->w16;
        for (r = 0; r < ly->n_out; ++r, w += n)
            acc[r] = dot32_asm(w, x, n, (int32_t)ly->bias[r]);
        return;
    }
#endif
    for (r = 0; r < ly->n_out; ++r)
        acc[r] = row_acc(ly, r, x);
}

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
typedef int fbg_dsp_unused;
#endif
