/* insn_window_plugin.c - QEMU TCG plugin: exact executed-instruction counts per measurement window.
 *
 * Built for the HOST (gcc -shared -fPIC), loaded by qemu-system-arm with
 *   -plugin ./insn_window.so,begin=ADDR,end=ADDR[,ex=LO:HI]...[,r=LO:HI]...[,out=FILE]
 *
 * The firmware brackets each measured call with two empty marker functions:
 *   fbg_mark_begin(); fbg_step(...); fbg_mark_end();
 * A window opens when the first instruction of the `begin` marker executes and closes at the
 * first instruction of the `end` marker. Inside a window every executed guest instruction is
 * counted EXCEPT those whose PC lies in an excluded range [LO, HI) - the harness wrapper and the
 * markers themselves - so a window's count is exactly the instructions executed by the measured
 * function and everything it calls (library, model code, libgcc helpers alike). Skipped
 * instructions of an IT block count as executed (they occupy an issue slot on the core too).
 *
 * Optional profile ranges r=LO:HI (e.g. one per function, from nm -S): executed instructions
 * with PC in [LO, HI) over the WHOLE run (windows or not), one "range LO HI COUNT" line each.
 *
 * The worst window (the largest count) is also kept instruction by instruction, for the
 * cycle estimate of fbgforce.target.cycles: every executed instruction outside the excluded
 * ranges gets a callback that counts its executions, the executions after which the next
 * executed instruction was not the one that follows it in memory (a taken branch, exact
 * whatever the instruction), and the executions it was entered by falling through from the
 * instruction before it in memory (so a load after a load is known to pipeline).
 *
 * Output (to FILE, or stderr): "insns_total T", "windows N", "sum S", "min A", "max B", then one
 * line "w COUNT" per window in execution order, then the "range" lines, then one line
 * "pc ADDR EXECUTED TAKEN SEQ_IN" per instruction executed in the worst window.
 *
 * Debian 12 ships QEMU 7.2 without qemu-plugin.h, so the few plugin API v1 declarations used are
 * written out here (they resolve against the qemu binary). QEMU >= 9 renamed the inline API
 * (*_inline_per_vcpu); port this file to the real header there. */
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define QEMU_PLUGIN_EXPORT __attribute__((visibility("default")))
typedef uint64_t qemu_plugin_id_t;
struct qemu_plugin_tb;
struct qemu_plugin_insn;
typedef struct qemu_info_t qemu_info_t; /* opaque here */
enum qemu_plugin_op { QEMU_PLUGIN_INLINE_ADD_U64 };
enum qemu_plugin_cb_flags { QEMU_PLUGIN_CB_NO_REGS, QEMU_PLUGIN_CB_R_REGS, QEMU_PLUGIN_CB_RW_REGS };
typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t, struct qemu_plugin_tb *);
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t, void *);
typedef void (*qemu_plugin_vcpu_udata_cb_t)(unsigned int vcpu_index, void *userdata);
extern void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t, qemu_plugin_vcpu_tb_trans_cb_t);
extern void qemu_plugin_register_vcpu_tb_exec_inline(struct qemu_plugin_tb *, enum qemu_plugin_op,
                                                     void *, uint64_t);
extern void qemu_plugin_register_vcpu_insn_exec_inline(struct qemu_plugin_insn *, enum qemu_plugin_op,
                                                       void *, uint64_t);
extern void qemu_plugin_register_vcpu_insn_exec_cb(struct qemu_plugin_insn *, qemu_plugin_vcpu_udata_cb_t,
                                                   enum qemu_plugin_cb_flags, void *);
extern size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *);
extern struct qemu_plugin_insn *qemu_plugin_tb_get_insn(const struct qemu_plugin_tb *, size_t);
extern uint64_t qemu_plugin_insn_vaddr(const struct qemu_plugin_insn *);
extern size_t qemu_plugin_insn_size(const struct qemu_plugin_insn *);
extern void qemu_plugin_register_atexit_cb(qemu_plugin_id_t, qemu_plugin_udata_cb_t, void *);

QEMU_PLUGIN_EXPORT int qemu_plugin_version = 1;

#define MAX_EXCLUDED 16
static uint64_t ex_lo[MAX_EXCLUDED], ex_hi[MAX_EXCLUDED];
static int n_excluded;
#define MAX_RANGES 128
static uint64_t r_lo[MAX_RANGES], r_hi[MAX_RANGES], r_count[MAX_RANGES];
static int n_ranges;
static uint64_t begin_pc = UINT64_MAX, end_pc = UINT64_MAX;
static const char *outpath;

