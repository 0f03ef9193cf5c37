/*
 * fbg_model.c - validation of a fixed-point model, including the accumulator bound proof.
 */
#include "fbg_contract.h"
#include "fbg_internal.h"

/* |bias| above this is refused so that the bound below cannot overflow int64 itself. */
#define FBG_BIAS_LIMIT ((int64_t)1 << 60)

/* relu_inputs: the layer's inputs are ReLU outputs in [0, 32767] (every layer after a net's
 * first), which is what the int32 bound of an acc32 layer may use. */
static fbg_status check_layer(const fbg_layer *ly, int relu_inputs)
{
    unsigned r, j;
    if (ly->n_in < 1u || ly->n_in > FBG_MAX_WIDTH || ly->n_out < 1u || ly->n_out > FBG_MAX_WIDTH)
        return FBG_ERR_SHAPE;
    if (ly->w_bits == 16u) {
        if (ly->w16 == NULL)
            return FBG_ERR_NULL;
    } else if (ly->w_bits == 8u) {
        if (ly->w8 == NULL)
            return FBG_ERR_NULL;
    } else {
        return FBG_ERR_RANGE;
    }
    if (ly->bias == NULL || ly->mult == NULL)
        return FBG_ERR_NULL;
    if (ly->shift < 1u || ly->shift > 62u || ly->acc32 > 1u)
        return FBG_ERR_RANGE;
    for (r = 0; r < ly->n_out; ++r)
        if (ly->mult[r] == INT32_MIN)   /* symmetric like sat32: |mult| must be an int32 */
            return FBG_ERR_RANGE;
    for (r = 0; r < ly->n_out; ++r) {
        /* Worst case |acc| = sum_j |w[r][j]| * 32767 + |bias[r]|: every layer input is an
         * int16 saturated to +-32767 (sat16 is symmetric). acc * mult + 2^(shift-1) must
         * stay inside int64: that is the whole overflow proof of the nets (fixed-point.md). */
        int64_t sumw = 0, sump = 0, bound, limit, b = ly->bias[r], m = ly->mult[r];
        for (j = 0; j < ly->n_in; ++j) {
            int32_t w = ly->w_bits == 16u ? ly->w16[(size_t)r * ly->n_in + j]
                                          : ly->w8[(size_t)r * ly->n_in + j];
            sumw += w < 0 ? -(int64_t)w : (int64_t)w;
            sump += w > 0 ? (int64_t)w : 0;
        }
        if (b >= FBG_BIAS_LIMIT || b <= -FBG_BIAS_LIMIT)
            return FBG_ERR_BOUND;
        bound = sumw * FBG_SAT16 + (b < 0 ? -b : b);
        /* An int32 layer: every partial sum of the row is within the same bound, so no
         * int32 addition can overflow (the product acc * mult is then < 2^61 anyway). */
        if (ly->acc32) {
            /* With inputs in [0, 32767] every partial sum lies in
             * [b - 32767 * sum|w<0|, b + 32767 * sum(w>0)]; any int16 inputs: |.| <= bound. */
            int64_t sumn = sumw - sump, s = sump > sumn ? sump : sumn;
            int64_t b32 = relu_inputs ? s * FBG_SAT16 + (b < 0 ? -b : b) : bound;
            if (b32 > INT32_MAX)
                return FBG_ERR_BOUND;
        }
        if (m < 0)
            m = -m;
        if (m != 0) {
            limit = (INT64_MAX - ((int64_t)1 << (ly->shift - 1u))) / m;
            if (bound > limit)
                return FBG_ERR_BOUND;
        }
    }
    return FBG_OK;
}

fbg_status fbg_model_check(const fbg_model *model)
{
    unsigned n, l, features;
    uint16_t net_in[FBG_N_NETS];
    static const uint16_t net_out[FBG_N_NETS] = {1u, 1u, 2u};
    fbg_status st;

    if (model == NULL)
        return FBG_ERR_NULL;
    st = fbg_params_check(model);
    if (st != FBG_OK)
        return st;
    /* The creep states' update rounds by track_creep_shift, which the rounding rule needs >= 1. */
    if (model->track_creep_q15 != 0u && model->track_creep_shift == 0u)
        return FBG_ERR_RANGE;
    /* So does the creep inverse's lag by creep_shift. */
    if (model->creep_q15 != 0u && model->creep_shift == 0u)
        return FBG_ERR_RANGE;
    /* And the settled-hold average by hold_shift. */
    if (model->hold_gain_q15 != 0 && model->hold_shift == 0u)
        return FBG_ERR_RANGE;
    /* The decision's CUSUM rise: off, its fields are 0; on, it replaces the Schmitt trigger's
     * rise (contact_on_q8 0, contact_rise_n 1) and clips the margin to a range. */
    if (model->contact_cusum_h_q8 == 0
            ? (model->contact_cusum_k_q8 != 0 || model->contact_cusum_lo_q8 != 0 ||
               model->contact_cusum_hi_q8 != 0)
            : (model->contact_cusum_lo_q8 > model->contact_cusum_hi_q8 ||
               model->contact_on_q8 != 0 || model->contact_rise_n != 1u))
        return FBG_ERR_RANGE;
    if (model->taps == NULL)
        return FBG_ERR_NULL;
    features = FBG_N_STRAIN + FBG_N_MEMORY_FEATURES(model);
    net_in[FBG_NET_CONTACT] = (uint16_t)features;
    net_in[FBG_NET_FORCE] = (uint16_t)features;
    /* z, contact, force, then the location averages (4 when loc_shift is on) */
    net_in[FBG_NET_LOCATION] = (uint16_t)(FBG_N_STRAIN + 2u + (model->loc_shift ? FBG_N_STRAIN : 0u));
    for (n = 0; n < FBG_N_NETS; ++n) {
        const fbg_net *net = &model->nets[n];
        if (net->layers[0].n_in != net_in[n] || net->layers[net->n_layers - 1u].n_out != net_out[n])
            return FBG_ERR_SHAPE;
        for (l = 0; l < net->n_layers; ++l) {
            if (l > 0u && net->layers[l].n_in != net->layers[l - 1u].n_out)
                return FBG_ERR_SHAPE;
            st = check_layer(&net->layers[l], l > 0u);
            if (st != FBG_OK)
                return st;
        }
    }
    return FBG_OK;
}
