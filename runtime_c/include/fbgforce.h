/*
 * fbgforce.h - the one public header of the fbgforce runtime (C99).
 *
 * Turns the peak wavelengths of four strain FBGs and one temperature-reference FBG into
 * contact, force and contact location, one sample at a time (1 kHz), exactly like the float
 * pipeline of fbgforce.model:
 *
 *   wl (int32 fm) -> tare -> temperature compensation -> causal FIR (Q15 taps)
 *                 -> standardise to int16 -> contact net -> force net -> location net
 *
 * Two builds of the same pipeline live in this library:
 *   fbg_*   fixed point (int16 weights/activations, int8 weights optional, int32 or int64
 *           accumulators per layer, whichever the exporter proved);
 *           no float or double anywhere (`make -C runtime_c check-nofloat` proves it);
 *   fbgf_*  single-precision float (for FPU targets and as the C float estimator).
 *
 * Style: like CMSIS-DSP / CMSIS-NN. The caller owns every struct (no malloc); all sizes are
 * compile-time constants (FBG_MAX_*, sizeof(fbg_state)); every call returns an fbg_status.
 * Units: wavelengths int32 femtometres (1 fm = 1e-6 nm; 1600 nm = 1.6e9 fm fits int32),
 * force mN, location um in the pad frame (origin top-left, x right, y down).
 * The arithmetic (one rounding rule, one saturation rule, Q formats) is in
 * docs/fixed-point.md; the blob layout in docs/model-format.md; the API walk-through in
 * docs/runtime.md.
 *
 * Typical use (fixed point); read_peaks_fm() and control() are the caller's, and
 * tests/test_c_library.py compiles these lines:
 *
 *   static fbg_model model;  static fbg_state st;  fbg_output out;  int k;
 *   if (fbg_model_from_blob(&model, blob, blob_len) != FBG_OK) return;  // or a generated model
 *   fbg_init(&st, &model, 0);
 *   fbg_tare_begin(&st);                                      // fingertip unloaded
 *   for (k = 0; k < 300; ++k) fbg_tare_add(&st, read_peaks_fm(), NULL);
 *   fbg_tare_end(&st);
 *   for (;;) {
 *       fbg_step(&st, read_peaks_fm(), &out);
 *       if (!(out.status & FBG_STATUS_SENSOR_FAULT) && out.contact)
 *           control(out.force_mN, out.x_um, out.y_um);
 *   }
 *
 * Thread safety: functions touch only the structs passed in; a const fbg_model may be shared
 * by any number of fbg_state instances.
 */
#ifndef FBGFORCE_H
#define FBGFORCE_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- BEGIN GENERATED constants: `python -m fbgforce.contract --write` from pkgroot/contract/; do not edit ---- */
#define FBG_N_CHANNELS 5  /* wl1..wl4 (strain), wlT (temperature reference) */
#define FBG_N_STRAIN 4  /* strain gratings */
#define FBG_MAX_TAPS 64  /* causal FIR length */
#define FBG_MAX_WIDTH 128  /* widest layer (inputs or outputs) of any net */
#define FBG_MAX_LAYERS 8  /* layers per net */
#define FBG_MAX_EMA 4  /* exponential-average memory states */
#define FBG_MAX_PLAY 4  /* play-operator memory states */
#define FBG_MAX_INPUTS 12  /* widest net input: z and the memory features */
#define FBG_N_NETS 3  /* contact, force, location (evaluation order) */
#define FBG_WL_MIN_FM 1000000000  /* 1000 nm: a peak below this is lost (0, sentinels) */
#define FBG_WL_MAX_FM 2000000000  /* 2000 nm: a peak above this is lost */
#define FBG_TEMP_COEFF_SHIFT 24  /* temperature coefficients are Q24 */
#define FBG_EMA_FRAC 15  /* fractional bits of the exponential-average states below Q(z_frac) */
#define FBG_MAX_EMA_SHIFT 15  /* largest exponential-average shift (time constant 2^15 samples) */
#define FBG_MAX_MEM_GAIN 8  /* largest memory-feature gain shift */
#define FBG_LOAD_COEFF_LIMIT 268435456  /* |load_coeff| below this: the load proxy sum fits int64 */
#define FBG_TRACK_BLOCK 64  /* samples per update of the at-rest baseline tracker */
#define FBG_TRACK_FRAC 16  /* fractional bits of the tracker's carried baseline correction */
#define FBG_TRACK_LIMIT_MAX_FM 100000000  /* largest track_limit_fm (100 nm): a tracked baseline stays within 100 nm of its tare */
#define FBG_MAX_REF_SHIFT 8  /* largest shift of the temperature reference's average (time constant 256 samples): its accumulator stays below 2^39 (docs/fixed-point.md) */
#define FBG_MAX_TRACK_CREEP_Q15 16384  /* largest track_creep_q15 (creep magnitude 0.5): the tracker's per-sample term stays below 2^17 (docs/fixed-point.md) */
#define FBG_MAX_CREEP_Q15 32767  /* largest creep_q15: the creep inverse's gain q = kappa / (1 - kappa) stays below 1 for a creep magnitude up to 0.5 (docs/fixed-point.md) */
#define FBG_MAX_HOLD_GAIN_Q15 4096  /* largest |hold_gain_q15| (12.5 %): the hold stage's product stays below 2^56 (docs/fixed-point.md) */
#define FBG_MAX_HOLD_RAMP_SHIFT 12  /* largest hold_ramp_shift (the gain ramps in over 4096 samples) */
#define FBG_MAX_CUSUM_Q8 536870912  /* largest contact_cusum_h_q8 and |contact_cusum_k_q8|, |_lo_q8|, |_hi_q8|: the CUSUM's sum stays inside int32 (docs/fixed-point.md) */
#define FBG_RELEASE_DWELL 8  /* consecutive samples with the contact net's margin at or below 0 before contact is released inside the decision's hold */
#define FBG_BLOB_VERSION 11  /* blob format this library reads and writes */
#define FBG_BLOB_HEADER_SIZE 16  /* magic, version, flags, total length, CRC-32 */
#define FBG_VERSION_MAJOR 0  /* library version */
#define FBG_VERSION_MINOR 2
#define FBG_VERSION_PATCH 0
#define FBG_NET_CONTACT 0
#define FBG_NET_FORCE 1
#define FBG_NET_LOCATION 2

