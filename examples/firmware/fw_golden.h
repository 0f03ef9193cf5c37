/* fw_golden.h - layout of the golden vectors that `fbgforce target-report` generates
 * (golden_vectors.c) from the Python integer reference, replayed by main.c. */
#ifndef FBG_FW_GOLDEN_H
#define FBG_FW_GOLDEN_H

#include <stdint.h>

#include "fbgforce.h"

/* One API call of the replayed session, in order. */
enum {
    FW_OP_STEP = 0,         /* fbg_step(wl) -> compare return status and the whole fbg_output */
    FW_OP_TARE_BEGIN = 1,   /* fbg_tare_begin() -> compare return status */
    FW_OP_TARE_ADD = 2,     /* fbg_tare_add(wl, &accepted) -> compare status and `accepted` */
    FW_OP_TARE_END = 3,     /* fbg_tare_end() -> compare status */
    FW_OP_SET_BASELINE = 4, /* fbg_set_baseline(wl) -> compare status */
    FW_OP_RESET = 5,        /* fbg_reset() -> compare status */
    FW_OP_INIT = 6          /* fbg_init(model, fw_golden_options) again: a fresh state */
};

typedef struct {
    int32_t wl_fm[FBG_N_CHANNELS]; /* input (steps, tare samples, baselines) */
    int8_t op;                     /* FW_OP_* */
    int8_t status;                 /* expected fbg_status return value */
    int8_t accepted;               /* expected `accepted` of FW_OP_TARE_ADD, else 0 */
    int8_t reserved;
    fbg_output out;                /* expected output of FW_OP_STEP (all bytes compared) */
} fw_record;

extern const fw_record fw_golden[];
extern const uint32_t fw_golden_count;
/* fbg_init options for the replay (FBG_OPT_*). */
extern const uint32_t fw_golden_options;

#endif
