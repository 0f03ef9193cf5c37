/*
 * fbg_stage_hold.c - the settled-hold gain of fbg_step's force (docs/fixed-point.md,
 * "settled-hold gain").
 */
#include "fbg_stages.h"

/* The settled-hold gain (docs/runtime.md, "In use"; docs/fixed-point.md, "settled-hold
 * gain"): the nets read a grip held still a little low, because a causal estimator cannot tell
 * a load that stands from one that has just begun to fall; once force_mN has stayed within its
 * band of its own average for hold_settle samples, no turn is left to mistake, and the trainer's
 * gain, measured on its synthetic holds, ramps in over 2^hold_ramp_shift samples. Bounds:
 * |force_mN| < 2^31, so hold_avg < 2^46; |hold_gain_q15| <= 2^12 and w <= 2^12, so the product
 * stays below 2^55. */
int32_t fbg_hold_stage(fbg_state *s, const fbg_model *m, int32_t force_mN, uint32_t *sat)
{
    const int64_t f = force_mN;
    int64_t dev, band;
    uint32_t w;
    if (m->hold_gain_q15 == 0)
        return force_mN;
    if (!s->hold_primed) {
        s->hold_avg = f * ((int64_t)1 << FBG_EMA_FRAC);
        s->hold_primed = 1u;
    } else {
        s->hold_avg += fbg_rshift_round(f * ((int64_t)1 << FBG_EMA_FRAC) - s->hold_avg, m->hold_shift);
    }
    dev = f - fbg_rshift_round(s->hold_avg, FBG_EMA_FRAC);
    band = fbg_rshift_round((f < 0 ? -f : f) * (int64_t)m->hold_band_q15, 15u);
    if (band < m->hold_band_mN)
        band = m->hold_band_mN;
    w = fbg_hold_weight(&s->hold_run, (dev < 0 ? -dev : dev) <= band, m->hold_settle,
                        m->hold_ramp_shift);
    return fbg_sat32(f + fbg_rshift_round(f * m->hold_gain_q15 * (int64_t)w,
                                          15u + m->hold_ramp_shift), sat);
}
