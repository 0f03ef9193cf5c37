/*
 * fbgf_float.c - the same pipeline in single-precision float (the "cfloat" engine and the
 * build for FPU targets). Mirrors fbgforce.model's float64 reference operation by operation;
 * only this file uses float (check-nofloat leaves it out). Its stages carry the names of the
 * fixed-point build's (fbg_stages.h) with its own prefix: fbgf_front_stage, fbgf_filter_stage,
 * fbgf_memory_stage, fbgf_contact_decision, fbgf_creep_update, fbgf_rest_track,
 * fbgf_hold_stage; reset, tare and baseline are the front end's (FBG_FRONT_API, fbg_front.h).
 */
#include <string.h>

#include "fbg_front.h"
#include "fbgf_dense.h"

size_t fbgf_state_size(void)
{
    return sizeof(fbgf_state);
}

/* exp(x) for x in [-87, 88] to ~2 ulp without libm (the library links nothing beyond
 * <string.h>): x = k ln2 + r, |r| <= ln2/2, degree-6 Taylor polynomial of exp(r), 2^k by
 * building the exponent bits. */
static float fbgf_exp(float x)
{
    const float ln2_hi = 0.693145751953125f, ln2_lo = 1.428606765330187e-06f;
    float kf, r, p;
    int32_t k;
    union {
        uint32_t u;
        float f;
    } two_k;
    /* Written so that NaN also lands in range: the float -> int conversion below would be
     * undefined behaviour for NaN or out-of-range values. */
    if (!(x > -87.0f))
        x = -87.0f;
    if (x > 88.0f)
        x = 88.0f;
    kf = x * 1.4426950408889634f;
    k = (int32_t)(kf + (kf >= 0.0f ? 0.5f : -0.5f));
    kf = (float)k;
    r = (x - kf * ln2_hi) - kf * ln2_lo;
    p = 1.0f + r * (1.0f + r * (0.5f + r * (1.0f / 6.0f + r * (1.0f / 24.0f + r * (1.0f / 120.0f + r * (1.0f / 720.0f))))));
    two_k.u = (uint32_t)(k + 127) << 23;
    return p * two_k.f;
}

/* Finite (not NaN, not +-inf) without libm: inf - inf and NaN - NaN are NaN. */
static int finite_f(float x)
{
    return x == x && x - x == 0.0f;
}

static int all_finite(const float *x, size_t n)
{
    size_t i;
    for (i = 0; i < n; ++i)
        if (!finite_f(x[i]))
            return 0;
    return 1;
}

/* 1 when a parameter of the decision over time, the tracker, the creep inverse or the hold lies
 * outside the ranges of fbg_model's (fbg_contract.c). */
static int in_use_params_out_of_range(const fbgf_model *model)
{
    return (!(model->contact_on >= 0.0f) || !finite_f(model->contact_on) ||
           !(model->contact_off <= 0.0f) || !finite_f(model->contact_off) ||
           model->contact_rise_n < 1u || model->track_shift > 20u ||
           !(model->track_creep >= 0.0f && model->track_creep <= 0.5f) ||
           model->track_creep_shift > FBG_MAX_EMA_SHIFT ||
           (model->track_creep != 0.0f && model->track_creep_shift == 0u) ||
           !(model->contact_cusum_h >= 0.0f && model->contact_cusum_h <= FBG_MAX_CUSUM_Q8 / 256.0f) ||
           !(model->contact_cusum_k >= -FBG_MAX_CUSUM_Q8 / 256.0f &&
             model->contact_cusum_k <= FBG_MAX_CUSUM_Q8 / 256.0f) ||
           !(model->contact_cusum_lo >= -FBG_MAX_CUSUM_Q8 / 256.0f &&
             model->contact_cusum_lo <= FBG_MAX_CUSUM_Q8 / 256.0f) ||
           !(model->contact_cusum_hi >= -FBG_MAX_CUSUM_Q8 / 256.0f &&
             model->contact_cusum_hi <= FBG_MAX_CUSUM_Q8 / 256.0f) ||
           (model->contact_cusum_h == 0.0f
                ? (model->contact_cusum_k != 0.0f || model->contact_cusum_lo != 0.0f ||
                   model->contact_cusum_hi != 0.0f)
                : (model->contact_cusum_lo > model->contact_cusum_hi ||
                   model->contact_on != 0.0f || model->contact_rise_n != 1u)) ||
           !(model->creep_q >= 0.0f && model->creep_q < 1.0f) ||
           model->creep_shift > FBG_MAX_EMA_SHIFT || (model->creep_q != 0.0f && model->creep_shift == 0u) ||
           !(model->hold_gain >= -0.125f && model->hold_gain <= 0.125f) ||
           model->hold_shift > FBG_MAX_EMA_SHIFT || (model->hold_gain != 0.0f && model->hold_shift == 0u) ||
           model->hold_ramp_shift > FBG_MAX_HOLD_RAMP_SHIFT ||
           !(model->hold_band_N >= 0.0f) || !finite_f(model->hold_band_N) ||
           !(model->hold_band_frac >= 0.0f && model->hold_band_frac <= 1.0f) ||
           !(model->track_step_max_pm >= 0.0f) || !finite_f(model->track_step_max_pm) ||
           !(model->track_limit_pm >= 0.0f) || !(model->track_limit_pm <= FBG_TRACK_LIMIT_MAX_FM * 1e-3f));
}

