/*
 * fbg_front.h - the integer front end of both builds (not installed): state checks, tare,
 * baseline, the fault rule, the tare difference and the FIR ring bookkeeping, and the API
 * wrappers around them (FBG_FRONT_API). The fixed-point stages and fbgf_float.c run these
 * same functions; only what follows the tare difference (the temperature compensation, the
 * FIR sums, the nets) is written per build.
 *
 * Integer only: the fixed-point sources include it, and check-nofloat compiles them with
 * -mgeneral-regs-only.
 *
 * fbg_state and fbgf_state hold the front end's fields under the same names but at different
 * offsets (the FIR history is int32 in one and float in the other, the activation buffers sit
 * elsewhere), so the front end reaches them through an fbg_front view that FBG_FRONT_OF makes
 * from either state. The functions are static inline: each build gets them folded into its
 * own code, the view's pointers become fixed offsets from the state, and the fixed-point
 * step pays nothing for the indirection.
 */
#ifndef FBG_FRONT_H
#define FBG_FRONT_H

#include <string.h>

#include "fbg_contract.h" /* FBG_MEMORY_STATES */
#include "fbg_internal.h"

/* The front end's view of one state (of either build). */
typedef struct {
    uint32_t magic_value;        /* FBG_STATE_MAGIC or FBGF_STATE_MAGIC */
    int model_set;               /* state->model != NULL when the view was made */
    uint32_t *magic;
    uint32_t *options;
    int32_t *baseline_fm;        /* FBG_N_CHANNELS */
    int32_t *prev_fm;            /* FBG_N_CHANNELS */
    void *hist;                  /* the FIR history, whatever its element type */
    size_t hist_size;
    void *last_comp;             /* the last filtered shifts, held into the FIR during a fault */
    size_t last_comp_size;
    void *mem[FBG_N_MEMORY_STATES];        /* the memory states (FBG_MEMORY_STATES of fbg_contract.h),
                                            * whatever their element type */
    size_t mem_size[FBG_N_MEMORY_STATES];
    uint8_t *mem_primed;
    uint8_t *ref_count;          /* the temperature reference's average, whatever its type */
    uint8_t *creep_primed;       /* the creep inverse's lags, whatever their type */
    int64_t *tare_sum;           /* FBG_N_CHANNELS */
    uint32_t *tare_count;
    uint16_t *pos;
    uint16_t *since_reset;
    uint16_t *same_run;          /* FBG_N_CHANNELS */
    uint8_t *tared;
    uint8_t *tare_active;
    uint8_t *prev_valid;
} fbg_front;

#define FBG_FRONT_MEM(s, member) (s)->member,
#define FBG_FRONT_MEM_SIZE(s, member) sizeof (s)->member,

/* The view of state s (a non-NULL fbg_state * or fbgf_state *; both name these fields
 * alike, which is why one initialiser serves both). */
#define FBG_FRONT_OF(s, magic_val)                                                            \
    ((fbg_front){.magic_value = (magic_val),                                                  \
                 .model_set = (s)->model != NULL, .magic = &(s)->magic,                       \
                 .options = &(s)->options, .baseline_fm = (s)->baseline_fm,                   \
                 .prev_fm = (s)->prev_fm, .hist = (s)->hist, .hist_size = sizeof (s)->hist,   \
                 .last_comp = (s)->last_comp, .last_comp_size = sizeof (s)->last_comp,        \
                 .mem = {FBG_MEMORY_STATES(FBG_FRONT_MEM, s)},                                \
                 .mem_size = {FBG_MEMORY_STATES(FBG_FRONT_MEM_SIZE, s)},                      \
                 .mem_primed = &(s)->mem_primed, .ref_count = &(s)->ref_count,                \
                 .creep_primed = &(s)->creep_primed,                                          \
                 .tare_sum = (s)->tare_sum, .tare_count = &(s)->tare_count, .pos = &(s)->pos, \
                 .since_reset = &(s)->since_reset, .same_run = (s)->same_run,                 \
                 .tared = &(s)->tared, .tare_active = &(s)->tare_active,                      \
                 .prev_valid = &(s)->prev_valid})

/* Initialised by fbg_init / fbgf_init, and not overwritten since. */
static inline int fbg_front_ok(fbg_front f)
{
    return *f.magic == f.magic_value && f.model_set;
}

/* fbg_init after the model check, on a state the caller has zeroed (before making the view,
 * which reads state->model) and gives its typed model pointer: the model's nominal baseline,
 * the options, the magic. */