static uint64_t total;    /* every executed instruction */
static uint64_t counted;  /* executed instructions outside the excluded ranges */
static uint64_t window_start;
static int window_open, nested_begin, stray_end;
static uint64_t *windows;
static size_t n_windows, cap_windows;

/* Per-instruction counts of the current and of the worst window, one slot per distinct PC. */
#define MAX_SLOTS 32768
#define HASH_SIZE 65536 /* power of two, > MAX_SLOTS */
static uint64_t slot_pc[MAX_SLOTS], slot_next[MAX_SLOTS];
static uint64_t cur_exec[MAX_SLOTS], cur_taken[MAX_SLOTS], cur_seq[MAX_SLOTS];
static uint64_t best_exec[MAX_SLOTS], best_taken[MAX_SLOTS], best_seq[MAX_SLOTS];
static uint64_t best_window;
static int32_t hash_slot[HASH_SIZE]; /* slot + 1, 0 = empty */
static int n_slots, prev_slot = -1;

static int slot_of(uint64_t pc, uint64_t size)
{
    uint32_t h = (uint32_t)((pc >> 1) * 2654435761u) & (HASH_SIZE - 1);
    while (hash_slot[h]) {
        if (slot_pc[hash_slot[h] - 1] == pc)
            return hash_slot[h] - 1;
        h = (h + 1) & (HASH_SIZE - 1);
    }
    if (n_slots == MAX_SLOTS) {
        fprintf(stderr, "insn_window: more than %d distinct instructions\n", MAX_SLOTS);
        exit(3);
    }
    slot_pc[n_slots] = pc;
    slot_next[n_slots] = pc + size;
    hash_slot[h] = n_slots + 1;
    return n_slots++;
}

static void on_insn(unsigned int vcpu, void *udata)
{
    int slot = (int)(intptr_t)udata;
    (void)vcpu;
    if (!window_open)
        return;
    if (prev_slot >= 0) {
        if (slot_next[prev_slot] == slot_pc[slot])
            cur_seq[slot]++;
        else
            cur_taken[prev_slot]++;
    }
    cur_exec[slot]++;
    prev_slot = slot;
}

static int excluded(uint64_t pc)
{
    for (int i = 0; i < n_excluded; i++)
        if (pc >= ex_lo[i] && pc < ex_hi[i])
            return 1;
    return 0;
}

static void on_begin(unsigned int vcpu, void *udata)
{
    (void)vcpu; (void)udata;
    if (window_open)
        nested_begin = 1;
    window_open = 1;
    window_start = counted;
    memset(cur_exec, 0, (size_t)n_slots * sizeof cur_exec[0]);
    memset(cur_taken, 0, (size_t)n_slots * sizeof cur_taken[0]);
    memset(cur_seq, 0, (size_t)n_slots * sizeof cur_seq[0]);
    prev_slot = -1;
}

static void on_end(unsigned int vcpu, void *udata)
{
    (void)vcpu; (void)udata;
    if (!window_open) {
        stray_end = 1;
        return;
    }
    window_open = 0;
    if (n_windows == cap_windows) {
        size_t cap = cap_windows ? 2 * cap_windows : 1024;
        uint64_t *p = realloc(windows, cap * sizeof *p);
        if (!p) {
            fprintf(stderr, "insn_window: out of memory\n");
            exit(3);
        }
        windows = p;
        cap_windows = cap;
    }
    windows[n_windows++] = counted - window_start;
    if (counted - window_start > best_window) {
        best_window = counted - window_start;
        memcpy(best_exec, cur_exec, (size_t)n_slots * sizeof cur_exec[0]);
        memcpy(best_taken, cur_taken, (size_t)n_slots * sizeof cur_taken[0]);
        memcpy(best_seq, cur_seq, (size_t)n_slots * sizeof cur_seq[0]);
    }
}

