/*
 * fbg_simd.h - host SIMD kernels of the fixed-point dense layers (not installed).
 *
 * x86-64: SSE2 (every x86-64 CPU has it) and AVX2 (chosen at run time when the CPU has it);
 * aarch64: NEON (every AArch64 CPU has it). Each kernel computes the int32 accumulators of
 * an acc32 layer, acc[r] = bias[r] + sum_j w[r][j] * x[j], with int16 or int8 weights, and
 * a hidden layer's outputs from them by the one rounding and saturation rule
 * (docs/fixed-point.md) on whole vectors of rows. Why the sums
 * are the portable C's bits in any summation order: docs/fixed-point.md, "Host SIMD
 * kernels". int64-accumulator layers run the portable C.
 *
 * This header has no intrinsics, so the stage files stay general-register translation units
 * (check-nofloat). FBG_HOST_SIMD=0 builds the portable C only.
 */
#ifndef FBG_SIMD_H
#define FBG_SIMD_H

#include "fbg_internal.h"

#ifndef FBG_HOST_SIMD
#if (defined(__x86_64__) || defined(__aarch64__)) && defined(__GNUC__) && \
    !(defined(FBG_USE_DSP) && FBG_USE_DSP)
#define FBG_HOST_SIMD 1
#else
#define FBG_HOST_SIMD 0
#endif
#endif

#if FBG_HOST_SIMD
#if !(defined(__x86_64__) || defined(__aarch64__)) || !defined(__GNUC__)
#error "FBG_HOST_SIMD=1 needs GCC or Clang on x86-64 or aarch64"
#endif

/* Inputs are copied into a zero-padded buffer of this many int16 beyond FBG_MAX_WIDTH, so a
 * kernel reads whole vectors of x (the widest vector holds 16 int16). */
#define FBG_SIMD_XPAD 16u

/* The kernel fbg_init stores for a requested FBG_OPT_KERNEL_* value: AUTO becomes the best
 * kernel this CPU runs, any other value itself if this CPU runs it; 0 if it cannot run. The
 * CPU is asked once (the answer is cached; asking again gives the same answer). */
uint32_t fbg_simd_resolve(uint32_t requested);

/* acc[r] = bias[r] + sum_j w[r][j] * x[j] for every row of an acc32 layer (ly->acc32 == 1),
 * with a resolved kernel other than FBG_OPT_KERNEL_PORTABLE. x has ly->n_in entries. */
void fbg_simd_acc32(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int32_t *acc);

/* A hidden acc32 layer: y[r] = sat16(max(rshift_round(acc[r] * mult[r], shift), 0)) with
 * acc as above; *sat = 1 if any row clamped at 32767 (the rule of fbg_stage_nets.c). */
void fbg_simd_hidden(uint32_t kernel, const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);

/* ---- x86-64 only: packed weights (fbg_pack; docs/runtime.md, "Packed weights") and the
 * AVX2 front stages ---- */
#if defined(__x86_64__)
#define FBG_SIMD_X86 1
#else
#define FBG_SIMD_X86 0
#endif

#if FBG_SIMD_X86
/*
 * A packed buffer starts with this header; net_off[n] is the byte offset from the header of
 * net n's packed layers (one block per layer, in order, back to back), 0 for a net that is
 * not packed: one with an int64-accumulator layer, which runs layer by layer as without
 * packing. */
typedef struct {
    uint32_t magic;               /* FBG_PACK_MAGIC once packed */
    uint32_t kernel;              /* the FBG_OPT_KERNEL_* value it was packed for */
    const fbg_model *model;       /* the model it was packed from */
    size_t bytes;                 /* the whole buffer as fbg_simd_pack_bytes counted it */
    uint32_t net_off[FBG_N_NETS];
} fbg_pack_header;

#define FBG_PACK_MAGIC 0x4B504246u /* "FBPK" */

/* Bytes of the packed form of a (checked) model for a resolved kernel; 0 if the kernel has
 * no packed form. */
size_t fbg_simd_pack_bytes(uint32_t kernel, const fbg_model *m);

/* Write the packed form into buf (fbg_simd_pack_bytes(kernel, m) bytes, FBG_PACK_ALIGN
 * aligned); the header last, so a buffer is marked packed only when it is. */
void fbg_simd_pack(uint32_t kernel, const fbg_model *m, void *buf);

/* Every layer of net n (n_layers of them) from a buffer packed for this kernel, in one call:
 * the hidden layers
 * through act[0], act[1], ... (each written up to its n_out rounded up to the kernel's row
 * group, 8 for AVX2 and 4 for SSE2, the rows past n_out 0; FBG_MAX_WIDTH, a multiple of 8,
 * holds that), then acc[r] = bias[r] + sum_j w[r][j] * x[j] of the output layer's rows;
 * *sat = 1 if a hidden row clamped (the same outputs and flag as the row kernels). Returns 0,
 * doing nothing, if the net is not packed. */
int fbg_simd_net_packed(uint32_t kernel, const void *packed, unsigned n, unsigned n_layers,
                        const int16_t *x, int16_t (*act)[FBG_MAX_WIDTH], int64_t *acc, uint32_t *sat);

/* The AVX2 variants of fbg_step's front, filter and memory stages (fbg_front_stage,
 * fbg_filter_stage and fbg_memory_stage of fbg_stages.h, whose portable references they equal
 * in every value, state and flag): called only for a state whose kernel is FBG_OPT_KERNEL_AVX2, so only on a CPU
 * that runs AVX2.
 * fbg_avx2_front: the fault rule on wl_fm (its states in s updated as fbg_fault_check updates
 * them; SENSOR_FAULT added to *status and last_comp into the ring at s->pos for a faulty
 * sample); for a clean one the tare difference, the temperature reference's average
 * (fbg_ref_update, the state's ref_acc) and the temperature compensation into the ring at
 * s->pos.
 * fbg_avx2_filter: the causal FIR from s->pos, sum_k taps[k] * hist[(pos - k) mod n_taps][c]
 * exactly in int64 (the same integers in another order), its filtered shift into
 * s->last_comp, in[c] = its standardised value;
 * returns 1 when the load proxy rshift_round(sum_c filt_c * load_coeff[c], load_shift) exceeds
 * load_max_mN.
 * fbg_avx2_memory: from z = in[0..3], the location averages (s->loc, loc[c]) when the model
 * has them, the load signal's states (s->ema, s->play, s->mem_primed) and features (in[4 ..]).
 * Each sets *sat = 1 where a clamp happened. */
void fbg_avx2_front(fbg_state *s, const int32_t *wl_fm, uint32_t *status, uint32_t *sat);
int fbg_avx2_filter(fbg_state *s, int16_t *in, uint32_t *sat);
void fbg_avx2_memory(fbg_state *s, int16_t *in, int16_t *loc, uint32_t *sat);

#endif /* FBG_SIMD_X86 */
#else
#define FBG_SIMD_X86 0

/* A build without host kernels runs the portable C only: AUTO and PORTABLE resolve to it. */
static inline uint32_t fbg_simd_resolve(uint32_t requested)
{
    return requested == FBG_OPT_KERNEL_AUTO || requested == FBG_OPT_KERNEL_PORTABLE
               ? (uint32_t)FBG_OPT_KERNEL_PORTABLE : 0u;
}
#endif /* FBG_HOST_SIMD */

#endif /* FBG_SIMD_H */
