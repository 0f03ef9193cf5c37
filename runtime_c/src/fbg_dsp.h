/*
 * fbg_dsp.h - Cortex-M4 DSP-extension inner loops of the fixed-point pipeline (not installed).
 *
 * Compiled only with -DFBG_USE_DSP=1 on a core with the DSP extension (__ARM_FEATURE_DSP:
 * Cortex-M4/M7/M33 with DSP); runtime_c/target.mk builds that variant as
 * build/cm4-dsp/libfbgforce.a. Every function here returns exactly the bits of the portable C
 * in fbg_stage_nets.c and fbg_stage_filter.c (same int64 sums, same rounding and saturation rule; docs/firmware.md says
 * why each step is exact), which the golden vectors check on the target for both builds.
 */
#ifndef FBG_DSP_H
#define FBG_DSP_H

#include "fbg_internal.h"

#ifndef FBG_USE_DSP
#define FBG_USE_DSP 0
#endif

#if FBG_USE_DSP
#if !defined(__ARM_FEATURE_DSP) || !defined(__ARM_FEATURE_SAT)
#error "FBG_USE_DSP=1 needs a core with the DSP extension (e.g. -mcpu=cortex-m4)"
#endif

/* One hidden layer (int16 or int8 weights): y[r] = sat16(max(rshift_round(acc[r] * mult[r],
 * shift), 0)) with acc[r] = bias[r] + sum_j w[r][j] * x[j] (int64); *sat = 1 if any row
 * clamped at 32767. */
void fbg_dsp_hidden(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat);

/* The hidden layers of net on x (fbg_dsp_hidden each), outputs alternately in act[0] and
 * act[1]; returns the input of the output layer (x itself for a net of one layer). */
const int16_t *fbg_dsp_run_hidden(const fbg_net *net, const int16_t *x,
                                  int16_t (*act)[FBG_MAX_WIDTH], uint32_t *sat);

/* acc[r] = fbg_dsp_row_acc(ly, r, x) for every row r of ly. */
void fbg_dsp_output_accs(const fbg_layer *ly, const int16_t *x, int64_t *acc);

/* Row r's accumulator bias[r] + sum_j w[r][j] * x[j] (int64), int16 or int8 weights. */
int64_t fbg_dsp_row_acc(const fbg_layer *ly, unsigned r, const int16_t *x);

/* rshift_round(acc * mult, 32) for int32 acc and mult (an output row of an int32 layer at
 * shift 32): |acc * mult + 2^31| < 2^62, so the result is below 2^30 in magnitude and sat32
 * never clamps it. GCC makes it SMULL and an ADDS/ADC (or SMLAL) on Cortex-M4. */
static inline int32_t fbg_dsp_rshift32_product(int32_t acc, int32_t mult)
{
    return (int32_t)(((int64_t)acc * mult + ((int64_t)1 << 31)) >> 32);
}

/* Steps 3 of fbg_step after the FIR sums f: z[c] = sat16(rshift_round(sat32(filt_c - mean_fm[c])
 * * z_mult[c], z_shift)) with filt_c = sat32(rshift_round(f[c], tap_q)); returns 1 when the
 * load proxy rshift_round(sum_c load_coeff[c] * filt_c, load_shift) exceeds load_max_mN. */
int fbg_dsp_standardise(const fbg_model *m, const int64_t f[FBG_N_STRAIN], int16_t z[FBG_N_STRAIN],
                        uint32_t *sat);

/* acc = bias + sum_j w[j] * x[j] over n int16 inputs (int64), one row of int16 weights. */
int64_t fbg_dsp_dot16(const int16_t *w, const int16_t *x, unsigned n, int64_t bias);

/* The causal FIR of all four strain channels at once: f[c] = sum_k taps[k] * hist[(pos-k) mod
 * n_taps][c] (int64), taps[k] weighting sample n - k as in fbg_step. */
void fbg_dsp_fir4(const int16_t *taps, unsigned n_taps, const int32_t (*hist)[FBG_N_STRAIN],
                  unsigned pos, int64_t f[FBG_N_STRAIN]);
#endif

#endif /* FBG_DSP_H */
