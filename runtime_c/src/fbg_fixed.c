/*
 * fbg_fixed.c - the fixed-point pipeline: init, tare, step, batch (docs/fixed-point.md).
 *
 * fbg_step runs one sample through stages in the order of export/intref.py's run: the front
 * (fault rule, tare, temperature compensation), the filter and standardisation, the memory
 * features, the nets with the contact decision, the outputs. Each stage is a static function
 * here with a portable reference beside it; where an instruction set has its own variant of
 * a stage, the stage picks it: at compile time on the target (FBG_USE_DSP, fbg_dsp.c) and by
 * the state's kernel on the host (FBG_OPT_KERNEL_*, fbg_simd_x86.c and fbg_simd_neon.c).
 *
 * No float or double in this file (check-nofloat builds it with -mgeneral-regs-only).
 * export/intref.py mirrors every operation here bit for bit.
 */
#include <string.h>

#include "fbg_front.h"
#include "fbg_simd.h" /* host SIMD dense layers (FBG_HOST_SIMD, docs/runtime.md) */
#if FBG_USE_DSP /* Cortex-M4 DSP-extension inner loops (fbg_dsp.c, docs/firmware.md) */
#include "fbg_dsp.h"
#endif

/* round(32768 / (1 + exp(-x))) for x = -8, -7.875, ..., 8, clamped to 32767
 * (docs/fixed-point.md; export/intref.py holds the same table and a test compares them). */
static const uint16_t sigmoid_table[129] = {
    11, 12, 14, 16, 18, 21, 23, 26, 30, 34, 38, 43,
    49, 56, 63, 72, 81, 92, 104, 118, 133, 151, 171, 194,
    219, 248, 281, 318, 360, 407, 461, 521, 589, 666, 753, 851,
    961, 1084, 1223, 1379, 1554, 1750, 1969, 2213, 2486, 2789, 3124, 3496,
    3906, 4357, 4851, 5391, 5978, 6613, 7297, 8031, 8813, 9641, 10513, 11424,
    12371, 13348, 14347, 15361, 16384, 17407, 18421, 19420, 20397, 21344, 22255, 23127,
    23955, 24737, 25471, 26155, 26790, 27377, 27917, 28411, 28862, 29272, 29644, 29979,
    30282, 30555, 30799, 31018, 31214, 31389, 31545, 31684, 31807, 31917, 32015, 32102,
    32179, 32247, 32307, 32361, 32408, 32450, 32487, 32520, 32549, 32574, 32597, 32617,
    32635, 32650, 32664, 32676, 32687, 32696, 32705, 32712, 32719, 32725, 32730, 32734,
    32738, 32742, 32745, 32747, 32750, 32752, 32754, 32756, 32757
};

uint32_t fbg_version(void)
{
    return ((uint32_t)FBG_VERSION_MAJOR << 16) | ((uint32_t)FBG_VERSION_MINOR << 8) |
           (uint32_t)FBG_VERSION_PATCH;
}

size_t fbg_state_size(void)
{
    return sizeof(fbg_state);
}

int32_t fbg_sigmoid_q15(int32_t x_q8)
{
    int32_t u, idx, frac, lo, hi;
    if (x_q8 <= -2048)
        return sigmoid_table[0];
    if (x_q8 >= 2048)
        return sigmoid_table[128];
    u = x_q8 + 2048; /* 0..4095: 32 steps of Q8 per table interval of 1/8 */
    idx = u >> 5;
    frac = u & 31;
    lo = sigmoid_table[idx];
    hi = sigmoid_table[idx + 1];
    /* hi >= lo (monotone table), so the interpolation term is non-negative. */
    return lo + (((hi - lo) * frac + 16) >> 5);
}

/* The shared front end's view of a fixed-point state (fbg_front.h). */
#define FRONT(s) FBG_FRONT_OF(s, FBG_STATE_MAGIC)

/* The FBG_OPT_KERNEL_* value an initialised state runs: it picks the host variants. */
static inline uint32_t state_kernel(const fbg_state *s)
{
    return s->options & FBG_OPT_KERNEL_MASK;
}

