/*
 * fuzz_common.h - helpers shared by the hard-case driver and the libFuzzer targets
 * (docs/robustness.md). Test code only: never linked into libfbgforce.
 *
 * hc_check_output() is the executable form of the output contract of fbgforce.h, the same
 * invariants tests/hardcase_support.py asserts on every sample:
 *   - only the defined FBG_STATUS_* bits;
 *   - contact is 0 or 1, contact_conf_q15 in [0, 32767];
 *   - no int32 output is INT32_MIN (saturation is symmetric, so a wrap would show here);
 *   - SENSOR_FAULT => the safe output (every field 0 but status);
 *   - no contact  => force_mN = x_um = y_um = 0;
 *   - contact and force_mN > model->overload_mN => OVERLOAD (the flag may also come from
 *     the input-side load rule, contact or not; never on a faulty sample);
 *   - NOT_TARED   <=> the state has not been tared;
 *   - contact_conf_q15 == fbg_sigmoid_q15(contact_margin_q8) outside faults.
 */
#ifndef FBG_FUZZ_COMMON_H
#define FBG_FUZZ_COMMON_H

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fbgforce.h"

/* Returns NULL when *o satisfies the contract, else a short description of the violation. */
static inline const char *hc_check_output(const fbg_output *o, const fbg_model *m, int tared)
{
    const int releasing = (o->status & FBG_STATUS_RELEASING) != 0u;
    if (o->status & ~(uint32_t)FBG_STATUS_ALL)
        return "undefined status bit";
    if (o->contact > 1u)
        return "contact not 0/1";
    if (o->contact_conf_q15 > 32767u)
        return "contact_conf_q15 above 32767";
    if (o->force_mN == INT32_MIN || o->x_um == INT32_MIN || o->y_um == INT32_MIN ||
        o->contact_margin_q8 == INT32_MIN)
        return "INT32_MIN output (asymmetric saturation or wrap)";
    if (o->reserved != 0u)
        return "reserved byte not 0";
    if (!!(o->status & FBG_STATUS_NOT_TARED) != !tared)
        return "NOT_TARED flag disagrees with the tare state";
    if (o->status & FBG_STATUS_SENSOR_FAULT) {
        if (o->force_mN || o->x_um || o->y_um || o->contact_margin_q8 || o->contact ||
            o->contact_conf_q15)
            return "SENSOR_FAULT without the safe output";
        if (o->status & FBG_STATUS_OVERLOAD)
            return "OVERLOAD on a faulty sample";
        return NULL;
    }
    /* Force and location where the decision holds: contact, or the release band after it. */
    if (o->contact && releasing)
        return "RELEASING with contact";
    if (!o->contact && !releasing && (o->force_mN || o->x_um || o->y_um))
        return "force/location without contact or RELEASING";
    if ((o->contact || releasing) && o->force_mN > m->overload_mN
        && !(o->status & FBG_STATUS_OVERLOAD))
        return "force_mN > overload_mN without OVERLOAD";
    if ((int32_t)o->contact_conf_q15 != fbg_sigmoid_q15(o->contact_margin_q8))
        return "contact_conf_q15 is not sigmoid(margin)";
    return NULL;
}

/* A heap copy of exactly len bytes (at least 1 allocated), 8-byte aligned as the zero-copy
 * loader requires (malloc's alignment), so AddressSanitizer/valgrind see any read past the
 * end. Returns NULL on allocation failure. */
static inline uint8_t *hc_exact_copy(const uint8_t *data, size_t len)
{
    uint8_t *p = (uint8_t *)malloc(len ? len : 1u);
    if (p != NULL && len)
        memcpy(p, data, len);
    return p;
}

/* Little-endian reads/writes, independent of host byte order. */
static inline uint32_t hc_rd32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static inline void hc_wr32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

/* Read a whole file into a fresh exact-size heap buffer; *len receives its size. */
static inline uint8_t *hc_read_file(const char *path, size_t *len)
{
    FILE *f = fopen(path, "rb");
    uint8_t *buf = NULL;
    long size;
    if (f == NULL)
        return NULL;
    if (fseek(f, 0, SEEK_END) == 0 && (size = ftell(f)) >= 0 && fseek(f, 0, SEEK_SET) == 0) {
        buf = (uint8_t *)malloc((size_t)size ? (size_t)size : 1u);
        if (buf != NULL && fread(buf, 1, (size_t)size, f) != (size_t)size) {
            free(buf);
            buf = NULL;
        }
        *len = (size_t)size;
    }
    fclose(f);
    return buf;
}

#endif /* FBG_FUZZ_COMMON_H */
