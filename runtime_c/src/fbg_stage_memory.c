/*
 * fbg_stage_memory.c - stage 3 of fbg_step: the memory features after z and the location
 * averages (docs/fixed-point.md, "memory").
 */
#include "fbg_stages.h"

/* ---- 3. Memory: the features after z in in[4 ..], the location averages in loc ---- */

/* The memory kinds' update rules (FBG_MEMORY_KINDS of fbg_contract.h, one function per kind,
 * docs/fixed-point.md, "memory"): from the load signal u, prime the states (primed == 0) as a
 * pad at rest after a release leaves them, step them and write their features to f[0 ..];
 * each returns the number of features it wrote. */
static unsigned ema_features(fbg_state *s, const fbg_model *m, int32_t u, int primed, int16_t *f,
                             uint32_t *sat)
{
    unsigned k;
    /* |state| <= 32767 * 2^EMA_FRAC < 2^30: each update moves it towards the target by at most
     * the whole distance, so it stays between its old value and the target. So |target -
     * state| <= 2^31 - 2^16 and, with ema_shift <= 15, the rounding stays in int32; the
     * feature is |u - (state >> 15)| <= 65534 times 2^gain <= 2^8: < 2^25. Primed at u. */
    const int32_t target = u * ((int32_t)1 << FBG_EMA_FRAC);
    if (!primed)
        for (k = 0; k < m->n_ema; ++k)
            s->ema[k] = target;
    for (k = 0; k < m->n_ema; ++k) {
        int32_t e = s->ema[k] + fbg_rshift_round32(target - s->ema[k], m->ema_shift[k]);
        s->ema[k] = e;
        f[k] = fbg_sat16_32((u - fbg_rshift_round32(e, FBG_EMA_FRAC)) * ((int32_t)1 << m->ema_gain[k]), sat);
    }
    return m->n_ema;
}

static unsigned play_features(fbg_state *s, const fbg_model *m, int32_t u, int primed, int16_t *f,
                              uint32_t *sat)
{
    unsigned k;
    if (!primed)   /* at u + width: the load last went down */
        for (k = 0; k < m->n_play; ++k)
            s->play[k] = u + m->play_width[k];
    for (k = 0; k < m->n_play; ++k) {
        /* The state stays within play_width of the current u: |state| < 2^16, and the
         * feature is |u - state| <= 32767 times 2^gain <= 2^8 (int32). */
        int32_t lo = u - m->play_width[k], hi = u + m->play_width[k];
        int32_t p = s->play[k];
        p = p < lo ? lo : (p > hi ? hi : p);
        s->play[k] = p;
        f[k] = fbg_sat16_32((u - p) * ((int32_t)1 << m->play_gain[k]), sat);
    }
    return m->n_play;
}

/* The portable reference. Append the memory features to z = in[0..3] and put the location
 * averages (when loc_shift is on) in loc[0..3] (docs/fixed-point.md, "memory"). The load
 * signal's states follow one load signal u, a fixed linear combination of z (the pad's hysteresis lives in
 * its force path, which all four beams share): every kind's features in the order of
 * FBG_MEMORY_KINDS. The first sample after init/tare/reset primes the states as a pad at rest
 * after a release leaves them, so the features read what they read at every rest of the
 * calibration data. A faulty sample never gets here (fbg_step returns before), so a fault
 * freezes them. */
static void memory_features(fbg_state *s, const fbg_model *m, int16_t *in, int16_t *loc,
                            uint32_t *sat)
{
    unsigned c;
    int64_t acc = 0;
    int32_t u;
    int16_t *f = in + FBG_N_STRAIN;
    const int primed = s->mem_primed;
    if (m->loc_shift) {
        /* A local flag: *sat may alias s->loc for the compiler. */
        uint32_t clamped = s->loc_z0_clamped;
        for (c = 0; c < FBG_N_STRAIN; ++c) {
            /* r = z - z0, z0 the standardisation of a zero filtered shift (loc_z0, set by
             * fbg_init; when it clamped, every step flags saturation): 0 at rest. The
             * state stays between its old value and the target r << EMA_FRAC, so both lie
             * within +-(2^30 - 2^15) and the update fits int32: |target - state| < 2^31 - 2^16,
             * plus at most 2^14 for the rounding (docs/fixed-point.md). */
            int32_t target = (int32_t)fbg_sat16_32((int32_t)in[c] - s->loc_z0[c], &clamped) *
                             ((int32_t)1 << FBG_EMA_FRAC);
            int32_t e = primed ? s->loc[c] : target;
            e += (target - e + ((int32_t)1 << (m->loc_shift - 1u))) >> m->loc_shift;
            s->loc[c] = e;
            /* |e| <= 32767 * 2^15, so the rounded value is within int16: no clamp. */
            loc[c] = (int16_t)((e + ((int32_t)1 << (FBG_EMA_FRAC - 1))) >> FBG_EMA_FRAC);
        }
        *sat |= clamped;
    }
    if (FBG_N_MEMORY_FEATURES(m) == 0u) {
        s->mem_primed = 1u;
        return;
    }
    for (c = 0; c < FBG_N_STRAIN; ++c)
        acc += (int64_t)in[c] * m->mem_mult[c];   /* |.| < 4 * 2^15 * 2^31 = 2^48 */
    u = fbg_sat16_rshift_round(acc, m->mem_shift, sat);
#define FBG_KIND_FEATURES(kind, KIND) f += kind##_features(s, m, u, primed, f, sat);
    FBG_MEMORY_KINDS(FBG_KIND_FEATURES)
#undef FBG_KIND_FEATURES
    s->mem_primed = 1u;
}

void fbg_memory_stage(fbg_state *s, const fbg_model *m, int16_t *in, int16_t *loc, uint32_t *sat)
{
#if FBG_SIMD_X86 /* AVX2: the location averages and the load signal's states in int32 lanes */
    if (state_kernel(s) == FBG_OPT_KERNEL_AVX2) {
        fbg_avx2_memory(s, in, loc, sat);
        return;
    }
#endif
    memory_features(s, m, in, loc, sat);
}
