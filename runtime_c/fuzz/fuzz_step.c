/*
 * fuzz_step.c - libFuzzer target for the streaming API: fbg_step, fbg_run, tare, baseline,
 * reset on the committed fuzz models (the .fbgm files in runtime_c/fuzz/models; docs/robustness.md).
 *
 * Input: byte 0 selects the model (small16, small8, stress, stress_bias), then a stream of
 * ops, one byte each (value % 8):
 *   0-3 step one sample            4 batch of 1..8 samples (fbg_run)
 *   5   tare over 0..7 samples     6 set_baseline to one sample      7 reset
 * A sample is 5 channels x 3 bytes (mode, int16 d), relative to the model's baseline b:
 *   mode%8: 0..4 b + d * {1, 16, 256, 4096, 65536} (saturated to int32; up to +-2.1e9 fm),
 *           5 a sentinel (0, -1, INT32_MIN, INT32_MAX, window edges +-1), 6 stuck (the
 *           channel's previous value), 7 previous value + (d mod 64) (noise-sized steps).
 * Two states run in lockstep: A with fbg_step per sample, B with fbg_run per op; their
 * outputs must be identical bytes. Every output must satisfy hc_check_output, and the
 * SENSOR_FAULT flag must equal an independent evaluation of the fault rule of fbgforce.h
 * (window, jump and stuck-peak rules).
 * Any violation aborts (a finding). Models: FBG_FUZZ_MODELS (env) or the compiled-in dir.
 */
#include "fuzz_common.h"

#ifndef FBG_FUZZ_MODELS_DIR
#define FBG_FUZZ_MODELS_DIR "runtime_c/fuzz/models"
#endif

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);
int LLVMFuzzerInitialize(int *argc, char ***argv);

#define N_MODELS 4
static const char *const model_names[N_MODELS] = {"small16", "small8", "stress", "stress_bias"};
static uint8_t *blobs[N_MODELS];
static fbg_model models[N_MODELS];
static int model_ok[N_MODELS];

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    const char *dir = getenv("FBG_FUZZ_MODELS");
    int i, loaded = 0;
    (void)argc;
    (void)argv;
    if (dir == NULL)
        dir = FBG_FUZZ_MODELS_DIR;
    for (i = 0; i < N_MODELS; ++i) {
        char path[4096];
        size_t len = 0;
        snprintf(path, sizeof path, "%s/%s.fbgm", dir, model_names[i]);
        blobs[i] = hc_read_file(path, &len);
        if (blobs[i] != NULL && fbg_model_from_blob(&models[i], blobs[i], len) == FBG_OK) {
            model_ok[i] = 1;
            ++loaded;
        } else {
            fprintf(stderr, "fuzz_step: cannot load %s\n", path);
        }
    }
    if (loaded == 0) {
        fprintf(stderr, "fuzz_step: no model loaded (set FBG_FUZZ_MODELS or run "
                        "'make -C runtime_c fuzz-corpus')\n");
        abort();
    }
    return 0;
}

typedef struct {
    const uint8_t *p;
    size_t left;
} input;

static unsigned next(input *in)
{
    if (in->left == 0u)
        return 0u;
    in->left--;
    return *in->p++;
}

static int32_t sat_i32(int64_t v)
{
    return v > INT32_MAX ? INT32_MAX : (v < INT32_MIN ? INT32_MIN : (int32_t)v);
}

/* Harness-side copy of the fault rule (fbgforce.h, fbg_step): an independent oracle. */
typedef struct {
    int32_t prev[FBG_N_CHANNELS];
    unsigned valid;
    unsigned run[FBG_N_CHANNELS]; /* repeats of the identical in-window value */
    int32_t last[FBG_N_CHANNELS]; /* last decoded sample, for "stuck" channels */
    int tared;
} tracker;

static int in_window(int32_t v)
{
    return v >= FBG_WL_MIN_FM && v <= FBG_WL_MAX_FM;
}

static int expect_fault(tracker *t, const int32_t wl[FBG_N_CHANNELS], int32_t jump,
                        unsigned stuck_max)
{
    int fault = 0, c;
    for (c = 0; c < FBG_N_CHANNELS; ++c) {
        if (!in_window(wl[c])) {
            fault = 1;
            t->run[c] = 0u;
            continue;
        }
        if ((t->valid >> c) & 1u) {
            int64_t d = (int64_t)wl[c] - t->prev[c];
            if (d > jump || d < -(int64_t)jump)
                fault = 1;
            t->run[c] = d == 0 ? (t->run[c] < 0xFFFFu ? t->run[c] + 1u : t->run[c]) : 0u;
        } else {
            t->run[c] = 0u;
        }
        if (stuck_max != 0u && t->run[c] >= stuck_max)
            fault = 1;
        t->prev[c] = wl[c];
        t->valid |= 1u << c;
    }
    return fault;
}

static void sample(input *in, const fbg_model *m, tracker *t, int32_t wl[FBG_N_CHANNELS])
{
    static const int32_t sentinels[8] = {0, -1, INT32_MIN, INT32_MAX, FBG_WL_MIN_FM - 1,
                                         FBG_WL_MIN_FM, FBG_WL_MAX_FM, FBG_WL_MAX_FM + 1};
    int c;
    for (c = 0; c < FBG_N_CHANNELS; ++c) {
        unsigned mode = next(in) & 7u;
        int16_t d = (int16_t)(uint16_t)(next(in) | (next(in) << 8));
        int64_t b = m->baseline_fm[c];
        switch (mode) {
        case 5: wl[c] = sentinels[(uint16_t)d & 7u]; break;
        case 6: wl[c] = t->last[c]; break;
        case 7: wl[c] = sat_i32((int64_t)t->last[c] + (d % 64)); break;
        default: wl[c] = sat_i32(b + (int64_t)d * ((int64_t)1 << (4u * mode))); break;
        }
        t->last[c] = wl[c];
    }
}