/* Return codes: 0 is success, every error has its own negative code. */
typedef enum {
    FBG_OK = 0,  /* success */
    FBG_ERR_NULL = -1,  /* a required pointer argument is NULL */
    FBG_ERR_TRUNCATED = -2,  /* blob shorter than its header or than its declared length */
    FBG_ERR_BAD_MAGIC = -3,  /* blob does not start with "FBGM" */
    FBG_ERR_VERSION = -4,  /* blob format version or header flags not supported by this library */
    FBG_ERR_CRC = -5,  /* CRC-32 over the blob body does not match */
    FBG_ERR_SHAPE = -6,  /* layer shapes inconsistent, too large, or nets of wrong I/O */
    FBG_ERR_RANGE = -7,  /* a parameter outside its allowed range, or non-zero padding */
    FBG_ERR_BOUND = -8,  /* accumulator worst-case bound would overflow int64 (int32 for an acc32 layer) */
    FBG_ERR_SIZE = -9,  /* declared length differs from the length the shapes imply */
    FBG_ERR_ALIGN = -10,  /* blob pointer not 8-byte aligned (arrays are used in place) */
    FBG_ERR_ENDIAN = -11,  /* host is not little-endian (blob arrays are little-endian) */
    FBG_ERR_STATE = -12,  /* state not initialised by fbg_init (or corrupted) */
    FBG_ERR_NOT_TARED = -13,  /* fbg_step with FBG_OPT_REQUIRE_TARE before a tare */
    FBG_ERR_TARE = -14,  /* tare_add/tare_end without tare_begin, or no valid sample */
    FBG_ERR_ARG = -15,  /* bad argument value (e.g. baseline outside the window) */
    FBG_ERR_MODEL_CHANGED = -16  /* the model was reloaded under the state (its blob_crc differs from fbg_init's): fbg_init again */
} fbg_status;

/* Output status flags (fbg_output.status; several may be set). */
#define FBG_STATUS_NOT_TARED 0x01  /* running on the model's nominal baseline */
#define FBG_STATUS_SATURATED 0x02  /* some value was clamped (int16/int32) this sample */
#define FBG_STATUS_OVERLOAD 0x04  /* beyond the trained force range (see fbg_model) */
#define FBG_STATUS_SENSOR_FAULT 0x08  /* a peak lost, jumped or stuck: outputs are the safe output */
#define FBG_STATUS_WARMUP 0x10  /* fewer than n_taps samples since init/tare/reset */
#define FBG_STATUS_BASELINE_LIMIT 0x20  /* the at-rest baseline tracker is at its bound: drift beyond what it may correct (re-tare) */
#define FBG_STATUS_OUT_OF_RANGE 0x40  /* a net input (z or a memory feature) outside the range the calibration data covered, with a margin: the nets extrapolate */
#define FBG_STATUS_RELEASING 0x80  /* contact has ended: the contact net's margin has stayed at or below 0 for FBG_RELEASE_DWELL samples; the force and location still follow the falling load until the decision's release band ends */
#define FBG_STATUS_ALL 0xFF  /* every flag above: no other bit is ever set */

/* fbg_init options: flags, and one FBG_OPT_KERNEL_* value. */
#define FBG_OPT_REQUIRE_TARE 0x01  /* fbg_step returns FBG_ERR_NOT_TARED until tared */
#define FBG_OPT_KERNEL_MASK 0xF0  /* the dense-layer kernel field of the options */
#define FBG_OPT_KERNEL_AUTO 0x00  /* the fastest kernel this CPU runs */
#define FBG_OPT_KERNEL_PORTABLE 0x10  /* portable C */
#define FBG_OPT_KERNEL_SSE2 0x20  /* x86-64 SSE2 */
#define FBG_OPT_KERNEL_AVX2 0x30  /* x86-64 AVX2 (if the CPU has it) */
#define FBG_OPT_KERNEL_NEON 0x40  /* aarch64 NEON */
/* ---- END GENERATED constants ---- */

/* ---- Sensor-fault rule (see fbg_step): a peak outside [FBG_WL_MIN_FM, FBG_WL_MAX_FM] is lost. */

/* ---------------------------------------------------------------------------------------
 * Fixed-point model: a const view of quantised weights. Filled by fbg_model_from_blob
 * (pointers into the blob, zero copy) or defined as a const object in generated C
 * (fbgforce export writes <name>_model.c/.h). Never modified by the library.
 * ------------------------------------------------------------------------------------- */

/* One dense layer: acc[r] = bias[r] + sum_j w[r][j] * x[j]        (int64 accumulator, or
 *                                                                   int32 when acc32 = 1)
 *                  y[r]   = rshift_round(acc[r] * mult[r], shift)
 * hidden layers:   y = sat16(max(y, 0))    (ReLU, int16 activations)
 * output layers:   y = sat32(y)            (physical units, see fbg_model)
 * acc32 = 1 declares that every row's worst case sum_j |w[r][j]| * 32767 + |bias[r]| fits
 * int32 (fbg_model_check refuses the model otherwise, FBG_ERR_BOUND), so the int32 sum is the
 * same number as the int64 one; the DSP build then uses SMLAD/SMMULR kernels. */
