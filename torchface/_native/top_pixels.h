/* The k highest scores of each row, in the order of a stable descending sort (torch.sort(descending=True,
 * stable=True)[:, :k]): score descending, equal scores by index ascending. What a template keeps of its candidate
 * pixels (torchface.template.points._top_pixels); torch.topk's order of equal scores is unspecified, and the
 * pixel selection keys of a 640x480 image hold equal pairs.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order): score (B, N) finite; out_index (B, k) int64, out_value (B, k); 1 <= k <= N.
 */

typedef struct {
    REAL v;
    int64_t i;
} FN(tf_scored);

/* a comes before b */
static inline int FN(tf_before)(const FN(tf_scored) *a, const FN(tf_scored) *b) {
    return a->v > b->v || (a->v == b->v && a->i < b->i);
}

/* v's radix key: a larger value has a smaller key, equal values (-0 and +0 too) equal keys; v finite. */
static inline uint64_t FN(tf_desc_key)(REAL v) {
    if (v == (REAL)0) v = (REAL)0; /* -0 as +0: the order's equal values */
    if (sizeof(REAL) == sizeof(uint32_t)) {
        uint32_t b;
        memcpy(&b, &v, sizeof b);
        b = (b & 0x80000000u) ? ~b : (b | 0x80000000u); /* ascending with the value */
        return (uint64_t)~b;
    }
    uint64_t b;
    memcpy(&b, &v, sizeof b);
    b = (b & 0x8000000000000000ull) ? ~b : (b | 0x8000000000000000ull);
    return ~b;
}

/* a[0, m) sorted in tf_before's order where a is in ascending index order: a stable radix sort (a byte of the
 * key a pass, least significant first; the passes where every key has the same byte left out) by the key
 * ascending, so equal values keep their index order. tmp: m elements. qsort took most of the kernel's time. */
static void FN(tf_sort_desc)(FN(tf_scored) *a, FN(tf_scored) *tmp, int64_t m) {
    FN(tf_scored) *from = a, *to = tmp;
    for (int shift = 0; shift < 8 * (int)sizeof(REAL); shift += 8) {
        int64_t count[256];
        memset(count, 0, sizeof(count));
        for (int64_t j = 0; j < m; ++j) count[(FN(tf_desc_key)(from[j].v) >> shift) & 255]++;
        if (count[(FN(tf_desc_key)(from[0].v) >> shift) & 255] == m) continue; /* one byte value: nothing moves */
        int64_t at = 0;
        for (int d = 0; d < 256; ++d) {
            int64_t c = count[d];
            count[d] = at;
            at += c;
        }
        for (int64_t j = 0; j < m; ++j) to[count[(FN(tf_desc_key)(from[j].v) >> shift) & 255]++] = from[j];
        FN(tf_scored) *t = from;
        from = to;
        to = t;
    }
    if (from != a) memcpy(a, from, sizeof(FN(tf_scored)) * (size_t)m);
}

#define TF_TOP_BUCKETS 4096

/* The first k of s[0, n) (collected in ascending index order) in the order, sorted, to out[0, k); 1 <= k <= n.
 * A histogram of the values finds the bucket that holds the k-th; only the elements from that bucket up are
 * sorted (about k of them when the values are spread). Returns 0, or -1 without memory. */
static int FN(tf_first_sorted)(FN(tf_scored) *s, int64_t n, int64_t k, FN(tf_scored) *out) {
    REAL lo = s[0].v, hi = s[0].v;
    for (int64_t j = 1; j < n; ++j) {
        lo = s[j].v < lo ? s[j].v : lo;
        hi = s[j].v > hi ? s[j].v : hi;
    }
    if (!(hi > lo)) { /* all equal: index order */
        memcpy(out, s, sizeof(FN(tf_scored)) * (size_t)k);
        return 0;
    }
    /* bucket(v) = floor((v - lo) * scale), non-decreasing in v (each operation rounds monotonically) */
    const double scale = (double)(TF_TOP_BUCKETS - 1) / ((double)hi - (double)lo);
    int64_t count[TF_TOP_BUCKETS];
    memset(count, 0, sizeof(count));
    for (int64_t j = 0; j < n; ++j) {
        int64_t c = (int64_t)(((double)s[j].v - (double)lo) * scale);
        count[c < 0 ? 0 : (c > TF_TOP_BUCKETS - 1 ? TF_TOP_BUCKETS - 1 : c)]++;
    }
    int64_t bucket = TF_TOP_BUCKETS - 1, taken = count[bucket];
    while (taken < k) taken += count[--bucket];
    FN(tf_scored) *keep = (FN(tf_scored) *)malloc(sizeof(FN(tf_scored)) * (size_t)(2 * taken + 1));
    if (!keep) return -1;
    int64_t m = 0;
    for (int64_t j = 0; j < n && m < taken; ++j) { /* branch-free: write always, advance where kept */
        int64_t c = (int64_t)(((double)s[j].v - (double)lo) * scale);
        c = c < 0 ? 0 : (c > TF_TOP_BUCKETS - 1 ? TF_TOP_BUCKETS - 1 : c);
        keep[m] = s[j];
        m += c >= bucket;
    }
    FN(tf_sort_desc)(keep, keep + taken, m);
    memcpy(out, keep, sizeof(FN(tf_scored)) * (size_t)k);
    free(keep);
    return 0;
}

