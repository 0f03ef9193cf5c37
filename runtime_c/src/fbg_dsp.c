/*
 * fbg_dsp.c - which Cortex-M4 DSP kernel runs each layer (fbg_dsp.h): the int32 pair
 * kernels for the layers the exporter writes, the int64, int8 and odd-height kernels for the rest,
 * and the output layers' rows.
 * See fbg_dsp_kernels.h for why the results equal the portable C bit for bit.
 */
#include "fbg_dsp_kernels.h"

#if FBG_USE_DSP
/* w_bits, shift, acc32 of an fbg_layer read as one little-endian word (bytes 4..6): the layers
 * the pair kernels take (16-bit weights, shift 32, int32 accumulators). */
#define FBG_DSP_PAIRS_KIND (16u | (32u << 8) | (1u << 16))
typedef char fbg_dsp_kind_layout[(offsetof(fbg_layer, w_bits) == 4 && offsetof(fbg_layer, shift) == 5 &&
                                  offsetof(fbg_layer, acc32) == 6 && offsetof(fbg_layer, n_in) == 0) ? 1 : -1];

/* Whether the pair kernels take this layer: an int32 layer at shift 32 (what the exporter
 * writes) with n even, at least two rows, the weights and y word-aligned and, beyond
 * FBG_DSP_FIRST_MAX_IN inputs (read with LDM), x too - as generated models, blobs and the activation buffers of fbg_state
 * give. The fields are read two words at a time: this runs for every layer of every step. */
static inline int pairs32_ok(const fbg_layer *ly, const int16_t *x, const int16_t *y,
                             unsigned *n_out)
{
    uint32_t dims, kind;
    unsigned n;
    memcpy(&dims, &ly->n_in, sizeof dims);
    memcpy(&kind, &ly->w_bits, sizeof kind);
    n = dims & 0xFFFFu;
    *n_out = dims >> 16;
    return (kind & 0xFFFFFFu) == FBG_DSP_PAIRS_KIND && *n_out >= 2u && n <= 8u * FBG_DSP_BODY_BLOCKS &&
           ((((uintptr_t)ly->w16 | (uintptr_t)y | (n > FBG_DSP_FIRST_MAX_IN ? (uintptr_t)x : 0u)) & 3u) | (n & 1u)) == 0u;
}

/* Every layer the even-height fast path of fbg_dsp_hidden does not take. */
static __attribute__((noinline)) void hidden_other(const fbg_layer *ly, const int16_t *x, int16_t *y,
                                                   uint32_t *sat)
{
    unsigned m;
    if (pairs32_ok(ly, x, y, &m)) { /* an odd number of rows: the last one in C */
        run_pairs32(ly, x, y, ly->n_in, sat);
        fbg_dsp_hidden16_32(ly, x, y, m - 1u, sat);
    }
#if FBG_DSP_ASM
    else if (ly->w_bits == 8u && ly->acc32 && ly->shift == 32u && (m = ly->n_out) >= 2u &&
             (ly->n_in & 1u) == 0u && ((uintptr_t)y & 3u) == 0u &&
             (ly->n_in <= 8u || ((uintptr_t)x & 3u) == 0u)) {
        /* int8 weights (int32 by construction), shift 32: the pairs in first2b32_asm (n <= 8)
         * or rows2b32_asm, the last row of an odd layer with dot8_32. */
        if (ly->n_in <= 8u)
            fbg_dsp_first2b32_asm(ly, x, y, sat);
        else
            fbg_dsp_rows2b32_asm(ly, x, y, sat);
        if (m & 1u) {
            uint32_t clamped = 0u;
            y[m - 1u] = (int16_t)relu_usat15(
                smmulr(fbg_dsp_dot8_32(ly->w8 + (size_t)(m - 1u) * ly->n_in, x, ly->n_in,
                               (int32_t)ly->bias[m - 1u]), ly->mult[m - 1u]), &clamped);
            *sat |= clamped != 0u;
        }
    }
#endif
    else if (ly->w_bits == 16u && ly->acc32)
        fbg_dsp_hidden16_32(ly, x, y, 0u, sat);
    else if (ly->w_bits == 16u)
        fbg_dsp_hidden16(ly, x, y, sat);
    else
        fbg_dsp_hidden8(ly, x, y, sat);
}

