/*
 * fbg_simd_x86_stages.c - the AVX2 variants of fbg_step's front, filter and memory stages.
 * How the kernels stay exact: fbg_simd_x86.c.
 */
#include "fbg_simd_x86.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
/* ---- AVX2 filter: the four channels in one vector of int64 --------------------------- */

/* Each tap: the four int32 history values sign-extended to int64 (VPMOVSXDQ), times the tap
 * (VPMULDQ multiplies the low dwords as signed: int32 by int16, exact in int64), added in
 * int64; the ring read as its two runs, newest first, so no index wraps. Within a run, four
 * taps at a time are widened to int32 in one vector whose two halves both hold them, so that
 * VPSHUFD puts tap j in the low dword of every 64-bit lane (all VPMULDQ reads); the run's
 * last len mod 4 taps one by one. The sum is the portable loop's sum of the same integers,
 * in another order, which fbg_model_check bounds within int64 whatever the order (every
 * partial sum is a sum of a subset of the terms). */
#define FIR_TAP(j) _mm256_mul_epi32(_mm256_cvtepi32_epi64(load128(hist[idx - (j)])), _mm256_shuffle_epi32(t4, (j) * 0x55))
AVX2 static inline __m256i fir_run(__m256i acc, const int16_t *taps, const int32_t (*hist)[FBG_N_STRAIN],
                                   size_t idx, unsigned len)
{
    unsigned k; /* idx a size_t: the four reads of a block take one address and offsets */
    for (k = 0; k + 4u <= len; k += 4u, idx -= 4u) {
        const __m256i t4 = _mm256_broadcastsi128_si256(
            _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)(taps + k))));
        acc = _mm256_add_epi64(acc, _mm256_add_epi64(_mm256_add_epi64(FIR_TAP(0), FIR_TAP(1)),
                                                     _mm256_add_epi64(FIR_TAP(2), FIR_TAP(3))));
    }
    for (; k < len; ++k, --idx)
        acc = _mm256_add_epi64(acc, _mm256_mul_epi32(_mm256_cvtepi32_epi64(load128(hist[idx])),
                                                     _mm256_set1_epi32(taps[k])));
    return acc;
}

/* The first run: taps 0 .. pos against hist[pos] down to hist[0]; the second: taps pos+1 ..
 * n_taps-1 against hist[n_taps-1] down to hist[pos+1]. idx - 3 stays >= 0 within a run's
 * blocks of four (idx counts down to the run's last entry). */
AVX2 static inline __m256i fir4_avx2(const int16_t *taps, unsigned n_taps, const int32_t (*hist)[FBG_N_STRAIN],
                                     unsigned pos)
{
    const __m256i acc = fir_run(_mm256_setzero_si256(), taps, hist, pos, pos + 1u);
    return fir_run(acc, taps + pos + 1u, hist, n_taps - 1u, n_taps - 1u - pos);
}

/* floor(v / 2^s) of int64 lanes (AVX2 has no 64-bit arithmetic shift): with m = -1 in the
 * negative lanes, v ^ m is -v - 1 >= 0 there, whose logical shift is floor((-v - 1) / 2^s),
 * and ^ m again gives -floor((-v - 1) / 2^s) - 1 = floor(v / 2^s). */
AVX2 static inline __m256i sra64(__m256i v, __m128i s)
{
    const __m256i m = _mm256_cmpgt_epi64(_mm256_setzero_si256(), v);
    return _mm256_xor_si256(_mm256_srl_epi64(_mm256_xor_si256(v, m), s), m);
}

/* clamp(v, -lim, lim) of int64 lanes, *flag gathering the lanes that clamped (fbg_sat32's or
 * fbg_sat16's flag). */
AVX2 static inline __m256i clamp64(__m256i v, int64_t lim, __m256i *flag)
{
    const __m256i hi = _mm256_set1_epi64x(lim), lo = _mm256_set1_epi64x(-lim);
    const __m256i over = _mm256_cmpgt_epi64(v, hi), under = _mm256_cmpgt_epi64(lo, v);
    *flag = _mm256_or_si256(*flag, _mm256_or_si256(over, under));
    return _mm256_blendv_epi8(_mm256_blendv_epi8(v, hi, over), lo, under);
}

