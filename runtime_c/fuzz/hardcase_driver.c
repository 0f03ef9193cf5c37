/*
 * hardcase_driver.c - runs the hard-case suite's operation streams through libfbgforce as a
 * plain C program, so the suite can run under AddressSanitizer + UndefinedBehaviorSanitizer
 * and valgrind memcheck (runtime_c/hardening.mk; docs/robustness.md). tests/test_hardcases_*.py
 * writes the streams and compares this program's output with the cffi module and with the
 * numpy integer reference, bit for bit.
 *
 *   hardcase_driver run MODEL.fbgm OPS.bin OUT.bin
 *   hardcase_driver blob FILE...          one line per file: "<status code> <status name>"
 *
 * OPS.bin is a sequence of little-endian int32 records:
 *   1 INIT  options                    fbg_init (the state starts "not tared")
 *   2 TARE  n  wl[n][5]                tare_begin, n x tare_add, tare_end
 *   3 BASE  wl[5]                      fbg_set_baseline
 *   4 STEP  n  wl[n][5]                n x fbg_step
 *   5 RUN   n  wl[n][5]                one fbg_run over exact-size heap buffers
 *   6 RESET                            fbg_reset
 * OUT.bin receives, per op, int32 records:
 *   INIT/BASE/RESET: op, status        TARE: op, status, accepted, baseline[5]
 *   STEP/RUN: op, status, n, then per sample force_mN, x_um, y_um, contact_margin_q8,
 *             status flags, contact_conf_q15, contact
 * Every output is checked against the contract (fuzz_common.h); a violation prints the op
 * and sample index and exits 3. Malformed OPS exit 2.
 */
#include "fuzz_common.h"

#define OUT_FIELDS 7

static FILE *g_out;

static void put(int32_t v)
{
    uint8_t b[4];
    hc_wr32(b, (uint32_t)v);
    if (fwrite(b, 1, 4, g_out) != 4) {
        fprintf(stderr, "hardcase_driver: write failed\n");
        exit(2);
    }
}

static void put_output(const fbg_output *o)
{
    put(o->force_mN);
    put(o->x_um);
    put(o->y_um);
    put(o->contact_margin_q8);
    put((int32_t)o->status);
    put((int32_t)o->contact_conf_q15);
    put((int32_t)o->contact);
}

typedef struct {
    const uint8_t *p;
    size_t left;
} reader;

static int32_t take(reader *r)
{
    int32_t v;
    if (r->left < 4u) {
        fprintf(stderr, "hardcase_driver: OPS file truncated\n");
        exit(2);
    }
    v = (int32_t)hc_rd32(r->p);
    r->p += 4;
    r->left -= 4u;
    return v;
}

/* n samples as an exact-size heap array (so a read past the n-th row is caught). */
static int32_t *take_samples(reader *r, int32_t n)
{
    size_t i, count;
    int32_t *wl;
    if (n < 0 || (size_t)n > r->left / (4u * FBG_N_CHANNELS)) {
        fprintf(stderr, "hardcase_driver: bad sample count %ld\n", (long)n);
        exit(2);
    }
    count = (size_t)n * FBG_N_CHANNELS;
    wl = (int32_t *)malloc(count ? count * sizeof *wl : 1u);
    if (wl == NULL)
        exit(2);
    for (i = 0; i < count; ++i)
        wl[i] = take(r);
    return wl;
}

static void check(const fbg_output *o, const fbg_model *m, int tared, size_t op, size_t i)
{
    const char *why = hc_check_output(o, m, tared);
    if (why != NULL) {
        fprintf(stderr, "hardcase_driver: contract violated at op %zu sample %zu: %s "
                "(status 0x%x force %ld x %ld y %ld)\n", op, i, why, (unsigned)o->status,
                (long)o->force_mN, (long)o->x_um, (long)o->y_um);
        exit(3);
    }
}

