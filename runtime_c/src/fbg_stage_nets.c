/*
 * fbg_stage_nets.c - stage 4 of fbg_step: the nets, layer by layer by the portable
 * reference, the DSP kernels (fbg_dsp.h) or the state's host kernel (fbg_simd.h), or from
 * packed weights in one call.
 */
#include "fbg_stages.h"

/* ---- 4. The nets: each layer's rows by the portable reference (layer_acc), the DSP kernels
 * (fbg_dsp.h) or the state's host kernel (fbg_simd.h) ---- */

/* The activation buffers are read with LDRD by the DSP kernels (fbgforce.h); the packed
 * kernels write whole groups of 8 rows into them. */
typedef char fbg_state_act_aligned[(offsetof(fbg_state, act) % 8u) == 0u ? 1 : -1];
typedef char fbg_state_act_groups[(FBG_MAX_WIDTH % 8) == 0 ? 1 : -1];

#if FBG_USE_DSP /* the rows in SMLAD/SMLALD, requantised with USAT (fbg_dsp.h): the same bits */
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
/* ACC += sum_j w[r][j] * x[j] over row R of layer LY (int16 or int8 weights; J the index), in
 * ACC's type: the same loops for the int32 and the int64 accumulator. */
#define FBG_ROW_SUM(acc, ly, r, x, j)                                                        \
    do {                                                                                     \
        if ((ly)->w_bits == 16u) {                                                           \
            const int16_t *w_ = (ly)->w16 + (size_t)(r) * (ly)->n_in;                        \
            for ((j) = 0; (j) < (ly)->n_in; ++(j))                                           \
                (acc) += (int32_t)w_[j] * (int32_t)(x)[j];                                   \
        } else {                                                                             \
            const int8_t *w_ = (ly)->w8 + (size_t)(r) * (ly)->n_in;                          \
            for ((j) = 0; (j) < (ly)->n_in; ++(j))                                           \
                (acc) += (int32_t)w_[j] * (int32_t)(x)[j];                                   \
        }                                                                                    \
    } while (0)

/* acc = bias[r] + sum_j w[r][j] * x[j] in int32 for an acc32 layer: fbg_model_check proved
 * sum_j |w[r][j]| * 32767 + |bias[r]| <= INT32_MAX, which bounds every partial sum too. */
static int32_t layer_acc32(const fbg_layer *ly, unsigned r, const int16_t *x)
{
    int32_t acc = (int32_t)ly->bias[r];
    unsigned j;
    FBG_ROW_SUM(acc, ly, r, x, j);
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
    FBG_ROW_SUM(acc, ly, r, x, j);
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
 * input of the output layer. Out of line, as when its three callers were the step's: inlined
 * into fbg_net_accs, its loop costs the portable Cortex-M4 build about 600 instructions per
 * step more. */
#if defined(__GNUC__)
__attribute__((noinline))
#endif
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

/* Every layer of net n on the net inputs in: acc = the accumulators of its output layer, which
 * it returns. Layer by layer, or from packed weights in one call where the state has them
 * (fbg_pack; x86-64 builds only). */
const fbg_layer *fbg_net_accs(fbg_state *s, const fbg_model *m, unsigned n, const int16_t *in,
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
