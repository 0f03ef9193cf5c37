/* dsp_kernel_test.c - the DSP-extension kernels of runtime_c/src/fbg_dsp*.c against the
 * arithmetic rules of docs/fixed-point.md, on random layers the golden vectors of one model
 * never reach: int16 and int8 weights, odd widths, rows starting at odd halfwords (unaligned words), every shift
 * 1..62, the largest multipliers the int64 bound proof allows (both signs), saturating and
 * all-negative rows, exact rounding ties (x = 0, bias = k 2^s + 2^(s-1) and neighbours), and
 * random FIR ring positions. Runs on QEMU mps2-an386; prints
 *   KERNEL_TEST cases=N mismatches=M fast=F aligned=A first=L int8=E saturated=S ...
 * and exits with 0 when M == 0 (fast = layers through rows3_asm or, A of them, rows3d_asm;
 * first = through first_asm). Every layer also goes through fbg_dsp_run_hidden (as a net's
 * one hidden layer), the int32 layers' rows through fbg_dsp_rshift32_product, and every case
 * checks fbg_dsp_standardise on random parameters. W and X are word-aligned arrays; off, offx = 1 misalign the
 * weights, the inputs (all four combinations occur). */
#include <stdint.h>
#include <string.h>

#include "fbg_dsp.h"
#include "semihost.h"

#define N_CASES 1500u

static int16_t W[FBG_MAX_WIDTH * FBG_MAX_WIDTH + 1] __attribute__((aligned(4)));
static int8_t W8[FBG_MAX_WIDTH * FBG_MAX_WIDTH + 1];
static int16_t X[FBG_MAX_WIDTH + 1] __attribute__((aligned(4)));
static int64_t B[FBG_MAX_WIDTH];
static int32_t M[FBG_MAX_WIDTH];
static int16_t Y_ref[FBG_MAX_WIDTH], Y_dsp[FBG_MAX_WIDTH];
static int32_t HIST[FBG_MAX_TAPS][FBG_N_STRAIN];
static int16_t TAPS[FBG_MAX_TAPS];

static uint32_t seed = 12345u;
static uint32_t rnd(void)
{
    seed = seed * 1103515245u + 12345u;
    return (seed >> 16) | (seed << 16);
}
static int16_t rnd16(void)
{
    int32_t v = (int16_t)(rnd() >> 7);
    return (int16_t)(v == -32768 ? -32767 : v); /* symmetric int16, as sat16 produces */
}

/* The rules, written from docs/fixed-point.md (not from the C stages). */
static int64_t ref_rshift_round(int64_t x, unsigned s) { return (x + ((int64_t)1 << (s - 1u))) >> s; }

static void ref_hidden(const fbg_layer *ly, const int16_t *x, int16_t *y, uint32_t *sat)
{
    unsigned r, j;
    for (r = 0; r < ly->n_out; ++r) {
        int64_t acc = ly->bias[r], v;
        for (j = 0; j < ly->n_in; ++j)
            acc += (int64_t)(ly->w_bits == 16u ? ly->w16[(uint32_t)r * ly->n_in + j]
                                               : ly->w8[(uint32_t)r * ly->n_in + j]) * x[j];
        v = ref_rshift_round(acc * ly->mult[r], ly->shift);
        if (v < 0)
            v = 0;
        if (v > 32767) {
            v = 32767;
            *sat = 1u;
        }
        y[r] = (int16_t)v;
    }
}

static int64_t ref_sat(int64_t v, int64_t lim, uint32_t *sat)
{
    if (v > lim || v < -lim) {
        *sat = 1u;
        return v > 0 ? lim : -lim;
    }
    return v;
}

/* fbg_dsp_output_accs against fbg_dsp_row_acc (checked against the rule below), and
 * fbg_dsp_rshift32_product against rshift_round(acc * mult, 32) for the accumulators of an
 * int32 layer's rows and their extremes. Returns the number of mismatches. */