static int run_ops(const char *model_path, const char *ops_path, const char *out_path)
{
    size_t blob_len = 0, ops_len = 0, op_index = 0, i;
    uint8_t *blob = hc_read_file(model_path, &blob_len);
    uint8_t *ops = hc_read_file(ops_path, &ops_len);
    fbg_model model;
    fbg_state st;
    fbg_status s;
    reader r;
    int tared = 0, inited = 0;

    if (blob == NULL || ops == NULL) {
        fprintf(stderr, "hardcase_driver: cannot read %s\n", blob == NULL ? model_path : ops_path);
        return 2;
    }
    s = fbg_model_from_blob(&model, blob, blob_len);
    if (s != FBG_OK) {
        fprintf(stderr, "hardcase_driver: %s: %s\n", model_path, fbg_status_str(s));
        return 2;
    }
    g_out = fopen(out_path, "wb");
    if (g_out == NULL)
        return 2;
    r.p = ops;
    r.left = ops_len;
    while (r.left > 0u) {
        int32_t op = take(&r);
        put(op);
        if (op != 1 && !inited) {
            fprintf(stderr, "hardcase_driver: op %ld before INIT\n", (long)op);
            return 2;
        }
        switch (op) {
        case 1:
            s = fbg_init(&st, &model, (uint32_t)take(&r));
            put(s);
            inited = s == FBG_OK;
            tared = 0;
            break;
        case 2: {
            int32_t n = take(&r), accepted = 0, base[FBG_N_CHANNELS];
            int32_t *wl = take_samples(&r, n);
            s = fbg_tare_begin(&st);
            for (i = 0; s == FBG_OK && i < (size_t)n; ++i) {
                int acc = 0;
                s = fbg_tare_add(&st, wl + i * FBG_N_CHANNELS, &acc);
                accepted += acc;
            }
            if (s == FBG_OK)
                s = fbg_tare_end(&st);
            if (s == FBG_OK)
                tared = 1;
            fbg_get_baseline(&st, base);
            put(s);
            put(accepted);
            for (i = 0; i < FBG_N_CHANNELS; ++i)
                put(base[i]);
            free(wl);
            break;
        }
        case 3: {
            int32_t *b = take_samples(&r, 1);
            s = fbg_set_baseline(&st, b);
            if (s == FBG_OK)
                tared = 1;
            put(s);
            free(b);
            break;
        }
        case 4:
        case 5: {
            int32_t n = take(&r);
            int32_t *wl = take_samples(&r, n);
            fbg_output *out = (fbg_output *)malloc(n ? (size_t)n * sizeof *out : 1u);
            if (out == NULL)
                return 2;
            if (op == 4) {
                s = FBG_OK;
                for (i = 0; i < (size_t)n; ++i) {
                    fbg_status si = fbg_step(&st, wl + i * FBG_N_CHANNELS, &out[i]);
                    if (s == FBG_OK)
                        s = si;
                }
            } else {
                s = fbg_run(&st, wl, (size_t)n, out);
            }
            put(s);
            put(n);
            for (i = 0; i < (size_t)n; ++i) {
                if (s == FBG_OK)
                    check(&out[i], &model, tared, op_index, i);
                put_output(&out[i]);
            }
            free(out);
            free(wl);
            break;
        }
        case 6:
            put(fbg_reset(&st));
            break;
        default:
            fprintf(stderr, "hardcase_driver: unknown op %ld\n", (long)op);
            return 2;
        }
        ++op_index;
    }
    if (fclose(g_out) != 0)
        return 2;
    free(ops);
    free(blob);
    return 0;
}

/* Load each file as a model blob from an exact-size heap copy; print the status. */
static int check_blobs(int argc, char **argv)
{
    int i;
    for (i = 0; i < argc; ++i) {
        size_t len = 0;
        uint8_t *blob = hc_read_file(argv[i], &len);
        fbg_model model;
        fbg_state st;
        fbg_status s;
        if (blob == NULL) {
            fprintf(stderr, "hardcase_driver: cannot read %s\n", argv[i]);
            return 2;
        }
        s = fbg_model_from_blob(&model, blob, len);
        if (s == FBG_OK) {
            /* An accepted model must also initialise and step without trouble. */
            static const int32_t wl[FBG_N_CHANNELS] = {1550000000, 1550000000, 1550000000,
                                                        1550000000, 1550000000};
            fbg_output out;
            s = fbg_init(&st, &model, 0u);
            if (s == FBG_OK)
                s = fbg_step(&st, wl, &out);
        }
        printf("%d %s\n", (int)s, fbg_status_str(s));
        free(blob);
    }
    return 0;
}

int main(int argc, char **argv)
{
    if (argc == 5 && strcmp(argv[1], "run") == 0)
        return run_ops(argv[2], argv[3], argv[4]);
    if (argc >= 2 && strcmp(argv[1], "blob") == 0)
        return check_blobs(argc - 2, argv + 2);
    fprintf(stderr, "usage: hardcase_driver run MODEL.fbgm OPS.bin OUT.bin\n"
                    "       hardcase_driver blob FILE...\n");
    return 2;
}
