/*
 * fbg_blob.c - zero-copy loader of model.fbgm blobs (layout: docs/model-format.md).
 *
 * Scalars are decoded byte by byte (little-endian), arrays are used in place, so the blob
 * must be 8-byte aligned and the host little-endian. Every read is bounds-checked against
 * the declared length, which is itself checked against the caller's len first.
 */
#include <string.h>

#include "fbg_internal.h"

#define FBG_PARAMS_END 144u   /* end of the fixed parameter block */
#define FBG_LAYER_ENTRY 8u    /* bytes per layer-table entry */

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

static int32_t rdi32(const uint8_t *p)
{
    uint32_t u = rd32(p);
    /* Two's-complement reinterpretation without implementation-defined conversion. */
    return (u & 0x80000000u) ? -(int32_t)(~u) - 1 : (int32_t)u;
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

fbg_status fbg_model_from_blob(fbg_model *model, const uint8_t *blob, size_t len)
{
    size_t total, off;
    unsigned n, l, c;
    const uint8_t *p;

    if (model == NULL || blob == NULL)
        return FBG_ERR_NULL;
    if (len < FBG_BLOB_HEADER_SIZE)
        return FBG_ERR_TRUNCATED;
    if (memcmp(blob, "FBGM", 4) != 0)
        return FBG_ERR_BAD_MAGIC;
    if (rd16(blob + 4) != FBG_BLOB_VERSION)
        return FBG_ERR_VERSION;
    total = (size_t)rd32(blob + 8);
    if (total > len)
        return FBG_ERR_TRUNCATED;
    if (total < FBG_PARAMS_END)
        return FBG_ERR_SIZE;
    if (fbg_crc32(blob + FBG_BLOB_HEADER_SIZE, total - FBG_BLOB_HEADER_SIZE) != rd32(blob + 12))
        return FBG_ERR_CRC;
    if (!host_is_little_endian())
        return FBG_ERR_ENDIAN;
    if (((uintptr_t)(const void *)blob & 7u) != 0u)
        return FBG_ERR_ALIGN;

    memset(model, 0, sizeof *model);
    p = blob + FBG_BLOB_HEADER_SIZE;
    for (c = 0; c < FBG_N_CHANNELS; ++c, p += 4)
        model->baseline_fm[c] = rdi32(p);
    model->jump_max_fm = rdi32(p);
    p += 4;
    for (c = 0; c < FBG_N_STRAIN; ++c, p += 4)
        model->temp_coeff_q24[c] = rdi32(p);
    for (c = 0; c < FBG_N_STRAIN; ++c, p += 4)
        model->mean_fm[c] = rdi32(p);
    for (c = 0; c < FBG_N_STRAIN; ++c, p += 4)
        model->z_mult[c] = rdi32(p);
    model->fq_mult = rdi32(p);
    model->force_offset_mN = rdi32(p + 4);
    model->xy_offset_um[0] = rdi32(p + 8);
    model->xy_offset_um[1] = rdi32(p + 12);
    model->overload_mN = rdi32(p + 16);
    p += 20;
    for (c = 0; c < FBG_N_STRAIN; ++c, p += 4)
        model->load_coeff[c] = rdi32(p);
    model->load_max_mN = rdi32(p);
    p += 4;
    model->n_taps = rd16(p);
    model->tap_q = p[2];
    model->z_frac = p[3];
    model->z_shift = p[4];
    model->fq_shift = p[5];
    model->load_shift = p[6];
    model->stuck_max = rd16(p + 10);
    for (n = 0; n < FBG_N_NETS; ++n) {
        model->nets[n].n_layers = p[7 + n];
        if (model->nets[n].n_layers < 1u || model->nets[n].n_layers > FBG_MAX_LAYERS)
            return FBG_ERR_SHAPE;
    }
    if (model->n_taps < 1u || model->n_taps > FBG_MAX_TAPS)
        return FBG_ERR_SHAPE;

    /* Layer table. */
    off = FBG_PARAMS_END;
    for (n = 0; n < FBG_N_NETS; ++n) {
        for (l = 0; l < model->nets[n].n_layers; ++l) {
            fbg_layer *ly = &model->nets[n].layers[l];
            if (off + FBG_LAYER_ENTRY > total)
                return FBG_ERR_SIZE;
            ly->n_in = rd16(blob + off);
            ly->n_out = rd16(blob + off + 2);
            ly->w_bits = blob[off + 4];
            ly->shift = blob[off + 5];
            ly->acc32 = blob[off + 6];   /* 0 or 1, checked by fbg_model_check */
            if (blob[off + 7] != 0u)
                return FBG_ERR_RANGE;
            off += FBG_LAYER_ENTRY;
            if (ly->n_in < 1u || ly->n_in > FBG_MAX_WIDTH || ly->n_out < 1u || ly->n_out > FBG_MAX_WIDTH)
                return FBG_ERR_SHAPE;
            if (ly->w_bits != 8u && ly->w_bits != 16u)
                return FBG_ERR_RANGE;
        }
    }

    /* Arrays, each at an 8-aligned offset; sizes are bounded (<= 128*128*2 bytes each), so
     * these sums cannot overflow size_t before they are compared with total. */
    off = align8(off);
    if (off + (size_t)model->n_taps * 2u > total)
        return FBG_ERR_SIZE;
    model->taps = (const int16_t *)(const void *)(blob + off);
    off = align8(off + (size_t)model->n_taps * 2u);
    for (n = 0; n < FBG_N_NETS; ++n) {
        for (l = 0; l < model->nets[n].n_layers; ++l) {
            fbg_layer *ly = &model->nets[n].layers[l];
            size_t nw = (size_t)ly->n_in * ly->n_out * (ly->w_bits / 8u);
            if (off + nw > total)
                return FBG_ERR_SIZE;
            if (ly->w_bits == 16u)
                ly->w16 = (const int16_t *)(const void *)(blob + off);
            else
                ly->w8 = (const int8_t *)(const void *)(blob + off);
            off = align8(off + nw);
            if (off + (size_t)ly->n_out * 8u > total)
                return FBG_ERR_SIZE;
            ly->bias = (const int64_t *)(const void *)(blob + off);
            off = align8(off + (size_t)ly->n_out * 8u);
            if (off + (size_t)ly->n_out * 4u > total)
                return FBG_ERR_SIZE;
            ly->mult = (const int32_t *)(const void *)(blob + off);
            off = align8(off + (size_t)ly->n_out * 4u);
        }
    }
    if (off != total)
        return FBG_ERR_SIZE;
    return fbg_model_check(model);
}
