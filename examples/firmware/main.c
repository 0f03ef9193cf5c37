/* main.c - replay golden vectors through libfbgforce on a bare-metal Cortex-M4 (QEMU mps2-an386)
 * and compare every output bit with the Python integer reference.
 *
 * Then checks that a state refuses to step on a model changed under it (model_swap_refused).
 * Prints one result line over semihosting:
 *   FBG_RESULT records=R steps=S mismatches=M first_mismatch=I init_status=X stack_bytes=B
 *              state_bytes=N dsp=D model_swap_refused=1
 * and exits with 0 when every record matched and the swap was refused, 1 otherwise, 2 when
 * fbg_init failed (99 = a CPU fault, from startup.c).
 *
 * Each fbg_step runs inside fw_timed_step() between the empty markers fbg_mark_begin/end, the
 * window the QEMU plugin (insn_window_plugin.c) counts instructions in: exactly one fbg_step
 * with everything it calls, nothing of this harness. */
#include <stdint.h>
#include <string.h>

#include "fbgforce.h"
#include "fw_golden.h"
#include "semihost.h"

/* The generated model source defines a ready `const fbg_model` with this name. */
#ifndef FBG_FW_MODEL_SYM
#define FBG_FW_MODEL_SYM fbg_model_default
#endif
extern const fbg_model FBG_FW_MODEL_SYM;

#ifndef FBG_USE_DSP
#define FBG_USE_DSP 0
#endif

/* The caller owns the state: in firmware a static object like this one (sizeof is the RAM). */
static fbg_state state;

__attribute__((noinline)) void fbg_mark_begin(void) { __asm__ volatile("" ::: "memory"); }
__attribute__((noinline)) void fbg_mark_end(void) { __asm__ volatile("" ::: "memory"); }

__attribute__((noinline)) fbg_status fw_timed_step(fbg_state *s, const int32_t *wl, fbg_output *out)
{
    fbg_status st;
    fbg_mark_begin();
    st = fbg_step(s, wl, out);
    fbg_mark_end();
    return st;
}

/* Stack high-water mark: paint the stack below the current frame, run, find the deepest word
 * that changed. The window is far below main's frame and far above .bss. */
#define FW_PAINT_BYTES 16384u
#define FW_PAINT_WORD 0xC5AC5AC5u
extern uint32_t __stack_limit;

static inline uint32_t *current_sp(void)
{
    uint32_t *sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    return sp;
}

__attribute__((noinline, optimize("no-tree-loop-distribute-patterns")))
static uint32_t *paint_stack(void)
{
    /* Up to just below this leaf function's own frame: everything deeper than main's frame
     * plus a few words is painted, so the measured depth is exact to within those words. */
    uint32_t *top = current_sp() - 4;
    uint32_t *low = top - FW_PAINT_BYTES / 4u;
    uint32_t *p;
    if (low < &__stack_limit)
        low = &__stack_limit;
    for (p = low; p < top; ++p)
        *p = FW_PAINT_WORD;
    return low;
}

static uint32_t stack_used_below(const uint32_t *low, const uint32_t *sp_at_call)
{
    const uint32_t *p = low;
    while (p < sp_at_call && *p == FW_PAINT_WORD)
        ++p;
    return (uint32_t)((const char *)sp_at_call - (const char *)p);
}

static void report_mismatch(uint32_t i, const fw_record *r, fbg_status st, int accepted, const fbg_output *o)
{
    sh_puts("FBG_MISMATCH");
    sh_kv("record", (int32_t)i);
    sh_kv("op", r->op);
    sh_kv("status", st);
    sh_kv("want_status", r->status);
    if (r->op == FW_OP_TARE_ADD) {
        sh_kv("accepted", accepted);
        sh_kv("want_accepted", r->accepted);
    }
    if (r->op == FW_OP_STEP) {
        sh_kv("force_mN", o->force_mN);
        sh_kv("want_force_mN", r->out.force_mN);
        sh_kv("x_um", o->x_um);
        sh_kv("want_x_um", r->out.x_um);
        sh_kv("y_um", o->y_um);
        sh_kv("want_y_um", r->out.y_um);
        sh_kv("margin_q8", o->contact_margin_q8);
        sh_kv("want_margin_q8", r->out.contact_margin_q8);
        sh_kv("conf_q15", o->contact_conf_q15);
        sh_kv("want_conf_q15", r->out.contact_conf_q15);
        sh_kv("contact", o->contact);
        sh_kv("want_contact", r->out.contact);
        sh_kv("flags", (int32_t)o->status);
        sh_kv("want_flags", (int32_t)r->out.status);
    }
    sh_puts("\n");
}

