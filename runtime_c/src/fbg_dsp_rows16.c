/*
 * fbg_dsp_rows16.c - int16-weight layers with int64 accumulators on the Cortex-M4 DSP extension:
 * three rows per pass (rows3_asm, rows3d_asm), the first layers with inputs in registers
 * (first_asm), their ACLE C versions, and the per-row SMLALD dot product.
 * See fbg_dsp_kernels.h for why the results equal the portable C bit for bit.
 */
#include "fbg_dsp_kernels.h"

#if FBG_USE_DSP
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
#endif /* !FBG_DSP_ASM */

#if FBG_DSP_ASM
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
__attribute__((naked, noinline)) void fbg_dsp_rows3_asm(fbg_dsp_job *job)
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
__attribute__((naked, noinline)) void fbg_dsp_rows3d_asm(fbg_dsp_job *job)
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

/* first_asm: a row's int64 accumulator r9:r8 from its bias (one LDRD). */
#define FBG_FIRST_ROW_BIAS                       \
        "ldrd    r8, r9, [r1], #8\n\t"

/* first_asm: one pair of weights (LDR) against the input pair in register X, into r9:r8. */
#define FBG_FIRST_PAIR(x)                        \
        "ldr     r10, [r0], #4\n\t"              \
        "smlald  r8, r9, r10, " x "\n\t"

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
__attribute__((naked, noinline)) void fbg_dsp_first_asm(fbg_dsp_job *job)
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
        FBG_FIRST_ROW_BIAS
        FBG_FIRST_PAIR("r4")
        FBG_FIRST_ROW_OUT
        "bne     2b\n\t"
        "b       9f\n\t"
        "4:\n\t"
        FBG_FIRST_ROW_BIAS
        FBG_FIRST_PAIR("r4")
        FBG_FIRST_PAIR("r5")
        FBG_FIRST_ROW_OUT
        "bne     4b\n\t"
        "b       9f\n\t"
        "6:\n\t"
        FBG_FIRST_ROW_BIAS
        FBG_FIRST_PAIR("r4")
        FBG_FIRST_PAIR("r5")
        FBG_FIRST_PAIR("r6")
        FBG_FIRST_ROW_OUT
        "bne     6b\n\t"
        "b       9f\n\t"
        "9:\n\t"
        "ldr     r0, [sp, #8]\n\t"
        "add     sp, sp, #16\n\t"
        FBG_Q_RESTORE("r0")
        "bx      lr\n\t");
}

#undef FBG_FIRST_ROW_OUT
#undef FBG_FIRST_PAIR
#undef FBG_FIRST_ROW_BIAS
#undef FBG_ROWS3_OUT
#undef FBG_ROWS3_REQUANT
#undef FBG_ROWS3_QUAD
#undef FBG_ROWS3_PAIR
#undef FBG_ROWS3_PAIR_LOADS
#endif /* FBG_DSP_ASM */

/* The job of a layer with shift >= 32 from its first row on: input x, output y, GROUPS the
 * groups of three rows (first_asm: the rows), round = 2^(shift-1). */
static inline void job_start(fbg_dsp_job *job, const fbg_layer *ly, const int16_t *x, int16_t *y,
                             uint32_t groups, int64_t round)
{
    job->w = ly->w16;
    job->x = x;
    job->bias = ly->bias;
    job->mult = ly->mult;
    job->y = y;
    job->n = ly->n_in;
    job->groups = groups;
    job->round_lo = (uint32_t)round;
    job->round_hi = (uint32_t)(round >> 32);
    job->s32 = ly->shift - 32u;
    job->clamped = 0u;
}

/* The kernels hidden16 and hidden16_32 call: the assembly (FBG_DSP_ASM) or its ACLE C. */
static void run_rows3(fbg_dsp_job *job, int aligned)
{
#if FBG_DSP_ASM
    if (aligned)
        fbg_dsp_rows3d_asm(job);
    else
        fbg_dsp_rows3_asm(job);
#else
    (void)aligned;
    rows3_c(job);
#endif
}

static void run_first(fbg_dsp_job *job)
{
#if FBG_DSP_ASM
    fbg_dsp_first_asm(job);
#else
    first_c(job);
#endif
}

void fbg_dsp_hidden16(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    const unsigned n = ly->n_in, m = ly->n_out, shift = ly->shift;
    const int16_t *w = ly->w16;
    const int64_t round = (int64_t)1 << (shift - 1u);
    uint32_t clamped = 0u;
    unsigned r = 0;

    if (shift >= 32u && (n == 2u || n == 4u || n == 6u)) {
        fbg_dsp_job job;
        job_start(&job, ly, x, y, m, round);
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
        job_start(&job, ly, x, y, m / 3u, round);
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

#else
/* ISO C forbids an empty translation unit: the portable build compiles this file to nothing. */
typedef int fbg_dsp_rows16_unused;
#endif
