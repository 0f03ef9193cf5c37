/*
 * fbg_dsp_kernels.h - what the Cortex-M4 DSP kernels (fbg_dsp*.c) share: the exact helpers,
 * the rows3 job, the assembly fragments of several kernels, and the kernels' declarations.
 *
 * Why the results are bit-identical to the portable C of the stages (fbg_stages.h):
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
#ifndef FBG_DSP_KERNELS_H
#define FBG_DSP_KERNELS_H

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

/* sat16(max(rshift_round(acc * mult, shift), 0)) of fbg_stage_nets.c; *clamped != 0 iff it clamped.
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

/* sat16(max(v, 0)) with the flag of fbg_stage_nets.c (USAT after the ReLU, as the assembly). */
static inline int32_t relu_usat15(int32_t v, uint32_t *clamped)
{
    int32_t y;
    v &= ~(v >> 31);
    y = __usat(v, 15);
    *clamped |= (uint32_t)(v - y);
    return y;
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

#if FBG_DSP_ASM
/* Assembly fragments that more than one kernel file pastes (string literals). */
/* The pair kernels' parameters (layer, input, output, flag), which their assembly reads from
 * r0-r3, as used for C. */
#define FBG_DSP_PAIR_ARGS_USED (void)ly, (void)x, (void)y, (void)sat

/* The pair kernels' exit after a frame of FRAME bytes: *sat |= Q, r4-r11 back, return. */
#define FBG_PAIR_KERNEL_EXIT(frame)              \
        "add     sp, sp, #" frame "\n\t"         \
        FBG_Q_READ                               \
        FBG_SAT_OR_Q                             \
        "pop     {r4-r11, pc}\n\t"

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
#endif /* FBG_DSP_ASM */

/* The kernels, one file per family: fbg_dsp_rows16.c (int16 weights, int64 sums),
 * fbg_dsp_rows32.c (int16 weights, int32 sums), fbg_dsp_rows8.c (int8 weights); the filter is
 * in fbg_dsp_fir.c and the choice of kernel per layer in fbg_dsp.c. Every layer kernel takes
 * the layer, its input and output and the saturation flag (*sat = 1 when a row clamped), except
 * the int64 three-row kernels, which take a job (above) built once per layer. */
#if FBG_DSP_ASM
void fbg_dsp_rows3_asm(fbg_dsp_job *job);
void fbg_dsp_rows3d_asm(fbg_dsp_job *job);
void fbg_dsp_first_asm(fbg_dsp_job *job);
void fbg_dsp_rows2d32_asm(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
void fbg_dsp_first2d32_asm(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
void fbg_dsp_rows2b32_asm(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
void fbg_dsp_first2b32_asm(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
int32_t fbg_dsp_dot32_asm(const int16_t *w, const int16_t *x, unsigned n, int32_t acc);
#else
void fbg_dsp_rows2_32_c(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
#endif
void fbg_dsp_hidden16(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
void fbg_dsp_hidden16_32(const fbg_layer *ly, const int16_t *x, int16_t *y, unsigned r0, uint32_t *sat);
void fbg_dsp_hidden8(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);
int32_t fbg_dsp_dot8_32(const int8_t *w, const int16_t *x, unsigned n, int32_t acc);
int64_t fbg_dsp_row_acc8(const fbg_layer *ly, unsigned r, const int16_t *x);

/* The pairs of rows of an int32 layer at shift 32: the first-layer kernel (inputs in
 * registers) for n <= FBG_DSP_FIRST_MAX_IN, else the unrolled one (x word-aligned); *sat |= 1
 * iff a row clamped. */
static inline void run_pairs32(const fbg_layer *ly, const int16_t *x, int16_t *y, unsigned n,
                               uint32_t *sat)
{
#if FBG_DSP_ASM
    if (n <= FBG_DSP_FIRST_MAX_IN)
        fbg_dsp_first2d32_asm(ly, x, y, sat);
    else
        fbg_dsp_rows2d32_asm(ly, x, y, sat);
#else
    (void)n;
    fbg_dsp_rows2_32_c(ly, x, y, sat);
#endif
}

/* acc + sum_j w[j] * x[j] with SMLAD (an int32 layer: no partial sum overflows). */
static inline int32_t dot16_32(const int16_t *w, const int16_t *x, unsigned n, int32_t acc)
{
    unsigned j = 0;
    for (; j + 2u <= n; j += 2u)
        acc = __smlad(ld2(w + j), ld2(x + j), acc);
    if (j < n)
        acc += (int32_t)w[j] * (int32_t)x[j];
    return acc;
}

#endif /* FBG_USE_DSP */

#endif /* FBG_DSP_KERNELS_H */