typedef struct {
    uint16_t n_in;
    uint16_t n_out;
    uint8_t w_bits;          /* 16: weights in w16; 8: weights in w8 */
    uint8_t shift;           /* requantisation shift, 1..62 */
    uint8_t acc32;           /* 0: int64 accumulator; 1: int32 (proven, see above) */
    uint8_t reserved;
    const int16_t *w16;      /* row-major n_out x n_in (NULL if w_bits == 8) */
    const int8_t *w8;        /* row-major n_out x n_in (NULL if w_bits == 16) */
    const int64_t *bias;     /* n_out, at accumulator scale */
    const int32_t *mult;     /* n_out, requantisation multipliers (per output row) */
} fbg_layer;

typedef struct {
    uint8_t n_layers;        /* 1..FBG_MAX_LAYERS; the last layer is the output layer */
    uint8_t reserved[3];
    fbg_layer layers[FBG_MAX_LAYERS];
} fbg_net;

/* ---- BEGIN GENERATED fixed: `python -m fbgforce.contract --write` from pkgroot/contract/; do not edit ---- */
/* Fixed-point model. The parameters are those of the blob (docs/model-format.md),
 * declared grouped by size so that the struct has no implicit padding. */
typedef struct {
    uint32_t writer_version;  /* VERSION_CODE of the library that wrote the blob (informational: any value loads) */
    int32_t baseline_fm[5];  /* nominal unloaded wavelengths (fm): the baseline before any tare [1000000000, 2000000000] */
    int32_t jump_max_fm;  /* SENSOR_FAULT when |wl - previous in-window wl| > jump_max_fm on any channel [1, 2147483647] */
    int32_t temp_coeff_q24[4];  /* comp_i = shift_i - rshift_round(shift_T * temp_coeff_q24[i], 24)  (fm) */
    int32_t mean_fm[4];  /* z_i = sat16(rshift_round(sat32(filt_i - mean_fm[i]) * z_mult[i], z_shift)) */
    int32_t z_mult[4];  /* standardisation multipliers */
    int32_t fq_mult;  /* location input: f_q = sat16(rshift_round(force_out * fq_mult, fq_shift)) */
    int32_t force_offset_mN;  /* force_mN = sat32(force_out + offset) */
    int32_t xy_offset_um[2];  /* x_um, y_um likewise */
    int32_t overload_mN;  /* OVERLOAD when contact and force_mN > this */
    int32_t load_coeff[4];  /* input-side overload: load_mN = rshift_round(sum_i load_coeff[i] * filt_i, load_shift) [-268435455, 268435455] */
    int32_t load_max_mN;  /* OVERLOAD when load_mN > load_max_mN */
    int32_t mem_mult[4];  /* memory input u = sat16(rshift_round(sum_i mem_mult[i] * z_i, mem_shift)): a load signal in Q(z_frac) */
    int32_t contact_on_q8;  /* contact rises when acc > 0 and margin_q8 >= contact_on_q8 ... [0, 2147483647] */
    int32_t contact_off_q8;  /* ... and stays while acc > 0 or margin_q8 > contact_off_q8 [-2147483647, 0] */
    int32_t track_gain[4];  /* per TRACK_BLOCK at rest: corr_i += sum(z_i - z0_i) * track_gain[i] (fm in Q(TRACK_FRAC)) */
    int32_t track_step_max_fm;  /* largest baseline step of one tracker block (fm) [0, 2147483647] */
    int32_t track_limit_fm;  /* largest |tracked - tared baseline| per channel (fm); BASELINE_LIMIT at it [0, 100000000] */
    int32_t hold_band_mN;  /* a contact sample is steady when |force_mN - rshift_round(hold_avg, EMA_FRAC)| <= max(hold_band_mN, rshift_round(|force_mN| * hold_band_q15, 15)) ... [0, 2147483647] */
    int32_t contact_cusum_h_q8;  /* the decision's CUSUM rise (0: off, the Schmitt trigger with its count; on: needs contact_on_q8 0, contact_rise_n 1, lo <= hi): out of contact S = max(0, S + clamp(margin_q8, lo, hi) - k), contact rises when S >= h (S = 0 then) [0, 536870912] */
    int32_t contact_cusum_k_q8;  /* the CUSUM's drift k (Q8 margin; 0 when the CUSUM is off) [-536870912, 536870912] */
    int32_t contact_cusum_lo_q8;  /* the CUSUM's clip of the margin, lower end (0 when off) [-536870912, 536870912] */
    int32_t contact_cusum_hi_q8;  /* the CUSUM's clip of the margin, upper end (0 when off) [-536870912, 536870912] */
    uint16_t n_taps;  /* causal FIR length [1, 64] */
    uint16_t stuck_max;  /* SENSOR_FAULT after this many identical samples on a channel; 0 disables the rule */
    int16_t play_width[4];  /* state = clamp(state, u - play_width[k], u + play_width[k]), Q(z_frac) [0, 32767] for k < n_play, else 0 */
    uint16_t track_settle;  /* samples of rest (tared, no contact, fault or warm-up) before a tracker block counts */
    int16_t in_lo[12];  /* OUT_OF_RANGE when a net input j < n_features (z, memory features) < in_lo[j] ... [-32767, 32767] */
    int16_t in_hi[12];  /* ... or > in_hi[j] (Q(z_frac); +-32767: never) [-32767, 32767] */
    uint16_t track_creep_q15;  /* the tracker's creep term (0: off; needs track_creep_shift >= 1): per sample at rest it sums (z_i - z0_i) - rshift_round((creep_i - (z0_i << EMA_FRAC)) * track_creep_q15, 30), the pad's creep magnitude in Q15 [0, 16384] */
    uint16_t creep_q15;  /* the pad's creep inverse (0: off; needs creep_shift >= 1), on each good sample's compensated shift c_i before the FIR: L_i = rshift_round(acc_i, creep_shift), e_i = sat32(c_i + rshift_round((c_i - L_i) * creep_q15, 15)) replaces c_i, acc_i += e_i - L_i; acc_i primed at c_i << creep_shift. q = kappa / (1 - kappa), kappa = m (1 - 2^-creep_shift), in Q15 [0, 32767] */
    int16_t hold_gain_q15;  /* the settled-hold gain (0: off; needs hold_shift >= 1): on a contact sample, force_mN += rshift_round(force_mN * hold_gain_q15 * w, 15 + hold_ramp_shift), w = clamp(hold_run - hold_settle, 0, 2^hold_ramp_shift) [-4096, 4096] */
    uint16_t hold_settle;  /* steady contact samples before the settled-hold gain starts to ramp in */
    uint16_t hold_band_q15;  /* ... (hold_avg += rshift_round((force_mN << EMA_FRAC) - hold_avg, hold_shift), primed at the first contact sample after no contact); hold_run counts steady samples [0, 32768] */
    uint8_t tap_q;  /* FIR taps are int16 in Q(tap_q) [1, 15] */
    uint8_t z_frac;  /* net inputs are int16 in Q(z_frac) [0, 14] */
    uint8_t z_shift;  /* shift of the standardisation (with z_mult) [1, 62] */
    uint8_t fq_shift;  /* shift of the location net's force input [1, 62] */
    uint8_t load_shift;  /* shift of the load proxy [1, 62] */
    uint8_t mem_shift;  /* shift of the memory input [1, 62] */
    uint8_t n_ema;  /* exponential-average memory states [0, 4] */
    uint8_t n_play;  /* play-operator memory states [0, 4] */
    uint8_t ema_shift[4];  /* state += rshift_round((u << EMA_FRAC) - state, ema_shift[k]) [1, 15] for k < n_ema, else 0 */
    uint8_t ema_gain[4];  /* feature = sat16((u - rshift_round(state, EMA_FRAC)) << ema_gain[k]) [0, 8] for k < n_ema, else 0 */
    uint8_t play_gain[4];  /* feature = sat16((u - state) << play_gain[k]) [0, 8] for k < n_play, else 0 */
    uint8_t loc_shift;  /* location averages (0: off): r_i = sat16(z_i - z0_i), z0_i the standardised zero shift; loc_i += rshift_round((r_i << EMA_FRAC) - loc_i, loc_shift); location input rshift_round(loc_i, EMA_FRAC) [0, 15] */
    uint8_t contact_rise_n;  /* consecutive samples of the rise condition before contact rises [1, 255] */
    uint8_t track_shift;  /* at-rest baseline tracker (0: off): time constant 2^track_shift samples [0, 20] */
    uint8_t ref_shift;  /* temperature reference average (0: off): from acc = 0, the n-th good sample adds (shift_T - rshift_round(acc, ref_shift)) * 2^(ref_shift - s), s = min(ref_shift, floor(log2 n)); r = rshift_round(acc, ref_shift) replaces shift_T in temp_coeff_q24's compensation [0, 8] */
    uint8_t track_creep_shift;  /* creep_i += rshift_round((z_i << EMA_FRAC) - creep_i, track_creep_shift) on every good sample, primed at z_i << EMA_FRAC: the creep's time constant 2^k samples [0, 15] */
    uint8_t creep_shift;  /* the pad's creep time constant 2^creep_shift samples (1..15 when creep_q15 is on) [0, 15] */
    uint8_t hold_shift;  /* time constant 2^hold_shift samples of the hold stage's average of force_mN [0, 15] */
    uint8_t hold_ramp_shift;  /* the settled-hold gain ramps in over 2^hold_ramp_shift samples [0, 12] */
    const int16_t *taps;     /* n_taps FIR taps in Q(tap_q), taps[k] weights n - k */
    fbg_net nets[FBG_N_NETS];
    uint32_t blob_crc;       /* the blob's CRC-32 (fbg_model_from_blob, generated C); a state
                              * refuses to step when it differs from fbg_init's */
} fbg_model;

