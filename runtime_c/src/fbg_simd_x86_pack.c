/*
 * fbg_simd_x86_pack.c - packed weights (fbg_pack) and the SSE2 and AVX2 nets that run from them.
 * How the kernels stay exact: fbg_simd_x86.c.
 */
#include "fbg_simd_x86.h"

#if FBG_HOST_SIMD && defined(__x86_64__)
/* ---- Packed weights (fbg_pack): no row sums to add up across a vector ------------------- */

/* A packed layer: this head, then its output rows in groups of `rows` (8 for AVX2, 4 for
 * SSE2; the rows past n_out are zeros), the groups in passes of up to PACK_PASS (nine
 * groups, then the rest: the kernel's passes over the inputs; nine, so that a layer of 70
 * rows runs in one pass). A pass of K groups holds the K
 * groups' biases as int32 (|bias| <= INT32_MAX in an acc32 layer), then their multipliers,
 * then for each input pair p the K groups' vectors of 2 * rows int16, (w[r][2p], w[r][2p+1])
 * for the group's rows r (the odd last column's partner is 0; int8 weights are widened, the
 * same values). A pair's vector against x[2p], x[2p+1] broadcast to every lane gives, through
 * (V)PMADDWD, each row's share of that pair in the row's own int32 lane: a group's
 * accumulator holds its rows' sums once every pair is added, with no horizontal sums, and
 * the pass reads its vectors in order. Every block is a multiple of 32 bytes long, so with the
 * buffer FBG_PACK_ALIGN-aligned every vector lies aligned. */
#define PACK_PASS 9u
typedef struct {
    int64_t round;      /* 2^(shift - 1) */
    int64_t top;        /* 32768 * 2^shift - 1, INT64_MAX when that overflows (requant8) */
    uint32_t shift;
    uint16_t n_in, n_out, n_groups;
    uint16_t high_word; /* 1: multipliers stored at shift 32 for requant8_high (high_word_requant) */
    uint16_t dot;       /* 1: an output layer in the dot-product form (dot_layer) */
    uint16_t reserved;
} packed_head;

typedef char packed_head_is_32_bytes[sizeof(packed_head) == 32u ? 1 : -1];

/* One field of the head at the start of a block, read where it lies (memcpy: the buffer's
 * declared type is the caller's), so that a kernel loads only the fields it uses. */
static inline unsigned head_u16(const unsigned char *block, size_t off)
{
    uint16_t v;
    memcpy(&v, block + off, sizeof v);
    return v;
}

static inline unsigned head_u32(const unsigned char *block, size_t off)
{
    uint32_t v;
    memcpy(&v, block + off, sizeof v);
    return v;
}

static inline int64_t head_i64(const unsigned char *block, size_t off)
{
    int64_t v;
    memcpy(&v, block + off, sizeof v);
    return v;
}
#define HEAD_U16(block, field) head_u16(block, offsetof(packed_head, field))
#define HEAD_I64(block, field) head_i64(block, offsetof(packed_head, field))
#define HEAD_U32(block, field) head_u32(block, offsetof(packed_head, field))

#define PACK_HEADER_BYTES ((sizeof(fbg_pack_header) + 31u) & ~(size_t)31u)

/* Rows per group of a kernel's packed form; 0: no packed form. */
static unsigned pack_rows(uint32_t kernel)
{
    return kernel == FBG_OPT_KERNEL_AVX2 ? 8u : kernel == FBG_OPT_KERNEL_SSE2 ? 4u : 0u;
}

/* Bytes of one group: biases and multipliers (4 bytes a row each), then 2 int16 a row per pair. */
static size_t packed_group_bytes(unsigned n_in, unsigned rows)
{
    return (size_t)rows * (8u + 4u * ((n_in + 1u) / 2u));
}

/* AVX2 packs an output layer of up to DOT_ROWS rows that reads a hidden layer's output
 * (l >= 1: the activation buffer, FBG_MAX_WIDTH long) in the dot-product form instead of
 * groups: a group of 8 rows would spend a broadcast and a multiply-add of 8 lanes on each
 * input pair for one or two rows. The block: the head, the rows' biases as int32 (32 bytes),
 * then each row's weights as int16, zero from n_in up to DOT_WIDTH(n_in) (whole vectors of
 * 16). The kernel multiplies whole vectors of x, so it reads x up to DOT_WIDTH(n_in) <=
 * FBG_MAX_WIDTH; the activations there past n_in meet those zero weights. */