/* A model reloaded in place under a running state (an update over the air without fbg_init):
 * fbg_model_from_blob gives the model it fills the new blob's CRC, which a RAM copy of the
 * linked model stands in for here. 1 if fbg_step refuses it with the safe output. */
static fbg_model swap_model;

static int model_swap_refused(void)
{
    fbg_output out;
    swap_model = FBG_FW_MODEL_SYM;
    if (fbg_init(&state, &swap_model, fw_golden_options & FBG_OPT_KERNEL_MASK) != FBG_OK ||
        fbg_step(&state, swap_model.baseline_fm, &out) != FBG_OK)
        return 0;
    swap_model.blob_crc ^= 1u;
    memset(&out, 0xA5, sizeof out);
    return fbg_step(&state, swap_model.baseline_fm, &out) == FBG_ERR_MODEL_CHANGED &&
           out.status == 0u && out.force_mN == 0 && out.contact == 0u;
}

int main(void)
{
    uint32_t i, mismatches = 0, steps = 0, first = 0xFFFFFFFFu, stack = 0;
    int swap_refused;
    fbg_status init_st;
    uint32_t *low = paint_stack();
    uint32_t *sp_main = current_sp();

    init_st = fbg_init(&state, &FBG_FW_MODEL_SYM, fw_golden_options);
    if (init_st != FBG_OK) {
        sh_puts("FBG_RESULT");
        sh_kv("records", (int32_t)fw_golden_count);
        sh_kv("init_status", init_st);
        sh_puts("\n");
        return 2;
    }
    for (i = 0; i < fw_golden_count; ++i) {
        const fw_record *r = &fw_golden[i];
        fbg_output out;
        fbg_status st = FBG_OK;
        int accepted = 0, ok;
        /* Poison the output so that a field the library forgets to write cannot match by luck. */
        memset(&out, 0xA5, sizeof out);
        switch (r->op) {
        case FW_OP_STEP:
            st = fw_timed_step(&state, r->wl_fm, &out);
            ++steps;
            break;
        case FW_OP_TARE_BEGIN: st = fbg_tare_begin(&state); break;
        case FW_OP_TARE_ADD: st = fbg_tare_add(&state, r->wl_fm, &accepted); break;
        case FW_OP_TARE_END: st = fbg_tare_end(&state); break;
        case FW_OP_SET_BASELINE: st = fbg_set_baseline(&state, r->wl_fm); break;
        case FW_OP_RESET: st = fbg_reset(&state); break;
        case FW_OP_INIT: st = fbg_init(&state, &FBG_FW_MODEL_SYM, fw_golden_options); break;
        default: st = (fbg_status)-128; break;
        }
        ok = st == r->status;
        if (r->op == FW_OP_STEP)
            ok = ok && memcmp(&out, &r->out, sizeof out) == 0;
        if (r->op == FW_OP_TARE_ADD)
            ok = ok && accepted == r->accepted;
        if (!ok) {
            if (mismatches < 5u)
                report_mismatch(i, r, st, accepted, &out);
            if (first == 0xFFFFFFFFu)
                first = i;
            ++mismatches;
        }
    }
    stack = stack_used_below(low, sp_main);
    swap_refused = model_swap_refused();

    sh_puts("FBG_RESULT");
    sh_kv("records", (int32_t)fw_golden_count);
    sh_kv("steps", (int32_t)steps);
    sh_kv("mismatches", (int32_t)mismatches);
    sh_kv("first_mismatch", (int32_t)first);
    sh_kv("init_status", init_st);
    sh_kv("stack_bytes", (int32_t)stack);
    sh_kv("state_bytes", (int32_t)sizeof(fbg_state));
    sh_kv("dsp", FBG_USE_DSP);
    sh_kv("model_swap_refused", swap_refused);
    sh_puts("\n");
    return mismatches || !swap_refused ? 1 : 0;
}