/* Per-sample result of the fixed-point pipeline. When contact == 0: force_mN =
 * x_um = y_um = 0. Safe output (SENSOR_FAULT, or an error return): all 0 but status. */
typedef struct {
    int32_t force_mN;  /* normal force, mN (0 when no contact) */
    int32_t x_um;  /* contact location, um (0 when no contact) */
    int32_t y_um;
    int32_t contact_margin_q8;  /* contact-net margin (logit difference) * 256 */
    uint32_t status;  /* FBG_STATUS_* flags */
    uint16_t contact_conf_q15;  /* P(contact) in Q15, 0..32767 (sigmoid of the margin) */
    uint8_t contact;  /* 1 = contact */
    uint8_t reserved;
} fbg_output;
/* ---- END GENERATED fixed ---- */

/* ---- BEGIN GENERATED state: `python -m fbgforce.contract --write` from pkgroot/contract/; do not edit ---- */
/* Caller-owned streaming state. Treat as opaque; size is sizeof(fbg_state). */
typedef struct {
    uint32_t magic;                              /* set by fbg_init */
    uint32_t options;
    const fbg_model *model;
    int32_t baseline_fm[FBG_N_CHANNELS];
    int32_t prev_fm[FBG_N_CHANNELS];             /* last in-window sample per channel */
    int32_t hist[FBG_MAX_TAPS][FBG_N_STRAIN];    /* FIR history (ring buffer) */
    int32_t last_comp[FBG_N_STRAIN];             /* the last good sample's filtered shifts, held into the FIR during a fault */
    /* Memory states of the load signal u (docs/fixed-point.md, "memory"), one array per kind
     * of fbgforce.contract.MEMORY_KINDS. */
    int32_t ema[FBG_MAX_EMA];                    /* exponential-average memory states, Q(z_frac + FBG_EMA_FRAC) */
    int32_t play[FBG_MAX_PLAY];                  /* play-operator memory states, Q(z_frac) */
    int32_t loc[FBG_N_STRAIN];                   /* location averages of z - z0, Q(z_frac + FBG_EMA_FRAC) */
    int32_t creep[FBG_N_STRAIN];                 /* the tracker's creep states: averages of z, Q(z_frac + FBG_EMA_FRAC), primed with the memory (mem_primed) */
    /* At-rest baseline tracker (docs/runtime.md, "In use"): the block's sum of z - z0, the
     * correction applied to baseline_fm[0..3] since the tare, and the carried fraction of
     * the next step in Q(FBG_TRACK_FRAC). */
    int32_t track_sum[FBG_N_STRAIN];
    int32_t drift_fm[FBG_N_STRAIN];
    int64_t track_frac[FBG_N_STRAIN];
    int64_t tare_sum[FBG_N_CHANNELS];
    int64_t ref_acc;                             /* the temperature reference's average r * 2^ref_shift (fm; docs/fixed-point.md, "temperature reference") */
    int64_t creep_acc[FBG_N_STRAIN];             /* the creep inverse's lags L_i * 2^creep_shift (fm; docs/fixed-point.md, "creep inverse") */
    int64_t hold_avg;                            /* the hold stage's average of force_mN, Q(FBG_EMA_FRAC) (docs/fixed-point.md, "settled-hold gain") */
    /* Right after the int64 arrays, so 8-byte aligned on every ABI: the DSP kernels read the
     * activations with LDRD (no copy to an aligned buffer per layer). */
    int16_t act[2][FBG_MAX_WIDTH];               /* activation ping-pong buffers */
    uint32_t tare_count;
    int32_t cusum_q8;                            /* the decision's CUSUM S (Q8 margin), in [0, contact_cusum_h_q8) out of contact and in the release band, 0 while contact is shown */
    uint16_t pos;                                /* next write index into hist */
    uint16_t since_reset;                        /* samples since init/tare, saturating */
    uint16_t same_run[FBG_N_CHANNELS];           /* repeats of the identical value */
    int16_t loc_z0[FBG_N_STRAIN];                /* z of a zero filtered shift (the model's) */
    uint8_t tared;
    uint8_t tare_active;
    uint8_t prev_valid;                          /* bit c: prev_fm[c] holds a sample */
    uint8_t mem_primed;                          /* memory states hold a sample */
    uint8_t ref_count;                           /* good samples in the temperature reference's average (up to 255: its gain has reached 2^-ref_shift by 2^ref_shift <= 256) */
    uint8_t creep_primed;                        /* the creep inverse's lags hold a sample */
    uint8_t loc_z0_clamped;                      /* 1: a loc_z0 clamped at +-32767 */
    uint8_t decision;                            /* the contact decision of the last step, held through the release band */
    uint8_t released;                            /* 1: in the release band, contact no longer shown */
    uint8_t release_run;                         /* samples with the margin at or below 0 so far, in contact (up to FBG_RELEASE_DWELL) */
    uint8_t rise_run;                            /* samples of the rise condition so far */
    uint8_t track_pos;                           /* samples into the tracker's block */
    uint8_t track_limited;                       /* 1: a channel's drift_fm is at its bound */
    uint16_t rest_run;                           /* samples at rest, saturating */
    uint16_t hold_run;                           /* steady contact samples so far, saturating */
    uint8_t hold_primed;                         /* hold_avg holds a contact sample's force */
    const void *packed;                          /* fbg_pack / fbg_use_pack buffer, or NULL */
    uint32_t model_crc;                          /* model->blob_crc at fbg_init */
} fbg_state;
/* ---- END GENERATED state ---- */

