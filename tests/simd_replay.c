/* simd_replay.c - replays a golden session (golden_vectors.c in the layout of
 * examples/firmware/fw_golden.h) once per dense-layer kernel named on the command line
 * (FBG_OPT_KERNEL_* values), comparing every return status, `accepted` flag and output byte.
 * Built by tests/test_simd.py natively and for aarch64 (run under qemu-aarch64) with the
 * model generated as replay_model.c. Prints one line per kernel; exit 0 iff all match. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fbgforce.h"
#include "fw_golden.h"
#include "replay_model.h"

static unsigned replay(uint32_t kernel, unsigned *steps)
{
    static fbg_state st;
    fbg_output out;
    unsigned i, bad = 0;
    int accepted;
    fbg_status got = fbg_init(&st, &replay_model, fw_golden_options | kernel);
    if (got != FBG_OK || fbg_kernel(&st) != kernel)
        return fw_golden_count + 1u;
    *steps = 0;
    for (i = 0; i < fw_golden_count; ++i) {
        const fw_record *r = &fw_golden[i];
        accepted = 0;
        switch (r->op) {
        case FW_OP_STEP:
            got = fbg_step(&st, r->wl_fm, &out);
            if (memcmp(&out, &r->out, sizeof out) != 0)
                got = (fbg_status)99; /* counted as a mismatch below */
            ++*steps;
            break;
        case FW_OP_TARE_BEGIN:
            got = fbg_tare_begin(&st);
            break;
        case FW_OP_TARE_ADD:
            got = fbg_tare_add(&st, r->wl_fm, &accepted);
            break;
        case FW_OP_TARE_END:
            got = fbg_tare_end(&st);
            break;
        case FW_OP_SET_BASELINE:
            got = fbg_set_baseline(&st, r->wl_fm);
            break;
        case FW_OP_RESET:
            got = fbg_reset(&st);
            break;
        default:
            got = fbg_init(&st, &replay_model, fw_golden_options | kernel);
            break;
        }
        if ((int)got != r->status || accepted != r->accepted)
            ++bad;
    }
    return bad;
}

int main(int argc, char **argv)
{
    int k, rc = 0;
    for (k = 1; k < argc; ++k) {
        uint32_t kernel = (uint32_t)strtoul(argv[k], NULL, 0);
        unsigned steps = 0, bad = replay(kernel, &steps);
        if (bad > fw_golden_count)
            printf("kernel 0x%02x: cannot run here\n", (unsigned)kernel);
        else
            printf("kernel 0x%02x: %u records (%u steps), %u differ\n", (unsigned)kernel,
                   (unsigned)fw_golden_count, steps, bad);
        if (bad != 0u)
            rc = 1;
    }
    return rc;
}
