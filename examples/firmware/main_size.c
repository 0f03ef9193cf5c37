/* main_size.c - the smallest firmware using the whole API (init, tare, step): linked only to
 * measure what libfbgforce and a model cost in flash and RAM (fw_size.elf; `fbgforce
 * target-report` sums every section that does not come from this harness). */
#include <stdint.h>

#include "fbgforce.h"

#ifndef FBG_FW_MODEL_SYM
#define FBG_FW_MODEL_SYM fbg_model_default
#endif
extern const fbg_model FBG_FW_MODEL_SYM;

static fbg_state state;
/* volatile: the compiler must not fold the samples into constants. */
static volatile int32_t sample[FBG_N_CHANNELS] = {1530000000, 1538000000, 1546000000, 1554000000,
                                                   1562000000};

int main(void)
{
    int32_t wl[FBG_N_CHANNELS];
    fbg_output out;
    int accepted = 0, c, k;
    if (fbg_init(&state, &FBG_FW_MODEL_SYM, 0u) != FBG_OK)
        return 2;
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        wl[c] = sample[c];
    fbg_tare_begin(&state);
    for (k = 0; k < 4; ++k)
        fbg_tare_add(&state, wl, &accepted);
    fbg_tare_end(&state);
    for (k = 0; k < 4; ++k)
        fbg_step(&state, wl, &out);
    return (int)(out.status & 0x7Fu);
}