static inline void hidden_layer(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    unsigned m;
    if (pairs32_ok(ly, x, y, &m) && (m & 1u) == 0u)
        run_pairs32(ly, x, y, ly->n_in, sat);
    else
        hidden_other(ly, x, y, sat);
}

void fbg_dsp_hidden(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    hidden_layer(ly, x, y, sat);
}

/* Rows of FBG_MAX_WIDTH int16 keep act[1] word-aligned when act[0] is. */
typedef char fbg_dsp_act_rows_aligned[(FBG_MAX_WIDTH % 2) == 0 ? 1 : -1];

const int16_t *fbg_dsp_run_hidden(const fbg_net *net, const int16_t *x,
                                  int16_t (*act)[FBG_MAX_WIDTH], uint32_t *sat)
{
    /* The layer test of fbg_dsp_hidden, less what holds by construction here: y and every
     * input after the first are rows of act (word-aligned), n_in <= FBG_MAX_WIDTH <= the
     * unrolled body and n_out >= 1 (fbg_model_check), so an even n_out is at least 2. */
    const fbg_layer *ly = net->layers, *end = ly + net->n_layers - 1u;
    uintptr_t x_odd = (uintptr_t)x & 3u;
    unsigned buf = 0u;
    for (; ly != end; ++ly, buf ^= 1u) {
        int16_t *const y = act[buf];
        uint32_t dims, kind;
        unsigned n;
        memcpy(&dims, &ly->n_in, sizeof dims);  /* n_in, n_out */
        memcpy(&kind, &ly->w_bits, sizeof kind); /* w_bits, shift, acc32 */
        n = dims & 0xFFFFu;
        /* (kind ^ FBG_DSP_PAIRS_KIND) << 8 is zero iff the low three bytes match */
        if ((((kind ^ FBG_DSP_PAIRS_KIND) << 8) | (dims & 0x10001u) | ((uintptr_t)ly->w16 & 3u)) == 0u &&
            (n <= FBG_DSP_FIRST_MAX_IN || x_odd == 0u))
            run_pairs32(ly, x, y, n, sat);
        else
            hidden_other(ly, x, y, sat);
        x = y;
        x_odd = 0u;
    }
    return x;
}


/* Row r's accumulator of an int32 layer (ly->acc32: every partial sum fits int32). */
static inline int32_t row_acc32(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    const unsigned n = ly->n_in;
    if (ly->w_bits == 16u) {
        const int16_t *w = ly->w16 + (size_t)r * n;
#if FBG_DSP_ASM
        if (((((uintptr_t)w | (uintptr_t)x) & 3u) | (n & 1u)) == 0u)
            return fbg_dsp_dot32_asm(w, x, n, (int32_t)ly->bias[r]);
#endif
        return dot16_32(w, x, n, (int32_t)ly->bias[r]);
    }
    return fbg_dsp_dot8_32(ly->w8 + (size_t)r * n, x, n, (int32_t)ly->bias[r]);
}

static inline int64_t row_acc(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    if (ly->acc32)
        return row_acc32(ly, r, x);
    if (ly->w_bits == 16u)
        return fbg_dsp_dot16(ly->w16 + (size_t)r * ly->n_in, x, ly->n_in, ly->bias[r]);
    return fbg_dsp_row_acc8(ly, r, x);
}

int64_t fbg_dsp_row_acc(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    return row_acc(ly, r, x);
}

void fbg_dsp_output_accs(const fbg_layer *ly, const int16_t *x, int64_t *acc)
{
    unsigned r;
#if FBG_DSP_ASM
    const unsigned n = ly->n_in;
    if (ly->acc32 && ly->w_bits == 16u &&
        ((((uintptr_t)ly->w16 | (uintptr_t)x) & 3u) | (n & 1u)) == 0u) {
        /* The test of row_acc32 once for the layer: with n even every row is word-aligned. */
        const int16_t *w = ly->w16;
        for (r = 0; r < ly->n_out; ++r, w += n)
            acc[r] = fbg_dsp_dot32_asm(w, x, n, (int32_t)ly->bias[r]);
        return;
    }
#endif
    for (r = 0; r < ly->n_out; ++r)
        acc[r] = row_acc(ly, r, x);
}

#else
/* ISO C forbids an empty translation unit: the portable build compiles this file to nothing. */
typedef int fbg_dsp_unused;
#endif
