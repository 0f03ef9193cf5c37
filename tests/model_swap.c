/* model_swap.c - a model reloaded in place under a running state (an update over the air
 * done without fbg_init) must be refused by fbg_step and fbg_run, on every kernel.
 *
 *     model_swap KERNEL[p] ... -- BLOB ...
 *
 * KERNEL: FBG_OPT_KERNEL_* values (hex); a trailing "p" runs the kernel from packed weights.
 * For every kernel and every ordered pair of blobs (a, b), a state is initialised on a model
 * loaded from a and stepped, then fbg_model_from_blob(&model, b) is called on that very model:
 *
 * - b loaded (a different model, or a itself from another copy): fbg_step and fbg_run return
 *   FBG_ERR_MODEL_CHANGED with the safe output unless b is a's bytes (then the model is the
 *   same and the state must go on exactly as a twin state that saw no reload);
 * - b refused before the model was touched: the state goes on as the twin;
 * - b refused after the model was overwritten (a half-written model): MODEL_CHANGED.
 *
 * Then fbg_init on the reloaded model (when b loaded) steps again. Blobs that do not load are
 * still used as b; each blob is also used as b cut after its parameters with a valid CRC (a
 * failure after the model was cleared). Built with AddressSanitizer + UBSan by
 * tests/test_simd.py, natively and for aarch64 under qemu. Prints one line per kernel:
 * "kernel 0xNN[ packed]: S swaps, R refused, 0 wrong" (S: reloads under a running state,
 * R: those that changed the model); exit 0 iff nothing was wrong. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fbgforce.h"
#include "../runtime_c/src/fbg_contract.h" /* FBG_PARAMS_SIZE: the blob's parameter block */

#define MAX_BLOBS 32
#define STEPS 40

typedef struct {
    uint8_t *bytes; /* malloc'd with exactly len bytes (8-aligned by malloc) */
    size_t len;
} blob_t;

static blob_t blobs[2 * MAX_BLOBS];
static size_t n_blobs;

static blob_t read_blob(const char *path)
{
    blob_t b = {NULL, 0};
    FILE *f = fopen(path, "rb");
    long n;
    if (f == NULL || fseek(f, 0, SEEK_END) != 0 || (n = ftell(f)) <= 0 || fseek(f, 0, SEEK_SET) != 0) {
        if (f != NULL)
            fclose(f);
        return b;
    }
    b.bytes = malloc((size_t)n);
    if (b.bytes != NULL && fread(b.bytes, 1, (size_t)n, f) == (size_t)n)
        b.len = (size_t)n;
    fclose(f);
    return b;
}

/* The blob cut right after its parameter block, its declared length and CRC made to match:
 * fbg_model_from_blob passes the CRC, clears the model, then fails on the layer table. */
static blob_t cut_blob(const blob_t *src)
{
    blob_t b = {NULL, 0};
    const size_t keep = FBG_BLOB_HEADER_SIZE + FBG_PARAMS_SIZE;
    uint32_t total, crc;
    if (src->len < keep)
        return b;
    b.bytes = malloc(keep);
    if (b.bytes == NULL)
        return b;
    memcpy(b.bytes, src->bytes, keep);
    total = (uint32_t)keep;
    memcpy(b.bytes + 8, &total, 4); /* little-endian host: fbg_model_from_blob refuses others */
    crc = fbg_crc32(b.bytes + 16, keep - 16u);
    memcpy(b.bytes + 12, &crc, 4);
    b.len = keep;
    return b;
}

/* Sample k near the model's baseline: a press rising and falling on the strain channels. */
static void sample(const fbg_model *m, unsigned k, int32_t wl[FBG_N_CHANNELS])
{
    unsigned c;
    int32_t load = (int32_t)(k % 40u < 20u ? k % 40u : 40u - k % 40u) * 20000;
    for (c = 0; c < FBG_N_CHANNELS; ++c)
        wl[c] = m->baseline_fm[c] + (c < FBG_N_STRAIN ? load * (int32_t)(c + 1) : 0);
}

static int is_safe(const fbg_output *o)
{
    static const fbg_output zero;
    return memcmp(o, &zero, sizeof zero) == 0;
}

typedef struct {
    fbg_state *st;
    unsigned char *pack_mem;
} runner;

static fbg_status start(runner *r, const fbg_model *m, uint32_t kernel, int packed)
{
    fbg_status got = fbg_init(r->st, m, kernel);
    size_t bytes;
    void *pack;
    if (got != FBG_OK || !packed)
        return got;
    bytes = fbg_pack_bytes(r->st);
    free(r->pack_mem);
    r->pack_mem = bytes != 0u ? malloc(bytes + FBG_PACK_ALIGN) : NULL;
    if (r->pack_mem == NULL)
        return FBG_ERR_ARG;
    pack = r->pack_mem + (FBG_PACK_ALIGN - (uintptr_t)r->pack_mem % FBG_PACK_ALIGN) % FBG_PACK_ALIGN;
    return fbg_pack(r->st, pack, bytes);
}