#define DOT_ROWS 2u
#define DOT_WIDTH(n_in) (((unsigned)(n_in) + 15u) & ~15u)
typedef char dot_reads_inside_act[(FBG_MAX_WIDTH % 16) == 0 ? 1 : -1];

static int dot_layer(const fbg_net *net, unsigned l, unsigned rows)
{
    return rows == 8u && l >= 1u && l + 1u == net->n_layers && net->layers[l].n_out <= DOT_ROWS;
}

/* The nets the packed form holds: those with only acc32 layers. */
static int packed_net(const fbg_net *net)
{
    unsigned l;
    for (l = 0; l < net->n_layers; ++l)
        if (!net->layers[l].acc32)
            return 0;
    return 1;
}

/* Weight w[r][j] of a layer as int16 (int8 weights widened: the same value). */
static int16_t weight16(const fbg_layer *ly, unsigned r, unsigned j)
{
    return ly->w_bits == 16u ? ly->w16[(size_t)r * ly->n_in + j] : (int16_t)ly->w8[(size_t)r * ly->n_in + j];
}

/* Whether row r of hidden layer l (not the last) may be left out of the packed form: the next
 * layer's column r is all zeros, so the row's output adds nothing anywhere, and the row can
 * never clamp, so it never raises the saturation flag either. Its accumulator lies in
 * [lo, hi]: the bias plus the weights against inputs in [-32767, 32767] (a first layer: sat16
 * inputs) or [0, 32767] (ReLU outputs), within int32 by the acc32 proof; the requantised
 * value rshift_round(acc * mult, shift) is monotonic in acc, so its largest value is at lo or
 * hi, and the row clamps (ReLU, then sat16) only if that exceeds 32767. Weight decay leaves
 * such units (all-zero rows and columns) in trained nets. */
static int row_unused(const fbg_net *net, unsigned l, unsigned r)
{
    const fbg_layer *ly = &net->layers[l], *next = &net->layers[l + 1u];
    int64_t pos = 0, neg = 0, lo, hi;
    unsigned i, j;
    for (i = 0; i < next->n_out; ++i)
        if (weight16(next, i, r) != 0)
            return 0;
    for (j = 0; j < ly->n_in; ++j) {
        const int64_t w = weight16(ly, r, j);
        if (w > 0)
            pos += w;
        else
            neg += w;
    }
    if (l == 0u) {
        hi = ly->bias[r] + FBG_SAT16 * (pos - neg);
        lo = ly->bias[r] - FBG_SAT16 * (pos - neg);
    } else {
        hi = ly->bias[r] + FBG_SAT16 * pos;
        lo = ly->bias[r] + FBG_SAT16 * neg;
    }
    return fbg_rshift_round(hi * ly->mult[r], ly->shift) <= FBG_SAT16 &&
           fbg_rshift_round(lo * ly->mult[r], ly->shift) <= FBG_SAT16;
}

/* Which rows and columns of a layer a packed net keeps: row[0 .. n_rows) and col[0 .. n_cols)
 * in order, the rows of row_unused left out, and with them the next layer's columns (the
 * activations of the kept rows are stored back to back). A first layer keeps every column
 * (the net inputs), an output layer every row. */
typedef struct {
    unsigned n_rows, n_cols;
    uint8_t row[FBG_MAX_WIDTH], col[FBG_MAX_WIDTH];
} pack_shape;

typedef char pack_shape_indices_fit[FBG_MAX_WIDTH <= 256 ? 1 : -1];

static unsigned kept_rows(const fbg_net *net, unsigned l, uint8_t *row)
{
    unsigned r, n = 0;
    for (r = 0; r < net->layers[l].n_out; ++r)
        if (l + 1u == net->n_layers || !row_unused(net, l, r))
            row[n++] = (uint8_t)r;
    return n;
}

static void pack_shape_of(const fbg_net *net, unsigned l, pack_shape *sh)
{
    unsigned j;
    sh->n_rows = kept_rows(net, l, sh->row);
    if (l > 0u) {
        sh->n_cols = kept_rows(net, l - 1u, sh->col);
    } else {
        sh->n_cols = net->layers[0].n_in;
        for (j = 0; j < sh->n_cols; ++j)
            sh->col[j] = (uint8_t)j;
    }
}