/* Steps 2 and 3 of fbg_step in lanes of int64, one channel each, the same operations as its
 * loop: filt = sat32(rshift_round(fir, tap_q)), d = sat32(filt - mean), in =
 * sat16(rshift_round(d * z_mult, z_shift)) (VPMULDQ: filt and d are int32 after their clamps,
 * the low dwords it reads; the products are exact in int64), and the load proxy's terms
 * filt * load_coeff added up. The rounding sums stay inside int64 as in the scalar code
 * (|fir| < 2^52, |d * z_mult| < 2^62, 2^(z_shift-1) <= 2^61). */
AVX2 static int filter4_avx2(const fbg_model *m, const int32_t (*hist)[FBG_N_STRAIN], unsigned pos,
                             int16_t *in, int32_t *held, int64_t *load)
{
    __m256i flag = _mm256_setzero_si256(), t;
    __m128i l, z;
    const __m256i fir = fir4_avx2(m->taps, m->n_taps, hist, pos);
    const __m256i filt = clamp64(sra64(_mm256_add_epi64(fir, _mm256_set1_epi64x((int64_t)1 << (m->tap_q - 1u))),
                                       _mm_cvtsi32_si128(m->tap_q)), FBG_SAT32, &flag);
    const __m256i d = clamp64(_mm256_sub_epi64(filt, _mm256_cvtepi32_epi64(load128(m->mean_fm))), FBG_SAT32, &flag);
    _mm_storeu_si128((__m128i *)(void *)held, _mm256_castsi256_si128(
        _mm256_permutevar8x32_epi32(filt, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6))));
    t = _mm256_add_epi64(_mm256_mul_epi32(d, _mm256_cvtepi32_epi64(load128(m->z_mult))),
                         _mm256_set1_epi64x((int64_t)1 << (m->z_shift - 1u)));
    t = clamp64(sra64(t, _mm_cvtsi32_si128(m->z_shift)), FBG_SAT16, &flag);
    /* The four values' low dwords (each an int16 value) into the low half, narrowed. */
    t = _mm256_permutevar8x32_epi32(t, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6));
    z = _mm256_castsi256_si128(t);
    _mm_storel_epi64((__m128i *)(void *)in, _mm_packs_epi32(z, z));
    t = _mm256_mul_epi32(filt, _mm256_cvtepi32_epi64(load128(m->load_coeff)));
    l = _mm_add_epi64(_mm256_castsi256_si128(t), _mm256_extracti128_si256(t, 1));
    l = _mm_add_epi64(l, _mm_unpackhi_epi64(l, l));
    *load = _mm_cvtsi128_si64(l);
    return !_mm256_testz_si256(flag, flag);
}

/* The location averages of memory_features (fbg_stage_memory.c) from z = in[0..3] as int32 lanes,
 * the same operations lane by lane: r = sat16(z - z0) (VPMINSD/VPMAXSD; a lane that moved
 * clamped), target = r * 2^15, the state primed at the target on the first sample, state +=
 * rshift_round(target - state, shift) with the arithmetic shift VPSRAD (the scalar loop's
 * bounds keep every lane's sum in int32), loc = rshift_round(state, 15), which lies within
 * int16, so VPACKSSDW narrows it unchanged. Returns 1 where a lane clamped. The constants
 * are loaded from memory (one instruction each, where building them takes three). */
static const int32_t loc_consts[3][4] = {{FBG_SAT16, FBG_SAT16, FBG_SAT16, FBG_SAT16},
                                          {-FBG_SAT16, -FBG_SAT16, -FBG_SAT16, -FBG_SAT16},
                                          {1 << (FBG_EMA_FRAC - 1), 1 << (FBG_EMA_FRAC - 1),
                                           1 << (FBG_EMA_FRAC - 1), 1 << (FBG_EMA_FRAC - 1)}};