/* Library version as (major << 16) | (minor << 8) | patch: FBG_VERSION_* of the header it was
 * built with, the same version as the Python package (fbgforce.contract.VERSION). */
uint32_t fbg_version(void);

/* Number of bytes of an fbg_state / fbgf_state (for bindings that cannot use sizeof). */
size_t fbg_state_size(void);
size_t fbgf_state_size(void);

/* Human-readable name of a status code ("FBG_ERR_CRC", ...); never NULL. */
const char *fbg_status_str(int status);

/* Fill *model from a blob (docs/model-format.md) without copying: the model points into the
 * blob, which must stay alive and unchanged. Checks, in this order: pointers (NULL), length
 * >= header (TRUNCATED), magic (BAD_MAGIC), version (VERSION), declared length <= len
 * (TRUNCATED), CRC-32 (CRC), then every field (SHAPE, RANGE, SIZE, BOUND) as fbg_model_check.
 * Never reads outside blob[0, len). The blob must be 8-byte aligned (ALIGN). Once the
 * header and CRC are good, model->blob_crc is the blob's CRC whatever follows, so a state
 * initialised on the model this call overwrites refuses to step (FBG_ERR_MODEL_CHANGED). */
fbg_status fbg_model_from_blob(fbg_model *model, const uint8_t *blob, size_t len);

/* Validate a model (shapes, ranges, non-NULL arrays, int64 accumulator bound proof).
 * fbg_init calls it, so a generated const model is checked once at start-up too. */