/* One swap a -> b on kernel; returns the number of wrong results (0 expected). */
static unsigned swap(uint32_t kernel, int packed, const blob_t *a, const blob_t *b, unsigned *swaps,
                     unsigned *refused)
{
    fbg_model model, twin_model, before;
    runner run = {NULL, NULL}, twin = {NULL, NULL};
    fbg_output out, twin_out, outs[3];
    int32_t wl[3 * FBG_N_CHANNELS];
    unsigned k, wrong = 0;
    fbg_status loaded, got;
    int same, touched;

    if (fbg_model_from_blob(&model, a->bytes, a->len) != FBG_OK ||
        fbg_model_from_blob(&twin_model, a->bytes, a->len) != FBG_OK)
        return 0; /* a is not a model: nothing to swap from */
    ++*swaps;
    run.st = malloc(sizeof *run.st);
    twin.st = malloc(sizeof *twin.st);
    if (run.st == NULL || twin.st == NULL || start(&run, &model, kernel, packed) != FBG_OK ||
        start(&twin, &twin_model, kernel, packed) != FBG_OK) {
        wrong = 1;
        goto done;
    }
    for (k = 0; k < STEPS; ++k) {
        sample(&model, k, wl);
        if (fbg_step(run.st, wl, &out) != FBG_OK || fbg_step(twin.st, wl, &twin_out) != FBG_OK)
            wrong++;
    }
    memcpy(&before, &model, sizeof model);
    loaded = fbg_model_from_blob(&model, b->bytes, b->len);
    touched = memcmp(&before, &model, sizeof model) != 0;
    same = loaded == FBG_OK && b->len == a->len && memcmp(a->bytes, b->bytes, a->len) == 0;
    for (k = STEPS; k < STEPS + 4u; ++k) {
        sample(&twin_model, k, wl);
        got = fbg_step(run.st, wl, &out);
        fbg_step(twin.st, wl, &twin_out);
        if (same || !touched) {
            if (got != FBG_OK || memcmp(&out, &twin_out, sizeof out) != 0)
                wrong++;
        } else if (got != FBG_ERR_MODEL_CHANGED || !is_safe(&out)) {
            wrong++;
        }
    }
    *refused += !same && touched;
    if (!same && touched) {
        for (k = 0; k < 3u; ++k)
            sample(&twin_model, k, wl + k * FBG_N_CHANNELS);
        memset(outs, 0xA5, sizeof outs);
        if (fbg_run(run.st, wl, 3u, outs) != FBG_ERR_MODEL_CHANGED || !is_safe(&outs[0]))
            wrong++;
    }
    if (loaded == FBG_OK) { /* fbg_init on the new model: it runs */
        if (start(&run, &model, kernel, packed) != FBG_OK)
            wrong++;
        for (k = 0; k < 8u; ++k) {
            sample(&model, k, wl);
            if (fbg_step(run.st, wl, &out) != FBG_OK)
                wrong++;
        }
    }
done:
    free(run.st);
    free(twin.st);
    free(run.pack_mem);
    free(twin.pack_mem);
    return wrong;
}

int main(int argc, char **argv)
{
    int i, first_blob = argc, failed = 0;
    size_t n_files, x, y;
    for (i = 1; i < argc; ++i)
        if (strcmp(argv[i], "--") == 0)
            first_blob = i + 1;
    for (i = first_blob; i < argc && n_blobs < MAX_BLOBS; ++i) {
        blob_t b = read_blob(argv[i]);
        if (b.bytes == NULL) {
            fprintf(stderr, "cannot read %s\n", argv[i]);
            return 2;
        }
        blobs[n_blobs++] = b;
    }
    n_files = n_blobs;
    for (x = 0; x < n_files; ++x) {
        blob_t cut = cut_blob(&blobs[x]);
        if (cut.bytes != NULL)
            blobs[n_blobs++] = cut;
    }
    for (i = 1; i < argc && strcmp(argv[i], "--") != 0; ++i) {
        int packed = argv[i][strlen(argv[i]) - 1] == 'p';
        uint32_t kernel = (uint32_t)strtoul(argv[i], NULL, 16);
        unsigned swaps = 0, refused = 0, wrong = 0;
        fbg_model m;
        fbg_state probe;
        if (fbg_model_from_blob(&m, blobs[0].bytes, blobs[0].len) != FBG_OK ||
            fbg_init(&probe, &m, kernel) != FBG_OK || (packed && fbg_pack_bytes(&probe) == 0u)) {
            printf("kernel 0x%02lx%s: cannot run here\n", (unsigned long)kernel, packed ? " packed" : "");
            failed = 1;
            continue;
        }
        for (x = 0; x < n_files; ++x)
            for (y = 0; y < n_blobs; ++y) {
                wrong += swap(kernel, packed, &blobs[x], &blobs[y], &swaps, &refused);
            }
        printf("kernel 0x%02lx%s: %u swaps, %u refused, %u wrong\n", (unsigned long)kernel,
               packed ? " packed" : "", swaps, refused, wrong);
        failed |= wrong != 0u;
    }
    for (x = 0; x < n_blobs; ++x)
        free(blobs[x].bytes);
    return failed;
}
