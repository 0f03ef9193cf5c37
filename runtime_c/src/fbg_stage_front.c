/*
 * fbg_stage_front.c - stage 1 of fbg_step: the fault rule, the tare difference, the
 * temperature compensation and the pad's creep inverse (docs/fixed-point.md).
 */
#include "fbg_stages.h"

/* ---- 1. Front: the fault rule, the tare difference, the temperature compensation ----
 * The compensation subtracts the reference grating's averaged shift (fbg_ref_update; the raw
 * shift when ref_shift is 0).
 * The sample's compensated strain shifts go into the FIR ring at pos; a faulty sample
 * (SENSOR_FAULT added to *status) feeds the ring last_comp, the filtered shifts of the last
 * good sample (the filter stage keeps them): a burst of faults then holds the filter's output
 * where it was, where holding one raw sample would hold its noise for the burst's length,
 * and the memory's play operators would keep that excursion after it. */

/* The portable reference. */
static void compensate(fbg_state *s, const fbg_model *m, const int32_t wl_fm[FBG_N_CHANNELS],
                       uint32_t *status, uint32_t *sat)
{
    int32_t shift[FBG_N_CHANNELS], ref;
    unsigned c;
    if (fbg_front_sample(FBG_FRONT(s), wl_fm, m->jump_max_fm, m->stuck_max, status, shift)) {
        memcpy(s->hist[s->pos], s->last_comp, sizeof s->last_comp);
        return;
    }
    ref = fbg_ref_update(&s->ref_acc, &s->ref_count, shift[FBG_N_STRAIN], m->ref_shift);
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        int64_t t = fbg_rshift_round((int64_t)ref * m->temp_coeff_q24[c], FBG_TEMP_COEFF_SHIFT);
        s->hist[s->pos][c] = fbg_sat32((int64_t)shift[c] - t, sat);
    }
}

/* The pad's creep inverse (docs/fixed-point.md, "creep inverse") on the ring entry a good
 * sample's compensation just wrote, shared by every kernel's front: a viscoelastic pad reads
 * s = (1 - m) e + m lag(e) of the elastic strain e, and e = c + q (c - L), L the lag of e
 * (acc = L * 2^creep_shift), undoes it before the FIR. Primed acc = c << creep_shift (e = c)
 * by the first good sample after init, tare, reset or a new baseline; a faulty sample never
 * gets here (its entry is last_comp, already filtered), so it holds acc. Bounds (proven in
 * docs/fixed-point.md): |c| <= SAT32 keeps |acc| <= 2^k (2^31 - 1/2) < 2^47 and |L| <= 2^31,
 * so (c - L) * creep_q15 < 2^32 * 2^15 fits int64, and e is clamped to int32 (SATURATED).
 * Called only with creep_q15 > 0 (off, the entry stays c). */
static void creep_inverse(fbg_state *s, const fbg_model *m, uint32_t *sat)
{
    int32_t *entry = s->hist[s->pos];
    const unsigned k = m->creep_shift;
    unsigned c;
    if (!s->creep_primed) {
        for (c = 0; c < FBG_N_STRAIN; ++c)
            s->creep_acc[c] = (int64_t)entry[c] * ((int64_t)1 << k); /* << of a negative is undefined */
        s->creep_primed = 1u;
        return;
    }
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        const int64_t lag = fbg_rshift_round(s->creep_acc[c], k);
        const int32_t e = fbg_sat32((int64_t)entry[c] +
                                        fbg_rshift_round(((int64_t)entry[c] - lag) * m->creep_q15, 15),
                                    sat);
        s->creep_acc[c] += e - lag;
        entry[c] = e;
    }
}

void fbg_front_stage(fbg_state *s, const fbg_model *m, const int32_t wl_fm[FBG_N_CHANNELS],
                        uint32_t *status, uint32_t *sat)
{
#if FBG_SIMD_X86 /* AVX2: the five channels' fault rule in one vector, the compensation in lanes */
    if (state_kernel(s) == FBG_OPT_KERNEL_AVX2)
        fbg_avx2_front(s, wl_fm, status, sat);
    else
#endif
        compensate(s, m, wl_fm, status, sat);
    /* SENSOR_FAULT here is this sample's: the step's status opens without it. Off
     * (creep_q15 0), nothing runs. */
    if (m->creep_q15 != 0u && !(*status & FBG_STATUS_SENSOR_FAULT))
        creep_inverse(s, m, sat);
}
