/*
 * fbg_dsp_rows32.c - int16-weight layers with int32 accumulators (fbg_layer.acc32) on the Cortex-M4
 * DSP extension: two rows per pass with SMLAD and SMMULR (rows2d32_asm, first2d32_asm, their
 * ACLE C version), the output rows (dot32_asm) and the rows the pair kernels do not take.
 * See fbg_dsp_kernels.h for why the results equal the portable C bit for bit.
 */
#include "fbg_dsp_kernels.h"

#if FBG_USE_DSP
#if !FBG_DSP_ASM
/* Two int32 rows per pass, SMLAD and SMMULR (rows2d32_asm, first2d32_asm): every pair of
 * rows of the layer (n_out & ~1 rows), n even, y word-aligned; *sat |= 1 iff a row clamped. */
__attribute__((noinline)) void fbg_dsp_rows2_32_c(const fbg_layer *ly, const int16_t *x,
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
/* rows2d32_asm's entry: the frame ([sp] bias, [4] mult, [8] out, [12] out end after the last
 * pair, [16] row bytes, [20] x, [24] where a pass starts (tail or body entry, Thumb bit),
 * [28] sat; written with one STM), the first pair's biases and the jump into its first pass. */
#define FBG_ROWS2D32_FRAME                       \
        "sub     sp, sp, #32\n\t"                \
        "mov     r10, r3\n\t"                    \
        "ldr     r11, [r0]\n\t"                  \
        "ldrd    r3, r4, [r0, #16]\n\t"          \
        "ldr     r0, [r0, #8]\n\t"               \
        "mov     r5, r2\n\t"                     \
        "lsr     r6, r11, #16\n\t"               \
        "bic     r6, r6, #1\n\t"                 \
        "add     r6, r2, r6, lsl #1\n\t"         \
        "uxth    r11, r11\n\t"                   \
        "lsl     r7, r11, #1\n\t"                \
        "mov     r8, r1\n\t"                     \
        "mov     lr, r1\n\t"                     \
        "add     r1, r0, r7\n\t"                 \
        "adr.w   r2, 8f\n\t"                     \
        "lsr     r12, r11, #3\n\t"               \
        "mov     r9, #44\n\t"                    \
        "mls     r2, r12, r9, r2\n\t"            \
        "orr     r2, r2, #1\n\t"                 \
        "mov     r9, r2\n\t"                     \
        "ands    r12, r11, #6\n\t"               \
        "beq     1f\n\t"                         \
        "adr.w   r9, 72f\n\t"                    \
        "cmp     r12, #2\n\t"                    \
        "beq     0f\n\t"                         \
        "adr.w   r9, 74f\n\t"                    \
        "cmp     r12, #4\n\t"                    \
        "beq     0f\n\t"                         \
        "adr.w   r9, 76f\n\t"                    \
        "0:\n\t"                                 \
        "orr     r9, r9, #1\n\t"                 \
        "1:\n\t"                                 \
        "add     r3, r3, #16\n\t"                \
        "stm     sp, {r3-r10}\n\t"               \
        "ldmdb   r3, {r9-r12}\n\t"               \
        "ldr     pc, [sp, #24]\n\t"

/* rows2d32_asm's tails: 2, 4 or 6 inputs, then into the body (r2). */
#define FBG_ROWS2D32_TAILS                       \
        "72:\n\t"                                \
        "ldr     r3, [lr], #4\n\t"               \
        "ldr     r7, [r0], #4\n\t"               \
        "smlad   r9, r7, r3, r9\n\t"             \
        "ldr     r7, [r1], #4\n\t"               \
        "smlad   r11, r7, r3, r11\n\t"           \
        "bx      r2\n\t"                         \
        "74:\n\t"                                \
        "ldrd    r3, r4, [lr], #8\n\t"           \
        "ldrd    r7, r8, [r0], #8\n\t"           \
        "smlad   r9, r7, r3, r9\n\t"             \
        "smlad   r9, r8, r4, r9\n\t"             \
        "ldrd    r7, r8, [r1], #8\n\t"           \
        "smlad   r11, r7, r3, r11\n\t"           \
        "smlad   r11, r8, r4, r11\n\t"           \
        "bx      r2\n\t"                         \
        "76:\n\t"                                \
        "ldmia.w lr!, {r3-r5}\n\t"               \
        "ldmia.w r0!, {r7, r8, r10}\n\t"         \
        "smlad   r9, r7, r3, r9\n\t"             \
        "smlad   r9, r8, r4, r9\n\t"             \
        "smlad   r9, r10, r5, r9\n\t"            \
        "ldmia.w r1!, {r7, r8, r10}\n\t"         \
        "smlad   r11, r7, r3, r11\n\t"           \
        "smlad   r11, r8, r4, r11\n\t"           \
        "smlad   r11, r10, r5, r11\n\t"          \
        "bx      r2\n\t"

/* rows2d32_asm's body: 16 blocks of 8 inputs, 44 bytes each (every instruction 32-bit). */
#define FBG_ROWS2D32_BODY                        \
        ".rept   16\n\t"                         \
        "ldmia.w lr!, {r3-r6}\n\t"               \
        "ldmia.w r0!, {r7, r8, r10, r12}\n\t"    \
        "smlad   r9, r7, r3, r9\n\t"             \
        "smlad   r9, r8, r4, r9\n\t"             \
        "smlad   r9, r10, r5, r9\n\t"            \
        "smlad   r9, r12, r6, r9\n\t"            \
        "ldmia.w r1!, {r7, r8, r10, r12}\n\t"    \
        "smlad   r11, r7, r3, r11\n\t"           \
        "smlad   r11, r8, r4, r11\n\t"           \
        "smlad   r11, r10, r5, r11\n\t"          \
        "smlad   r11, r12, r6, r11\n\t"          \
        ".endr\n\t"

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
__attribute__((naked, noinline)) void fbg_dsp_rows2d32_asm(const fbg_layer *ly, const int16_t *x,
                                                          int16_t *y, uint32_t *sat)
{
    FBG_DSP_PAIR_ARGS_USED;
    __asm__ volatile(
        FBG_Q_CLEAR_PUSH
        FBG_ROWS2D32_FRAME
        FBG_ROWS2D32_TAILS
        /* the body: 16 blocks of 8 inputs, 44 bytes each (every instruction 32-bit) */
        FBG_ROWS2D32_BODY
        FBG_ROWS2_PASS_END
        FBG_PAIR_KERNEL_EXIT("32"));
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

/* first2d32_asm's entry: the frame ([sp] the output end, [4] sat), the inputs into r4-r9 as
 * far as n needs them, and the jump to the loop for n (entering the two-pair loops of n = 6,
 * 8 and 10 at the pair that leaves an even number of pairs). */
#define FBG_FIRST2D32_ENTRY                      \
        "sub     sp, sp, #8\n\t"                 \
        "str     r3, [sp, #4]\n\t"               \
        "mov     r3, r2\n\t"                     \
        "ldrh    r9, [r0, #2]\n\t"               \
        "bic     r7, r9, #1\n\t"                 \
        "add     r7, r3, r7, lsl #1\n\t"         \
        "str     r7, [sp]\n\t"                   \
        "mov     r10, r1\n\t"                    \
        "ldr     r1, [r0, #16]\n\t"              \
        "ldr     r2, [r0, #20]\n\t"              \
        "ldrh    r12, [r0]\n\t"                  \
        "ldr     r0, [r0, #8]\n\t"               \
        "ldr     r4, [r10]\n\t"                  \
        "cmp     r12, #4\n\t"                    \
        "blo     2f\n\t"                         \
        "ldr     r5, [r10, #4]\n\t"              \
        "beq     4f\n\t"                         \
        "ldr     r6, [r10, #8]\n\t"              \
        "cmp     r12, #6\n\t"                    \
        "bne     7f\n\t"                         \
        "tst     r9, #2\n\t"                     \
        "bne     61f\n\t"                        \
        "b       6f\n\t"                         \
        "7:\n\t"                                 \
        "ldr     r7, [r10, #12]\n\t"             \
        "ubfx    r11, r9, #1, #2\n\t"            \
        "cmp     r12, #8\n\t"                    \
        "bne     10f\n\t"                        \
        "cmp     r11, #2\n\t"                    \
        "beq     83f\n\t"                        \
        "bhi     82f\n\t"                        \
        "cmp     r11, #1\n\t"                    \
        "beq     84f\n\t"                        \
        "b       8f\n\t"

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
__attribute__((naked, noinline)) void fbg_dsp_first2d32_asm(const fbg_layer *ly, const int16_t *x,
                                                           int16_t *y, uint32_t *sat)
{
    FBG_DSP_PAIR_ARGS_USED;
    __asm__ volatile(
        FBG_Q_CLEAR_PUSH
        FBG_FIRST2D32_ENTRY
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
        FBG_PAIR_KERNEL_EXIT("8"));
}
#undef FBG_PAIR12
#undef FBG_PAIR10
#undef FBG_PAIR8
#undef FBG_PAIR6
#undef FBG_PAIR_OUT

/* dot32_asm: acc + sum_j w[j] * x[j] for one row of an int32 layer (the output layers' rows,
 * fbg_dsp_row_acc), w and x word-aligned, n even: 8 inputs per LDM pair and four SMLAD
 * (8 instructions per 8 MACs with the loop test), then the n % 8 inputs two at a time. */
__attribute__((naked, noinline)) int32_t fbg_dsp_dot32_asm(const int16_t *w, const int16_t *x,
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
#endif /* FBG_DSP_ASM */

/* An int32 int16-weight hidden layer that the pair kernels do not take (see
 * fbg_dsp_hidden): SMLAD rows with C requantisation, any shift and alignment; from row r0 on. */
void fbg_dsp_hidden16_32(const fbg_layer *ly, const int16_t *x, int16_t *y, unsigned r0,
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

#else
/* ISO C forbids an empty translation unit: the portable build compiles this file to nothing. */
typedef int fbg_dsp_rows32_unused;
#endif