AVX2 static int loc4_avx2(fbg_state *s, unsigned shift, __m128i z, int16_t *loc)
{
    const __m128i d = _mm_sub_epi32(z, _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)s->loc_z0)));
    const __m128i r = _mm_max_epi32(_mm_min_epi32(d, load128(loc_consts[0])), load128(loc_consts[1]));
    const __m128i target = _mm_slli_epi32(r, FBG_EMA_FRAC);
    __m128i e = s->mem_primed ? load128(s->loc) : target;
    e = _mm_add_epi32(e, _mm_sra_epi32(_mm_add_epi32(_mm_sub_epi32(target, e), _mm_set1_epi32((int32_t)1 << (shift - 1u))),
                                       _mm_cvtsi32_si128((int)shift)));
    _mm_storeu_si128((__m128i *)(void *)s->loc, e);
    e = _mm_srai_epi32(_mm_add_epi32(e, load128(loc_consts[2])), FBG_EMA_FRAC);
    _mm_storel_epi64((__m128i *)(void *)loc, _mm_packs_epi32(e, e));
    return !_mm_testc_si128(_mm_cmpeq_epi32(d, r), _mm_cmpeq_epi32(d, d));
}

/* Step 1's fault rule (fbg_fault_check of fbg_internal.h) for the five channels in lanes 0-4
 * of int32 (lanes 5-7 hold 0 and are masked off by lanes5; load5 and store5 touch only the
 * five), the same tests lane
 * by lane: a lane out of the window [FBG_WL_MIN_FM, FBG_WL_MAX_FM] is faulty and its run
 * restarts, prev and its valid bit unchanged; an in-window lane whose prev holds a sample is
 * faulty past jump_max_fm either way (the difference is exact in int32: both in the window)
 * and counts a repeat of the identical value (saturating at 0xFFFF, VPMINUD), faulty at
 * stuck_max repeats when that is not 0; an in-window lane becomes prev, valid. Returns 1 for
 * a faulty sample; *w = the sample's lanes (lanes 5-7: 0, never stored). */
static const int32_t lanes5[8] = {-1, -1, -1, -1, -1, 0, 0, 0};
/* Five int32 into lanes 0-4 (the rest 0), and lanes 0-4 back: plain loads and stores, not
 * VPMASKMOVD (its store is microcoded and slow on AMD cores). */
AVX2 static inline __m256i load5(const int32_t *p)
{
    return _mm256_inserti128_si256(_mm256_castsi128_si256(load128(p)), _mm_cvtsi32_si128(p[4]), 1);
}

AVX2 static inline void store5(int32_t *p, __m256i v)
{
    _mm_storeu_si128((__m128i *)(void *)p, _mm256_castsi256_si128(v));
    p[4] = _mm_cvtsi128_si32(_mm256_extracti128_si256(v, 1));
}

