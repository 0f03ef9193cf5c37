/* simd_replay.c - replays a golden session (golden_vectors.c in the layout of
 * examples/firmware/fw_golden.h) once per dense-layer kernel named on the command line
 * (FBG_OPT_KERNEL_* values; a trailing "p" runs the kernel from weights fbg_pack packed into
 * a buffer of exactly fbg_pack_bytes), comparing every return status, `accepted` flag and
 * output byte. Built by tests/test_simd.py natively and for aarch64 (run under qemu-aarch64)
 * with the model generated as replay_model.c. Prints one line per kernel; exit 0 iff all
 * match. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fbgforce.h"
#include "fw_golden.h"
#include "replay_model.h"

/* fbg_init, then (pack) fbg_use_pack of the buffer packed at the first call. */
static fbg_status init(fbg_state *st, uint32_t kernel, const void *pack)
{
    fbg_status got = fbg_init(st, &replay_model, fw_golden_options | kernel);
    return got == FBG_OK && pack != NULL ? fbg_use_pack(st, pack) : got;
}

static unsigned replay(uint32_t kernel, int packed, unsigned *steps)
{
    static fbg_state st;
    fbg_output out;
    unsigned i, bad = 0;
    int accepted;
    void *pack = NULL;
    unsigned char *mem = NULL;
    fbg_status got = fbg_init(&st, &replay_model, fw_golden_options | kernel);
    if (got != FBG_OK || fbg_kernel(&st) != kernel)
        return fw_golden_count + 1u;
    if (packed) {
        /* Exactly the bytes asked for, FBG_PACK_ALIGN-aligned (malloc aligns to 16 at least):
         * a read past the packed form leaves the allocation (AddressSanitizer). */
        size_t bytes = fbg_pack_bytes(&st);
        mem = bytes != 0u ? malloc(bytes + FBG_PACK_ALIGN) : NULL;
        if (mem == NULL)
            return fw_golden_count + 1u;
        pack = mem + (FBG_PACK_ALIGN - (uintptr_t)mem % FBG_PACK_ALIGN) % FBG_PACK_ALIGN;
        if (fbg_pack(&st, pack, bytes) != FBG_OK) {
            free(mem);
            return fw_golden_count + 1u;
        }
    }
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
            got = init(&st, kernel, pack);
            break;
        }
        if ((int)got != r->status || accepted != r->accepted)
            ++bad;
    }
    free(mem);
    return bad;
}

int main(int argc, char **argv)
{
    int k, rc = 0;
    for (k = 1; k < argc; ++k) {
        char *end;
        uint32_t kernel = (uint32_t)strtoul(argv[k], &end, 0);
        int packed = *end == 'p';
        unsigned steps = 0, bad = replay(kernel, packed, &steps);
        if (bad > fw_golden_count)
            printf("kernel 0x%02x%s: cannot run here\n", (unsigned)kernel, packed ? " packed" : "");
        else
            printf("kernel 0x%02x%s: %u records (%u steps), %u differ\n", (unsigned)kernel,
                   packed ? " packed" : "", (unsigned)fw_golden_count, steps, bad);
        if (bad != 0u)
            rc = 1;
    }
    return rc;
}