static inline void fbg_front_init(fbg_front f, const int32_t model_baseline_fm[FBG_N_CHANNELS],
                                  uint32_t options)
{
    *f.options = options;
    memcpy(f.baseline_fm, model_baseline_fm, FBG_N_CHANNELS * sizeof *f.baseline_fm);
    *f.magic = f.magic_value;
}

/* Forget the FIR history, the memory states, the temperature reference's average and the
 * creep inverse's lags (the next good sample primes them) and the fault tracker; baseline and
 * tare stay. */
static inline void fbg_front_clear(fbg_front f)
{
    unsigned k;
    memset(f.hist, 0, f.hist_size);
    memset(f.last_comp, 0, f.last_comp_size);
    for (k = 0; k < FBG_N_MEMORY_STATES; ++k)
        memset(f.mem[k], 0, f.mem_size[k]);
    *f.mem_primed = 0u;
    *f.ref_count = 0u;
    *f.creep_primed = 0u;
    memset(f.prev_fm, 0, FBG_N_CHANNELS * sizeof *f.prev_fm);
    *f.prev_valid = 0u;
    memset(f.same_run, 0, FBG_N_CHANNELS * sizeof *f.same_run);
    *f.pos = 0u;
    *f.since_reset = 0u;
}

static inline fbg_status fbg_front_reset(fbg_front f)
{
    if (!fbg_front_ok(f))
        return FBG_ERR_STATE;
    fbg_front_clear(f);
    return FBG_OK;
}

static inline fbg_status fbg_front_tare_begin(fbg_front f)
{
    if (!fbg_front_ok(f))
        return FBG_ERR_STATE;
    memset(f.tare_sum, 0, FBG_N_CHANNELS * sizeof *f.tare_sum);
    *f.tare_count = 0u;
    *f.tare_active = 1u;
    return FBG_OK;
}

static inline fbg_status fbg_front_tare_add(fbg_front f, const int32_t wl_fm[FBG_N_CHANNELS],
                                            int *accepted)
{
    int ok;
    if (!fbg_front_ok(f))
        return FBG_ERR_STATE;
    if (!*f.tare_active)
        return FBG_ERR_TARE;
    ok = fbg_tare_accept(wl_fm, f.tare_sum, f.tare_count);
    if (accepted != NULL)
        *accepted = ok;
    return FBG_OK;
}

static inline fbg_status fbg_front_tare_end(fbg_front f)
{
    if (!fbg_front_ok(f))
        return FBG_ERR_STATE;
    if (!*f.tare_active)
        return FBG_ERR_TARE;
    *f.tare_active = 0u;
    if (*f.tare_count == 0u)
        return FBG_ERR_TARE;
    fbg_tare_mean(f.tare_sum, *f.tare_count, f.baseline_fm);
    *f.tared = 1u;
    fbg_front_clear(f);
    return FBG_OK;
}

static inline fbg_status fbg_front_set_baseline(fbg_front f,
                                                const int32_t baseline_fm[FBG_N_CHANNELS])
{
    if (!fbg_front_ok(f))
        return FBG_ERR_STATE;
    if (!fbg_baseline_ok(baseline_fm))
        return FBG_ERR_ARG;
    memcpy(f.baseline_fm, baseline_fm, FBG_N_CHANNELS * sizeof *f.baseline_fm);
    *f.tared = 1u;
    fbg_front_clear(f);
    return FBG_OK;
}

/* The checks that open a step. FBG_OK with *status = the step's starting flags (NOT_TARED
 * before a tare); otherwise the step's error, and *status is what its safe output carries. */
static inline fbg_status fbg_front_step_begin(fbg_front f, uint32_t *status)
{
    if (!fbg_front_ok(f)) {
        *status = 0u;
        return FBG_ERR_STATE;
    }
    *status = *f.tared ? 0u : FBG_STATUS_NOT_TARED;
    if ((*f.options & FBG_OPT_REQUIRE_TARE) && !*f.tared)
        return FBG_ERR_NOT_TARED;
    return FBG_OK;
}

/* The fault rule, then the tare difference: returns 1 for a faulty sample (SENSOR_FAULT added
 * to *status; the caller feeds the FIR its held last_comp), else 0 with
 * shift_fm[c] = sat32(wl_fm[c] - baseline_fm[c]) for every channel, the reference channel
 * FBG_N_STRAIN included (which never clamps: see below). */
