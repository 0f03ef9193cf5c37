/*
 * fbg_blob.c - zero-copy loader of model.fbgm blobs (layout: docs/model-format.md).
 *
 * Scalars are decoded byte by byte (little-endian), arrays are used in place, so the blob
 * must be 8-byte aligned and the host little-endian. Every read is bounds-checked against
 * the declared length, which is itself checked against the caller's len first.
 */
#include <string.h>

#include "fbg_contract.h"
#include "fbg_internal.h"

uint32_t fbg_crc32(const uint8_t *data, size_t len)
{
    /* Bitwise (table-free) CRC-32: 8 shifts per byte is fast enough for a load-time check
     * and keeps 1 KB of table out of flash. */
    uint32_t crc = 0xFFFFFFFFu;
    size_t i;
    unsigned b;
    if (data == NULL)
        return 0u;
    for (i = 0; i < len; ++i) {
        crc ^= data[i];
        for (b = 0; b < 8u; ++b)
            crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    return crc ^ 0xFFFFFFFFu;
}

static uint16_t rd16(const uint8_t *p)
{
    return (uint16_t)(p[0] | (p[1] << 8));
}

static uint32_t rd32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

size_t fbg_blob_declared_size(const uint8_t *blob, size_t len)
{
    if (blob == NULL || len < FBG_BLOB_HEADER_SIZE)
        return 0u;
    return (size_t)rd32(blob + 8);
}

static size_t align8(size_t x)
{
    return (x + 7u) & ~(size_t)7u;
}

static int host_is_little_endian(void)
{
    const uint16_t one = 1u;
    uint8_t first;
    memcpy(&first, &one, 1);
    return first == 1u;
}

/* Claim the array of nbytes at *off: it and its zero padding up to the next multiple of 8
 * must lie inside the declared length (SIZE), and the padding must be zero (RANGE). */
static fbg_status take(const uint8_t *blob, size_t total, size_t *off, size_t nbytes,
                       const void **where)
{
    size_t end, k;
    if (*off + nbytes > total)
        return FBG_ERR_SIZE;
    end = align8(*off + nbytes);
    if (end > total)
        return FBG_ERR_SIZE;
    for (k = *off + nbytes; k < end; ++k)
        if (blob[k] != 0u)
            return FBG_ERR_RANGE;
    *where = blob + *off;
    *off = end;
    return FBG_OK;
}

/* The check order below is the contract: export/blob.py follows it step for step, so both
 * readers give every blob the same verdict and code (tests/test_blob_verdict.py). */
/* The blob's header: size, magic, version, CRC, byte order and alignment; *total = the size
 * the header gives. */
static fbg_status header_check(const uint8_t *blob, size_t len, size_t *total)
{
    if (len < FBG_BLOB_HEADER_SIZE)
        return FBG_ERR_TRUNCATED;
    if (memcmp(blob, "FBGM", 4) != 0)
        return FBG_ERR_BAD_MAGIC;
    if (rd16(blob + 4) != FBG_BLOB_VERSION || rd16(blob + 6) != 0u)
        return FBG_ERR_VERSION;
    *total = (size_t)rd32(blob + 8);
    if (*total > len)
        return FBG_ERR_TRUNCATED;
    if (*total < FBG_PARAMS_END)
        return FBG_ERR_SIZE;
    if (fbg_crc32(blob + FBG_BLOB_HEADER_SIZE, *total - FBG_BLOB_HEADER_SIZE) != rd32(blob + 12))
        return FBG_ERR_CRC;
    if (!host_is_little_endian())
        return FBG_ERR_ENDIAN;
    if (((uintptr_t)(const void *)blob & 7u) != 0u)
        return FBG_ERR_ALIGN;
    return FBG_OK;
}

/* The layer table after the parameters: every layer's shape and kind; *off = its end. */
static fbg_status layer_table(fbg_model *model, const uint8_t *blob, size_t total, size_t *off)
{
    unsigned n, l;
    *off = FBG_PARAMS_END;
    for (n = 0; n < FBG_N_NETS; ++n) {
        for (l = 0; l < model->nets[n].n_layers; ++l) {
            fbg_layer *ly = &model->nets[n].layers[l];
            const size_t at = *off;
            if (at + FBG_LAYER_ENTRY > total)
                return FBG_ERR_SIZE;
            ly->n_in = rd16(blob + at);
            ly->n_out = rd16(blob + at + 2);
            ly->w_bits = blob[at + 4];
            ly->shift = blob[at + 5];
            ly->acc32 = blob[at + 6];
            if (blob[at + 7] != 0u || ly->acc32 > 1u)
                return FBG_ERR_RANGE;
            *off = at + FBG_LAYER_ENTRY;
            if (ly->n_in < 1u || ly->n_in > FBG_MAX_WIDTH || ly->n_out < 1u || ly->n_out > FBG_MAX_WIDTH)
                return FBG_ERR_SHAPE;
            if (ly->w_bits != 8u && ly->w_bits != 16u)
                return FBG_ERR_RANGE;
        }
    }
    return FBG_OK;
}

/* The arrays after the table, each at an 8-aligned offset from *off on; sizes are bounded
 * (<= 128*128*2 bytes each), so these sums cannot overflow size_t before they are compared
 * with total. */
static fbg_status arrays(fbg_model *model, const uint8_t *blob, size_t total, size_t *off)
{
    unsigned n, l;
    fbg_status st;
    const void *where;
    if ((st = take(blob, total, off, 0u, &where)) != FBG_OK)   /* the table's padding */
        return st;
    if ((st = take(blob, total, off, (size_t)model->n_taps * 2u, &where)) != FBG_OK)
        return st;
    model->taps = (const int16_t *)where;
    for (n = 0; n < FBG_N_NETS; ++n) {
        for (l = 0; l < model->nets[n].n_layers; ++l) {
            fbg_layer *ly = &model->nets[n].layers[l];
            size_t nw = (size_t)ly->n_in * ly->n_out * (ly->w_bits / 8u);
            if ((st = take(blob, total, off, nw, &where)) != FBG_OK)
                return st;
            if (ly->w_bits == 16u)
                ly->w16 = (const int16_t *)where;
            else
                ly->w8 = (const int8_t *)where;
            if ((st = take(blob, total, off, (size_t)ly->n_out * 8u, &where)) != FBG_OK)
                return st;
            ly->bias = (const int64_t *)where;
            if ((st = take(blob, total, off, (size_t)ly->n_out * 4u, &where)) != FBG_OK)
                return st;
            ly->mult = (const int32_t *)where;
        }
    }
    return FBG_OK;
}

fbg_status fbg_model_from_blob(fbg_model *model, const uint8_t *blob, size_t len)
{
    size_t total = 0u, off = 0u;
    fbg_status st;

    if (model == NULL || blob == NULL)
        return FBG_ERR_NULL;
    st = header_check(blob, len, &total);
    if (st != FBG_OK)
        return st;

    memset(model, 0, sizeof *model);
    /* First, so that a state whose model this call overwrites, even if it then fails, sees
     * another model (fbg_step: FBG_ERR_MODEL_CHANGED). */
    model->blob_crc = rd32(blob + 12);
    fbg_params_decode(model, blob + FBG_BLOB_HEADER_SIZE);
    if (!fbg_params_padding_ok(blob + FBG_BLOB_HEADER_SIZE))
        return FBG_ERR_RANGE;
    st = fbg_params_check(model);
    if (st == FBG_OK)
        st = layer_table(model, blob, total, &off);
    if (st == FBG_OK)
        st = arrays(model, blob, total, &off);
    if (st != FBG_OK)
        return st;
    if (off != total)
        return FBG_ERR_SIZE;
    return fbg_model_check(model);
}