fbg_status fbg_model_check(const fbg_model *model);

/* Bytes a blob occupies as declared in its header (0 if shorter than the header). */
size_t fbg_blob_declared_size(const uint8_t *blob, size_t len);

/* CRC-32 (IEEE 802.3, reflected, poly 0xEDB88320, init/xorout 0xFFFFFFFF) as in zlib. */
uint32_t fbg_crc32(const uint8_t *data, size_t len);

/* Initialise a state for a model: baseline = model nominal baseline (status NOT_TARED),
 * zero FIR history. options: FBG_OPT_* flags, or-ed with at most one FBG_OPT_KERNEL_* value
 * (the dense-layer kernels; AUTO, 0, is the fastest this CPU runs; every kernel gives the
 * same bits). FBG_ERR_ARG if the requested kernel cannot run on this CPU or build. */
fbg_status fbg_init(fbg_state *state, const fbg_model *model, uint32_t options);

/* The FBG_OPT_KERNEL_* value a state runs (never AUTO: the one fbg_init chose); 0 if the
 * state is NULL or not initialised. */
uint32_t fbg_kernel(const fbg_state *state);

/* ---- Packed weights (host SIMD kernels; docs/runtime.md, "Packed weights") ----
 * The SSE2 and AVX2 kernels run faster from a copy of the model's nets packed for them (four
 * or eight rows' weights interleaved per input pair, so no row sums need adding up across a
 * vector, and each net runs in one call). The caller owns that copy's memory, as it owns the
 * state:
 *
 *   size_t n = fbg_pack_bytes(&st);            // 0: this state's kernel has no packed form
 *   if (n != 0) fbg_pack(&st, buf, n);         // buf: n bytes, FBG_PACK_ALIGN-aligned
 *
 * The buffer must stay alive and unchanged while a state uses it; any number of states of the
 * same model and kernel may share it (fbg_use_pack). fbg_init forgets it (the state runs the
 * unpacked kernels until fbg_pack or fbg_use_pack again); reset and tare keep it. The bits
 * are those of every other kernel. Builds without host SIMD kernels (Cortex-M, NEON,
 * FBG_HOST_SIMD=0) have no packed form: fbg_pack_bytes returns 0 there. */
#define FBG_PACK_ALIGN 32  /* alignment in bytes of a packed-weights buffer */

/* Bytes fbg_pack needs for this state's model and kernel; 0 if the kernel has no packed form
 * (portable C, NEON) or the state is NULL or not initialised. */
size_t fbg_pack_bytes(const fbg_state *state);

/* Pack the state's model for the state's kernel into buf[0, len) and make the state use it.
 * FBG_ERR_NULL (state or buf NULL), FBG_ERR_STATE (not initialised), FBG_ERR_ARG (the kernel
 * has no packed form, len < fbg_pack_bytes(state), or buf not FBG_PACK_ALIGN-aligned); on
 * an error the state and buf are unchanged. */
fbg_status fbg_pack(fbg_state *state, void *buf, size_t len);

/* Make a state use weights fbg_pack packed for another state (or itself); NULL goes back to
 * the unpacked kernels. FBG_ERR_ARG if packed was not packed by fbg_pack for this state's
 * model and kernel (the state is then unchanged). */
fbg_status fbg_use_pack(fbg_state *state, const void *packed);

/* Clear the FIR history, the memory states, the fault tracker, the decision over time and
 * the at-rest tracker's block (docs/runtime.md, "In use"). Keeps the baseline as the tracker
 * left it (tare and tared flag too); the tracker's bound counts from it again. */
fbg_status fbg_reset(fbg_state *state);

/* Tare = average of valid samples between begin and end becomes the baseline. Samples with
 * any channel outside [FBG_WL_MIN_FM, FBG_WL_MAX_FM] are skipped (tare_add returns FBG_OK
 * and *accepted = 0; accepted may be NULL). tare_end: FBG_ERR_TARE if nothing was accepted
 * (baseline unchanged); else sets the baseline (mean rounded half up), clears NOT_TARED and
 * resets the FIR history. Stepping during a tare is allowed (it uses the old baseline). */
fbg_status fbg_tare_begin(fbg_state *state);
fbg_status fbg_tare_add(fbg_state *state, const int32_t wl_fm[FBG_N_CHANNELS], int *accepted);
fbg_status fbg_tare_end(fbg_state *state);

/* Set the baseline directly (e.g. stored from a previous tare); every channel must lie in
 * [FBG_WL_MIN_FM, FBG_WL_MAX_FM] (else FBG_ERR_ARG). Resets the FIR history, the decision
 * and the at-rest tracker (as a tare does). fbg_get_baseline reads the baseline the tracker
 * has moved it to (store that one to resume after a restart). */
fbg_status fbg_set_baseline(fbg_state *state, const int32_t baseline_fm[FBG_N_CHANNELS]);
fbg_status fbg_get_baseline(const fbg_state *state, int32_t baseline_fm[FBG_N_CHANNELS]);