static uint32_t check_output_rows(const fbg_layer *ly, const int16_t *x)
{
    static int64_t accs[FBG_MAX_WIDTH];
    uint32_t bad = 0u;
    unsigned r;
    fbg_dsp_output_accs(ly, x, accs);
    for (r = 0; r < ly->n_out; ++r) {
        const int32_t acc = (int32_t)fbg_dsp_row_acc(ly, r, x), mult = ly->mult[r];
        bad += accs[r] != acc;
        const int32_t edge[3] = {acc, INT32_MAX, -INT32_MAX};
        unsigned k;
        for (k = 0; k < 3u; ++k) {
            bad += fbg_dsp_rshift32_product(edge[k], mult) != ref_rshift_round((int64_t)edge[k] * mult, 32u);
            bad += fbg_dsp_rshift32_product(edge[k], k == 0u ? INT32_MAX : -INT32_MAX) !=
                   ref_rshift_round((int64_t)edge[k] * (k == 0u ? INT32_MAX : -INT32_MAX), 32u);
        }
    }
    return bad;
}

static int16_t ACT[2][FBG_MAX_WIDTH] __attribute__((aligned(4)));

/* fbg_dsp_run_hidden on a net whose one hidden layer is ly, input x: the output must be
 * ACT[0] holding y_ref (n_out values), with the flag sat_ref. */
static uint32_t check_run_hidden(const fbg_layer *ly, const int16_t *x, const int16_t *y_ref,
                                 uint32_t sat_ref)
{
    static fbg_net net;
    uint32_t sat = 0u;
    const int16_t *y;
    memset(&net, 0, sizeof net);
    net.n_layers = 2u;
    net.layers[0] = *ly;
    net.layers[1] = *ly; /* the output layer: not run */
    memset(ACT, 0x5A, sizeof ACT);
    y = fbg_dsp_run_hidden(&net, x, ACT, &sat);
    return y != ACT[0] || memcmp(y, y_ref, ly->n_out * sizeof *y) != 0 || sat != sat_ref;
}

/* fbg_dsp_standardise against the rules of docs/fixed-point.md (step 3 and the load proxy)
 * on random parameters: every tap_q and z_shift, sums that saturate filt, differences that
 * overflow int32 or land exactly on INT32_MIN, rounding ties. Returns 1 on a mismatch;
 * counts the cases with and without a clamp and those over the load limit. */
static uint32_t check_standardise(uint32_t *clamps, uint32_t *unclamped, uint32_t *overloads)
{
    static fbg_model mdl;
    int64_t f[FBG_N_STRAIN], load = 0;
    int16_t z_ref[FBG_N_STRAIN], z_dsp[FBG_N_STRAIN];
    uint32_t sat_ref = 0u, sat_dsp = 0u;
    int over_ref, over_dsp;
    unsigned ch, gentle;
    /* Its own random stream: the layers' cases stay those of the stream above. */
    static uint32_t own_seed = 424242u;
    const uint32_t layer_seed = seed;
    seed = own_seed;
    gentle = rnd() & 1u; /* half the cases with values that mostly fit */
    memset(&mdl, 0, sizeof mdl);
    mdl.tap_q = (uint8_t)(1u + rnd() % 15u);
    mdl.z_shift = (uint8_t)(gentle ? 24u + rnd() % 39u : 1u + rnd() % 62u);
    mdl.load_shift = (uint8_t)(1u + rnd() % 62u);
    mdl.load_max_mN = (int32_t)rnd() >> (rnd() % 31u);
    for (ch = 0; ch < FBG_N_STRAIN; ++ch) {
        int64_t filt, d;
        /* |f| < 2^53; a rounding tie at tap_q when the low bits come out so. */
        f[ch] = ((int64_t)(int32_t)rnd() << (rnd() % 22u)) + (rnd() & 3u ? 0 : ((int64_t)1 << (mdl.tap_q - 1u)));
        if ((rnd() & 7u) == 0u)
            f[ch] = ((int64_t)(int32_t)rnd() >> (rnd() % 31u)) * ((int64_t)1 << mdl.tap_q) + ((int64_t)1 << (mdl.tap_q - 1u));
        if ((rnd() & 15u) == 0u) /* filt at +-2^31 before the clamp (sat32 is symmetric) */
            f[ch] = ((rnd() & 1u) ? -1 : 1) * ((int64_t)1 << (31u + mdl.tap_q)) + (int64_t)(rnd() % (1u << (mdl.tap_q - 1u)));
        if (gentle)
            f[ch] = ((int64_t)((int32_t)rnd() >> (rnd() % 16u)) << mdl.tap_q) + (int64_t)(rnd() % (1u << mdl.tap_q));
        mdl.mean_fm[ch] = (int32_t)rnd() >> (rnd() % 32u + gentle);
        if (mdl.mean_fm[ch] == INT32_MIN)
            mdl.mean_fm[ch] = -INT32_MAX;
        mdl.z_mult[ch] = (int32_t)rnd() >> (rnd() % 32u + 8u * gentle);
        if (mdl.z_mult[ch] == INT32_MIN)
            mdl.z_mult[ch] = -INT32_MAX;
        mdl.load_coeff[ch] = ((int32_t)rnd() >> 3) % 268435456;
        filt = ref_sat(ref_rshift_round(f[ch], mdl.tap_q), INT32_MAX, &sat_ref);
        if ((rnd() % 10u) == 0u && filt < 0)
            mdl.mean_fm[ch] = (int32_t)(filt + ((int64_t)1 << 31)); /* filt - mean = INT32_MIN */
        d = ref_sat(filt - mdl.mean_fm[ch], INT32_MAX, &sat_ref);
        z_ref[ch] = (int16_t)ref_sat(ref_rshift_round(d * mdl.z_mult[ch], mdl.z_shift), 32767, &sat_ref);
        load += filt * mdl.load_coeff[ch];
    }
    own_seed = seed;
    seed = layer_seed;
    over_ref = ref_rshift_round(load, mdl.load_shift) > mdl.load_max_mN;
    over_dsp = fbg_dsp_standardise(&mdl, f, z_dsp, &sat_dsp);
    *clamps += sat_ref;
    *unclamped += !sat_ref;
    *overloads += (uint32_t)over_ref;
    return memcmp(z_ref, z_dsp, sizeof z_ref) != 0 || sat_ref != sat_dsp || over_ref != over_dsp;
}