static const int32_t lane_bits[8] = {1, 2, 4, 8, 16, 32, 64, 128};
AVX2 static int fault5_avx2(fbg_state *s, const int32_t *wl, __m256i *w)
{
    const fbg_model *m = s->model;
    const __m256i zero = _mm256_setzero_si256(), m5 = load256(lanes5), bits = load256(lane_bits);
    const __m256i jmax = _mm256_set1_epi32(m->jump_max_fm);
    const unsigned valid = s->prev_valid;
    uint16_t run16[8] = {0};
    __m256i out, in_window, active, d, jump, n, faulty;
    __m128i packed;
    const __m256i prev = load5(s->prev_fm);
    *w = load5(wl);
    out = _mm256_and_si256(m5, _mm256_or_si256(_mm256_cmpgt_epi32(_mm256_set1_epi32(FBG_WL_MIN_FM), *w),
                                                _mm256_cmpgt_epi32(*w, _mm256_set1_epi32(FBG_WL_MAX_FM))));
    in_window = _mm256_andnot_si256(out, m5);
    active = _mm256_and_si256(in_window, _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32((int)valid), bits), bits));
    d = _mm256_sub_epi32(*w, prev);
    jump = _mm256_or_si256(_mm256_cmpgt_epi32(d, jmax), _mm256_cmpgt_epi32(_mm256_sub_epi32(zero, jmax), d));
    memcpy(run16, s->same_run, sizeof s->same_run);
    n = _mm256_add_epi32(_mm256_cvtepu16_epi32(load128(run16)), _mm256_srli_epi32(m5, 31));
    n = _mm256_and_si256(_mm256_and_si256(active, _mm256_cmpeq_epi32(d, zero)),
                         _mm256_min_epu32(n, _mm256_set1_epi32(0xFFFF)));
    faulty = _mm256_or_si256(out, _mm256_and_si256(jump, active));
    if (m->stuck_max != 0u)
        faulty = _mm256_or_si256(faulty, _mm256_cmpgt_epi32(n, _mm256_set1_epi32((int)m->stuck_max - 1)));
    packed = _mm_packus_epi32(_mm256_castsi256_si128(n), _mm256_extracti128_si256(n, 1));
    _mm_storeu_si128((__m128i *)(void *)run16, packed);
    memcpy(s->same_run, run16, sizeof s->same_run);
    store5(s->prev_fm, _mm256_blendv_epi8(prev, *w, in_window));
    if (valid != 0x1Fu) { /* until every channel has had an in-window sample */
        int32_t lanes[8];
        unsigned c, v = valid;
        _mm256_storeu_si256((__m256i *)(void *)lanes, in_window);
        for (c = 0; c < FBG_N_CHANNELS; ++c)
            if (lanes[c])
                v |= 1u << c;
        s->prev_valid = (uint8_t)v;
    }
    return !_mm256_testz_si256(faulty, faulty);
}

/* Step 1's temperature compensation of fbg_step in lanes of int64, one channel each, the
 * same operations as its loop: comp = sat32(shift_c - rshift_round(ref * coeff_c, 24))
 * (VPMULDQ of ref, the reference's average that fbg_ref_update gave for this sample,
 * broadcast, by the sign-extended coefficients: exact in int64, |.| < 2^30 * 2^31), stored
 * where the loop's values go: the ring at pos. Returns 1 where a lane clamped. */
AVX2 static int comp4_avx2(fbg_state *s, __m256i shift, int32_t ref)
{
    __m256i flag = _mm256_setzero_si256();
    const __m256i p = _mm256_mul_epi32(_mm256_set1_epi32(ref),
                                       _mm256_cvtepi32_epi64(load128(s->model->temp_coeff_q24)));
    const __m256i t = sra64(_mm256_add_epi64(p, _mm256_set1_epi64x((int64_t)1 << (FBG_TEMP_COEFF_SHIFT - 1))),
                            _mm_cvtsi32_si128(FBG_TEMP_COEFF_SHIFT));
    const __m256i c = clamp64(_mm256_sub_epi64(_mm256_cvtepi32_epi64(_mm256_castsi256_si128(shift)), t), FBG_SAT32, &flag);
    const __m128i comp = _mm256_castsi256_si128(_mm256_permutevar8x32_epi32(c, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6)));
    _mm_storeu_si128((__m128i *)(void *)s->hist[s->pos], comp);
    return !_mm256_testz_si256(flag, flag);
}

/* The memory kinds' update rules of fbg_stage_memory.c (<kind>_features, FBG_MEMORY_KINDS), the
 * states of a kind in the lanes of one vector, the same operations: the scalar loop's bounds
 * hold in every lane. The states of lanes k >= n stay as they are (blended back); the features
 * go to f[0 ..] as a whole vector of four, the entries past the kind's last being overwritten
 * by the next kind's or ones no net reads. Each returns the number of features of its kind
 * and sets *clamped where an in-use feature clamped. */
static const int32_t lane_index4[4] = {0, 1, 2, 3};

/* All ones in the lanes k < n. */
AVX2 static __m128i lanes_in_use(unsigned n)
{
    return _mm_cmpgt_epi32(_mm_set1_epi32((int)n), load128(lane_index4));
}

