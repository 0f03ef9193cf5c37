/*
 * fbg_internal.h - integer helpers shared by the fixed-point and float builds (not installed).
 *
 * The ONE rounding rule and the ONE saturation rule of docs/fixed-point.md live here:
 *   rshift_round(x, s) = (x + 2^(s-1)) >> s       arithmetic shift: round half up, s >= 1
 *                                                  (int64; int32 where a bound allows)
 *   sat16(x) = clamp(x, -32767, 32767)             symmetric: negation never overflows
 *   sat32(x) = clamp(x, -2147483647, 2147483647)   symmetric likewise
 * export/intref.py implements exactly the same functions in numpy.
 */
#ifndef FBG_INTERNAL_H
#define FBG_INTERNAL_H

#include "fbgforce.h"

/* The rounding rule needs an arithmetic right shift of negative values, which C99 leaves
 * implementation-defined: refuse to compile where it is not (array size -1). */
typedef char fbg_require_arithmetic_shift[(((int64_t)-5 >> 1) == -3) ? 1 : -1];
typedef char fbg_require_arithmetic_shift32[(((int32_t)-5 >> 1) == -3) ? 1 : -1];

#define FBG_STATE_MAGIC 0x46424753u  /* "FBGS" */
#define FBGF_STATE_MAGIC 0x46424746u /* "FBGF" */
#define FBG_SAT16 32767
#define FBG_SAT32 2147483647

static inline int64_t fbg_rshift_round(int64_t x, unsigned s)
{
    return (x + ((int64_t)1 << (s - 1u))) >> s;
}

/* The same rule in int32, for a caller that has bounded |x| + 2^(s-1) below 2^31 (then the
 * result equals fbg_rshift_round's, with 32-bit instead of 64-bit shifts). */
static inline int32_t fbg_rshift_round32(int32_t x, unsigned s)
{
    return (x + ((int32_t)1 << (s - 1u))) >> s;
}

/* flag accumulates "a clamp happened" for FBG_STATUS_SATURATED. */
static inline int16_t fbg_sat16(int64_t x, uint32_t *flag)
{
    if (x > FBG_SAT16) {
        *flag = 1u;
        return (int16_t)FBG_SAT16;
    }
    if (x < -FBG_SAT16) {
        *flag = 1u;
        return (int16_t)-FBG_SAT16;
    }
    return (int16_t)x;
}

static inline int32_t fbg_sat32(int64_t x, uint32_t *flag)
{
    if (x > FBG_SAT32) {
        *flag = 1u;
        return (int32_t)FBG_SAT32;
    }
    if (x < -(int64_t)FBG_SAT32) {
        *flag = 1u;
        return (int32_t)-FBG_SAT32;
    }
    return (int32_t)x;
}

/* fbg_sat16 of an int32: the same clamp with 32-bit compares. */
static inline int16_t fbg_sat16_32(int32_t x, uint32_t *flag)
{
    if (x > FBG_SAT16 || x < -FBG_SAT16) {
        *flag = 1u;
        return (int16_t)(x > 0 ? FBG_SAT16 : -FBG_SAT16);
    }
    return (int16_t)x;
}

/* fbg_sat16(fbg_rshift_round(x, s)) for 1 <= s <= 62 and x + 2^(s-1) inside int64. A 32-bit
 * core shifts a 64-bit value by a variable amount in about ten instructions whatever s is;
 * here each range of s takes a few 32-bit operations on the two words of the sum. */
static inline int16_t fbg_sat16_rshift_round(int64_t x, unsigned s, uint32_t *flag)
{
#if UINTPTR_MAX > 0xFFFFFFFFu /* a 64-bit core: one shift */
    return fbg_sat16(fbg_rshift_round(x, s), flag);
#else
    if (s > 32u) {
        /* 2^(s-1) has a zero low word, so only the high word of the sum moves; floor(sum /
         * 2^s) is that word shifted by s - 32, an int32. */
        const int32_t hi = (int32_t)(x >> 32) + ((int32_t)1 << (s - 33u));
        return fbg_sat16_32(hi >> (s - 32u), flag);
    } else {
        const int64_t g = x + (int64_t)(uint32_t)(1u << (s - 1u));
        const uint32_t lo = (uint32_t)g;
        const int32_t hi = (int32_t)(g >> 32);
        const int32_t qhi = s == 32u ? hi >> 31 : hi >> s;
        const uint32_t qlo = s == 32u ? (uint32_t)hi : (lo >> s) | ((uint32_t)hi << (32u - s));
        if (qhi != ((int32_t)qlo >> 31)) { /* beyond int32: clamps, with the sign of qhi */
            *flag = 1u;
            return (int16_t)(qhi < 0 ? -FBG_SAT16 : FBG_SAT16);
        }
        return fbg_sat16_32((int32_t)qlo, flag);
    }
#endif
}