/* Process one sample wl_fm = {wl1, wl2, wl3, wl4, wlT} (fm).
 * Sensor-fault rule: channel c is faulty when wl_fm[c] < FBG_WL_MIN_FM or > FBG_WL_MAX_FM
 * (a lost peak: 0, -1, INT32 sentinels), or when it jumps by more than model->jump_max_fm
 * from the previous in-window sample of that channel (prev is updated by every in-window
 * sample, so a genuine step faults one sample only), or when it has repeated the identical
 * value for model->stuck_max consecutive samples (a frozen peak; the counter restarts on
 * any change or out-of-window sample; stuck_max 0 = off). A faulty T channel (reference gone)
 * faults the sample too. On a fault: the FIR is fed its last input again (time base kept),
 * the nets are not run, *out is the safe output with FBG_STATUS_SENSOR_FAULT.
 * Returns FBG_OK (the output status says the rest), FBG_ERR_NULL, FBG_ERR_STATE,
 * FBG_ERR_NOT_TARED (with FBG_OPT_REQUIRE_TARE) or FBG_ERR_MODEL_CHANGED (the model's
 * blob_crc is no longer the one fbg_init saw: it was reloaded in place; fbg_init again); on
 * the last two *out is the safe output and the state is unchanged. */
fbg_status fbg_step(fbg_state *state, const int32_t wl_fm[FBG_N_CHANNELS], fbg_output *out);

/* Batch: n samples, wl_fm row-major n x 5, out[n]. Same as n calls of fbg_step; stops at
 * the first error and returns it (that sample's output is the safe output; later outputs
 * are not written). */
fbg_status fbg_run(fbg_state *state, const int32_t *wl_fm, size_t n, fbg_output *out);

/* Integer sigmoid used for contact_conf_q15: x_q8 = margin * 256 -> P in Q15 (0..32767).
 * Table of 129 points on [-8, 8] with linear interpolation (docs/fixed-point.md). */
int32_t fbg_sigmoid_q15(int32_t x_q8);

/* ---------------------------------------------------------------------------------------
 * Float build (single precision): the same pipeline as fbgforce.model in float32, for FPU
 * targets (Cortex-M4F) and as the "cfloat" engine. The model is a view of float arrays
 * (generated C writes <name>_model_f32; the Python binding builds one from numpy).
 * Tare, fault rule and status flags are those of the fixed-point build (input is the same
 * int32 fm; the tare difference is exact in integers before conversion to float).
 * ------------------------------------------------------------------------------------- */
typedef struct {
    uint16_t n_in;
    uint16_t n_out;
    const float *w;          /* row-major n_out x n_in */
    const float *b;          /* n_out */
} fbgf_layer;

typedef struct {
    uint8_t n_layers;
    uint8_t reserved[3];
    fbgf_layer layers[FBG_MAX_LAYERS];
} fbgf_net;

/* ---- BEGIN GENERATED float: `python -m fbgforce.contract --write` from pkgroot/contract/; do not edit ---- */
/* Float model: the same pipeline in single precision. */
typedef struct {
    int32_t baseline_fm[5];
    int32_t jump_max_fm;
    float temp_coeff[4];
    float input_mean_pm[4];
    float input_std_pm[4];
    float force_offset_N;
    float force_scale;
    float xy_offset_mm[2];
    float xy_scale[2];
    float overload_N;
    float mem_weight[4];  /* memory input u = sum_i mem_weight[i] * z_i */
    float play_width[4];  /* in standardised units */
    float contact_on;  /* decision over time as fbg_model, on the margin */
    float contact_off;
    float track_step_max_pm;  /* per block: corr_i += clamp(sum(filt_i) / 2^track_shift, +-track_step_max_pm) */
    float track_limit_pm;  /* |corr_i| <= track_limit_pm (BASELINE_LIMIT at it) */
    float track_creep;  /* the tracker's creep term as fbg_model, 0..0.5 (0: off): per sample at rest it sums filt_i - track_creep * creep_pm_i */
    float hold_gain;  /* the settled-hold gain as fbg_model, its excess over 1 itself, |hold_gain| <= 0.125 (0: off): force_N *= 1 + hold_gain * w / 2^hold_ramp_shift */
    float hold_band_N;  /* steady: |force_N - hold_avg_N| <= max(hold_band_N, hold_band_frac * |force_N|), hold_avg_N += (force_N - hold_avg_N) / 2^hold_shift */
    float hold_band_frac;  /* 0..1 */
    float contact_cusum_h;  /* the decision's CUSUM rise as fbg_model, on the margin (0: off; on: contact_on 0, contact_rise_n 1, lo <= hi): S = max(0, S + clamp(margin, lo, hi) - k), contact rises when S >= h */
    float contact_cusum_k;
    float contact_cusum_lo;
    float contact_cusum_hi;
    float in_lo[12];  /* OUT_OF_RANGE as fbg_model, standardised units */
    float in_hi[12];
    float creep_q;  /* the pad's creep inverse as fbg_model, its gain q = kappa / (1 - kappa) itself, 0 <= q < 1 (0: off): e_i = c_i + creep_q * (c_i - creep_lag_pm_i) replaces c_i, creep_lag_pm_i += (e_i - creep_lag_pm_i) / 2^creep_shift */
    uint16_t stuck_max;
    uint16_t n_taps;  /* 1..FBG_MAX_TAPS */
    uint16_t track_settle;
    uint16_t hold_settle;
    uint8_t n_ema;  /* as fbg_model */
    uint8_t n_play;
    uint8_t ema_shift[4];  /* state += (u - state) / 2^ema_shift[k] */
    uint8_t ema_gain[4];
    uint8_t play_gain[4];
    uint8_t loc_shift;  /* location averages of z - z_rest (0: off): state += (r - state) / 2^loc_shift */
    uint8_t contact_rise_n;  /* 1..255 */
    uint8_t track_shift;  /* at-rest baseline tracker as fbg_model (0: off) */
    uint8_t track_creep_shift;  /* creep_pm_i += (filt_i - creep_pm_i) / 2^track_creep_shift on every good sample (1..15 when track_creep > 0) */
    uint8_t hold_shift;  /* 1..15 when hold_gain is on */
    uint8_t hold_ramp_shift;  /* 0..FBG_MAX_HOLD_RAMP_SHIFT */
    uint8_t ref_shift;  /* temperature reference average as fbg_model (0: off): r += (shift_T - r) / 2^s, s = min(ref_shift, floor(log2 n)) at the n-th good sample */
    uint8_t creep_shift;  /* the pad's creep time constant (1..15 when creep_q > 0) */
    uint8_t pad_[2];  /* explicit padding, keep 0 */
    const float *taps;       /* taps[k] weights sample n - k */
    fbgf_net nets[FBG_N_NETS];   /* contact net has 2 outputs (logits) */
} fbgf_model;

