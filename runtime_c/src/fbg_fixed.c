/*
 * fbg_fixed.c - the fixed-point pipeline's API: init, tare, step, batch (docs/fixed-point.md).
 *
 * fbg_step runs one sample through the stages of fbg_stages.h (one file each) in the order of
 * export/intref.py's run: the front (fault rule, tare, temperature compensation), the filter
 * and standardisation, the memory features, the nets with the contact decision, the tracker,
 * the outputs with the settled-hold gain.
 *
 * No float or double in this file (check-nofloat builds it with -mgeneral-regs-only).
 */
#include <string.h>

#include "fbg_stages.h"

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

fbg_status fbg_init(fbg_state *state, const fbg_model *model, uint32_t options)
{
    fbg_status st;
    uint32_t kernel, clamped = 0u;
    unsigned c;
    st = state == NULL || model == NULL ? FBG_ERR_NULL : fbg_model_check(model);
    if (st != FBG_OK)
        return st;
    kernel = fbg_simd_resolve(options & FBG_OPT_KERNEL_MASK);
    if (kernel == 0u)
        return FBG_ERR_ARG;
    memset(state, 0, sizeof *state);
    state->model = model;
    state->model_crc = model->blob_crc;
    fbg_front_init(FBG_FRONT(state), model->baseline_fm, (options & ~(uint32_t)FBG_OPT_KERNEL_MASK) | kernel);
    /* The location averages' rest reference is a model constant: computed here, not per step. */
    for (c = 0; c < FBG_N_STRAIN; ++c)
        state->loc_z0[c] = fbg_sat16_rshift_round((int64_t)-model->mean_fm[c] * model->z_mult[c],
                                                  model->z_shift, &clamped);
    state->loc_z0_clamped = (uint8_t)clamped;
    return FBG_OK;
}

uint32_t fbg_kernel(const fbg_state *state)
{
    if (state == NULL || !fbg_front_ok(FBG_FRONT((fbg_state *)state))) /* the view is only read */
        return 0u;
    return state_kernel(state);
}

size_t fbg_pack_bytes(const fbg_state *state)
{
#if FBG_SIMD_X86
    if (state == NULL || !fbg_front_ok(FBG_FRONT((fbg_state *)state))) /* the view is only read */
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
    if (!fbg_front_ok(FBG_FRONT(state)))
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
    if (!fbg_front_ok(FBG_FRONT(state)))
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

/* ---- The step's restart (docs/runtime.md, "In use") ---- */

/* Reset, tare and a new baseline restart the decision and the tracker. The baseline the
 * tracker reached stays through a reset (it is the best estimate of the unloaded gratings)
 * and becomes the reference of its bound, as a new baseline would; a tare replaces it: so a
 * reset is no different here. */
static fbg_status fbg_in_use_after(fbg_state *s, fbg_status st, int reset)
{
    (void)reset;
    if (st != FBG_OK)
        return st;   /* refused: nothing was cleared */
    FBG_RESTART_IN_USE(s);
    s->cusum_q8 = 0;
    memset(s->track_sum, 0, sizeof s->track_sum);
    memset(s->drift_fm, 0, sizeof s->drift_fm);
    memset(s->track_frac, 0, sizeof s->track_frac);
    return FBG_OK;
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

/* ---- Reset, tare and baseline: the front end's, then fbg_in_use_after ---- */

FBG_FRONT_API(fbg, fbg_state, FBG_STATE_MAGIC, fbg_in_use_after)

fbg_status fbg_get_baseline(const fbg_state *state, int32_t baseline_fm[FBG_N_CHANNELS])
{
    if (state == NULL || baseline_fm == NULL)
        return FBG_ERR_NULL;
    if (!fbg_front_ok(FBG_FRONT((fbg_state *)state))) /* the view is only read here */
        return FBG_ERR_STATE;
    memcpy(baseline_fm, state->baseline_fm, sizeof state->baseline_fm);
    return FBG_OK;
}

/* ---- Outputs ---- */

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
    const fbg_layer *last = fbg_net_accs(s, m, FBG_NET_CONTACT, in, acc, sat);
    out->contact_margin_q8 = output_row(last, 0u, acc[0], sat);
    out->contact = fbg_contact_decision(s, m, acc[0] > 0, out->contact_margin_q8);
    out->contact_conf_q15 = (uint16_t)fbg_sigmoid_q15(out->contact_margin_q8);
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
    const fbg_layer *last = fbg_net_accs(s, m, FBG_NET_FORCE, in, acc, sat);
    force_out = output_row(last, 0u, acc[0], sat);
    out->force_mN = fbg_sat32_add(force_out, m->force_offset_mN, sat);
    in[FBG_N_STRAIN] = (int16_t)(1 << m->z_frac);
    in[FBG_N_STRAIN + 1] = fbg_sat16_rshift_round((int64_t)force_out * m->fq_mult, m->fq_shift, sat);
    if (m->loc_shift)
        memcpy(in + FBG_N_STRAIN + 2, loc, FBG_N_STRAIN * sizeof *loc);
    last = fbg_net_accs(s, m, FBG_NET_LOCATION, in, acc, sat);
    out->x_um = fbg_sat32_add(output_row(last, 0u, acc[0], sat), m->xy_offset_um[0], sat);
    out->y_um = fbg_sat32_add(output_row(last, 1u, acc[1], sat), m->xy_offset_um[1], sat);
    out->force_mN = fbg_hold_stage(s, m, out->force_mN, sat);
    return out->force_mN > m->overload_mN ? FBG_STATUS_OVERLOAD : 0u;
}

/* The checks that open a step: FBG_OK with *status = the step's starting flags, or the error
 * with the safe output in out. */
static fbg_status step_begin(fbg_state *s, const int32_t *wl_fm, fbg_output *out, uint32_t *status)
{
    fbg_status st;
    if (s == NULL || wl_fm == NULL || out == NULL)
        return FBG_ERR_NULL;
    st = fbg_front_step_begin(FBG_FRONT(s), status);
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
    fbg_front_stage(s, m, wl_fm, &status, &sat);
    if (fbg_front_push_done(FBG_FRONT(s), m->n_taps, &status)) {
        safe_output(out, status);
        fbg_rest_track(s, m, NULL);
        return FBG_OK;
    }
    /* 2. Filter and standardise into z = in[0..3], which the tracker's creep states follow
     *    (before the memory stage marks the states primed); 3. the memory features after z. */
    status |= fbg_filter_stage(s, m, in, &sat);
    fbg_creep_update(s, m, in);
    fbg_memory_stage(s, m, in, loc, &sat);
    status |= out_of_range(m, in);

    /* 4. Contact net and the decision, the tracker on samples at rest; while the decision
     *    holds (contact, and the release band after it) the force and location nets. */
    memset(out, 0, sizeof *out);
    contact_outputs(s, m, in, out, &sat);
    fbg_rest_track(s, m, s->decision || !s->tared || (status & FBG_STATUS_WARMUP) ? NULL : in);
    if (s->decision) {
        status |= force_location_outputs(s, m, in, loc, out, &sat);
        if (s->released)
            status |= FBG_STATUS_RELEASING;
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