/* Each net's shape (inputs as the model's features give them, outputs as its role needs),
 * every layer's pointers and finite weights. */
static fbg_status nets_check(const fbgf_model *model, const uint16_t net_in[FBG_N_NETS])
{
    static const uint16_t net_out[FBG_N_NETS] = {2u, 1u, 2u};
    unsigned n, l;
    for (n = 0; n < FBG_N_NETS; ++n) {
        const fbgf_net *net = &model->nets[n];
        if (net->n_layers < 1u || net->n_layers > FBG_MAX_LAYERS)
            return FBG_ERR_SHAPE;
        if (net->layers[0].n_in != net_in[n] || net->layers[net->n_layers - 1u].n_out != net_out[n])
            return FBG_ERR_SHAPE;
        for (l = 0; l < net->n_layers; ++l) {
            const fbgf_layer *ly = &net->layers[l];
            if (ly->n_in < 1u || ly->n_in > FBG_MAX_WIDTH || ly->n_out < 1u || ly->n_out > FBG_MAX_WIDTH)
                return FBG_ERR_SHAPE;
            if (l > 0u && ly->n_in != net->layers[l - 1u].n_out)
                return FBG_ERR_SHAPE;
            if (ly->w == NULL || ly->b == NULL)
                return FBG_ERR_NULL;
            if (!all_finite(ly->w, (size_t)ly->n_in * ly->n_out) || !all_finite(ly->b, ly->n_out))
                return FBG_ERR_RANGE;
        }
    }
    return FBG_OK;
}

fbg_status fbgf_model_check(const fbgf_model *model)
{
    uint16_t net_in[FBG_N_NETS];
    unsigned c, features;
    fbg_status st;
    if (model == NULL)
        return FBG_ERR_NULL;
    st = fbgf_memory_check(model);
    if (st != FBG_OK)
        return st;
    features = FBG_N_STRAIN + FBG_N_MEMORY_FEATURES(model);
    net_in[FBG_NET_CONTACT] = (uint16_t)features;
    net_in[FBG_NET_FORCE] = (uint16_t)features;
    net_in[FBG_NET_LOCATION] = (uint16_t)(FBG_N_STRAIN + 2u + (model->loc_shift ? FBG_N_STRAIN : 0u));
    if (model->loc_shift > FBG_MAX_EMA_SHIFT)
        return FBG_ERR_RANGE;
    if (!all_finite(model->mem_weight, FBG_N_STRAIN))
        return FBG_ERR_RANGE;
    if (in_use_params_out_of_range(model))
        return FBG_ERR_RANGE;
    for (c = 0; c < FBG_MAX_INPUTS; ++c)
        if (!(model->in_lo[c] <= model->in_hi[c]))   /* NaN or crossed bounds */
            return FBG_ERR_RANGE;
    if (model->n_taps < 1u || model->n_taps > FBG_MAX_TAPS)
        return FBG_ERR_SHAPE;
    if (model->taps == NULL)
        return FBG_ERR_NULL;
    if (model->jump_max_fm <= 0 || !fbg_baseline_ok(model->baseline_fm) ||
        model->ref_shift > FBG_MAX_REF_SHIFT)
        return FBG_ERR_RANGE;
    for (c = 0; c < FBG_N_STRAIN; ++c)
        if (!(model->input_std_pm[c] > 0.0f))
            return FBG_ERR_RANGE;
    /* A NaN/inf parameter would make every output NaN: refuse the model instead
     * (docs/robustness.md). overload_N may be +inf ("no overload threshold"), not NaN. */
    if (!all_finite(model->temp_coeff, FBG_N_STRAIN) || !all_finite(model->input_mean_pm, FBG_N_STRAIN) ||
        !all_finite(model->input_std_pm, FBG_N_STRAIN) || !all_finite(model->xy_offset_mm, 2) ||
        !all_finite(model->xy_scale, 2) || !finite_f(model->force_offset_N) ||
        !finite_f(model->force_scale) || model->overload_N != model->overload_N ||
        !all_finite(model->taps, model->n_taps))
        return FBG_ERR_RANGE;
    return nets_check(model, net_in);
}

/* The shared front end's view of a float state (fbg_front.h). */
#define FBGF_FRONT(s) FBG_FRONT_OF(s, FBGF_STATE_MAGIC)

/* The memory kinds' update rules (FBG_MEMORY_KINDS), as fbg_stage_memory.c's <kind>_features in float:
 * from the load signal u, prime the states (primed == 0) as at rest after a release, step them
 * and write their features to f[0 ..]; each returns the number of features it wrote. */
