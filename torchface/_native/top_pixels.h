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

static int FN(tf_scored_cmp)(const void *x, const void *y) {
    const FN(tf_scored) *a = (const FN(tf_scored) *)x, *b = (const FN(tf_scored) *)y;
    return FN(tf_before)(a, b) ? -1 : (FN(tf_before)(b, a) ? 1 : 0);
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
    FN(tf_scored) *keep = (FN(tf_scored) *)malloc(sizeof(FN(tf_scored)) * (size_t)(taken + 1));
    if (!keep) return -1;
    int64_t m = 0;
    for (int64_t j = 0; j < n && m < taken; ++j) { /* branch-free: write always, advance where kept */
        int64_t c = (int64_t)(((double)s[j].v - (double)lo) * scale);
        c = c < 0 ? 0 : (c > TF_TOP_BUCKETS - 1 ? TF_TOP_BUCKETS - 1 : c);
        keep[m] = s[j];
        m += c >= bucket;
    }
    qsort(keep, (size_t)m, sizeof(FN(tf_scored)), FN(tf_scored_cmp));
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
