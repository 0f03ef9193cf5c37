/*
 * fbg_stages.h - the stages of the fixed-point step (not installed), one file each, in the
 * order fbg_step (fbg_fixed.c) runs them, which is export/intref.py's:
 *   fbg_stage_front.c     the fault rule, tare difference, temperature compensation, creep inverse
 *   fbg_stage_filter.c    the FIR over the ring, the standardisation, the input-side overload
 *   fbg_stage_memory.c    the memory features after z and the location averages
 *   fbg_stage_nets.c      the nets' layers: the accumulators of a net's output layer
 *   fbg_stage_decision.c  the contact decision over time
 *   fbg_stage_tracker.c   the creep states and the at-rest baseline tracker
 *   fbg_stage_hold.c      the settled-hold gain
 * Each stage is one function with a portable reference beside it; where an instruction set has
 * its own variant of a stage, the stage picks it: at compile time on the target (FBG_USE_DSP,
 * fbg_dsp.h) and by the state's kernel on the host (FBG_OPT_KERNEL_*, fbg_simd.h). The float
 * build (fbgf_float.c) names its stages alike, with its fbgf_ prefix.
 *
 * No float or double in the stages (check-nofloat builds them with -mgeneral-regs-only);
 * export/intref.py mirrors every operation bit for bit.
 */
#ifndef FBG_STAGES_H
#define FBG_STAGES_H

#include "fbg_front.h"
#include "fbg_simd.h" /* host SIMD dense layers (FBG_HOST_SIMD, docs/runtime.md) */
#if FBG_USE_DSP /* Cortex-M4 DSP-extension inner loops (fbg_dsp.h, docs/firmware.md) */
#include "fbg_dsp.h"
#endif

/* The shared front end's view of a fixed-point state (fbg_front.h). */
#define FBG_FRONT(s) FBG_FRONT_OF(s, FBG_STATE_MAGIC)

/* The FBG_OPT_KERNEL_* value an initialised state runs: it picks the host variants. */
static inline uint32_t state_kernel(const fbg_state *s)
{
    return s->options & FBG_OPT_KERNEL_MASK;
}

/* 1. Front: a sample's compensated strain shifts into the FIR ring at s->pos (the last good
 *    filtered shifts for a faulty one, SENSOR_FAULT then added to *status). */
void fbg_front_stage(fbg_state *s, const fbg_model *m, const int32_t wl_fm[FBG_N_CHANNELS],
                     uint32_t *status, uint32_t *sat);
/* 2. Filter: z = in[0..3]; FBG_STATUS_OVERLOAD for an input-side overload, else 0. */
uint32_t fbg_filter_stage(fbg_state *s, const fbg_model *m, int16_t *in, uint32_t *sat);
/* 3. Memory: the memory features after z in in[4 ..], the location averages in loc. */
void fbg_memory_stage(fbg_state *s, const fbg_model *m, int16_t *in, int16_t *loc, uint32_t *sat);
/* 4. Nets: every layer of net n on the net inputs in; acc = the accumulators of its output
 *    layer, which it returns. */
const fbg_layer *fbg_net_accs(fbg_state *s, const fbg_model *m, unsigned n, const int16_t *in,
                              int64_t *acc, uint32_t *sat);
/* 5. Decision: the contact decision over time from the net's raw decision and margin. */
uint8_t fbg_contact_decision(fbg_state *s, const fbg_model *m, int raw, int32_t margin_q8);
/* The tracker: the creep states on every good sample (z), the baseline on samples at rest
 * (z, or NULL for a sample that is not). */
void fbg_creep_update(fbg_state *s, const fbg_model *m, const int16_t *z);
void fbg_rest_track(fbg_state *s, const fbg_model *m, const int16_t *z);
/* The hold: the settled-hold gain applied to a contact step's force. */
int32_t fbg_hold_stage(fbg_state *s, const fbg_model *m, int32_t force_mN, uint32_t *sat);

#endif /* FBG_STAGES_H */