/* At least one vector, so that the kernel's first multiply-add reads weights of the block
 * (every column of the layer may have gone with the rows before). */
static unsigned dot_width(unsigned n_in)
{
    return n_in == 0u ? 16u : DOT_WIDTH(n_in);
}

static size_t packed_layer_bytes(const pack_shape *sh, unsigned rows, int dot)
{
    if (dot)
        return sizeof(packed_head) + 32u + (size_t)sh->n_rows * dot_width(sh->n_cols) * 2u;
    return sizeof(packed_head) + (size_t)((sh->n_rows + rows - 1u) / rows) * packed_group_bytes(sh->n_cols, rows);
}

size_t fbg_simd_pack_bytes(uint32_t kernel, const fbg_model *m)
{
    const unsigned rows = pack_rows(kernel);
    size_t total = PACK_HEADER_BYTES;
    pack_shape sh;
    unsigned n, l;
    if (rows == 0u)
        return 0u;
    for (n = 0; n < FBG_N_NETS; ++n)
        if (packed_net(&m->nets[n]))
            for (l = 0; l < m->nets[n].n_layers; ++l) {
                pack_shape_of(&m->nets[n], l, &sh);
                total += packed_layer_bytes(&sh, rows, dot_layer(&m->nets[n], l, rows));
            }
    return total;
}

/* Whether AVX2 can requantise the layer at shift 32 (requant8_high): shift <= 32 and every
 * multiplier times 2^(32 - shift) an int32, which the pack then stores. Then
 * acc * mult * 2^(32-shift) + 2^31 is the rounding sum times 2^(32-shift), exact in int64
 * (|acc| <= 2^31 in an acc32 layer), and its floor over 2^32, the high dword, is the
 * quotient floor((acc * mult + 2^(shift-1)) / 2^shift) (docs/fixed-point.md, "Host SIMD
 * kernels"). */
static int high_word_requant(const fbg_layer *ly)
{
    unsigned r;
    if (ly->shift > 32u)
        return 0;
    for (r = 0; r < ly->n_out; ++r) {
        const int64_t m = (int64_t)ly->mult[r] * ((int64_t)1 << (32u - ly->shift));
        if (m > INT32_MAX || m < INT32_MIN)
            return 0;
    }
    return 1;
}

/* The dot-product form's block after the head (dot_layer). */
static void pack_dot(const fbg_layer *ly, const pack_shape *sh, unsigned char *dst)
{
    const unsigned width = dot_width(sh->n_cols);
    unsigned r, j;
    memset(dst, 0, 32u);
    for (r = 0; r < sh->n_rows; ++r) {
        const int32_t bias = (int32_t)ly->bias[sh->row[r]];
        memcpy(dst + 4u * r, &bias, sizeof bias);
    }
    dst += 32u;
    for (r = 0; r < sh->n_rows; ++r)
        for (j = 0; j < width; ++j, dst += 2u) {
            const int16_t w = j < sh->n_cols ? weight16(ly, sh->row[r], sh->col[j]) : 0;
            memcpy(dst, &w, sizeof w);
        }
}

/* One layer's block at dst (its kept rows and columns, sh). Plain stores through memcpy: the
 * buffer's declared type is the caller's. */