static unsigned ema_features_f(fbgf_state *s, const fbgf_model *m, float u, int primed, float *f)
{
    unsigned k;
    if (!primed)
        for (k = 0; k < m->n_ema; ++k)
            s->ema[k] = u;
    for (k = 0; k < m->n_ema; ++k) {
        s->ema[k] += (u - s->ema[k]) / (float)(1u << m->ema_shift[k]);
        f[k] = (u - s->ema[k]) * (float)(1u << m->ema_gain[k]);
    }
    return m->n_ema;
}

static unsigned play_features_f(fbgf_state *s, const fbgf_model *m, float u, int primed, float *f)
{
    unsigned k;
    if (!primed)
        for (k = 0; k < m->n_play; ++k)
            s->play[k] = u + m->play_width[k];
    for (k = 0; k < m->n_play; ++k) {
        float w = m->play_width[k], p = s->play[k];
        p = p < u - w ? u - w : (p > u + w ? u + w : p);
        s->play[k] = p;
        f[k] = (u - p) * (float)(1u << m->play_gain[k]);
    }
    return m->n_play;
}

/* Memory features after z, as fbg_memory_stage in float (the states follow the
 * load signal u, are primed by the first sample after a reset as at rest after a release,
 * and are frozen during a fault); loc[] gets the location averages of z - z_rest. */
static void fbgf_memory_stage(fbgf_state *s, const fbgf_model *m, float *in, float *loc)
{
    unsigned c;
    int primed;
    float u = 0.0f, *f = in + FBG_N_STRAIN;
    if (m->loc_shift) {
        for (c = 0; c < FBG_N_STRAIN; ++c) {
            /* z_rest = -mean / std: the standardised zero shift */
            float r = in[c] + m->input_mean_pm[c] / m->input_std_pm[c];
            if (!s->mem_primed)
                s->loc[c] = r;
            s->loc[c] += (r - s->loc[c]) / (float)(1u << m->loc_shift);
            loc[c] = s->loc[c];
        }
    }
    if (FBG_N_MEMORY_FEATURES(m) == 0u) {
        s->mem_primed = 1u;
        return;
    }
    for (c = 0; c < FBG_N_STRAIN; ++c)
        u += m->mem_weight[c] * in[c];
    primed = s->mem_primed;
#define FBG_KIND_FEATURES(kind, KIND) f += kind##_features_f(s, m, u, primed, f);
    FBG_MEMORY_KINDS(FBG_KIND_FEATURES)
#undef FBG_KIND_FEATURES
    s->mem_primed = 1u;
}

fbg_status fbgf_init(fbgf_state *state, const fbgf_model *model, uint32_t options)
{
    fbg_status st;
    st = state == NULL || model == NULL ? FBG_ERR_NULL : fbgf_model_check(model);
    if (st != FBG_OK)
        return st;
    memset(state, 0, sizeof *state);
    state->model = model;
    fbg_front_init(FBGF_FRONT(state), model->baseline_fm, options);
    return FBG_OK;
}

/* Reset, tare and a new baseline restart the decision and the tracker, as fbg_in_use_after
 * does: the correction made so far stays through a reset (held) and the bound counts from
 * there; a tare or a new baseline replaces it. */
static fbg_status fbgf_in_use_after(fbgf_state *s, fbg_status st, int reset)
{
    unsigned c;
    if (st != FBG_OK)
        return st;
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        s->held_pm[c] = reset ? s->held_pm[c] + s->drift_pm[c] : 0.0f;
        s->drift_pm[c] = 0.0f;
        s->track_sum[c] = 0.0f;
    }
    FBG_RESTART_IN_USE(s);
    s->cusum = 0.0f;
    return FBG_OK;
}

/* fbg_hold_stage in float: force_N of a contact sample times 1 + hold_gain * w /
 * 2^hold_ramp_shift once it has been steady for hold_settle samples. */
static float fbgf_hold_stage(fbgf_state *s, const fbgf_model *m, float force_N)
{
    const float ramp = (float)(1ul << m->hold_ramp_shift);
    float band, dev;
    uint32_t w;
    if (m->hold_gain == 0.0f)
        return force_N;
    if (!s->hold_primed) {
        s->hold_avg_N = force_N;
        s->hold_primed = 1u;
    } else {
        s->hold_avg_N += (force_N - s->hold_avg_N) / (float)(1ul << m->hold_shift);
    }
    dev = force_N - s->hold_avg_N;
    band = m->hold_band_frac * (force_N < 0.0f ? -force_N : force_N);
    if (band < m->hold_band_N)
        band = m->hold_band_N;
    w = fbg_hold_weight(&s->hold_run, (dev < 0.0f ? -dev : dev) <= band, m->hold_settle,
                        m->hold_ramp_shift);
    return force_N + force_N * m->hold_gain * ((float)w / ramp);
}