/* Rows [b0, b1). Returns 0, or -1 without memory. */
int FN(tf_top_pixels)(const TFTopProblem *p, int b0, int b1) {
    const int64_t N = p->N, k = p->k;
    FN(tf_scored) *s = (FN(tf_scored) *)malloc(sizeof(FN(tf_scored)) * (size_t)(N + 1 + k));
    if (!s) return -1;
    FN(tf_scored) *out = s + N + 1;
    int status = 0;
    for (int b = b0; b < b1 && status == 0; ++b) {
        const REAL *score = (const REAL *)p->score + (size_t)b * N;
        /* the non-negative scores (the candidates) first: each comes before every negative one */
        int64_t n = 0;
        for (int64_t j = 0; j < N; ++j) { /* branch-free: write always, advance where kept */
            s[n].v = score[j];
            s[n].i = j;
            n += score[j] >= (REAL)0;
        }
        int64_t first = n < k ? n : k;
        if (first > 0) status = FN(tf_first_sorted)(s, n, first, out);
        if (status == 0 && first < k) {
            int64_t rest = 0;
            for (int64_t j = 0; j < N; ++j) {
                s[rest].v = score[j];
                s[rest].i = j;
                rest += !(score[j] >= (REAL)0);
            }
            status = FN(tf_first_sorted)(s, rest, k - first, out + first);
        }
        int64_t *idx = p->out_index + (size_t)b * k;
        REAL *val = (REAL *)p->out_value + (size_t)b * k;
        for (int64_t j = 0; j < k; ++j) { idx[j] = out[j].i; val[j] = out[j].v; }
    }
    free(s);
    return status;
}

/* A template's pixels at the chosen candidates (torchface.template.points._top_pixels after its top-k): at each
 * of a stream's k chosen pixels (index, value from tf_top_pixels on the float32 scores), its triangle (the
 * coverage's, 0 for background), its barycentric coordinates (rasterizer.Coverage.barycentrics: e_i =
 * c_i a + (c_{4+i} b + c_{8+i}) over (e_0 + e_1) + e_2, zeros for background), its gray value and whether it is
 * a candidate (value >= 0): the same arithmetic as the torch code, in one pass instead of a score of tensor
 * operations per pyramid level.
 * Layouts (C order): index (B, k) int64, value (B, k) float32; pix_to_face (B, H W) int64; gray (B, H W);
 * coefficients (13, num_columns), stream b's triangle f being column (b + batch_offset) F + f; ray_a (W),
 * ray_b (H); out: face_index (B, k) int64, bary (B, k, 3), intensity (B, k), valid (B, k) uint8.
 */
int FN(tf_pick_pixels)(const TFPickProblem *p, int b0, int b1) {
    const int64_t k = p->k, W = p->W, HW = (int64_t)p->H * p->W, F = p->F;
    const size_t N = (size_t)p->num_columns;
    const REAL *coef = (const REAL *)p->coefficients, *ray_a = (const REAL *)p->ray_a, *ray_b = (const REAL *)p->ray_b;
    for (int b = b0; b < b1; ++b) {
        const int64_t *index = p->index + (size_t)b * k, *face = p->pix_to_face + (size_t)b * HW;
        const float *value = p->value + (size_t)b * k;
        const REAL *gray = (const REAL *)p->gray + (size_t)b * HW;
        int64_t *out_face = p->out_face + (size_t)b * k;
        REAL *bary = (REAL *)p->out_bary + (size_t)b * k * 3, *intensity = (REAL *)p->out_intensity + (size_t)b * k;
        uint8_t *valid = p->out_valid + (size_t)b * k;
        for (int64_t j = 0; j < k; ++j) {
            const int64_t pix = index[j], f = face[pix];
            out_face[j] = f < 0 ? 0 : f;
            intensity[j] = gray[pix];
            valid[j] = (uint8_t)(value[j] >= 0.0f);
            REAL *w = bary + 3 * j;
            if (f < 0) {
                w[0] = w[1] = w[2] = (REAL)0;
                continue;
            }
            const int64_t row = pix / W, col = pix - row * W;
            const size_t c = (size_t)(((int64_t)b + p->batch_offset) * F + f);
            const REAL a = ray_a[col], bb = ray_b[row];
            const REAL e0 = coef[0 * N + c] * a + (coef[4 * N + c] * bb + coef[8 * N + c]);
            const REAL e1 = coef[1 * N + c] * a + (coef[5 * N + c] * bb + coef[9 * N + c]);
            const REAL e2 = coef[2 * N + c] * a + (coef[6 * N + c] * bb + coef[10 * N + c]);
            const REAL sum = (e0 + e1) + e2;
            w[0] = e0 / sum;
            w[1] = e1 / sum;
            w[2] = e2 / sum;
        }
    }
    return 0;
}