static void tb_trans(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    (void)id;
    size_t n = qemu_plugin_tb_n_insns(tb);
    qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &total, n);
    for (size_t i = 0; i < n; i++) {
        struct qemu_plugin_insn *insn = qemu_plugin_tb_get_insn(tb, i);
        uint64_t pc = qemu_plugin_insn_vaddr(insn);
        /* Markers must lie in an excluded range, so the order of callback and inline add on the
         * marker instruction itself cannot matter. */
        if (pc == begin_pc)
            qemu_plugin_register_vcpu_insn_exec_cb(insn, on_begin, QEMU_PLUGIN_CB_NO_REGS, NULL);
        else if (pc == end_pc)
            qemu_plugin_register_vcpu_insn_exec_cb(insn, on_end, QEMU_PLUGIN_CB_NO_REGS, NULL);
        if (!excluded(pc)) {
            qemu_plugin_register_vcpu_insn_exec_inline(insn, QEMU_PLUGIN_INLINE_ADD_U64, &counted, 1);
            qemu_plugin_register_vcpu_insn_exec_cb(insn, on_insn, QEMU_PLUGIN_CB_NO_REGS,
                                                   (void *)(intptr_t)slot_of(pc, qemu_plugin_insn_size(insn)));
        }
        for (int r = 0; r < n_ranges; r++)
            if (pc >= r_lo[r] && pc < r_hi[r])
                qemu_plugin_register_vcpu_insn_exec_inline(insn, QEMU_PLUGIN_INLINE_ADD_U64, &r_count[r], 1);
    }
}

static void at_exit(qemu_plugin_id_t id, void *p)
{
    (void)id; (void)p;
    FILE *f = outpath ? fopen(outpath, "w") : stderr;
    if (!f) {
        fprintf(stderr, "insn_window: cannot write %s\n", outpath);
        return;
    }
    uint64_t sum = 0, mn = UINT64_MAX, mx = 0;
    for (size_t i = 0; i < n_windows; i++) {
        sum += windows[i];
        if (windows[i] < mn) mn = windows[i];
        if (windows[i] > mx) mx = windows[i];
    }
    if (!n_windows) mn = 0;
    fprintf(f, "insns_total %llu\nwindows %llu\nsum %llu\nmin %llu\nmax %llu\n",
            (unsigned long long)total, (unsigned long long)n_windows, (unsigned long long)sum,
            (unsigned long long)mn, (unsigned long long)mx);
    fprintf(f, "unclosed %d\nnested_begin %d\nstray_end %d\n", window_open, nested_begin, stray_end);
    for (size_t i = 0; i < n_windows; i++)
        fprintf(f, "w %llu\n", (unsigned long long)windows[i]);
    for (int r = 0; r < n_ranges; r++)
        fprintf(f, "range %llu %llu %llu\n", (unsigned long long)r_lo[r], (unsigned long long)r_hi[r],
                (unsigned long long)r_count[r]);
    for (int i = 0; i < n_slots; i++)
        if (best_exec[i])
            fprintf(f, "pc %llu %llu %llu %llu\n", (unsigned long long)slot_pc[i],
                    (unsigned long long)best_exec[i], (unsigned long long)best_taken[i],
                    (unsigned long long)best_seq[i]);
    if (outpath)
        fclose(f);
}

QEMU_PLUGIN_EXPORT int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info, int argc,
                                           char **argv)
{
    (void)info;
    for (int i = 0; i < argc; i++) {
        const char *a = argv[i];
        if (!strncmp(a, "begin=", 6)) {
            begin_pc = strtoull(a + 6, NULL, 0) & ~1ull; /* drop the Thumb bit of a symbol value */
        } else if (!strncmp(a, "end=", 4)) {
            end_pc = strtoull(a + 4, NULL, 0) & ~1ull;
        } else if (!strncmp(a, "ex=", 3)) {
            char *colon = strchr(a + 3, ':');
            if (!colon || n_excluded == MAX_EXCLUDED) {
                fprintf(stderr, "insn_window: bad or too many ex= ranges: %s\n", a);
                return -1;
            }
            ex_lo[n_excluded] = strtoull(a + 3, NULL, 0) & ~1ull;
            ex_hi[n_excluded] = strtoull(colon + 1, NULL, 0);
            n_excluded++;
        } else if (!strncmp(a, "r=", 2)) {
            char *colon = strchr(a + 2, ':');
            if (!colon || n_ranges == MAX_RANGES) {
                fprintf(stderr, "insn_window: bad or too many r= ranges: %s\n", a);
                return -1;
            }
            r_lo[n_ranges] = strtoull(a + 2, NULL, 0) & ~1ull;
            r_hi[n_ranges] = strtoull(colon + 1, NULL, 0);
            n_ranges++;
        } else if (!strncmp(a, "out=", 4)) {
            outpath = strdup(a + 4);
        } else {
            fprintf(stderr, "insn_window: unknown argument %s\n", a);
            return -1;
        }
    }
    if (begin_pc == UINT64_MAX || end_pc == UINT64_MAX) {
        fprintf(stderr, "insn_window: begin= and end= are required\n");
        return -1;
    }
    qemu_plugin_register_vcpu_tb_trans_cb(id, tb_trans);
    qemu_plugin_register_atexit_cb(id, at_exit, NULL);
    return 0;
}