static inline int fbg_front_sample(fbg_front f, const int32_t wl_fm[FBG_N_CHANNELS],
                                   int32_t jump_max_fm, uint16_t stuck_max, uint32_t *status,
                                   int32_t shift_fm[FBG_N_CHANNELS])
{
    unsigned c;
    if (fbg_fault_check(wl_fm, f.prev_fm, f.prev_valid, f.same_run, jump_max_fm, stuck_max)) {
        *status |= FBG_STATUS_SENSOR_FAULT;
        return 1;
    }
    /* A sample that passed the fault rule is in the window [1e9, 2e9] fm, and so is every
     * baseline (the model's is checked at init, fbg_set_baseline checks, a tare mean is the
     * mean of in-window samples): the difference is within +-1e9, exact in int32, and sat32
     * of docs/fixed-point.md never clamps here. */
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        shift_fm[c] = wl_fm[c] - f.baseline_fm[c];
    return 0;
}

/* After the caller has written the new sample into hist[*pos]: count it towards the warm-up
 * (WARMUP while fewer than n_taps samples since init, reset or tare). Returns 1 when the
 * sample is faulty: the ring then moves on here and the step ends with the safe output;
 * otherwise the caller runs the FIR from *pos and moves the ring on itself. */
static inline int fbg_front_push_done(fbg_front f, uint16_t n_taps, uint32_t *status)
{
    if (*f.since_reset < 0xFFFFu)
        (*f.since_reset)++;
    if (*f.since_reset < n_taps)
        *status |= FBG_STATUS_WARMUP;
    if (*status & FBG_STATUS_SENSOR_FAULT) {
        *f.pos = (uint16_t)((*f.pos + 1u) % n_taps);
        return 1;
    }
    return 0;
}

/* What a reset, a tare and a new baseline restart in both builds' states, beyond the front end:
 * the decision over time, the tracker's block and the settled-hold count. */
#define FBG_RESTART_IN_USE(s)                                                                 \
    ((s)->decision = 0u, (s)->released = 0u, (s)->release_run = 0u, (s)->rise_run = 0u,       \
     (s)->rest_run = 0u, (s)->track_pos = 0u, (s)->track_limited = 0u, (s)->hold_run = 0u,    \
     (s)->hold_primed = 0u)

/* The front-end half of a build's API, defined once for both builds: PREFIX_reset,
 * PREFIX_tare_begin, PREFIX_tare_add, PREFIX_tare_end and PREFIX_set_baseline on STATE_T
 * (whose initialised magic is MAGIC). Each checks its pointers and runs the front end; reset,
 * tare end and a new baseline then hand the front end's status to RESTART(state, status,
 * reset), the build's restart of its decision, tracker and hold (reset 1 for a reset, 0 for
 * a tare or a new baseline), which returns the status. */
#define FBG_FRONT_API(prefix, state_t, magic, restart)                                         \
    fbg_status prefix##_reset(state_t *state)                                                  \
    {                                                                                          \
        return state == NULL ? FBG_ERR_NULL                                                    \
                             : restart(state, fbg_front_reset(FBG_FRONT_OF(state, magic)), 1); \
    }                                                                                          \
                                                                                               \
    fbg_status prefix##_tare_begin(state_t *state)                                             \
    {                                                                                          \
        return state == NULL ? FBG_ERR_NULL : fbg_front_tare_begin(FBG_FRONT_OF(state, magic)); \
    }                                                                                          \
                                                                                               \
    fbg_status prefix##_tare_add(state_t *state, const int32_t wl_fm[FBG_N_CHANNELS],          \
                                 int *accepted)                                                \
    {                                                                                          \
        if (state == NULL || wl_fm == NULL)                                                    \
            return FBG_ERR_NULL;                                                               \
        return fbg_front_tare_add(FBG_FRONT_OF(state, magic), wl_fm, accepted);                \
    }                                                                                          \
                                                                                               \
    fbg_status prefix##_tare_end(state_t *state)                                               \
    {                                                                                          \
        return state == NULL ? FBG_ERR_NULL                                                    \
                             : restart(state, fbg_front_tare_end(FBG_FRONT_OF(state, magic)), 0); \
    }                                                                                          \
                                                                                               \
    fbg_status prefix##_set_baseline(state_t *state,                                           \
                                     const int32_t baseline_fm[FBG_N_CHANNELS])                \
    {                                                                                          \
        if (state == NULL || baseline_fm == NULL)                                              \
            return FBG_ERR_NULL;                                                               \
        return restart(state, fbg_front_set_baseline(FBG_FRONT_OF(state, magic), baseline_fm), 0); \
    }

#endif /* FBG_FRONT_H */