fbg_status fbg_init(fbg_state *state, const fbg_model *model, uint32_t options)
{
    fbg_status st;
    uint32_t kernel, clamped = 0u;
    unsigned c;
    if (state == NULL || model == NULL)
        return FBG_ERR_NULL;
    st = fbg_model_check(model);
    if (st != FBG_OK)
        return st;
    kernel = fbg_simd_resolve(options & FBG_OPT_KERNEL_MASK);
    if (kernel == 0u)
        return FBG_ERR_ARG;
    memset(state, 0, sizeof *state);
    state->model = model;
    state->model_crc = model->blob_crc;
    fbg_front_init(FRONT(state), model->baseline_fm, (options & ~(uint32_t)FBG_OPT_KERNEL_MASK) | kernel);
    /* The location averages' rest reference is a model constant: computed here, not per step. */
    for (c = 0; c < FBG_N_STRAIN; ++c)
        state->loc_z0[c] = fbg_sat16_rshift_round((int64_t)-model->mean_fm[c] * model->z_mult[c],
                                                  model->z_shift, &clamped);
    state->loc_z0_clamped = (uint8_t)clamped;
    return FBG_OK;
}

uint32_t fbg_kernel(const fbg_state *state)
{
    if (state == NULL || !fbg_front_ok(FRONT((fbg_state *)state))) /* the view is only read */
        return 0u;
    return state_kernel(state);
}

size_t fbg_pack_bytes(const fbg_state *state)
{
#if FBG_SIMD_X86
    if (state == NULL || !fbg_front_ok(FRONT((fbg_state *)state))) /* the view is only read */
        return 0u;
    return fbg_simd_pack_bytes(state_kernel(state), state->model);
#else
    (void)state;
    return 0u;
#endif
}

fbg_status fbg_pack(fbg_state *state, void *buf, size_t len)
{
    size_t need;
    if (state == NULL || buf == NULL)
        return FBG_ERR_NULL;
    if (!fbg_front_ok(FRONT(state)))
        return FBG_ERR_STATE;
    need = fbg_pack_bytes(state);
    if (need == 0u || len < need || ((uintptr_t)buf % FBG_PACK_ALIGN) != 0u)
        return FBG_ERR_ARG;
#if FBG_SIMD_X86
    fbg_simd_pack(state_kernel(state), state->model, buf);
    state->packed = buf;
#endif
    return FBG_OK;
}

fbg_status fbg_use_pack(fbg_state *state, const void *packed)
{
    if (state == NULL)
        return FBG_ERR_NULL;
    if (!fbg_front_ok(FRONT(state)))
        return FBG_ERR_STATE;
    if (packed != NULL) {
#if FBG_SIMD_X86
        fbg_pack_header h;
        if (((uintptr_t)packed % FBG_PACK_ALIGN) != 0u)
            return FBG_ERR_ARG;
        memcpy(&h, packed, sizeof h);
        if (h.magic != FBG_PACK_MAGIC || h.model != state->model ||
            h.kernel != state_kernel(state) ||
            h.bytes != fbg_simd_pack_bytes(h.kernel, state->model))
            return FBG_ERR_ARG;
#else
        return FBG_ERR_ARG;
#endif
    }
    state->packed = packed;
    return FBG_OK;
}

/* ---- The decision over time and the at-rest tracker (docs/runtime.md, "In use") ---- */

/* Reset, tare and a new baseline restart the decision and the tracker. The baseline the
 * tracker reached stays through a reset (it is the best estimate of the unloaded gratings)
 * and becomes the reference of its bound, as a new baseline would; a tare replaces it. */
static fbg_status in_use_after(fbg_state *s, fbg_status st)
{
    if (st != FBG_OK)
        return st;   /* refused: nothing was cleared */
    s->decision = 0u;
    s->rise_run = 0u;
    s->cusum_q8 = 0;
    s->rest_run = 0u;
    s->track_pos = 0u;
    s->track_limited = 0u;
    s->hold_run = 0u;
    s->hold_primed = 0u;
    memset(s->track_sum, 0, sizeof s->track_sum);
    memset(s->drift_fm, 0, sizeof s->drift_fm);
    memset(s->track_frac, 0, sizeof s->track_frac);
    return FBG_OK;
}