/* fbg_sat32((int64_t)a + b): on int32 overflow the true sum has the sign of a (and b). */
static inline int32_t fbg_sat32_add(int32_t a, int32_t b, uint32_t *flag)
{
#if defined(__GNUC__) /* GCC and clang: one ADDS and a branch on V instead of 64-bit compares */
    int32_t r;
    if (__builtin_add_overflow(a, b, &r)) {
        *flag = 1u;
        return a < 0 ? -FBG_SAT32 : FBG_SAT32;
    }
    if (r == INT32_MIN) {
        *flag = 1u;
        return -FBG_SAT32;
    }
    return r;
#else
    return fbg_sat32((int64_t)a + b, flag);
#endif
}

static inline int fbg_wl_in_window(int32_t wl)
{
    return wl >= FBG_WL_MIN_FM && wl <= FBG_WL_MAX_FM;
}

/* Apply the sensor-fault rule of fbg_step to one sample; updates prev/prev_valid and the
 * identical-value run counters. Returns 1 if the sample is faulty. Integer only (shared with
 * the float build). */
static inline int fbg_fault_check(const int32_t wl[FBG_N_CHANNELS], int32_t prev[FBG_N_CHANNELS],
                                  uint8_t *prev_valid, uint16_t run[FBG_N_CHANNELS],
                                  int32_t jump_max_fm, uint16_t stuck_max)
{
    int fault = 0;
    unsigned c, valid = *prev_valid; /* one load and one store: uint8_t aliases everything */
    for (c = 0; c < FBG_N_CHANNELS; ++c) {
        const int32_t w = wl[c];
        unsigned n;
        if (!fbg_wl_in_window(w)) {
            fault = 1;
            run[c] = 0u;
            continue;
        }
        n = 0u;
        if (valid & (1u << c)) {
            /* prev[c] is only ever an in-window sample, like w: both in [1e9, 2e9], so the
             * difference is within +-1e9 and exact in int32; jump_max_fm >= 1 is an int32, so
             * is its negation. */
            const int32_t d = w - prev[c];
            if (d > jump_max_fm || d < -jump_max_fm)
                fault = 1;
            if (d == 0)
                n = run[c] < 0xFFFFu ? run[c] + 1u : 0xFFFFu;
        }
        run[c] = (uint16_t)n;
        if (stuck_max != 0u && n >= stuck_max)
            fault = 1;
        prev[c] = w;
        valid |= 1u << c;
    }
    *prev_valid = (uint8_t)valid;
    return fault;
}

/* Tare accumulation shared by both builds. */
static inline int fbg_tare_accept(const int32_t wl[FBG_N_CHANNELS], int64_t sum[FBG_N_CHANNELS],
                                  uint32_t *count)
{
    unsigned c;
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        if (!fbg_wl_in_window(wl[c]))
            return 0;
    if (*count == 0xFFFFFFFFu)
        return 0;
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        sum[c] += wl[c];
    *count += 1u;
    return 1;
}

/* Mean of the tare samples, rounded half up: floor((sum + count/2) / count) on non-negative
 * sums (all samples are in the window, so sums are positive). */
static inline void fbg_tare_mean(const int64_t sum[FBG_N_CHANNELS], uint32_t count,
                                 int32_t out[FBG_N_CHANNELS])
{
    unsigned c;
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        out[c] = (int32_t)((sum[c] + (int64_t)(count / 2u)) / (int64_t)count);
}

/* The contact decision over time of both builds (docs/runtime.md, "In use"). decision is held
 * while the net's own decision or staying (the margin above contact_off) says so; within that
 * hold, contact is shown until positive (the net's own decision, or the margin above 0) has
 * failed on FBG_RELEASE_DWELL consecutive samples (counted in release_run): from there to the
 * hold's end (the release band) released is 1, the force and location still follow the
 * falling load, and contact shows again only by a new rise. The dwell keeps contact through
 * the margin's noise on a light held load, which the band alone used to. Returns 1 when the
 * build's rise rule is to run this sample (out of the hold, or in the release band): it does
 * not on the sample the hold ends or contact is released, as it does not on the sample
 * contact rises. */
static inline int fbg_decision_wants_rise(uint8_t *decision, uint8_t *released,
                                          uint8_t *release_run, int positive, int staying)
{
    if (*decision && !staying) {
        *decision = 0u;
        *released = 0u;
        *release_run = 0u;
        return 0;
    }
    if (*decision && !*released) {
        *release_run = positive ? 0u : (uint8_t)(*release_run + 1u);
        if (*release_run >= FBG_RELEASE_DWELL) {
            *released = 1u;
            *release_run = 0u;
        }
        return 0;
    }
    return 1;
}