FBG_FRONT_API(fbgf, fbgf_state, FBGF_STATE_MAGIC, fbgf_in_use_after)

/* Dense ReLU MLP over n samples (rows x + i * x_stride); a[0] and a[1] are ping-pong buffers of
 * n rows of FBG_MAX_WIDTH. Returns the output rows (stride FBG_MAX_WIDTH, inside a). */
static const float *fbgf_net_outputs(fbgf_kernel kernel, const fbgf_net *net, const float *x, size_t x_stride,
                         size_t n, float *a[2])
{
    unsigned l, buf = 0u;
    for (l = 0; l < net->n_layers; ++l) {
        fbgf_dense(kernel, &net->layers[l], x, x_stride, a[buf], FBG_MAX_WIDTH, n, l + 1u < net->n_layers);
        x = a[buf];
        x_stride = FBG_MAX_WIDTH;
        buf ^= 1u;
    }
    return x;
}

/* fir_tap spells out the four strain channels. */
typedef char fbgf_require_four_strain_channels[FBG_N_STRAIN == 4 ? 1 : -1];

static void fir_tap(float a[FBG_N_STRAIN], float tap, const float h[FBG_N_STRAIN])
{
    a[0] += tap * h[0];
    a[1] += tap * h[1];
    a[2] += tap * h[2];
    a[3] += tap * h[3];
}

/* The temperature reference of a sample that passed the fault rule (docs/fixed-point.md,
 * "temperature reference", in float): the average of the reference grating's shift_t (pm),
 * the n-th good sample after init, tare, reset or a new baseline moving it by
 * (shift_t - r) / 2^min(ref_shift, floor(log2 n)); the raw shift when ref_shift is 0. */
static float ref_update(fbgf_state *s, const fbgf_model *m, float shift_t)
{
    unsigned n, k = m->ref_shift, shift = k;
    if (k == 0u)
        return shift_t;
    n = (unsigned)s->ref_count + 1u;
    if (n < (1u << k)) {
        shift = 0u;
        while ((2u << shift) <= n)
            ++shift;
    }
    if (s->ref_count == 0u)
        s->ref_pm = shift_t;
    else
        s->ref_pm += (shift_t - s->ref_pm) * (1.0f / (float)(1u << shift));
    if (s->ref_count < 255u)
        ++s->ref_count;
    return s->ref_pm;
}

/* fbg_creep_update in float: the tracker's creep states follow the filtered shifts
 * (pm) of every sample that passed the fault rule, primed with the memory states. */
static void fbgf_creep_update(fbgf_state *s, const fbgf_model *m, const float *filt)
{
    unsigned c;
    if (m->track_creep == 0.0f)
        return;
    for (c = 0; c < FBG_N_STRAIN; ++c)
        s->creep_pm[c] = s->mem_primed ? s->creep_pm[c] + (filt[c] - s->creep_pm[c]) *
                                             (1.0f / (float)(1u << m->track_creep_shift))
                                       : filt[c];
}

/* The creep inverse of fbg_front_stage in float: the pad's creep taken out of a good sample's
 * compensated shifts comp (pm) before they enter the ring, e = c + creep_q (c - L), then
 * L += (e - L) / 2^creep_shift; primed L = c by the first good sample after init, tare, reset
 * or a new baseline. */
static void fbgf_creep_inverse(fbgf_state *s, const fbgf_model *m, float *comp)
{
    unsigned c;
    if (m->creep_q == 0.0f)
        return;
    if (!s->creep_primed) {
        memcpy(s->creep_lag_pm, comp, sizeof s->creep_lag_pm);
        s->creep_primed = 1u;
        return;
    }
    for (c = 0; c < FBG_N_STRAIN; ++c) {
        const float lag = s->creep_lag_pm[c];
        comp[c] += m->creep_q * (comp[c] - lag);
        s->creep_lag_pm[c] = lag + (comp[c] - lag) * (1.0f / (float)(1u << m->creep_shift));
    }
}

/* 1. Front, as fbg_front_stage: the fault rule, the temperature compensation (less the
 * tracker's correction) and the creep inverse of a sample into the FIR ring at s->pos; a
 * faulty sample feeds the ring the last good filtered shifts. */
static void fbgf_front_stage(fbgf_state *s, const fbgf_model *m, const int32_t wl_fm[FBG_N_CHANNELS],
                             uint32_t *status)
{
    float comp[FBG_N_STRAIN];
    int32_t shift[FBG_N_CHANNELS];
    unsigned c;
    if (fbg_front_sample(FBGF_FRONT(s), wl_fm, m->jump_max_fm, m->stuck_max, status, shift)) {
        memcpy(comp, s->last_comp, sizeof comp);
    } else {
        /* The integer difference is exact; as float it keeps 24 bits (exact below 16.7 nm). */
        float shift_t = ref_update(s, m, (float)shift[FBG_N_STRAIN] * 1e-3f);
        for (c = 0; c < FBG_N_STRAIN; ++c)
            comp[c] = (float)shift[c] * 1e-3f - m->temp_coeff[c] * shift_t -
                      (s->held_pm[c] + s->drift_pm[c]);
        fbgf_creep_inverse(s, m, comp);
    }
    for (c = 0; c < FBG_N_STRAIN; ++c)
        s->hist[s->pos][c] = comp[c];
}