/* The contact decision over time (docs/runtime.md, "In use"; docs/fixed-point.md). raw is the
 * net's own decision (acc > 0), margin_q8 the output row as computed, the sign of its
 * multiplier included: every engine reads both as they are, so a negative multiplier gives
 * the same (inverted) decision everywhere. Contact stays while raw or margin_q8 >
 * contact_off_q8. It rises by one of two rules:
 * - contact_cusum_h_q8 = 0: a Schmitt trigger with a count, after contact_rise_n consecutive
 *   samples of raw and margin_q8 >= contact_on_q8 (with on = off = 0, rise_n = 1 and a
 *   positive multiplier that is raw itself: margin_q8 > 0 implies acc > 0, acc > 0 implies
 *   margin_q8 >= 0);
 * - else a one-sided CUSUM: S = max(0, S + clamp(margin_q8, lo, hi) - k), contact rises when
 *   S >= h, and S restarts at 0. Bound: S < h <= 2^29 before the update (it rises, and
 *   restarts, on reaching h; it is 0 in contact and after init, reset, tare or a new
 *   baseline) and |clamp - k| <= 2^30 (every parameter within +-FBG_MAX_CUSUM_Q8), so S + d
 *   lies in [-2^30, 2^29 + 2^30): int32. A fault never gets here, so it holds S. */
static uint8_t contact_decision(fbg_state *s, const fbg_model *m, int raw, int32_t margin_q8)
{
    int32_t d;
    if (m->contact_cusum_h_q8 == 0)
        return fbg_decide(&s->decision, &s->rise_run, raw, margin_q8 >= m->contact_on_q8,
                          margin_q8 > m->contact_off_q8, m->contact_rise_n);
    if (s->decision) {
        s->decision = (uint8_t)(raw || margin_q8 > m->contact_off_q8);
        return s->decision;
    }
    d = margin_q8 < m->contact_cusum_lo_q8 ? m->contact_cusum_lo_q8
      : (margin_q8 > m->contact_cusum_hi_q8 ? m->contact_cusum_hi_q8 : margin_q8);
    d -= m->contact_cusum_k_q8;
    s->cusum_q8 = s->cusum_q8 + d > 0 ? s->cusum_q8 + d : 0;
    if (s->cusum_q8 >= m->contact_cusum_h_q8) {
        s->decision = 1u;
        s->cusum_q8 = 0;
    }
    return s->decision;
}

/* The tracker's creep states (docs/fixed-point.md, "In use"), on every sample that passed the
 * fault rule, z the standardised channels: a viscoelastic pad gives back a press's load for a
 * second or more after the release, so each state averages z through contact and rest alike
 * (creep += rshift_round((z << EMA_FRAC) - creep, track_creep_shift)), and rest_track takes
 * track_creep of it, relative to z0, out of what it learns. Primed at z << EMA_FRAC with the
 * memory states (the first good sample after init, tare, reset or a new baseline); a fault
 * never gets here, so it holds them. |creep| <= 32767 * 2^EMA_FRAC < 2^30 as the averages'
 * states (ema_features): the update and its rounding fit int32. Off (track_creep_q15 0):
 * nothing runs. */