static void pack_layer(const fbg_layer *ly, const pack_shape *sh, unsigned rows, int dot, unsigned char *dst)
{
    const unsigned pairs = (sh->n_cols + 1u) / 2u;
    packed_head h;
    unsigned g0, k, g, i, p, c;
    memset(&h, 0, sizeof h);
    h.shift = ly->shift;
    h.round = (int64_t)1 << (ly->shift - 1u);
    h.top = ly->shift < 48u ? ((int64_t)32768 << ly->shift) - 1 : INT64_MAX;
    h.n_in = (uint16_t)sh->n_cols;
    h.n_out = (uint16_t)sh->n_rows;
    h.n_groups = (uint16_t)((sh->n_rows + rows - 1u) / rows);
    /* SSE2 requantises from the multipliers as they are. */
    h.high_word = (uint16_t)(rows == 8u && high_word_requant(ly));
    h.dot = (uint16_t)dot;
    memcpy(dst, &h, sizeof h);
    dst += sizeof h;
    if (dot) {
        pack_dot(ly, sh, dst);
        return;
    }
    for (g0 = 0; g0 < h.n_groups; g0 += k) {
        k = h.n_groups - g0 < PACK_PASS ? h.n_groups - g0 : PACK_PASS;
        for (g = g0; g < g0 + k; ++g)
            for (i = 0; i < rows; ++i) {
                const unsigned r = g * rows + i, src = r < sh->n_rows ? sh->row[r] : 0u;
                const int32_t bias = r < sh->n_rows ? (int32_t)ly->bias[src] : 0;
                const int32_t mult = r >= sh->n_rows ? 0
                                     : h.high_word ? (int32_t)((int64_t)ly->mult[src] * ((int64_t)1 << (32u - h.shift)))
                                                   : ly->mult[src];
                memcpy(dst + 4u * ((g - g0) * rows + i), &bias, sizeof bias);
                memcpy(dst + 4u * ((k + g - g0) * rows + i), &mult, sizeof mult);
            }
        dst += 8u * k * rows;
        for (p = 0; p < pairs; ++p)
            for (g = g0; g < g0 + k; ++g)
                for (i = 0; i < rows; ++i)
                    for (c = 0; c < 2u; ++c) {
                        const unsigned r = g * rows + i, j = 2u * p + c;
                        const int16_t w = r < sh->n_rows && j < sh->n_cols ? weight16(ly, sh->row[r], sh->col[j]) : 0;
                        memcpy(dst, &w, sizeof w);
                        dst += sizeof w;
                    }
    }
}

void fbg_simd_pack(uint32_t kernel, const fbg_model *m, void *buf)
{
    const unsigned rows = pack_rows(kernel);
    unsigned char *base = (unsigned char *)buf;
    fbg_pack_header hd;
    pack_shape sh;
    size_t off = PACK_HEADER_BYTES;
    unsigned n, l;
    memset(&hd, 0, sizeof hd);
    memset(base, 0, PACK_HEADER_BYTES);
    for (n = 0; n < FBG_N_NETS; ++n) {
        if (!packed_net(&m->nets[n]))
            continue;
        hd.net_off[n] = (uint32_t)off;
        for (l = 0; l < m->nets[n].n_layers; ++l) {
            const int dot = dot_layer(&m->nets[n], l, rows);
            pack_shape_of(&m->nets[n], l, &sh);
            pack_layer(&m->nets[n].layers[l], &sh, rows, dot, base + off);
            off += packed_layer_bytes(&sh, rows, dot);
        }
    }
    hd.magic = FBG_PACK_MAGIC;
    hd.kernel = kernel;
    hd.model = m;
    hd.bytes = off;
    memcpy(base, &hd, sizeof hd);
}

/* The passes over the input pairs of a packed layer: K groups (1 <= K <= PACK_PASS) per
 * pass, so each broadcast pair serves K groups (all the groups of a layer of up to 72 rows
 * in one pass), two pairs per loop iteration (four where K <= 2). In a pass at b (VB bytes a vector): the biases
 * at b, the multipliers at b + K VB, the vector of group i for pair p at
 * w + (p K + i) VB with w = b + 2 K VB. PK_LISTK(M, A, B) is M(0, A, B); ...; M(K-1, A, B). */
#define PK_LIST1(M, A, B) M(0, A, B)
#define PK_LIST2(M, A, B) PK_LIST1(M, A, B); M(1, A, B)
#define PK_LIST3(M, A, B) PK_LIST2(M, A, B); M(2, A, B)
#define PK_LIST4(M, A, B) PK_LIST3(M, A, B); M(3, A, B)
#define PK_LIST5(M, A, B) PK_LIST4(M, A, B); M(4, A, B)
#define PK_LIST6(M, A, B) PK_LIST5(M, A, B); M(5, A, B)
#define PK_LIST7(M, A, B) PK_LIST6(M, A, B); M(6, A, B)
#define PK_LIST8(M, A, B) PK_LIST7(M, A, B); M(7, A, B)
#define PK_LIST9(M, A, B) PK_LIST8(M, A, B); M(8, A, B)
/* One pass of K groups: T the vector type, BCAST(p) the broadcast pair p (BCAST##_LAST the
 * odd last column with a zero partner); ACC(i) declares
 * accumulator a##i from its bias, MADD(i, w, xb) adds the products of the vector at w + i VB,
 * OUT(i, K, 0) finishes group i of the K. */