/* fbg_sat16_rshift_round (fbg_internal.h: two-word arithmetic on this 32-bit core) against
 * sat16(rshift_round(x, s)) for every s and x of every magnitude that keeps x + 2^(s-1) in
 * int64, ties included. Returns the number of mismatches. */
static uint32_t check_sat16_rshift_round(void)
{
    uint32_t bad = 0u;
    unsigned s, k;
    const uint32_t layer_seed = seed; /* its own stream: the layers' cases stay as they were */
    seed = 777u;
    for (s = 1u; s <= 62u; ++s) {
        for (k = 0; k < 200u; ++k) {
            int64_t x = (int64_t)(((uint64_t)rnd() << 32) | rnd()) >> (rnd() % 64u), want;
            if (k % 5u == 2u && s < 30u) { /* shifted value 2^e + a small one, e >= 32 */
                x = (((int64_t)1 << (32u + rnd() % (30u - s))) + (int64_t)(rnd() & 0xFFFFu)) * ((int64_t)1 << s);
                if (rnd() & 1u)
                    x = -x;
            }
            if (k % 5u == 1u) /* around the int32 range of the shifted value */
                x = (int64_t)(((uint64_t)rnd() << 32) | rnd()) >> (s < 31u ? 31u - s + rnd() % 3u : 0u);
            uint32_t flag_ref = 0u, flag = 0u;
            if (k % 5u == 0u) /* a tie: x = (2q + 1) 2^(s-1) */
                x = ((int64_t)((int32_t)rnd() >> (s > 29u ? s - 29u : rnd() % 32u)) * 2 + 1) * ((int64_t)1 << (s - 1u));
            if (x > INT64_MAX - ((int64_t)1 << (s - 1u)))
                x = INT64_MAX - ((int64_t)1 << (s - 1u));
            want = ref_sat(ref_rshift_round(x, s), 32767, &flag_ref);
            bad += fbg_sat16_rshift_round(x, s, &flag) != want || flag != flag_ref;
        }
    }
    seed = layer_seed;
    return bad;
}

/* Every entry of the first-layer kernel: int32 layers at shift 32 of 2-12 inputs and 2-17
 * rows (every pair count modulo 4, with and without an odd last row), half of them with
 * multipliers large enough to clamp, against the rule. Counts the layers in *layers. */