/* sat16 of the features f into out[0..3]; 1 where a lane in use clamped. */
AVX2 static int store_features4(__m128i f, __m128i used, int16_t *out)
{
    const __m128i lim = load128(loc_consts[0]), nlim = load128(loc_consts[1]);
    const __m128i flag = _mm_and_si128(used, _mm_or_si128(_mm_cmpgt_epi32(f, lim), _mm_cmpgt_epi32(nlim, f)));
    f = _mm_max_epi32(_mm_min_epi32(f, lim), nlim);
    _mm_storel_epi64((__m128i *)(void *)out, _mm_packs_epi32(f, f));
    return !_mm_testz_si128(flag, flag);
}

/* The exponential averages: e += (target - e + 2^(shift-1)) >> shift (VPSRAVD: each lane its
 * own shift), feature = sat16((u - rshift_round(e, 15)) << gain) (VPSLLVD). */
AVX2 static unsigned ema_features_avx2(fbg_state *s, __m128i u, int primed, int16_t *f, int *clamped)
{
    const fbg_model *m = s->model;
    const __m128i used = lanes_in_use(m->n_ema), target = _mm_slli_epi32(u, FBG_EMA_FRAC);
    __m128i e = primed ? load128(s->ema) : target, shift, fe;
    int32_t word;
    memcpy(&word, m->ema_shift, sizeof word);
    shift = _mm_cvtepu8_epi32(_mm_cvtsi32_si128(word));
    e = _mm_add_epi32(e, _mm_srav_epi32(_mm_add_epi32(_mm_sub_epi32(target, e),
                                                      _mm_srli_epi32(_mm_sllv_epi32(_mm_set1_epi32(1), shift), 1)),
                                       shift));
    _mm_storeu_si128((__m128i *)(void *)s->ema, _mm_blendv_epi8(load128(s->ema), e, used));
    memcpy(&word, m->ema_gain, sizeof word);
    fe = _mm_sllv_epi32(_mm_sub_epi32(u, _mm_srai_epi32(_mm_add_epi32(e, load128(loc_consts[2])), FBG_EMA_FRAC)),
                        _mm_cvtepu8_epi32(_mm_cvtsi32_si128(word)));
    *clamped |= store_features4(fe, used, f);
    return m->n_ema;
}

/* The play operators: p = clamp(p, u - width, u + width), feature = sat16((u - p) << gain). */
AVX2 static unsigned play_features_avx2(fbg_state *s, __m128i u, int primed, int16_t *f, int *clamped)
{
    const fbg_model *m = s->model;
    const __m128i used = lanes_in_use(m->n_play);
    const __m128i width = _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)m->play_width));
    __m128i p = primed ? load128(s->play) : _mm_add_epi32(u, width);
    int32_t word;
    p = _mm_min_epi32(_mm_max_epi32(p, _mm_sub_epi32(u, width)), _mm_add_epi32(u, width));
    _mm_storeu_si128((__m128i *)(void *)s->play, _mm_blendv_epi8(load128(s->play), p, used));
    memcpy(&word, m->play_gain, sizeof word);
    *clamped |= store_features4(_mm_sllv_epi32(_mm_sub_epi32(u, p), _mm_cvtepu8_epi32(_mm_cvtsi32_si128(word))),
                                used, f);
    return m->n_play;
}

/* Every kind's states fill the four lanes of one vector, and its four features stored from
 * its offset (at most FBG_N_STRAIN plus the earlier kinds' limits) stay inside in[]. */
#define FBG_KIND_LANES(kind, KIND) typedef char kind##_lanes_avx2[FBG_MAX_##KIND == 4 ? 1 : -1];
FBG_MEMORY_KINDS(FBG_KIND_LANES)
#undef FBG_KIND_LANES
#define FBG_KIND_LIMIT(kind, KIND) + FBG_MAX_##KIND
typedef char memory4_stores_inside_in[FBG_N_STRAIN FBG_MEMORY_KINDS(FBG_KIND_LIMIT) <= FBG_MAX_INPUTS ? 1 : -1];
#undef FBG_KIND_LIMIT