#define PK_PASS(K, T, VB, BCAST, ACC, MADD, OUT)                                             \
    do {                                                                                     \
        const size_t kb = (size_t)(K) * (VB);                                                \
        const unsigned char *w = b + 2u * kb;                                                \
        PK_LIST##K(ACC, 0, 0);                                                               \
        p = 0;                                                                               \
        if ((K) <= 2) /* four broadcasts: wider passes spill accumulators */              \
            for (; p + 4u <= full; p += 4u, w += 4u * kb) {                                  \
                const T xb0 = BCAST(p), xb1 = BCAST(p + 1u), xb2 = BCAST(p + 2u), xb3 = BCAST(p + 3u); \
                PK_LIST##K(MADD, w, xb0);                                                    \
                PK_LIST##K(MADD, w + kb, xb1);                                               \
                PK_LIST##K(MADD, w + 2u * kb, xb2);                                          \
                PK_LIST##K(MADD, w + 3u * kb, xb3);                                          \
            }                                                                                \
        for (; p + 2u <= full; p += 2u, w += 2u * kb) {                                      \
            const T xb0 = BCAST(p), xb1 = BCAST(p + 1u);                                     \
            PK_LIST##K(MADD, w, xb0);                                                        \
            PK_LIST##K(MADD, w + kb, xb1);                                                   \
        }                                                                                    \
        if (p < full) {                                                                      \
            const T xb = BCAST(p);                                                           \
            PK_LIST##K(MADD, w, xb);                                                         \
            w += kb;                                                                         \
        }                                                                                    \
        if (n_in & 1u) { /* the odd last column, paired with 0 */                            \
            const T xlast = BCAST##_LAST;                                                    \
            PK_LIST##K(MADD, w, xlast);                                                      \
            w += kb;                                                                         \
        }                                                                                    \
        PK_LIST##K(OUT, K, 0);                                                               \
        b = w;                                                                               \
        grp += (K);                                                                          \
    } while (0)