/* 2. Filter, as fbg_filter_stage: the FIR into filt (pm) and z = in[0..3]; then the ring
 * moves on. Taps outer, channels inner: each channel sums its taps in order (newest sample
 * first), and the four independent sums can share vector instructions. The ring is walked as
 * two straight runs (pos down to 0, then the top down to pos + 1). */
static void fbgf_filter_stage(fbgf_state *s, const fbgf_model *m, float in[FBG_MAX_INPUTS],
                              float filt[FBG_N_STRAIN])
{
    float a[FBG_N_STRAIN];
    unsigned c, k, idx;
    for (c = 0; c < FBG_N_STRAIN; ++c)
        a[c] = 0.0f;
    k = 0u;
    for (idx = s->pos + 1u; idx-- > 0u; ++k)
        fir_tap(a, m->taps[k], s->hist[idx]);
    for (idx = m->n_taps; k < m->n_taps; ++k)
        fir_tap(a, m->taps[k], s->hist[--idx]);
    for (c = 0; c < FBG_N_STRAIN; ++c)
        in[c] = (a[c] - m->input_mean_pm[c]) / m->input_std_pm[c];
    memcpy(filt, a, sizeof a);
    memcpy(s->last_comp, a, sizeof a); /* held into the ring through a fault */
    s->pos = (uint16_t)((s->pos + 1u) % m->n_taps);
}

/* Everything before the nets: the front, filter and memory stages into in[], the location
 * averages into loc[] (when the model has them). Returns 1 when the nets must run (out->status
 * then holds the status so far), 0 when out is final (*st is what the step returns). */
static int step_inputs(fbgf_state *s, const int32_t wl_fm[FBG_N_CHANNELS], fbgf_output *out,
                       float in[FBG_MAX_INPUTS], float loc[FBG_N_STRAIN], float filt[FBG_N_STRAIN],
                       fbg_status *st)
{
    const fbgf_model *m;
    uint32_t status;
    unsigned c;

    memset(out, 0, sizeof *out);
    *st = fbg_front_step_begin(FBGF_FRONT(s), &status);
    if (*st != FBG_OK) {
        out->status = status;
        return 0;
    }
    m = s->model;
    fbgf_front_stage(s, m, wl_fm, &status);
    if (fbg_front_push_done(FBGF_FRONT(s), m->n_taps, &status)) {
        out->status = status;
        return 0;
    }
    fbgf_filter_stage(s, m, in, filt);
    fbgf_creep_update(s, m, filt);
    fbgf_memory_stage(s, m, in, loc);
    for (c = 0; c < FBG_N_STRAIN + FBG_N_MEMORY_FEATURES(m); ++c)
        if (!(in[c] >= m->in_lo[c] && in[c] <= m->in_hi[c]))
            status |= FBG_STATUS_OUT_OF_RANGE;
    out->status = status;
    return 1;
}

/* The contact decision from the contact net's logits y. Returns 1 when the force and
 * location nets must run. */
static int contact_output(const float *y, fbgf_output *out)
{
    float margin = y[1] - y[0];
    if (!finite_f(margin)) {
        /* Float overflow inside the nets (finite parameters, extreme inputs): the float
         * analogue of a clamp. Safe output, never a NaN/inf (docs/robustness.md). */
        out->status |= FBG_STATUS_SATURATED;
        return 0;
    }
    out->margin = margin;
    out->contact = margin > 0.0f ? 1u : 0u;
    out->p_contact = 1.0f / (1.0f + fbgf_exp(-margin));
    return out->contact;
}

/* The force from the force net's output f; in[] becomes the location net's input. */
static void force_output(const fbgf_model *m, float f, fbgf_output *out, float in[FBG_MAX_INPUTS],
                         const float loc[FBG_N_STRAIN])
{
    out->force_N = m->force_offset_N + m->force_scale * f;
    if (out->force_N > m->overload_N)
        out->status |= FBG_STATUS_OVERLOAD;
    in[FBG_N_STRAIN] = 1.0f;      /* the location net reads z1..z4, contact, force */
    in[FBG_N_STRAIN + 1] = f;
    if (m->loc_shift)             /* ... and the location averages */
        memcpy(in + FBG_N_STRAIN + 2, loc, FBG_N_STRAIN * sizeof *loc);
}

/* The location from the location net's outputs y. Returns 0 for a non-finite output, which
 * becomes the safe one. */