typedef struct {
    float force_N;  /* 0 when no contact */
    float x_mm;  /* 0 when no contact */
    float y_mm;
    float p_contact;  /* softmax probability of contact */
    float margin;  /* logit[1] - logit[0] */
    uint32_t status;  /* FBG_STATUS_* */
    uint8_t contact;
    uint8_t reserved[3];
} fbgf_output;
/* ---- END GENERATED float ---- */

/* ---- BEGIN GENERATED float state: `python -m fbgforce.contract --write` from pkgroot/contract/; do not edit ---- */
/* Caller-owned streaming state. Treat as opaque; size is sizeof(fbgf_state). */
typedef struct {
    uint32_t magic;                              /* set by fbgf_init */
    uint32_t options;
    const fbgf_model *model;
    int32_t baseline_fm[FBG_N_CHANNELS];
    int32_t prev_fm[FBG_N_CHANNELS];             /* last in-window sample per channel */
    float hist[FBG_MAX_TAPS][FBG_N_STRAIN];      /* FIR history (ring buffer) */
    float last_comp[FBG_N_STRAIN];               /* the last good sample's filtered shifts, held into the FIR during a fault */
    /* Memory states of the load signal u (docs/fixed-point.md, "memory"), one array per kind
     * of fbgforce.contract.MEMORY_KINDS. */
    float ema[FBG_MAX_EMA];                      /* exponential-average memory states, standardised units */
    float play[FBG_MAX_PLAY];                    /* play-operator memory states, standardised units */
    float loc[FBG_N_STRAIN];                     /* location averages of z - z_rest */
    float creep_pm[FBG_N_STRAIN];                /* the tracker's creep states: averages of the filtered shifts (pm), primed with the memory (mem_primed) */
    float ref_pm;                                /* the temperature reference's average (pm) */
    float hold_avg_N;                            /* the hold stage's average of force_N */
    float creep_lag_pm[FBG_N_STRAIN];            /* the creep inverse's lags L_i (pm) */
    int64_t tare_sum[FBG_N_CHANNELS];
    uint32_t tare_count;
    float cusum;                                 /* the decision's CUSUM S (margin), as fbg_state's cusum_q8 */
    uint16_t pos;                                /* next write index into hist */
    uint16_t since_reset;                        /* samples since init/tare, saturating */
    uint16_t same_run[FBG_N_CHANNELS];           /* repeats of the identical value */
    uint8_t tared;
    uint8_t tare_active;
    uint8_t prev_valid;                          /* bit c: prev_fm[c] holds a sample */
    uint8_t mem_primed;                          /* memory states hold a sample */
    uint8_t ref_count;                           /* good samples in the temperature reference's average (up to 255: its gain has reached 2^-ref_shift by 2^ref_shift <= 256) */
    uint8_t creep_primed;                        /* the creep inverse's lags hold a sample */
    /* The decision over time and the at-rest baseline tracker, as fbg_state's: the block's
     * sum of filtered shifts (pm); the correction subtracted from the compensated shifts is
     * held_pm (made before the last reset) + drift_pm (since, bounded by track_limit_pm). */
    float track_sum[FBG_N_STRAIN];
    float drift_pm[FBG_N_STRAIN];
    float held_pm[FBG_N_STRAIN];
    uint16_t rest_run;                           /* samples at rest, saturating */
    uint8_t decision;                            /* the contact decision of the last step, held through the release band */
    uint8_t released;                            /* 1: in the release band, contact no longer shown */
    uint8_t release_run;                         /* samples with the margin at or below 0 so far, in contact (up to FBG_RELEASE_DWELL) */
    uint8_t rise_run;                            /* samples of the rise condition so far */
    uint8_t track_pos;                           /* samples into the tracker's block */
    uint8_t track_limited;                       /* 1: a channel's drift_pm is at its bound */
    uint16_t hold_run;                           /* steady contact samples so far, saturating */
    uint8_t hold_primed;                         /* hold_avg_N holds a contact sample's force */
    uint8_t reserved_[1];
    float act[2][FBG_MAX_WIDTH];                 /* activation ping-pong buffers */
} fbgf_state;
/* ---- END GENERATED float state ---- */

fbg_status fbgf_model_check(const fbgf_model *model);
fbg_status fbgf_init(fbgf_state *state, const fbgf_model *model, uint32_t options);
fbg_status fbgf_reset(fbgf_state *state);
fbg_status fbgf_tare_begin(fbgf_state *state);
fbg_status fbgf_tare_add(fbgf_state *state, const int32_t wl_fm[FBG_N_CHANNELS], int *accepted);
fbg_status fbgf_tare_end(fbgf_state *state);
fbg_status fbgf_set_baseline(fbgf_state *state, const int32_t baseline_fm[FBG_N_CHANNELS]);
fbg_status fbgf_step(fbgf_state *state, const int32_t wl_fm[FBG_N_CHANNELS], fbgf_output *out);
fbg_status fbgf_run(fbgf_state *state, const int32_t *wl_fm, size_t n, fbgf_output *out);

#ifdef __cplusplus
}
#endif

#endif /* FBGFORCE_H */
