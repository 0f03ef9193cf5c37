/*
 * fbg_stage_tracker.c - the at-rest baseline tracker of fbg_step and its creep states
 * (docs/fixed-point.md, "In use").
 */
#include "fbg_stages.h"

/* The tracker's creep states (docs/fixed-point.md, "In use"), on every sample that passed the
 * fault rule, z the standardised channels: a viscoelastic pad gives back a press's load for a
 * second or more after the release, so each state averages z through contact and rest alike
 * (creep += rshift_round((z << EMA_FRAC) - creep, track_creep_shift)), and rest_track takes
 * track_creep of it, relative to z0, out of what it learns. Primed at z << EMA_FRAC with the
 * memory states (the first good sample after init, tare, reset or a new baseline); a fault
 * never gets here, so it holds them. |creep| <= 32767 * 2^EMA_FRAC < 2^30 as the averages'
 * states (ema_features): the update and its rounding fit int32. Off (track_creep_q15 0):
 * nothing runs. */
void fbg_creep_update(fbg_state *s, const fbg_model *m, const int16_t *z)
{
    unsigned c;
    if (m->track_creep_q15 == 0u)
        return;
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        const int32_t target = (int32_t)z[c] * ((int32_t)1 << FBG_EMA_FRAC);
        s->creep[c] = s->mem_primed
                          ? s->creep[c] + fbg_rshift_round32(target - s->creep[c], m->track_creep_shift)
                          : target;
    }
}

/* The at-rest baseline tracker, once per step that returns FBG_OK. z is the standardised
 * channels of a sample at rest (tared, no fault, no warm-up, decision 0), NULL otherwise.
 * Every FBG_TRACK_BLOCK steps, a block that was at rest throughout and came after
 * track_settle samples of rest moves the strain baselines by its sum of z - z0 times
 * track_gain (a first-order follower with time constant 2^track_shift samples, in fm with
 * a carried fraction), each step at most track_step_max_fm and the whole correction at most
 * track_limit_fm from the tare. A load, a fault or a warm-up freezes it: it never learns
 * from a sample the nets call contact. With the creep term on, each sample at rest adds
 * (z - z0) - corr, corr = rshift_round((creep - (z0 << EMA_FRAC)) * track_creep_q15, 30): the
 * pad's creep still in the grating, not drift. Bounds: |creep - (z0 << EMA_FRAC)| <= 65534 *
 * 2^15 < 2^31 times track_creep_q15 <= 2^14 is below 2^45 (int64), so |corr| <= 32767; and
 * corr is within 1/2 of m * (creep / 2^15 - z0), m <= 1/2, so a sample's term is within 1/2
 * of z - m * creep / 2^15 - (1 - m) * z0: at most 65534 as without the term
 * (docs/fixed-point.md). |track_sum| <= 64 * 65534 < 2^23, so the product with
 * |track_gain| < 2^31 stays below 2^54; |track_frac| < 2^(TRACK_FRAC - 1) after a step, and
 * |drift_fm| <= 1e8 keeps the baseline within 1e8 fm of the tare, so wl - baseline stays
 * within +-1.1e9 (int32). */
void fbg_rest_track(fbg_state *s, const fbg_model *m, const int16_t *z)
{
    unsigned c;
    int block;
    if (z != NULL) {
        for (c = 0; c < FBG_N_STRAIN; ++c) {
            int32_t r = (int32_t)z[c] - s->loc_z0[c];
            if (m->track_creep_q15 != 0u)
                r -= (int32_t)fbg_rshift_round(((int64_t)s->creep[c] - (int64_t)s->loc_z0[c] *
                                                ((int64_t)1 << FBG_EMA_FRAC)) * m->track_creep_q15, 30);
            s->track_sum[c] += r;
        }
    }
    block = fbg_track_block(&s->rest_run, &s->track_pos, z != NULL, m->track_shift, m->track_settle);
    if (block < 0)
        return;
    if (block) {
        for (c = 0; c < FBG_N_STRAIN; ++c) {
            int64_t frac = s->track_frac[c] + (int64_t)s->track_sum[c] * m->track_gain[c];
            int64_t step = fbg_rshift_round(frac, FBG_TRACK_FRAC);
            int64_t drift;
            if (step > m->track_step_max_fm || step < -(int64_t)m->track_step_max_fm) {
                step = step > 0 ? m->track_step_max_fm : -(int64_t)m->track_step_max_fm;
                frac = 0;   /* no wind-up: the clamped remainder is not carried */
            } else {
                frac -= step * ((int64_t)1 << FBG_TRACK_FRAC);
            }
            drift = (int64_t)s->drift_fm[c] + step;
            if (drift > m->track_limit_fm || drift < -(int64_t)m->track_limit_fm) {
                drift = drift > 0 ? m->track_limit_fm : -(int64_t)m->track_limit_fm;
                frac = 0;
                s->track_limited = 1u;
            }
            s->baseline_fm[c] += (int32_t)(drift - s->drift_fm[c]);
            s->drift_fm[c] = (int32_t)drift;
            s->track_frac[c] = frac;
        }
    }
    memset(s->track_sum, 0, sizeof s->track_sum);
}