/* Every group of a layer: passes of PACK_PASS groups, then one of the rest. */
#define PK_LAYER(T, VB, BCAST, ACC, MADD, OUT)                                               \
    do {                                                                                     \
        while (n_groups - grp >= PACK_PASS)                                                \
            PK_PASS(9, T, VB, BCAST, ACC, MADD, OUT);                                        \
        switch (n_groups - grp) {                                                          \
        case 1: PK_PASS(1, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 2: PK_PASS(2, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 3: PK_PASS(3, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 4: PK_PASS(4, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 5: PK_PASS(5, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 6: PK_PASS(6, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 7: PK_PASS(7, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        case 8: PK_PASS(8, T, VB, BCAST, ACC, MADD, OUT); break;                             \
        default: break;                                                                      \
        }                                                                                    \
    } while (0)
typedef char pack_pass_is_9[PACK_PASS == 9u ? 1 : -1]; /* PK_LAYER's passes */

/* Input pair p (x[2p] in the low half) as one int32; memcpy: x is int16 storage. */
static inline int32_t x_pair(const int16_t *x, unsigned p)
{
    int32_t v;
    memcpy(&v, x + 2u * p, sizeof v);
    return v;
}

/* The common start of a packed kernel: the head's counts and the whole input pairs (a pass
 * broadcasts an odd last column, with a zero partner, only where there is one). */
#define PK_BEGIN                                                                             \
    const unsigned char *b = block + sizeof(packed_head);                                    \
    const unsigned n_in = HEAD_U16(block, n_in), n_groups = HEAD_U16(block, n_groups);       \
    const unsigned full = n_in / 2u;                                                         \
    unsigned grp = 0u, p

/* SSE2: groups of four rows, 16-byte vectors; the sums requantised by the scalar rule. */
#define PK4_BCAST(p) _mm_set1_epi32(x_pair(x, p))
#define PK4_BCAST_LAST _mm_set1_epi32((int32_t)(uint16_t)x[n_in - 1u])
#define PK4_ACC(i, p_, xb_) lanes32x4 a##i = (lanes32x4)load128(b + 16u * (i))
#define PK4_MADD(i, w, xb) a##i += (lanes32x4)_mm_madd_epi16(load128((w) + 16u * (i)), xb)
#define PK4_ACC_OUT(i, p_, xb_) _mm_storeu_si128((__m128i *)(void *)(acc + 4u * (grp + (i))), (__m128i)a##i)
#define PK4_HIDDEN_OUT(i, p_, xb_)                                                           \
    do {                                                                                     \
        int32_t t[4], m[4];                                                                  \
        unsigned q;                                                                          \
        _mm_storeu_si128((__m128i *)(void *)t, (__m128i)a##i);                               \
        memcpy(m, b + kb + 16u * (i), sizeof m);                                             \
        for (q = 0; q < 4u; ++q) {                                                           \
            int64_t v = fbg_rshift_round((int64_t)t[q] * m[q], shift);                       \
            y[4u * (grp + (i)) + q] = fbg_sat16(v < 0 ? 0 : v, sat);                         \
        }                                                                                    \
    } while (0)

/* One hidden layer; returns the next layer's block. */
static inline const unsigned char *hidden_packed_sse2(const unsigned char *block, const int16_t *x,
                                                      int16_t *y, uint32_t *sat)
{
    PK_BEGIN;
    const unsigned shift = HEAD_U32(block, shift);
    PK_LAYER(__m128i, 16u, PK4_BCAST, PK4_ACC, PK4_MADD, PK4_HIDDEN_OUT);
    return b;
}

/* The output layer: its rows' accumulators into acc (n_out rounded up to 4); returns n_out. */
static inline unsigned acc32_packed_sse2(const unsigned char *block, const int16_t *x, int32_t *acc)
{
    PK_BEGIN;
    PK_LAYER(__m128i, 16u, PK4_BCAST, PK4_ACC, PK4_MADD, PK4_ACC_OUT);
    return HEAD_U16(block, n_out);
}

/* Every layer of a packed net (n_layers blocks from block on). */
static unsigned net_packed_sse2(const unsigned char *block, unsigned n_layers, const int16_t *x,
                                int16_t (*act)[FBG_MAX_WIDTH], int32_t *acc, uint32_t *sat)
{
    unsigned l;
    for (l = 0; l + 1u < n_layers; ++l) {
        block = hidden_packed_sse2(block, x, act[l & 1u], sat);
        x = act[l & 1u];
    }
    return acc32_packed_sse2(block, x, acc);
}

/* AVX2: groups of eight rows, 32-byte vectors; eight rows requantised at once (requant8). */
#define PK8_BCAST(p) _mm256_set1_epi32(x_pair(x, p))
#define PK8_BCAST_LAST _mm256_set1_epi32((int32_t)(uint16_t)x[n_in - 1u])
#define PK8_ACC(i, p_, xb_) lanes32 a##i = (lanes32)load256(b + 32u * (i))
#define PK8_MADD(i, w, xb) a##i += (lanes32)_mm256_madd_epi16(load256((w) + 32u * (i)), xb)
#define PK8_ACC_OUT(i, p_, xb_) _mm256_storeu_si256((__m256i *)(void *)(acc + 8u * (grp + (i))), (__m256i)a##i)
#define PK8_HIDDEN_OUT(i, p_, xb_)                                                           \
    _mm_storeu_si128((__m128i *)(void *)(y + 8u * (grp + (i))),                              \
                     requant8((__m256i)a##i, load256(b + kb + 32u * (i)), round, top, shift, &big))

/* requant8 where high_word_requant holds, from multipliers stored at shift 32 (m' = mult *
 * 2^(32-shift)) at mult: t = acc * m' + 2^31 exactly in int64 (VPMULDQ of the even rows, then
 * of the odd ones against the multipliers read 4 bytes on, whose low dwords are the odd
 * rows'), and the quotient is t's high dword (for the even rows shifted down, the odd ones'
 * already in place: one blend puts the eight in row order), returned before ReLU.
 * *peak keeps each lane's largest value (VPMAXSD; it starts at 0, so it stays >= 0): a bit
 * above bit 14 in some lane is a row that clamped (fbg_sat16's flag). */
AVX2 static inline __m256i requant8_high(__m256i acc, const unsigned char *mult, __m256i *peak)
{
    const __m256i round = _mm256_set1_epi64x((int64_t)1 << 31);
    const __m256i t0 = _mm256_add_epi64(_mm256_mul_epi32(acc, load256(mult)), round);
    const __m256i t1 = _mm256_add_epi64(_mm256_mul_epi32(_mm256_srli_epi64(acc, 32), load256(mult + 4)), round);
    const __m256i q = _mm256_blend_epi32(_mm256_srli_epi64(t0, 32), t1, 0xAA);
    *peak = _mm256_max_epi32(*peak, q);
    return q;
}

/* requant8_high's int32 quotients of group i into rq[i]; then, at each odd i, groups i-1 and
 * i narrowed to int16 together (VPACKSSDW of the two interleaves them by 64 bits and
 * saturates at 32767, the clamp; VPMAXSW with 0 is the ReLU, which commutes with that
 * narrowing: a negative value stays negative; VPERMQ puts the rows back in order) and stored
 * as one vector of 16 rows, and the pass's last group alone when K is odd. The multipliers
 * of the pass's last group are followed by its first weights: the read 4 bytes on stays
 * inside the block. */
#define PK8_HIGH_OUT(i, K, xb_)                                                              \
    do {                                                                                     \
        rq[i] = requant8_high((__m256i)a##i, b + kb + 32u * (i), &big);                      \
        if ((i) & 1u)                                                                        \
            _mm256_storeu_si256((__m256i *)(void *)(y + 8u * (grp + (i) - 1u)),              \
                                _mm256_permute4x64_epi64(_mm256_max_epi16(_mm256_packs_epi32(rq[(i) - ((i) & 1u)], rq[i]), \
                                                                          _mm256_setzero_si256()), 0xD8)); \
        else if ((i) + 1u == (K))                                                            \
            _mm_storeu_si128((__m128i *)(void *)(y + 8u * (grp + (i))),                      \
                             _mm_max_epi16(_mm_packs_epi32(_mm256_castsi256_si128(rq[i]), _mm256_extracti128_si256(rq[i], 1)), \
                                           _mm_setzero_si128()));                            \
    } while (0)

/* One hidden layer; big collects the rows that clamped (a bit above bit 14 in a lane, which
 * stays >= 0: requant8 sets all but the sign bit of a clamped lane, requant8_high keeps the
 * lane's largest value there); returns the next layer's block. */
AVX2 __attribute__((always_inline)) static inline const unsigned char *hidden_packed_avx2(const unsigned char *block, const int16_t *x,
                                                           int16_t *y, __m256i *bigp)
{
    PK_BEGIN;
    __m256i big = *bigp;
    if (HEAD_U16(block, high_word)) {
        __m256i rq[PACK_PASS];
        PK_LAYER(__m256i, 32u, PK8_BCAST, PK8_ACC, PK8_MADD, PK8_HIGH_OUT);
    } else {
        const __m256i round = _mm256_set1_epi64x(HEAD_I64(block, round));
        const __m256i top = _mm256_set1_epi64x(HEAD_I64(block, top));
        const __m128i shift = _mm_cvtsi32_si128((int)HEAD_U32(block, shift));
        PK_LAYER(__m256i, 32u, PK8_BCAST, PK8_ACC, PK8_MADD, PK8_HIDDEN_OUT);
    }
    *bigp = big;
    return b;
}

/* The output layer in groups: its rows' accumulators into acc (n_out rounded up to 8). */
AVX2 __attribute__((always_inline)) static inline void acc32_packed_avx2(const unsigned char *block, const int16_t *x, int32_t *acc)
{
    PK_BEGIN;
    PK_LAYER(__m256i, 32u, PK8_BCAST, PK8_ACC, PK8_MADD, PK8_ACC_OUT);
}

/* The output layer in the dot-product form (dot_layer): each row's whole vectors of 16
 * weights against x's, one multiply-add and one add a vector, the lanes added up at the end
 * (any order: the int32 proof), the bias added, sign-extended into acc. */
AVX2 __attribute__((always_inline)) static inline void acc_dot_avx2(const unsigned char *block, const int16_t *x, int64_t *acc)
{
    const unsigned char *w = block + sizeof(packed_head) + 32u;
    const unsigned width = dot_width(HEAD_U16(block, n_in));
    unsigned j;
    int32_t bias;
    lanes32 a0, a1;
    __m128i s;
    a0 = (lanes32)_mm256_madd_epi16(load256(w), load256(x));
    if (HEAD_U16(block, n_out) == 1u) {
        for (j = 16u; j < width; j += 16u)
            MADD(a0, load256(w + 2u * j), load256(x + j));
        s = sum1_row((__m256i)a0);
        memcpy(&bias, block + sizeof(packed_head), sizeof bias);
        acc[0] = (int32_t)((uint32_t)_mm_cvtsi128_si32(s) + (uint32_t)bias);
        return;
    }
    a1 = (lanes32)_mm256_madd_epi16(load256(w + 2u * width), load256(x));
    for (j = 16u; j < width; j += 16u) {
        const __m256i xv = load256(x + j);
        MADD(a0, load256(w + 2u * j), xv);
        MADD(a1, load256(w + 2u * (width + j)), xv);
    }
    s = sum2_rows((__m256i)a0, (__m256i)a1);
    s = _mm_add_epi32(s, _mm_loadl_epi64((const __m128i *)(const void *)(block + sizeof(packed_head))));
    _mm_storeu_si128((__m128i *)(void *)acc, _mm_cvtepi32_epi64(s));
}

AVX2 static void net_packed_avx2(const unsigned char *block, unsigned n_layers, const int16_t *x,
                                 int16_t (*act)[FBG_MAX_WIDTH], int64_t *acc, uint32_t *sat)
{
    /* Every bit but the low 15 of a lane: a clamped row. */
    const __m256i clamped = _mm256_set1_epi32(~0x7FFF);
    __m256i big = _mm256_setzero_si256();
    int32_t acc32[FBG_MAX_WIDTH];
    unsigned l, r, n_out;
    for (l = 0; l + 1u < n_layers; ++l) {
        block = hidden_packed_avx2(block, x, act[l & 1u], &big);
        x = act[l & 1u];
    }
    /* Rows past n_out have multiplier 0: they requantise to 0 and never clamp. */
    if (!_mm256_testz_si256(big, clamped))
        *sat = 1u;
    if (HEAD_U16(block, dot)) {
        acc_dot_avx2(block, x, acc);
        return;
    }
    acc32_packed_avx2(block, x, acc32);
    n_out = HEAD_U16(block, n_out);
    for (r = 0; r < n_out; ++r)
        acc[r] = acc32[r];
}

/* SSE2's packed net and the copy of its int32 accumulators: kept out of line, so that the
 * AVX2 path through fbg_simd_net_packed needs no frame (a call every net of every step). */
__attribute__((noinline)) static void net_packed_sse2_acc64(const unsigned char *block, unsigned n_layers,
                                                            const int16_t *x, int16_t (*act)[FBG_MAX_WIDTH],
                                                            int64_t *acc, uint32_t *sat)
{
    int32_t acc32[FBG_MAX_WIDTH];
    unsigned r, n_out = net_packed_sse2(block, n_layers, x, act, acc32, sat);
    for (r = 0; r < n_out; ++r)
        acc[r] = acc32[r];
}

int fbg_simd_net_packed(uint32_t kernel, const void *packed, unsigned n, unsigned n_layers,
                        const int16_t *x, int16_t (*act)[FBG_MAX_WIDTH], int64_t *acc, uint32_t *sat)
{
    uint32_t off;
    /* memcpy: the caller's buffer may have any declared type. */
    memcpy(&off, (const unsigned char *)packed + offsetof(fbg_pack_header, net_off) + n * sizeof off,
           sizeof off);
    if (off == 0u)
        return 0;
    if (kernel == FBG_OPT_KERNEL_AVX2)
        net_packed_avx2((const unsigned char *)packed + off, n_layers, x, act, acc, sat);
    else
        net_packed_sse2_acc64((const unsigned char *)packed + off, n_layers, x, act, acc, sat);
    return 1;
}

#else
/* ISO C forbids an empty translation unit: other targets compile this file to nothing. */
typedef int fbg_simd_x86_pack_unused;
#endif