static uint32_t check_first_layers(uint32_t *layers)
{
    uint32_t bad = 0u;
    unsigned n, m, i, r;
    for (n = 2u; n <= 12u; n += 2u) {
        for (m = 2u; m <= 17u; ++m) {
            fbg_layer ly;
            uint32_t sat_ref = 0u, sat_dsp = 0u;
            for (i = 0; i < n * m; ++i)
                W[i] = (int16_t)(rnd16() >> 5); /* sum |w| * 32767 + |b| < 2^31: int32 rows */
            for (i = 0; i < n; ++i)
                X[i] = rnd16();
            for (r = 0; r < m; ++r) {
                B[r] = (int64_t)(int32_t)(rnd() >> 2) - (1 << 29);
                M[r] = (int32_t)(rnd() % ((m & 1u) ? (1u << 30) : (1u << 20))) * ((rnd() & 1u) ? 1 : -1);
            }
            memset(&ly, 0, sizeof ly);
            ly.n_in = (uint16_t)n;
            ly.n_out = (uint16_t)m;
            ly.w_bits = 16u;
            ly.shift = 32u;
            ly.acc32 = 1u;
            ly.w16 = W;
            ly.bias = B;
            ly.mult = M;
            ref_hidden(&ly, X, Y_ref, &sat_ref);
            memset(Y_dsp, 0x5A, sizeof Y_dsp);
            fbg_dsp_hidden(&ly, X, Y_dsp, &sat_dsp);
            bad += memcmp(Y_ref, Y_dsp, m * sizeof Y_ref[0]) != 0 || sat_ref != sat_dsp;
            bad += check_run_hidden(&ly, X, Y_ref, sat_ref);
            ++*layers;
        }
    }
    return bad;
}

