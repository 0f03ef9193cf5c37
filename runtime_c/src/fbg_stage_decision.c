/*
 * fbg_stage_decision.c - stage 5 of fbg_step: the contact decision over time
 * (docs/runtime.md, "In use").
 */
#include "fbg_stages.h"

/* One sample of the rise out of contact (and in the release band), by one of two rules; 1 when
 * contact rises. raw is the net's own decision (acc > 0), margin_q8 the output row as computed,
 * the sign of its multiplier included: every engine reads both as they are, so a negative
 * multiplier gives the same (inverted) decision everywhere.
 * - contact_cusum_h_q8 = 0: a Schmitt trigger with a count, after contact_rise_n consecutive
 *   samples of raw and margin_q8 >= contact_on_q8 (with on = off = 0, rise_n = 1 and a
 *   positive multiplier that is raw itself: margin_q8 > 0 implies acc > 0, acc > 0 implies
 *   margin_q8 >= 0);
 * - else a one-sided CUSUM: S = max(0, S + clamp(margin_q8, lo, hi) - k), contact rises when
 *   S >= h, and S restarts at 0. Bound: S < h <= 2^29 before the update (it rises, and
 *   restarts, on reaching h; it is 0 while contact is shown and after init, reset, tare or a
 *   new baseline) and |clamp - k| <= 2^30 (every parameter within +-FBG_MAX_CUSUM_Q8), so
 *   S + d lies in [-2^30, 2^29 + 2^30): int32. A fault never gets here, so it holds S. */
static int contact_rises(fbg_state *s, const fbg_model *m, int raw, int32_t margin_q8)
{
    int32_t d;
    if (m->contact_cusum_h_q8 == 0)
        return fbg_rise_count(&s->rise_run, raw && margin_q8 >= m->contact_on_q8,
                              m->contact_rise_n);
    d = margin_q8 < m->contact_cusum_lo_q8 ? m->contact_cusum_lo_q8
      : (margin_q8 > m->contact_cusum_hi_q8 ? m->contact_cusum_hi_q8 : margin_q8);
    d -= m->contact_cusum_k_q8;
    s->cusum_q8 = s->cusum_q8 + d > 0 ? s->cusum_q8 + d : 0;
    if (s->cusum_q8 < m->contact_cusum_h_q8)
        return 0;
    s->cusum_q8 = 0;
    return 1;
}

/* The contact decision over time (docs/runtime.md, "In use"; docs/fixed-point.md): the hold and
 * the release band of fbg_decision_wants_rise, the rise of contact_rises. Returns the contact
 * shown. */
uint8_t fbg_contact_decision(fbg_state *s, const fbg_model *m, int raw, int32_t margin_q8)
{
    if (fbg_decision_wants_rise(&s->decision, &s->released, &s->release_run,
                                raw || margin_q8 > 0, raw || margin_q8 > m->contact_off_q8)
        && contact_rises(s, m, raw, margin_q8)) {
        s->decision = 1u;
        s->released = 0u;
    }
    return (uint8_t)(s->decision && !s->released);
}