static int location_output(const fbgf_model *m, const float *y, fbgf_output *out)
{
    out->x_mm = m->xy_offset_mm[0] + m->xy_scale[0] * y[0];
    out->y_mm = m->xy_offset_mm[1] + m->xy_scale[1] * y[1];
    if (!finite_f(out->force_N) || !finite_f(out->x_mm) || !finite_f(out->y_mm)) {
        uint32_t status = out->status;
        memset(out, 0, sizeof *out);
        out->status = (status & ~(uint32_t)(FBG_STATUS_OVERLOAD | FBG_STATUS_RELEASING))
                    | FBG_STATUS_SATURATED;
        return 0;
    }
    return 1;
}

/* contact_rises of fbg_stage_decision.c on the float margin, 1 when contact rises: the
 * Schmitt trigger with its count, or with contact_cusum_h > 0 the CUSUM rise S = max(0, S +
 * clamp(margin, lo, hi) - k), contact when S >= h (S = 0 then). */
static int fbgf_contact_rises(fbgf_state *s, const fbgf_model *m, float margin)
{
    float d;
    if (m->contact_cusum_h == 0.0f)
        return fbg_rise_count(&s->rise_run, margin > 0.0f && margin >= m->contact_on,
                              m->contact_rise_n);
    d = margin < m->contact_cusum_lo ? m->contact_cusum_lo
      : (margin > m->contact_cusum_hi ? m->contact_cusum_hi : margin);
    d = s->cusum + (d - m->contact_cusum_k);
    s->cusum = d > 0.0f ? d : 0.0f;
    if (s->cusum < m->contact_cusum_h)
        return 0;
    s->cusum = 0.0f;
    return 1;
}

/* fbg_contact_decision on the float margin: the hold and the release band of
 * fbg_decision_wants_rise, the rise of fbgf_contact_rises. Returns the contact shown. */
static uint8_t fbgf_contact_decision(fbgf_state *s, const fbgf_model *m, float margin)
{
    if (fbg_decision_wants_rise(&s->decision, &s->released, &s->release_run, margin > 0.0f,
                                margin > 0.0f || margin > m->contact_off)
        && fbgf_contact_rises(s, m, margin)) {
        s->decision = 1u;
        s->released = 0u;
    }
    return (uint8_t)(s->decision && !s->released);
}

/* fbg_rest_track in float: filt is the filtered shifts (pm) of a sample at rest,
 * NULL otherwise; each sample adds filt - track_creep * creep_pm (creep_pm is 0 with the term
 * off); a block at rest throughout, after track_settle samples of rest, adds
 * clamp(sum / 2^track_shift, +-track_step_max_pm) to the correction, whose part since
 * the last reset or tare stays within +-track_limit_pm. */
static void fbgf_rest_track(fbgf_state *s, const fbgf_model *m, const float *filt)
{
    unsigned c;
    int block;
    if (filt != NULL)
        for (c = 0; c < FBG_N_STRAIN; ++c)
            s->track_sum[c] += filt[c] - m->track_creep * s->creep_pm[c];
    block = fbg_track_block(&s->rest_run, &s->track_pos, filt != NULL, m->track_shift, m->track_settle);
    if (block < 0)
        return;
    if (block) {
        const float scale = 1.0f / (float)(1ul << m->track_shift);
        for (c = 0; c < FBG_N_STRAIN; ++c) {
            float step = s->track_sum[c] * scale, drift;
            step = step > m->track_step_max_pm ? m->track_step_max_pm
                 : (step < -m->track_step_max_pm ? -m->track_step_max_pm : step);
            drift = s->drift_pm[c] + step;
            if (drift > m->track_limit_pm || drift < -m->track_limit_pm) {
                drift = drift > 0.0f ? m->track_limit_pm : -m->track_limit_pm;
                s->track_limited = 1u;
            }
            s->drift_pm[c] = drift;
        }
    }
    for (c = 0; c < FBG_N_STRAIN; ++c)
        s->track_sum[c] = 0.0f;
}

#if FBGF_RUN_BATCHED
/* The model's decision is the contact net's own and no tracker runs: fbgf_run may batch. */
static int in_use_off(const fbgf_model *m)
{
    return m->track_shift == 0u && m->contact_on == 0.0f && m->contact_off == 0.0f &&
           m->contact_rise_n == 1u && m->contact_cusum_h == 0.0f && m->hold_gain == 0.0f;
}
#endif