/* The load signal's memory features of memory_features (fbg_stage_memory.c) from z (int32 lanes):
 * u = sat16(rshift_round(sum_c z_c * mem_mult_c, mem_shift)) (VPMULDQ: exact int64 products,
 * their sum < 2^48, then the scalar rule), then every kind's states, primed on the first
 * sample, and features to in[4 ..] in the order of FBG_MEMORY_KINDS. Returns 1 where a clamp
 * happened. */
AVX2 static int memory4_avx2(fbg_state *s, __m128i z, int16_t *in)
{
    const fbg_model *m = s->model;
    const __m256i prod = _mm256_mul_epi32(_mm256_cvtepi32_epi64(z), _mm256_cvtepi32_epi64(load128(m->mem_mult)));
    __m128i l = _mm_add_epi64(_mm256_castsi256_si128(prod), _mm256_extracti128_si256(prod, 1));
    const int primed = s->mem_primed;
    uint32_t sat = 0u;
    int clamped;
    int16_t *f = in + FBG_N_STRAIN;
    __m128i u;
    l = _mm_add_epi64(l, _mm_unpackhi_epi64(l, l));
    u = _mm_set1_epi32(fbg_sat16_rshift_round(_mm_cvtsi128_si64(l), m->mem_shift, &sat));
    clamped = sat != 0u;
#define FBG_KIND_FEATURES(kind, KIND) f += kind##_features_avx2(s, u, primed, f, &clamped);
    FBG_MEMORY_KINDS(FBG_KIND_FEATURES)
#undef FBG_KIND_FEATURES
    return clamped;
}

/* The stages of fbg_step in AVX2 (fbg_simd.h). The front: the fault rule; for a clean sample
 * the tare difference (within +-1e9 for in-window values: fbg_front_sample) and the
 * compensation into the ring; for a faulty one last_comp (the last filtered shifts, which
 * filter4_avx2 keeps) into the ring. */
AVX2 void fbg_avx2_front(fbg_state *s, const int32_t *wl_fm, uint32_t *status, uint32_t *sat)
{
    __m256i w, shift;
    int32_t ref;
    if (fault5_avx2(s, wl_fm, &w)) {
        *status |= FBG_STATUS_SENSOR_FAULT;
        _mm_storeu_si128((__m128i *)(void *)s->hist[s->pos], load128(s->last_comp));
        return;
    }
    shift = _mm256_sub_epi32(w, load5(s->baseline_fm));
    /* The reference's average is one scalar recursion: it runs before the vector part. */
    ref = fbg_ref_update(&s->ref_acc, &s->ref_count, _mm256_extract_epi32(shift, FBG_N_STRAIN),
                         s->model->ref_shift);
    if (comp4_avx2(s, shift, ref))
        *sat = 1u;
}

AVX2 int fbg_avx2_filter(fbg_state *s, int16_t *in, uint32_t *sat)
{
    const fbg_model *m = s->model;
    int64_t load;
    if (filter4_avx2(m, (const int32_t(*)[FBG_N_STRAIN])s->hist, s->pos, in, s->last_comp, &load))
        *sat = 1u;
    return fbg_rshift_round(load, m->load_shift) > m->load_max_mN;
}

/* The memory features from z = in[0..3] (int16 values, widened to int32 lanes): the location
 * averages, then the load signal's, and the flags of the clamps in each and of
 * memory_features' loc_z0_clamped. */
AVX2 void fbg_avx2_memory(fbg_state *s, int16_t *in, int16_t *loc, uint32_t *sat)
{
    const fbg_model *m = s->model;
    const __m128i z = _mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(const void *)in));
    int clamped = 0;
    if (m->loc_shift)
        clamped |= loc4_avx2(s, m->loc_shift, z, loc) | s->loc_z0_clamped;
    if (FBG_N_MEMORY_FEATURES(m) != 0u)
        clamped |= memory4_avx2(s, z, in);
    s->mem_primed = 1u;
    if (clamped)
        *sat = 1u;
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_stages_unused;
#endif
