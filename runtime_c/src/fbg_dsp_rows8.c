/*
 * fbg_dsp_rows8.c - int8-weight layers on the Cortex-M4 DSP extension: SXTB16 widens four weights
 * into two int16 pairs; two rows per pass in assembly for int32 layers at shift 32
 * (rows2b32_asm, first2b32_asm), in C with SMLALD otherwise (hidden8), and single rows.
 * See fbg_dsp_kernels.h for why the results equal the portable C bit for bit.
 */
#include "fbg_dsp_kernels.h"

#if FBG_USE_DSP
#if FBG_DSP_ASM
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

/* rows2b32_asm: x (word-aligned) re-paired into xp at sp + 40: LDM of 8 inputs, PKHBT/PKHTB, STM. */
#define FBG_ROWS2B32_REPAIR_X                    \
        "add     r12, sp, #40\n\t"               \
        "bic     r7, r8, #7\n\t"                 \
        "add     r7, r1, r7, lsl #1\n\t"         \
        "cmp     r1, r7\n\t"                     \
        "beq     2f\n\t"                         \
        "1:\n\t"                                 \
        "ldmia   r1!, {r3-r6}\n\t"               \
        "pkhbt   r9, r3, r4, lsl #16\n\t"        \
        "pkhtb   r10, r4, r3, asr #16\n\t"       \
        "pkhbt   r11, r5, r6, lsl #16\n\t"       \
        "pkhtb   lr, r6, r5, asr #16\n\t"        \
        "stmia   r12!, {r9, r10, r11, lr}\n\t"   \
        "cmp     r1, r7\n\t"                     \
        "bne     1b\n\t"                         \
        "2:\n\t"                                 \
        "tst     r8, #4\n\t"                     \
        "beq     3f\n\t"                         \
        "ldmia   r1!, {r3, r4}\n\t"              \
        "pkhbt   r9, r3, r4, lsl #16\n\t"        \
        "pkhtb   r10, r4, r3, asr #16\n\t"       \
        "stmia   r12!, {r9, r10}\n\t"            \
        "3:\n\t"                                 \
        "tst     r8, #2\n\t"                     \
        "itt     ne\n\t"                         \
        "ldrne   r3, [r1]\n\t"                   \
        "strne   r3, [r12]\n\t"

/* rows2b32_asm's frame after the re-pairing, the first pair's biases, the tail's address ([32]:
 * none, 2, 4 or 4 + 2 inputs) and the loop's entry ([24]: two 8-input groups per loop test,
 * entered at the second for an odd count), then the jump into the first pass. */