fbg_status fbgf_step(fbgf_state *s, const int32_t wl_fm[FBG_N_CHANNELS], fbgf_output *out)
{
    const fbgf_model *m;
    float in[FBG_MAX_INPUTS], loc[FBG_N_STRAIN], filt[FBG_N_STRAIN], *act[2];
    const float *y;
    fbgf_kernel kernel;
    fbg_status st;
    int ran;

    if (s == NULL || wl_fm == NULL || out == NULL)
        return FBG_ERR_NULL;
    ran = step_inputs(s, wl_fm, out, in, loc, filt, &st);
    if (st != FBG_OK)
        return st;
    m = s->model;
    if (s->track_limited)
        out->status |= FBG_STATUS_BASELINE_LIMIT;
    if (!ran) {
        fbgf_rest_track(s, m, NULL);    /* a fault: the decision holds, the tracker restarts */
        return FBG_OK;
    }
    kernel = fbgf_dense_kernel();
    act[0] = s->act[0];
    act[1] = s->act[1];
    y = fbgf_net_outputs(kernel, &m->nets[FBG_NET_CONTACT], in, FBG_MAX_INPUTS, 1u, act);
    if (!finite_f(y[1] - y[0])) {      /* the safe output, and as a fault for the states */
        contact_output(y, out);
        fbgf_rest_track(s, m, NULL);
        return FBG_OK;
    }
    contact_output(y, out);
    out->contact = fbgf_contact_decision(s, m, out->margin);
    fbgf_rest_track(s, m, s->decision || !s->tared || (out->status & FBG_STATUS_WARMUP) ? NULL : filt);
    if (!s->decision) {
        s->hold_primed = 0u;
        s->hold_run = 0u;
        return FBG_OK;
    }
    if (s->released)
        out->status |= FBG_STATUS_RELEASING;
    y = fbgf_net_outputs(kernel, &m->nets[FBG_NET_FORCE], in, FBG_MAX_INPUTS, 1u, act);
    force_output(m, y[0], out, in, loc);
    y = fbgf_net_outputs(kernel, &m->nets[FBG_NET_LOCATION], in, FBG_MAX_INPUTS, 1u, act);
    if (!location_output(m, y, out)) {
        s->hold_primed = 0u;
        s->hold_run = 0u;
    } else if (m->hold_gain != 0.0f) {
        out->force_N = fbgf_hold_stage(s, m, out->force_N);
        if (out->force_N > m->overload_N)
            out->status |= FBG_STATUS_OVERLOAD;
    }
    return FBG_OK;
}

#if FBGF_RUN_BATCHED
/* fbgf_run runs the nets of FBGF_RUN_CHUNK samples together, so that each block of weights is
 * loaded once for all of them; run_chunk's buffers take 2 x 16 x FBG_MAX_WIDTH floats (16 kB)
 * of stack. */

#if FBGF_HAVE_AVX2 && FBGF_RUN_LANES
/* The first n_in inputs of the n samples in `in` into lanes (fbgf_dense_lanes); the lanes past
 * n get zeros. */
static void to_lanes(float in[][FBG_MAX_INPUTS], size_t n, unsigned n_in, float *x)
{
    unsigned j;
    size_t k;
    for (j = 0; j < n_in; ++j)
        for (k = 0; k < FBGF_RUN_CHUNK; ++k)
            x[j * FBGF_RUN_CHUNK + k] = k < n ? in[k][j] : 0.0f;
}

/* fbgf_net_outputs for samples in lanes: `x` holds the net's inputs (to_lanes); returns the outputs, output
 * r of sample k at [r * FBGF_RUN_CHUNK + k]. */
static const float *fbgf_net_lanes(const fbgf_net *net, const float *x, size_t n, float *a[2])
{
    const unsigned n_vec = (unsigned)((n + 7u) / 8u);
    unsigned l, buf = 0u;
    for (l = 0; l < net->n_layers; ++l) {
        fbgf_dense_lanes(&net->layers[l], x, a[buf], n_vec, l + 1u < net->n_layers);
        x = a[buf];
        buf ^= 1u;
    }
    return x;
}

/* The nets of run_chunk on the AVX2+FMA kernel with the samples in lanes: each sample gets the
 * bits of fbgf_step, whose kernel sums every output in the same order (fbgf_dense.c). in[k] and
 * loc[k] belong to out[who[k]]; the rows of the contact samples move to the front of in[]. */
static void run_nets_lanes(const fbgf_model *m, float in[][FBG_MAX_INPUTS],
                           float loc[][FBG_N_STRAIN], const size_t *who, size_t n_run,
                           fbgf_output *out, float *act[2])
{
    float x[FBG_MAX_INPUTS * FBGF_RUN_CHUNK], y2[2];
    size_t k, n_contact = 0u, row[FBGF_RUN_CHUNK];
    const float *y;
    to_lanes(in, n_run, m->nets[FBG_NET_CONTACT].layers[0].n_in, x);
    y = fbgf_net_lanes(&m->nets[FBG_NET_CONTACT], x, n_run, act);
    for (k = 0; k < n_run; ++k) {
        y2[0] = y[k];
        y2[1] = y[FBGF_RUN_CHUNK + k];
        if (contact_output(y2, out + who[k])) {
            if (n_contact != k)
                memcpy(in[n_contact], in[k], sizeof in[k]);
            row[n_contact++] = k;
        }
    }
    if (n_contact == 0u)
        return;
    to_lanes(in, n_contact, m->nets[FBG_NET_FORCE].layers[0].n_in, x);
    y = fbgf_net_lanes(&m->nets[FBG_NET_FORCE], x, n_contact, act);
    for (k = 0; k < n_contact; ++k)
        force_output(m, y[k], out + who[row[k]], in[k], loc[row[k]]);
    to_lanes(in, n_contact, m->nets[FBG_NET_LOCATION].layers[0].n_in, x);
    y = fbgf_net_lanes(&m->nets[FBG_NET_LOCATION], x, n_contact, act);
    for (k = 0; k < n_contact; ++k) {
        y2[0] = y[k];
        y2[1] = y[FBGF_RUN_CHUNK + k];
        location_output(m, y2, out + who[row[k]]);
    }
}
#endif