/* The Schmitt trigger's rise count of both builds: 1, and the count restarts, when cond has
 * held for rise_n consecutive samples. */
static inline int fbg_rise_count(uint8_t *rise_run, int cond, uint8_t rise_n)
{
    if (!cond) {
        *rise_run = 0u;
        return 0;
    }
    if (*rise_run < 255u)
        (*rise_run)++;
    if (*rise_run < rise_n)
        return 0;
    *rise_run = 0u;
    return 1;
}

/* The settled-hold gain's count of both builds (docs/runtime.md, "In use"): steady says the
 * sample lies within the band of the force's average (each build compares in its own units).
 * Returns the gain's weight w in [0, 2^ramp_shift]: 0 until settle steady samples in a row,
 * then rising by one per steady sample; an unsteady sample sets the count back to 0. */
static inline uint32_t fbg_hold_weight(uint16_t *run, int steady, uint16_t settle,
                                       unsigned ramp_shift)
{
    const uint32_t ramp = 1ul << ramp_shift;
    uint32_t w;
    if (steady) {
        if (*run < settle + ramp && *run < 0xFFFFu)
            (*run)++;
    } else {
        *run = 0u;
    }
    w = *run > settle ? (uint32_t)*run - settle : 0u;
    return w > ramp ? ramp : w;
}

/* The at-rest tracker's block of both builds (docs/runtime.md, "In use"): a sample at rest
 * counts towards rest_run (saturating), any other sample restarts it, and every
 * FBG_TRACK_BLOCK samples a block ends. Returns 1 when this sample ends a block that moves
 * the baseline (the tracker is on, track_shift != 0, and the block was at rest throughout,
 * after settle samples of rest), 0 when it ends one that does not, -1 inside a block. */
static inline int fbg_track_block(uint16_t *rest_run, uint8_t *track_pos, int at_rest,
                                  unsigned track_shift, unsigned settle)
{
    if (!at_rest)
        *rest_run = 0u;
    else if (*rest_run < 0xFFFFu)
        (*rest_run)++;
    if (++*track_pos < FBG_TRACK_BLOCK)
        return -1;
    *track_pos = 0u;
    return track_shift != 0u && *rest_run >= (uint32_t)FBG_TRACK_BLOCK + settle;
}

/* The fixed-point build's temperature reference (docs/fixed-point.md, "temperature
 * reference"): the average r of the reference grating's shift shift_t, kept as acc = r * 2^k
 * in fm, r = rshift_round(acc, k). The n-th good sample after init, tare, reset or a new
 * baseline (*count == n - 1, saturating at 255) moves r by (shift_t - r) / 2^s, s = min(k,
 * floor(log2 n)): the first sets r to shift_t, the next ones give (nearly) the running mean
 * of the samples so far until the gain reaches 2^-k (by n = 2^k <= 256). A gain of 2^-k
 * from the second sample on would keep the first sample's noise in r for about 2^k samples:
 * a step on all four compensated gratings at once, which the memory's play operators hold for
 * as long as the pad rests. k = ref_shift <= FBG_MAX_REF_SHIFT; k == 0 is the raw shift
 * and leaves the state alone. r stays between the smallest and largest shift_t seen since the
 * first sample (each step moves it towards shift_t by at most shift_t - r), so |r| < 2^30 and
 * |acc| < 2^(k+31), and a step's addend |shift_t - r| * 2^(k - s) < 2^(31+k): the compensation's
 * product with temp_coeff_q24 keeps the bound it has with shift_t. Called only for a sample
 * that passed the fault rule: a faulty one holds the average. */
static inline int32_t fbg_ref_update(int64_t *acc, uint8_t *count, int32_t shift_t, unsigned k)
{
    unsigned n, s = k;
    if (k == 0u)
        return shift_t;
    n = (unsigned)*count + 1u;
    if (n < (1u << k)) { /* floor(log2 n) < k: the gain still falls */
        s = 0u;
        while ((2u << s) <= n)
            ++s;
    }
    /* multiplies: << of a negative is undefined */
    if (*count == 0u)
        *acc = (int64_t)shift_t * ((int64_t)1 << k);
    else
        *acc += ((int64_t)shift_t - fbg_rshift_round(*acc, k)) * ((int64_t)1 << (k - s));
    if (*count < 255u)
        ++*count;
    return (int32_t)fbg_rshift_round(*acc, k);
}

static inline int fbg_baseline_ok(const int32_t b[FBG_N_CHANNELS])
{
    unsigned c;
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        if (!fbg_wl_in_window(b[c]))
            return 0;
    return 1;
}

#endif /* FBG_INTERNAL_H */