#define FBG_ROWS2B32_FRAME                                                               \
        "add     r1, sp, #40\n\t"                                                        \
        "ldrh    r6, [r0, #2]\n\t"                                                       \
        "str     r8, [sp, #16]\n\t"                                                      \
        "str     r1, [sp, #20]\n\t"                                                      \
        "mov     lr, r1\n\t"                                                             \
        "str     r2, [sp, #8]\n\t"                                                       \
        "bic     r6, r6, #1\n\t"                                                         \
        "add     r6, r2, r6, lsl #1\n\t"                                                 \
        "str     r6, [sp, #12]\n\t"                                                      \
        "bic     r7, r8, #7\n\t"                                                         \
        "add     r2, r1, r7, lsl #1\n\t"                                                 \
        "ldr     r3, [r0, #16]\n\t"                                                      \
        "ldmia   r3!, {r9-r12}\n\t"                                                      \
        "str     r3, [sp]\n\t"                                                           \
        "ldr     r3, [r0, #20]\n\t"                                                      \
        "str     r3, [sp, #4]\n\t"                                                       \
        "ldr     r0, [r0, #12]\n\t"                                                      \
        "add     r1, r0, r8\n\t"                                                         \
        /* the tail: none, 2, 4 or 4 + 2 inputs */                                       \
        "and     r7, r8, #6\n\t"                                                         \
        "adr.w   r3, 8f\n\t"                                                             \
        "cmp     r7, #2\n\t"                                                             \
        "it      eq\n\t"                                                                 \
        "adreq.w r3, 72f\n\t"                                                            \
        "cmp     r7, #4\n\t"                                                             \
        "it      eq\n\t"                                                                 \
        "adreq.w r3, 74f\n\t"                                                            \
        "cmp     r7, #6\n\t"                                                             \
        "it      eq\n\t"                                                                 \
        "adreq.w r3, 76f\n\t"                                                            \
        "orr     r3, r3, #1\n\t"                                                         \
        "str     r3, [sp, #32]\n\t"                                                      \
        /* 8-input groups: two per loop test, entered at the second for an odd count */  \
        "cmp     r8, #8\n\t"                                                             \
        "blo     0f\n\t"                                                                 \
        "tst     r8, #8\n\t"                                                             \
        "ite     ne\n\t"                                                                 \
        "adrne.w r3, 10f\n\t"                                                            \
        "adreq.w r3, 1f\n\t"                                                             \
        "orr     r3, r3, #1\n\t"                                                         \
        "0:\n\t"                                                                         \
        "str     r3, [sp, #24]\n\t"                                                      \
        "bx      r3\n\t"

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
__attribute__((naked, noinline)) void fbg_dsp_rows2b32_asm(const fbg_layer *ly, const int16_t *x,
                                                          int16_t *y, uint32_t *sat)
{
    FBG_DSP_PAIR_ARGS_USED;
    __asm__ volatile(
        FBG_Q_CLEAR_PUSH
        /* frame: [sp] bias, [4] mult, [8] out, [12] out end, [16] row bytes (n), [20] xp,
         * [24] where a pass starts (loop or tail), [28] sat, [32] the tail after the loop;
         * [40..] xp (FBG_MAX_WIDTH / 2 words); r2 = end of the 8-input groups of xp in the
         * MAC loop */
        "sub     sp, sp, #296\n\t"
        "str     r3, [sp, #28]\n\t"
        "ldrh    r8, [r0]\n\t"
        FBG_ROWS2B32_REPAIR_X
        FBG_ROWS2B32_FRAME
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
        FBG_PAIR_KERNEL_EXIT("296"));
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

/* first2b32_asm's entry: sat kept on the stack, Q cleared, the output end in lr, the inputs
 * re-paired into r4-r7 as far as n needs them, and the jump to the loop for n. */
#define FBG_FIRST2B32_ENTRY                      \
        "push    {r3-r11, lr}\n\t"               \
        "mov     r12, #0\n\t"                    \
        "msr     APSR_nzcvq, r12\n\t"            \
        "mov     r3, r2\n\t"                     \
        "ldrh    r9, [r0, #2]\n\t"               \
        "bic     lr, r9, #1\n\t"                 \
        "add     lr, r3, lr, lsl #1\n\t"         \
        "ldr     r2, [r0, #20]\n\t"              \
        "ldrh    r12, [r0]\n\t"                  \
        "mov     r10, r1\n\t"                    \
        "ldr     r1, [r0, #16]\n\t"              \
        "ldr     r0, [r0, #12]\n\t"              \
        "ldr     r4, [r10]\n\t"                  \
        "cmp     r12, #4\n\t"                    \
        "blo     2f\n\t"                         \
        "ldr     r5, [r10, #4]\n\t"              \
        "pkhbt   r8, r4, r5, lsl #16\n\t"        \
        "pkhtb   r5, r5, r4, asr #16\n\t"        \
        "mov     r4, r8\n\t"                     \
        "beq     4f\n\t"                         \
        "ldr     r6, [r10, #8]\n\t"              \
        "cmp     r12, #6\n\t"                    \
        "beq     6f\n\t"                         \
        "ldr     r7, [r10, #12]\n\t"             \
        "pkhbt   r8, r6, r7, lsl #16\n\t"        \
        "pkhtb   r7, r7, r6, asr #16\n\t"        \
        "mov     r6, r8\n\t"                     \
        "b       8f\n\t"

/* first2b32_asm: an int8-weight int32 first layer (shift 32) of n = 2, 4, 6 or 8 inputs, two
 * rows per pass, the inputs re-paired once into registers (r4-r7: (x0, x2), (x1, x3) per four,
 * the natural pair for the last two when n % 4 == 2; LDR, which may be unaligned, and
 * PKHBT/PKHTB); the rows are adjacent, one pointer walks both (single LDR/LDRSB, any
 * alignment). Per pair: LDM of the biases, per row one LDR + 2 SXTB16 + 2 SMLAD per four
 * weights and 2 LDRSB + SMLABB + SMLATB per two, the requantisation of first2d32_asm and the
 * loop test (output end in lr): 20, 22, 30 and 32 instructions for 4, 8, 12 and 16 MACs.
 * y word-aligned (the caller checks). */
__attribute__((naked, noinline)) void fbg_dsp_first2b32_asm(const fbg_layer *ly, const int16_t *x,
                                                           int16_t *y, uint32_t *sat)
{
    FBG_DSP_PAIR_ARGS_USED;
    __asm__ volatile(
        FBG_FIRST2B32_ENTRY
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
#undef ROWS2B32_TAIL4
#undef ROWS2B32_GROUP
#endif /* FBG_DSP_ASM */

/* One row of an int32 layer with int8 weights (the output layers' rows): no re-paired copy
 * of x; the two SXTB16 halves (w0, w2), (w1, w3) are re-packed into (w0, w1), (w2, w3) to meet
 * the inputs as they lie (two PKH per four weights). */
int32_t fbg_dsp_dot8_32(const int8_t *w, const int16_t *x, unsigned n, int32_t acc)
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
__attribute__((noinline)) void fbg_dsp_hidden8(const fbg_layer *ly, const int16_t *x, int16_t *y,
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

/* Separate (noinline) so that the int16 path does not carry its 256-byte buffer on the stack. */
__attribute__((noinline)) int64_t fbg_dsp_row_acc8(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    const unsigned n = ly->n_in;
    int16x2_t xp[FBG_MAX_WIDTH / 2];
    repair8(x, n & ~3u, xp);
    return dot8(ly->w8 + (size_t)r * n, x, xp, n, ly->bias[r]);
}

#else
/* ISO C forbids an empty translation unit: the portable build compiles this file to nothing. */
typedef int fbg_dsp_rows8_unused;
#endif