/* n samples through the front end one by one (the state advances in order), then each net
 * for all samples that need it, layer by layer. Every sample's outputs are those fbgf_step
 * gives: the nets are pure functions of their inputs and fbgf_dense computes a sample the
 * same way whatever else it runs with. */
static fbg_status run_chunk(fbgf_state *s, fbgf_kernel kernel, const int32_t *wl_fm, size_t n,
                            fbgf_output *out)
{
    const fbgf_model *m = s->model;
    float in[FBGF_RUN_CHUNK][FBG_MAX_INPUTS], in2[FBGF_RUN_CHUNK][FBG_MAX_INPUTS];
    float loc[FBGF_RUN_CHUNK][FBG_N_STRAIN];
    float buf0[FBGF_RUN_CHUNK][FBG_MAX_WIDTH], buf1[FBGF_RUN_CHUNK][FBG_MAX_WIDTH], *act[2];
    size_t i, k, n_run = 0u, n_contact = 0u, who[FBGF_RUN_CHUNK], touched[FBGF_RUN_CHUNK];
    size_t row[FBGF_RUN_CHUNK];   /* the row of in[] and loc[] of each contact sample */
    fbg_status st = FBG_OK;
    const float *y;

    act[0] = &buf0[0][0];
    act[1] = &buf1[0][0];
    float filt[FBG_N_STRAIN];
    for (i = 0; i < n && st == FBG_OK; ++i)
        if (step_inputs(s, wl_fm + i * FBG_N_CHANNELS, out + i, in[n_run], loc[n_run], filt, &st))
            who[n_run++] = i;
    if (n_run == 0u)
        return st;
#if FBGF_HAVE_AVX2 && FBGF_RUN_LANES
    if (kernel == FBGF_KERNEL_AVX2_FMA) {
        run_nets_lanes(m, in, loc, who, n_run, out, act);
        return st;
    }
#endif
    y = fbgf_net_outputs(kernel, &m->nets[FBG_NET_CONTACT], &in[0][0], FBG_MAX_INPUTS, n_run, act);
    for (k = 0; k < n_run; ++k)
        if (contact_output(y + k * FBG_MAX_WIDTH, out + who[k])) {
            memcpy(in2[n_contact], in[k], sizeof in[k]);
            row[n_contact] = k;
            touched[n_contact++] = who[k];
        }
    if (n_contact == 0u)
        return st;
    y = fbgf_net_outputs(kernel, &m->nets[FBG_NET_FORCE], &in2[0][0], FBG_MAX_INPUTS, n_contact, act);
    for (k = 0; k < n_contact; ++k)
        force_output(m, y[k * FBG_MAX_WIDTH], out + touched[k], in2[k], loc[row[k]]);
    y = fbgf_net_outputs(kernel, &m->nets[FBG_NET_LOCATION], &in2[0][0], FBG_MAX_INPUTS, n_contact, act);
    for (k = 0; k < n_contact; ++k)
        location_output(m, y + k * FBG_MAX_WIDTH, out + touched[k]);
    return st;
}
#endif

fbg_status fbgf_run(fbgf_state *state, const int32_t *wl_fm, size_t n, fbgf_output *out)
{
    size_t i;
    fbg_status st;
    if (state == NULL || (n > 0u && (wl_fm == NULL || out == NULL)))
        return FBG_ERR_NULL;
#if FBGF_RUN_BATCHED
    /* The decision over time and the tracker carry state from sample to sample through the
     * nets' outputs: then one step at a time (the batch is the nets of many samples at once). */
    if (fbg_front_ok(FBGF_FRONT(state)) && in_use_off(state->model)) {
        const fbgf_kernel kernel = fbgf_dense_kernel();
        for (i = 0; i < n; i += FBGF_RUN_CHUNK) {
            size_t len = n - i < FBGF_RUN_CHUNK ? n - i : FBGF_RUN_CHUNK;
            st = run_chunk(state, kernel, wl_fm + i * FBG_N_CHANNELS, len, out + i);
            if (st != FBG_OK)
                return st;
        }
        return FBG_OK;
    }
#endif
    for (i = 0; i < n; ++i) {
        st = fbgf_step(state, wl_fm + i * FBG_N_CHANNELS, out + i);
        if (st != FBG_OK)
            return st;
    }
    return FBG_OK;
}