static void creep_update(fbg_state *s, const fbg_model *m, const int16_t *z)
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
static void rest_track(fbg_state *s, const fbg_model *m, const int16_t *z)
{
    unsigned c;
    if (z != NULL) {
        if (s->rest_run < 0xFFFFu)
            s->rest_run++;
        for (c = 0; c < FBG_N_STRAIN; ++c) {
            int32_t r = (int32_t)z[c] - s->loc_z0[c];
            if (m->track_creep_q15 != 0u)
                r -= (int32_t)fbg_rshift_round(((int64_t)s->creep[c] - (int64_t)s->loc_z0[c] *
                                                ((int64_t)1 << FBG_EMA_FRAC)) * m->track_creep_q15, 30);
            s->track_sum[c] += r;
        }
    } else {
        s->rest_run = 0u;
    }
    if (++s->track_pos < FBG_TRACK_BLOCK)
        return;
    s->track_pos = 0u;
    if (m->track_shift != 0u && s->rest_run >= (uint32_t)FBG_TRACK_BLOCK + m->track_settle) {
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

/* Net inputs beyond what the calibration covered (z and the memory features): flagged, the
 * nets still run. */
static uint32_t out_of_range(const fbg_model *m, const int16_t *in)
{
    unsigned c;
    for (c = 0; c < FBG_N_STRAIN + FBG_N_MEMORY_FEATURES(m); ++c)
        if (in[c] < m->in_lo[c] || in[c] > m->in_hi[c])
            return FBG_STATUS_OUT_OF_RANGE;
    return 0u;
}

/* ---- Reset, tare and baseline: the front end's, then in_use_after ---- */

fbg_status fbg_reset(fbg_state *state)
{
    return state == NULL ? FBG_ERR_NULL : in_use_after(state, fbg_front_reset(FRONT(state)));
}

fbg_status fbg_tare_begin(fbg_state *state)
{
    return state == NULL ? FBG_ERR_NULL : fbg_front_tare_begin(FRONT(state));
}

fbg_status fbg_tare_add(fbg_state *state, const int32_t wl_fm[FBG_N_CHANNELS], int *accepted)
{
    if (state == NULL || wl_fm == NULL)
        return FBG_ERR_NULL;
    return fbg_front_tare_add(FRONT(state), wl_fm, accepted);
}

fbg_status fbg_tare_end(fbg_state *state)
{
    return state == NULL ? FBG_ERR_NULL : in_use_after(state, fbg_front_tare_end(FRONT(state)));
}

fbg_status fbg_set_baseline(fbg_state *state, const int32_t baseline_fm[FBG_N_CHANNELS])
{
    if (state == NULL || baseline_fm == NULL)
        return FBG_ERR_NULL;
    return in_use_after(state, fbg_front_set_baseline(FRONT(state), baseline_fm));
}

fbg_status fbg_get_baseline(const fbg_state *state, int32_t baseline_fm[FBG_N_CHANNELS])
{
    if (state == NULL || baseline_fm == NULL)
        return FBG_ERR_NULL;
    if (!fbg_front_ok(FRONT((fbg_state *)state))) /* the view is only read here */
        return FBG_ERR_STATE;
    memcpy(baseline_fm, state->baseline_fm, sizeof state->baseline_fm);
    return FBG_OK;
}

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
    if (fbg_front_sample(FRONT(s), wl_fm, m->jump_max_fm, m->stuck_max, status, shift)) {
        memcpy(s->hist[s->pos], s->last_comp, sizeof s->last_comp);
        return;
    }
    ref = fbg_ref_update(&s->ref_acc, &s->ref_primed, shift[FBG_N_STRAIN], m->ref_shift);
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

static void front_stage(fbg_state *s, const fbg_model *m, const int32_t wl_fm[FBG_N_CHANNELS],
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
static uint32_t filter_stage(fbg_state *s, const fbg_model *m, int16_t *in, uint32_t *sat)
{
    int overload;
#if FBG_USE_DSP /* all four channels per tap, no per-tap index wrap, the same int64 sums; the
                  * standardisation on 32-bit words (fbg_dsp.c says why each is exact) */
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

static void memory_stage(fbg_state *s, const fbg_model *m, int16_t *in, int16_t *loc, uint32_t *sat)
{
#if FBG_SIMD_X86 /* AVX2: the location averages and the load signal's states in int32 lanes */
    if (state_kernel(s) == FBG_OPT_KERNEL_AVX2) {
        fbg_avx2_memory(s, in, loc, sat);
        return;
    }
#endif
    memory_features(s, m, in, loc, sat);
}

/* ---- 4. The nets: each layer's rows by the portable reference (layer_acc), the DSP kernels
 * (fbg_dsp.c) or the state's host kernel (fbg_simd.h) ---- */

/* The activation buffers are read with LDRD by the DSP kernels (fbgforce.h); the packed
 * kernels write whole groups of 8 rows into them. */
typedef char fbg_state_act_aligned[(offsetof(fbg_state, act) % 8u) == 0u ? 1 : -1];
typedef char fbg_state_act_groups[(FBG_MAX_WIDTH % 8) == 0 ? 1 : -1];

#if FBG_USE_DSP /* the rows in SMLAD/SMLALD, requantised with USAT (fbg_dsp.c): the same bits */
/* Run the hidden layers of a net on x; returns the input of the output layer. */
static const int16_t *run_hidden(fbg_state *s, const fbg_net *net, const int16_t *x, uint32_t *sat)
{
    return fbg_dsp_run_hidden(net, x, s->act, sat);
}

/* The accumulators of every row of a net's output layer. */
static void output_accs(const fbg_state *s, const fbg_layer *ly, const int16_t *x, int64_t *acc)
{
    (void)s;
    fbg_dsp_output_accs(ly, x, acc);
}
#else
/* The portable reference of a layer. */
/* acc = bias[r] + sum_j w[r][j] * x[j] in int32 for an acc32 layer: fbg_model_check proved
 * sum_j |w[r][j]| * 32767 + |bias[r]| <= INT32_MAX, which bounds every partial sum too. */
static int32_t layer_acc32(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    int32_t acc = (int32_t)ly->bias[r];
    unsigned j;
    if (ly->w_bits == 16u) {
        const int16_t *w = ly->w16 + (size_t)r * ly->n_in;
        for (j = 0; j < ly->n_in; ++j)
            acc += (int32_t)w[j] * (int32_t)x[j];
    } else {
        const int8_t *w = ly->w8 + (size_t)r * ly->n_in;
        for (j = 0; j < ly->n_in; ++j)
            acc += (int32_t)w[j] * (int32_t)x[j];
    }
    return acc;
}

/* acc = bias[r] + sum_j w[r][j] * x[j] in int64. Products of int16 (or int8) by int16 fit
 * int32; fbg_model_check proved |acc| * |mult| + 2^(shift-1) < 2^63. */
static int64_t layer_acc(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    int64_t acc = ly->bias[r];
    unsigned j;
    if (ly->acc32)
        return layer_acc32(ly, r, x);
    if (ly->w_bits == 16u) {
        const int16_t *w = ly->w16 + (size_t)r * ly->n_in;
        for (j = 0; j < ly->n_in; ++j)
            acc += (int32_t)w[j] * (int32_t)x[j];
    } else {
        const int8_t *w = ly->w8 + (size_t)r * ly->n_in;
        for (j = 0; j < ly->n_in; ++j)
            acc += (int32_t)w[j] * (int32_t)x[j];
    }
    return acc;
}
/* Hidden-layer output of row r from its accumulator: ReLU, then sat16. */
static inline int16_t hidden_value(const fbg_layer *ly, unsigned r, int64_t acc, uint32_t *sat)
{
    int64_t v = fbg_rshift_round(acc * ly->mult[r], ly->shift);
    return fbg_sat16(v < 0 ? 0 : v, sat);
}

static void hidden_rows(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    unsigned r;
    for (r = 0; r < ly->n_out; ++r)
        y[r] = hidden_value(ly, r, layer_acc(ly, r, x), sat);
}

static void output_rows(const fbg_layer *ly, const int16_t *x, int64_t *acc)
{
    unsigned r;
    for (r = 0; r < ly->n_out; ++r)
        acc[r] = layer_acc(ly, r, x);
}

#if FBG_HOST_SIMD
/* The state's host kernel (SSE2, AVX2, NEON: fbg_simd.h) for an acc32 layer; 0 where the
 * portable reference runs the layer (an int64-accumulator layer, the portable kernel). */
static inline uint32_t host_kernel(const fbg_state *s, const fbg_layer *ly)
{
    uint32_t kernel = state_kernel(s);
    return ly->acc32 && kernel != FBG_OPT_KERNEL_PORTABLE ? kernel : 0u;
}

static void net_hidden_layer(const fbg_state *s, const fbg_layer *ly, const int16_t *x, int16_t *y,
                         uint32_t *sat)
{
    uint32_t kernel = host_kernel(s, ly);
    if (kernel != 0u)
        fbg_simd_hidden(kernel, ly, x, y, sat);
    else
        hidden_rows(ly, x, y, sat);
}

/* The accumulators of every row of a net's output layer. */
static void output_accs(const fbg_state *s, const fbg_layer *ly, const int16_t *x, int64_t *acc)
{
    uint32_t kernel = host_kernel(s, ly);
    if (kernel != 0u) {
        int32_t acc32[FBG_MAX_WIDTH];
        unsigned r;
        fbg_simd_acc32(kernel, ly, x, acc32);
        for (r = 0; r < ly->n_out; ++r)
            acc[r] = acc32[r];
    } else {
        output_rows(ly, x, acc);
    }
}
#else
static void net_hidden_layer(const fbg_state *s, const fbg_layer *ly, const int16_t *x, int16_t *y,
                         uint32_t *sat)
{
    (void)s;
    hidden_rows(ly, x, y, sat);
}

/* The accumulators of every row of a net's output layer. */
static void output_accs(const fbg_state *s, const fbg_layer *ly, const int16_t *x, int64_t *acc)
{
    (void)s;
    output_rows(ly, x, acc);
}
#endif

/* Run the hidden layers of a net on x, through the activation buffers in turn; returns the
 * input of the output layer. */
static const int16_t *run_hidden(fbg_state *s, const fbg_net *net, const int16_t *x, uint32_t *sat)
{
    unsigned l;
    for (l = 0; l + 1u < net->n_layers; ++l) {
        int16_t *y = s->act[l & 1u];
        net_hidden_layer(s, &net->layers[l], x, y, sat);
        x = y;
    }
    return x;
}
#endif

/* Output row r of a net's last layer in its physical unit from its accumulator, saturated to
 * int32. */
static inline int32_t output_row(const fbg_layer *ly, unsigned r, int64_t acc, uint32_t *sat)
{
#if FBG_USE_DSP /* an int32 row at shift 32: one SMMULR-like product, never clamped */
    if (ly->acc32 && ly->shift == 32u)
        return fbg_dsp_rshift32_product((int32_t)acc, ly->mult[r]);
#endif
    return fbg_sat32(fbg_rshift_round(acc * ly->mult[r], ly->shift), sat);
}

/* Every layer of net n on the net inputs in: acc = the accumulators of its output layer, which
 * it returns. Layer by layer, or from packed weights in one call where the state has them
 * (fbg_pack; x86-64 builds only). */
static inline const fbg_layer *net_accs(fbg_state *s, const fbg_model *m, unsigned n, const int16_t *in,
                                        int64_t *acc, uint32_t *sat)
{
    const fbg_net *net = &m->nets[n];
    const fbg_layer *last = &net->layers[net->n_layers - 1u];
#if FBG_SIMD_X86
    if (s->packed != NULL &&
        fbg_simd_net_packed(state_kernel(s), s->packed, n, net->n_layers, in, s->act, acc, sat))
        return last;
#endif
    output_accs(s, last, run_hidden(s, net, in, sat), acc);
    return last;
}

/* ---- 5. Outputs ---- */

static void safe_output(fbg_output *out, uint32_t status)
{
    memset(out, 0, sizeof *out);
    out->status = status;
}

/* The contact net (one output row, the logit margin in Q8; raw contact iff its acc > 0), the
 * decision over time and the confidence, into a zeroed out. */
static void contact_outputs(fbg_state *s, const fbg_model *m, const int16_t *in, fbg_output *out,
                            uint32_t *sat)
{
    int64_t acc[2]; /* an output layer has 1 or 2 rows (fbg_model_check) */
    const fbg_layer *last = net_accs(s, m, FBG_NET_CONTACT, in, acc, sat);
    out->contact_margin_q8 = output_row(last, 0u, acc[0], sat);
    out->contact = contact_decision(s, m, acc[0] > 0, out->contact_margin_q8);
    out->contact_conf_q15 = (uint16_t)fbg_sigmoid_q15(out->contact_margin_q8);
}

/* The settled-hold gain (docs/runtime.md, "In use"; docs/fixed-point.md, "settled-hold
 * gain"): the nets read a grip held still a little low, because a causal estimator cannot tell
 * a load that stands from one that has just begun to fall; once force_mN has stayed within its
 * band of its own average for hold_settle samples, no turn is left to mistake, and the trainer's
 * gain, measured on its synthetic holds, ramps in over 2^hold_ramp_shift samples. Bounds:
 * |force_mN| < 2^31, so hold_avg < 2^46; |hold_gain_q15| <= 2^12 and w <= 2^12, so the product
 * stays below 2^55. */
static int32_t hold_stage(fbg_state *s, const fbg_model *m, int32_t force_mN, uint32_t *sat)
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

/* A contact step's force and location. The force net's output (mN before the offset) feeds
 * the location net quantised: its inputs are [z1..z4, contact in Q(z_frac), that force in
 * Q(z_frac), location averages], written over the memory features after z, which are no
 * longer needed. Returns FBG_STATUS_OVERLOAD when the force exceeds overload_mN, else 0. */
static uint32_t force_location_outputs(fbg_state *s, const fbg_model *m, int16_t *in,
                                       const int16_t *loc, fbg_output *out, uint32_t *sat)
{
    int64_t acc[2];
    int32_t force_out;
    const fbg_layer *last = net_accs(s, m, FBG_NET_FORCE, in, acc, sat);
    force_out = output_row(last, 0u, acc[0], sat);
    out->force_mN = fbg_sat32_add(force_out, m->force_offset_mN, sat);
    in[FBG_N_STRAIN] = (int16_t)(1 << m->z_frac);
    in[FBG_N_STRAIN + 1] = fbg_sat16_rshift_round((int64_t)force_out * m->fq_mult, m->fq_shift, sat);
    if (m->loc_shift)
        memcpy(in + FBG_N_STRAIN + 2, loc, FBG_N_STRAIN * sizeof *loc);
    last = net_accs(s, m, FBG_NET_LOCATION, in, acc, sat);
    out->x_um = fbg_sat32_add(output_row(last, 0u, acc[0], sat), m->xy_offset_um[0], sat);
    out->y_um = fbg_sat32_add(output_row(last, 1u, acc[1], sat), m->xy_offset_um[1], sat);
    out->force_mN = hold_stage(s, m, out->force_mN, sat);
    return out->force_mN > m->overload_mN ? FBG_STATUS_OVERLOAD : 0u;
}

/* The checks that open a step: FBG_OK with *status = the step's starting flags, or the error
 * with the safe output in out. */
static fbg_status step_begin(fbg_state *s, const int32_t *wl_fm, fbg_output *out, uint32_t *status)
{
    fbg_status st;
    if (s == NULL || wl_fm == NULL || out == NULL)
        return FBG_ERR_NULL;
    st = fbg_front_step_begin(FRONT(s), status);
    if (st != FBG_OK) {
        safe_output(out, *status);
        return st;
    }
    /* The state's history, memory states and packed weights are sized and made for the model
     * fbg_init saw: a model reloaded in place (another blob) must not be run on them. */
    if (s->model->blob_crc != s->model_crc) {
        safe_output(out, 0u);
        return FBG_ERR_MODEL_CHANGED;
    }
    if (s->track_limited)
        *status |= FBG_STATUS_BASELINE_LIMIT;
    return FBG_OK;
}

fbg_status fbg_step(fbg_state *s, const int32_t wl_fm[FBG_N_CHANNELS], fbg_output *out)
{
    const fbg_model *m;
    uint32_t status, sat = 0u;
    int16_t in[FBG_MAX_INPUTS], loc[FBG_N_STRAIN];
    const fbg_status st = step_begin(s, wl_fm, out, &status);
    if (st != FBG_OK)
        return st;
    m = s->model;

    /* 1. Front. A faulty sample ends here with the safe output: the ring moves on, the
     *    decision holds, the tracker restarts. */
    front_stage(s, m, wl_fm, &status, &sat);
    if (fbg_front_push_done(FRONT(s), m->n_taps, &status)) {
        safe_output(out, status);
        rest_track(s, m, NULL);
        return FBG_OK;
    }
    /* 2. Filter and standardise into z = in[0..3], which the tracker's creep states follow
     *    (before the memory stage marks the states primed); 3. the memory features after z. */
    status |= filter_stage(s, m, in, &sat);
    creep_update(s, m, in);
    memory_stage(s, m, in, loc, &sat);
    status |= out_of_range(m, in);

    /* 4. Contact net and the decision, the tracker on samples at rest; on contact the force
     *    and location nets. */
    memset(out, 0, sizeof *out);
    contact_outputs(s, m, in, out, &sat);
    rest_track(s, m, out->contact || !s->tared || (status & FBG_STATUS_WARMUP) ? NULL : in);
    if (out->contact) {
        status |= force_location_outputs(s, m, in, loc, out, &sat);
    } else {
        s->hold_primed = 0u;
        s->hold_run = 0u;
    }
    out->status = status | (sat ? FBG_STATUS_SATURATED : 0u);
    return FBG_OK;
}

fbg_status fbg_run(fbg_state *state, const int32_t *wl_fm, size_t n, fbg_output *out)
{
    size_t i;
    fbg_status st;
    if (state == NULL || (n > 0u && (wl_fm == NULL || out == NULL)))
        return FBG_ERR_NULL;
    for (i = 0; i < n; ++i) {
        st = fbg_step(state, wl_fm + i * FBG_N_CHANNELS, out + i);
        if (st != FBG_OK)
            return st;
    }
    return FBG_OK;
}
