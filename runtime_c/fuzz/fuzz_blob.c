/*
 * fuzz_blob.c - libFuzzer target for the model-blob loader (docs/robustness.md).
 *
 * Input: byte 0 = mode, the rest = the blob.
 *   mode bit 0: repair the CRC-32 field before loading, so that mutations of the header,
 *               parameters and layer table get past the CRC gate and reach the field checks;
 *   mode bit 1: load from an address that is 8-byte aligned + 1 (must give FBG_ERR_ALIGN or
 *               an earlier error, never a misaligned read).
 * The blob is copied into an exact-size heap buffer, so any read past its end is an
 * AddressSanitizer report. Properties checked (abort = finding):
 *   - the status is one of the documented codes;
 *   - FBG_OK only if the declared length fits in the buffer and fbg_model_check agrees;
 *   - an accepted model initialises, tares and steps through extreme samples with every
 *     output inside the contract of fbgforce.h (hc_check_output).
 */
#include "fuzz_common.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

static void fail(const char *why, int status)
{
    fprintf(stderr, "fuzz_blob: %s (status %d %s)\n", why, status, fbg_status_str(status));
    abort();
}

static void exercise(const fbg_model *m)
{
    static const int32_t rows[][FBG_N_CHANNELS] = {
        {1550000000, 1550000000, 1550000000, 1550000000, 1550000000},
        {2000000000, 2000000000, 2000000000, 2000000000, 1000000000},
        {2000000000, 2000000000, 2000000000, 2000000000, 1000000000},
        {1000000000, 1000000000, 1000000000, 1000000000, 2000000000},
        {1000000000, 1000000000, 1000000000, 1000000000, 2000000000},
        {INT32_MIN, 0, -1, INT32_MAX, 1550000000},
        {1546000000, 1538000000, 1530000000, 1554000000, 1562000000},
    };
    fbg_state st;
    fbg_output out[sizeof rows / sizeof rows[0]];
    const char *why;
    size_t i, n = sizeof rows / sizeof rows[0];
    int s = fbg_init(&st, m, 0u);
    if (s != FBG_OK)
        fail("accepted model does not initialise", s);
    s = fbg_run(&st, &rows[0][0], n, out);
    if (s != FBG_OK)
        fail("fbg_run failed on an accepted model", s);
    for (i = 0; i < n; ++i)
        if ((why = hc_check_output(&out[i], m, 0)) != NULL)
            fail(why, (int)i);
    s = fbg_tare_begin(&st);
    for (i = 0; s == FBG_OK && i < n; ++i)
        s = fbg_tare_add(&st, rows[i], NULL);
    if (s == FBG_OK)
        s = fbg_tare_end(&st);
    if (s != FBG_OK)
        fail("tare failed", s);
    for (i = 0; i < n; ++i) {
        s = fbg_step(&st, rows[n - 1 - i], &out[i]);
        if (s != FBG_OK)
            fail("fbg_step failed", s);
        if ((why = hc_check_output(&out[i], m, 1)) != NULL)
            fail(why, (int)i);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    uint8_t mode, *buf, *blob;
    size_t len;
    fbg_model model;
    int s;

    if (size < 1u)
        return 0;
    mode = data[0];
    len = size - 1u;
    /* The blob always ends exactly where the allocation ends, so a read past len is caught.
     * Misaligned mode: 7 spare bytes in front of it (malloc's alignment is at least 8, so
     * buf + 7 is not 8-aligned). */
    buf = (uint8_t *)malloc((mode & 2u) ? len + 7u : (len ? len : 1u));
    if (buf == NULL)
        return 0;
    blob = (mode & 2u) ? buf + 7 : buf;
    if (len)
        memcpy(blob, data + 1, len);
    if ((mode & 1u) && len >= FBG_BLOB_HEADER_SIZE) {
        uint32_t total = hc_rd32(blob + 8);
        if (total >= FBG_BLOB_HEADER_SIZE && total <= len)
            hc_wr32(blob + 12, fbg_crc32(blob + FBG_BLOB_HEADER_SIZE, total - FBG_BLOB_HEADER_SIZE));
    }

    s = fbg_model_from_blob(&model, blob, len);
    if (s > 0 || s < FBG_ERR_ARG)
        fail("undocumented status", s);
    if (s == FBG_OK) {
        if (fbg_blob_declared_size(blob, len) > len)
            fail("accepted a blob longer than the buffer", s);
        if ((mode & 2u) && (((uintptr_t)(const void *)blob) & 7u))
            fail("accepted a misaligned blob", s);
        if (fbg_model_check(&model) != FBG_OK)
            fail("loader and fbg_model_check disagree", s);
        exercise(&model);
    }
    free(buf);
    return 0;
}
