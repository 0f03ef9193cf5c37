/*
 * fbg_stage_filter.c - stage 2 of fbg_step: the causal FIR, the standardisation and
 * the input-side overload (docs/fixed-point.md).
 */
#include "fbg_stages.h"

/* ---- 2. Filter and standardise: the causal FIR over the ring (newest sample at pos, taps[k]
 * weighting n - k), z = in[0..3] in Q(z_frac) int16, and the input-side overload (the linear
 * load proxy beyond anything seen in calibration); then the ring moves on. ---- */

#if !FBG_USE_DSP
/* The portable reference; returns 1 when the load proxy exceeds load_max_mN. */
static int filter_standardise(fbg_state *s, const fbg_model *m, int16_t *in, uint32_t *sat)
{
    int64_t load = 0;
    unsigned c;
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        int64_t f = 0;
        int32_t filt, d;
        unsigned k, idx = s->pos;
        for (k = 0; k < m->n_taps; ++k) {
            f += (int64_t)m->taps[k] * s->hist[idx][c];
            idx = idx == 0u ? (unsigned)m->n_taps - 1u : idx - 1u;
        }
        filt = fbg_sat32(fbg_rshift_round(f, m->tap_q), sat);
        s->last_comp[c] = filt;
        d = fbg_sat32((int64_t)filt - m->mean_fm[c], sat);
        in[c] = fbg_sat16(fbg_rshift_round((int64_t)d * m->z_mult[c], m->z_shift), sat);
        load += (int64_t)filt * m->load_coeff[c]; /* |.| < 2^59 each (fbg_model_check) */
    }
    return fbg_rshift_round(load, m->load_shift) > m->load_max_mN;
}
#endif

/* Returns FBG_STATUS_OVERLOAD for an input-side overload, else 0. */
uint32_t fbg_filter_stage(fbg_state *s, const fbg_model *m, int16_t *in, uint32_t *sat)
{
    int overload;
#if FBG_USE_DSP /* all four channels per tap, no per-tap index wrap, the same int64 sums; the
                  * standardisation on 32-bit words (fbg_dsp_kernels.h says why each is exact) */
    int64_t fir[FBG_N_STRAIN];
    uint32_t again = 0u; /* the clamp is flagged once, by the standardisation */
    unsigned c;
    fbg_dsp_fir4(m->taps, m->n_taps, (const int32_t(*)[FBG_N_STRAIN])s->hist, s->pos, fir);
    overload = fbg_dsp_standardise(m, fir, in, sat);
    for (c = 0; c < FBG_N_STRAIN; ++c)
        s->last_comp[c] = fbg_sat32(fbg_rshift_round(fir[c], m->tap_q), &again);
#elif FBG_SIMD_X86 /* AVX2: the four channels in int64 lanes */
    overload = state_kernel(s) == FBG_OPT_KERNEL_AVX2 ? fbg_avx2_filter(s, in, sat)
                                                     : filter_standardise(s, m, in, sat);
#else
    overload = filter_standardise(s, m, in, sat);
#endif
    s->pos = (uint16_t)((s->pos + 1u) % m->n_taps);
    return overload ? FBG_STATUS_OVERLOAD : 0u;
}