int main(void)
{
    static const uint16_t widths[] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 14, 20, 30, 40, 50, 62, 63, 70, 127, 128};
    const uint32_t n_widths = sizeof widths / sizeof widths[0];
    uint32_t c, mismatches = 0, fast = 0, fast_aligned = 0, first = 0, int8_layers = 0, saturated = 0;
    uint32_t acc32_layers = 0, acc32_fast = 0, acc32_first = 0, acc32_first_wide = 0, acc32_at_bound = 0,
             acc32_sat = 0;
    uint32_t acc32_int8 = 0, acc32_int8_sat = 0, acc32_int8_fast = 0;
    uint32_t standardise_clamped = 0, standardise_exact = 0, standardise_overload = 0;
    uint32_t first_sweep = 0;
    mismatches += check_sat16_rshift_round();
    for (c = 0; c < N_CASES; ++c) {
        unsigned n = widths[rnd() % n_widths], m = widths[rnd() % n_widths], mode = c % 6u, off = (c / 6u) % 2u,
                 offx = (c / 12u) % 2u;
        unsigned shift = 1u + rnd() % 62u, i, r;
        uint32_t sat_ref = 0u, sat_dsp = 0u;
        int bits8 = (c % 3u) == 2u;
        fbg_layer ly;
        if (mode >= 2u)
            shift = 32u + rnd() % 31u;
        if (mode == 5u)
            shift = 32u + rnd() % 27u; /* |bias| < 2^60 with the tie constructions below */
        for (i = 0; i < n * m; ++i) {
            W[off + i] = mode == 1u ? (int16_t)((rnd() & 1u) ? 32767 : -32767) : rnd16();
            if (bits8) {
                W8[off + i] = (int8_t)(W[off + i] >> 8);
                if (W8[off + i] == -128)
                    W8[off + i] = -127;
                W[off + i] = W8[off + i]; /* the bound below reads W */
            }
        }
        for (i = 0; i < n; ++i) {
            int16_t v = rnd16();
            X[offx + i] = mode == 3u ? (int16_t)(v < 0 ? -v : v) : v; /* ReLU outputs: >= 0 */
            if (mode == 5u)
                X[offx + i] = 0;
        }
        for (r = 0; r < m; ++r) {
            /* Largest |mult| with sum|w| * 32767 + |b| times it inside int64 (the proof). */
            int64_t sumw = 0, bound, lim;
            for (i = 0; i < n; ++i)
                sumw += W[off + r * n + i] < 0 ? -(int64_t)W[off + r * n + i] : W[off + r * n + i];
            B[r] = (int64_t)(int32_t)rnd() * (int64_t)(rnd() % 4096u);
            bound = sumw * 32767 + (B[r] < 0 ? -B[r] : B[r]);
            lim = (INT64_MAX - ((int64_t)1 << (shift - 1u))) / (bound ? bound : 1);
            if (lim > (1 << 30))
                lim = 1 << 30;
            M[r] = (mode == 1u || mode == 4u) ? (int32_t)lim : (int32_t)(rnd() % (uint32_t)(lim + 1));
            if (rnd() & 1u)
                M[r] = -M[r];
            if (mode == 5u) {
                /* acc = bias exactly; p = bias * 1 sits on or next to a rounding tie. */
                int64_t unit = (int64_t)1 << shift, half = unit >> 1;
                int64_t k = (int64_t)(rnd() % 7u) - 3;
                static const int64_t delta[4] = {0, -1, 1, 0};
                B[r] = k * unit + ((rnd() & 1u) ? half : -half) + delta[rnd() % 4u];
                M[r] = (rnd() & 1u) ? 1 : -1;
            }
        }
        memset(&ly, 0, sizeof ly);
        ly.n_in = (uint16_t)n;
        ly.n_out = (uint16_t)m;
        ly.w_bits = bits8 ? 8u : 16u;
        ly.shift = (uint8_t)shift;
        if (bits8)
            ly.w8 = W8 + off;
        else
            ly.w16 = W + off;
        ly.bias = B;
        ly.mult = M;
        ref_hidden(&ly, X + offx, Y_ref, &sat_ref);
        memset(Y_dsp, 0x5A, sizeof Y_dsp);
        fbg_dsp_hidden(&ly, X + offx, Y_dsp, &sat_dsp);
        mismatches += check_run_hidden(&ly, X + offx, Y_ref, sat_ref);
        if (memcmp(Y_ref, Y_dsp, m * sizeof Y_ref[0]) != 0 || sat_ref != sat_dsp) {
            if (mismatches < 5u) {
                sh_puts("KERNEL_MISMATCH");
                sh_kv("case", (int32_t)c);
                sh_kv("n", (int32_t)n);
                sh_kv("m", (int32_t)m);
                sh_kv("shift", (int32_t)shift);
                sh_puts("\n");
            }
            ++mismatches;
        }
        for (r = 0; r < m; ++r) {
            int64_t acc = B[r];
            for (i = 0; i < n; ++i)
                acc += (int64_t)W[off + r * n + i] * X[offx + i];
            if (fbg_dsp_row_acc(&ly, r, X + offx) != acc) {
                ++mismatches;
                break;
            }
        }
        first += !bits8 && shift >= 32u && (n == 2u || n == 4u || n == 6u);
        if (!bits8 && shift >= 32u && m >= 3u && !(n == 2u || n == 4u || n == 6u)) {
            ++fast;
            /* The condition under which fbg_dsp_rows16.c takes the LDRD variant (rows3d_asm; a
             * misaligned input is copied to an aligned buffer first). */
            fast_aligned += (((uintptr_t)(W + off) & 3u) == 0u && (n & 1u) == 0u);
        }
        if (bits8) {
            /* The same int8 layer as an int32 one (its bound is below 2^29), shift 32 or any. */
            uint32_t s8_ref = 0u, s8_dsp = 0u;
            for (r = 0; r < m; ++r) {
                B[r] = (int64_t)(int32_t)(rnd() >> 4) * ((rnd() & 1u) ? 1 : -1);
                M[r] = (int32_t)(rnd() % (1u << 30)) * ((rnd() & 1u) ? 1 : -1);
            }
            ly.acc32 = 1u;
            ly.shift = (uint8_t)((rnd() % 4u) != 0u ? 32u : 1u + rnd() % 62u);
            ref_hidden(&ly, X + offx, Y_ref, &s8_ref);
            memset(Y_dsp, 0x5A, sizeof Y_dsp);
            fbg_dsp_hidden(&ly, X + offx, Y_dsp, &s8_dsp);
            if (memcmp(Y_ref, Y_dsp, m * sizeof Y_ref[0]) != 0 || s8_ref != s8_dsp) {
                sh_puts("KERNEL_MISMATCH_ACC32_INT8\n");
                ++mismatches;
            }
            for (r = 0; r < m; ++r) { /* the output layers' rows (dot8_32) */
                int64_t acc = B[r];
                for (i = 0; i < n; ++i)
                    acc += (int64_t)W8[off + r * n + i] * X[offx + i];
                if (fbg_dsp_row_acc(&ly, r, X + offx) != acc) {
                    sh_puts("KERNEL_MISMATCH_ACC32_INT8_ROW\n");
                    ++mismatches;
                    break;
                }
            }
            /* The conditions under which fbg_dsp.c runs rows2b32_asm. */
            acc32_int8_fast += ly.shift == 32u && m >= 2u && (n & 1u) == 0u &&
                               ((uintptr_t)(X + offx) & 3u) == 0u;
            acc32_int8 += 1u;
            acc32_int8_sat += s8_ref != 0u;
        }
        int8_layers += (uint32_t)bits8;
        saturated += sat_ref != 0u;
        mismatches += check_standardise(&standardise_clamped, &standardise_exact, &standardise_overload);
        /* FIR: random taps, history and ring position. */
        {
            unsigned nt = 1u + rnd() % FBG_MAX_TAPS, pos = rnd() % nt, k, ch;
            int64_t f[FBG_N_STRAIN];
            for (k = 0; k < nt; ++k) {
                TAPS[k] = rnd16();
                for (ch = 0; ch < FBG_N_STRAIN; ++ch)
                    HIST[k][ch] = (int32_t)rnd();
            }
            fbg_dsp_fir4(TAPS, nt, (const int32_t(*)[FBG_N_STRAIN])HIST, pos, f);
            for (ch = 0; ch < FBG_N_STRAIN; ++ch) {
                int64_t want = 0;
                unsigned idx = pos;
                for (k = 0; k < nt; ++k) {
                    want += (int64_t)TAPS[k] * HIST[idx][ch];
                    idx = idx == 0u ? nt - 1u : idx - 1u;
                }
                if (want != f[ch]) {
                    ++mismatches;
                    break;
                }
            }
        }
        /* int32 layers (fbg_layer.acc32): weights scaled down until the loader's proof holds
         * (sum|w| * 32767 + |b| <= INT32_MAX, any int16 inputs), shift 32 (the SMMULR kernels)
         * three times in four, else any shift; every other case the inputs sit at the
         * saturation limits with the signs of row 0's weights, so that its accumulator equals
         * the bound. */
        if (!bits8) {
            unsigned k = 0, sh32 = (rnd() % 4u) != 0u ? 32u : 1u + rnd() % 62u;
            for (;;) {
                int64_t worst = 0;
                for (r = 0; r < m; ++r) {
                    int64_t sw = 0;
                    for (i = 0; i < n; ++i) {
                        int32_t w = W[off + r * n + i] >> k;
                        sw += w < 0 ? -w : w;
                    }
                    if (sw > worst)
                        worst = sw;
                }
                if (worst * 32767 <= INT32_MAX - 65536)
                    break;
                ++k;
            }
            for (i = 0; i < n * m; ++i)
                W[off + i] = (int16_t)(W[off + i] >> k);
            for (r = 0; r < m; ++r) {
                int64_t sw = 0, room;
                for (i = 0; i < n; ++i)
                    sw += W[off + r * n + i] < 0 ? -W[off + r * n + i] : W[off + r * n + i];
                room = INT32_MAX - sw * 32767;
                B[r] = (int64_t)(rnd() % (uint32_t)(room + 1)) * ((rnd() & 1u) ? 1 : -1);
                M[r] = (mode == 1u) ? (1 << 30) : (int32_t)(rnd() % (1u << 30));
                if (rnd() & 1u)
                    M[r] = -M[r];
            }
            if ((c & 1u) == 0u) {
                for (i = 0; i < n; ++i)
                    X[offx + i] = (int16_t)(W[off + i] < 0 ? -32767 : 32767);
                B[0] = B[0] < 0 ? -B[0] : B[0];
            }
            memset(&ly, 0, sizeof ly);
            ly.n_in = (uint16_t)n;
            ly.n_out = (uint16_t)m;
            ly.w_bits = 16u;
            ly.shift = (uint8_t)sh32;
            ly.acc32 = 1u;
            ly.w16 = W + off;
            ly.bias = B;
            ly.mult = M;
            sat_ref = sat_dsp = 0u;
            ref_hidden(&ly, X + offx, Y_ref, &sat_ref);
            memset(Y_dsp, 0x5A, sizeof Y_dsp);
            fbg_dsp_hidden(&ly, X + offx, Y_dsp, &sat_dsp);
            mismatches += check_run_hidden(&ly, X + offx, Y_ref, sat_ref);
            mismatches += check_output_rows(&ly, X + offx);
            if (memcmp(Y_ref, Y_dsp, m * sizeof Y_ref[0]) != 0 || sat_ref != sat_dsp) {
                if (mismatches < 5u) {
                    sh_puts("KERNEL_MISMATCH_ACC32");
                    sh_kv("case", (int32_t)c);
                    sh_kv("n", (int32_t)n);
                    sh_kv("m", (int32_t)m);
                    sh_kv("shift", (int32_t)sh32);
                    sh_puts("\n");
                }
                ++mismatches;
            }
            for (r = 0; r < m; ++r) {
                int64_t acc = B[r];
                for (i = 0; i < n; ++i)
                    acc += (int64_t)W[off + r * n + i] * X[offx + i];
                if (r == 0u && (c & 1u) == 0u) {
                    int64_t sw = 0;
                    for (i = 0; i < n; ++i)
                        sw += W[off + i] < 0 ? -W[off + i] : W[off + i];
                    acc32_at_bound += acc == sw * 32767 + B[0];
                }
                if (fbg_dsp_row_acc(&ly, r, X + offx) != acc) {
                    ++mismatches;
                    break;
                }
            }
            ++acc32_layers;
            acc32_sat += sat_ref != 0u;
            /* The conditions under which fbg_dsp.c runs first2d32_asm and rows2d32_asm. */
            acc32_first += sh32 == 32u && m >= 2u && (n & 1u) == 0u && n <= 12u &&
                           ((uintptr_t)(W + off) & 3u) == 0u;
            /* those with 10 or 12 inputs (six input registers, two loads per row) */
            acc32_first_wide += sh32 == 32u && m >= 2u && (n == 10u || n == 12u) &&
                                ((uintptr_t)(W + off) & 3u) == 0u;
            acc32_fast += sh32 == 32u && m >= 2u && (n & 1u) == 0u && n > 12u &&
                          ((uintptr_t)(W + off) & 3u) == 0u && ((uintptr_t)(X + offx) & 3u) == 0u;
        }
    }
    {
        const uint32_t layer_seed = seed; /* the random cases above stay what they were */
        mismatches += check_first_layers(&first_sweep);
        seed = layer_seed;
    }
    sh_puts("KERNEL_TEST");
    sh_kv("cases", (int32_t)N_CASES);
    sh_kv("mismatches", (int32_t)mismatches);
    sh_kv("fast", (int32_t)fast);
    sh_kv("aligned", (int32_t)fast_aligned);
    sh_kv("first", (int32_t)first);
    sh_kv("int8", (int32_t)int8_layers);
    sh_kv("saturated", (int32_t)saturated);
    sh_kv("acc32", (int32_t)acc32_layers);
    sh_kv("acc32_fast", (int32_t)acc32_fast);
    sh_kv("acc32_first", (int32_t)acc32_first);
    sh_kv("acc32_first_wide", (int32_t)acc32_first_wide);
    sh_kv("first_sweep", (int32_t)first_sweep);
    sh_kv("acc32_at_bound", (int32_t)acc32_at_bound);
    sh_kv("acc32_saturated", (int32_t)acc32_sat);
    sh_kv("acc32_int8", (int32_t)acc32_int8);
    sh_kv("acc32_int8_saturated", (int32_t)acc32_int8_sat);
    sh_kv("acc32_int8_fast", (int32_t)acc32_int8_fast);
    sh_kv("standardise_clamped", (int32_t)standardise_clamped);
    sh_kv("standardise_exact", (int32_t)standardise_exact);
    sh_kv("standardise_overload", (int32_t)standardise_overload);
    sh_puts("\n");
    return mismatches ? 1 : 0;
}