static void fail(const char *why, unsigned op)
{
    fprintf(stderr, "fuzz_step: op %u: %s\n", op, why);
    abort();
}

static void check_pair(const fbg_output *a, const fbg_output *b, const fbg_model *m, tracker *t,
                       int fault, unsigned op)
{
    const char *why;
    if (memcmp(a, b, sizeof *a) != 0)
        fail("fbg_step and fbg_run outputs differ", op);
    if ((why = hc_check_output(a, m, t->tared)) != NULL)
        fail(why, op);
    if (!!(a->status & FBG_STATUS_SENSOR_FAULT) != fault)
        fail("SENSOR_FAULT flag disagrees with the fault rule", op);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    input in;
    const fbg_model *m;
    fbg_state a, b;
    tracker t;
    unsigned op_i = 0, mi;

    if (size < 1u)
        return 0;
    mi = data[0] % N_MODELS;
    if (!model_ok[mi])
        return 0;
    m = &models[mi];
    in.p = data + 1;
    in.left = size - 1u;
    memset(&t, 0, sizeof t);
    memcpy(t.last, m->baseline_fm, sizeof t.last);
    if (fbg_init(&a, m, 0u) != FBG_OK || fbg_init(&b, m, 0u) != FBG_OK)
        fail("fbg_init failed on a loaded model", 0u);

    while (in.left > 0u && op_i < 512u) {
        unsigned op = next(&in) & 7u, k, i;
        int32_t wl[8][FBG_N_CHANNELS];
        fbg_output oa[8], ob[8];
        int faults[8];
        ++op_i;
        if (op <= 4u) {
            k = op == 4u ? 1u + (next(&in) & 7u) : 1u;
            for (i = 0; i < k; ++i) {
                sample(&in, m, &t, wl[i]);
                faults[i] = expect_fault(&t, wl[i], m->jump_max_fm, m->stuck_max);
            }
            for (i = 0; i < k; ++i)
                if (fbg_step(&a, wl[i], &oa[i]) != FBG_OK)
                    fail("fbg_step returned an error", op_i);
            {
                /* Exact-size heap copies for the batch call. */
                int32_t *hw = (int32_t *)hc_exact_copy((const uint8_t *)wl, k * sizeof wl[0]);
                fbg_output *ho = (fbg_output *)malloc(k * sizeof *ho);
                if (hw == NULL || ho == NULL)
                    abort();
                if (fbg_run(&b, hw, k, ho) != FBG_OK)
                    fail("fbg_run returned an error", op_i);
                memcpy(ob, ho, k * sizeof *ho);
                free(hw);
                free(ho);
            }
            for (i = 0; i < k; ++i)
                check_pair(&oa[i], &ob[i], m, &t, faults[i], op_i);
        } else if (op == 5u) {
            int acc_a = 0, acc_b = 0, any = 0, sa, sb;
            k = next(&in) & 7u;
            if (fbg_tare_begin(&a) != FBG_OK || fbg_tare_begin(&b) != FBG_OK)
                fail("tare_begin failed", op_i);
            for (i = 0; i < k; ++i) {
                int ok = 1, c;
                sample(&in, m, &t, wl[0]);
                for (c = 0; c < FBG_N_CHANNELS; ++c)
                    ok &= in_window(wl[0][c]);
                if (fbg_tare_add(&a, wl[0], &acc_a) != FBG_OK || fbg_tare_add(&b, wl[0], &acc_b) != FBG_OK)
                    fail("tare_add failed", op_i);
                if (acc_a != ok || acc_b != ok)
                    fail("tare_add accepted/refused against the window rule", op_i);
                any |= ok;
            }
            sa = fbg_tare_end(&a);
            sb = fbg_tare_end(&b);
            if (sa != sb || (sa == FBG_OK) != any || (sa != FBG_OK && sa != FBG_ERR_TARE))
                fail("tare_end status", op_i);
            if (sa == FBG_OK) {
                t.tared = 1;
                t.valid = 0u; /* tare_end clears the fault tracker */
                memset(t.run, 0, sizeof t.run);
            }
        } else if (op == 6u) {
            int ok = 1, c, sa, sb;
            sample(&in, m, &t, wl[0]);
            for (c = 0; c < FBG_N_CHANNELS; ++c)
                ok &= in_window(wl[0][c]);
            sa = fbg_set_baseline(&a, wl[0]);
            sb = fbg_set_baseline(&b, wl[0]);
            if (sa != sb || sa != (ok ? FBG_OK : FBG_ERR_ARG))
                fail("set_baseline status", op_i);
            if (ok) {
                t.tared = 1;
                t.valid = 0u;
                memset(t.run, 0, sizeof t.run);
            }
        } else {
            if (fbg_reset(&a) != FBG_OK || fbg_reset(&b) != FBG_OK)
                fail("reset failed", op_i);
            t.valid = 0u;
            memset(t.run, 0, sizeof t.run);
        }
        if (memcmp(&a.baseline_fm, &b.baseline_fm, sizeof a.baseline_fm) != 0)
            fail("baselines of the twin states differ", op_i);
    }
    return 0;
}
