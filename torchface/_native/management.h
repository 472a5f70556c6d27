/* Template management's per-frame decisions (torchface.tracker.managed.managed_step), one stream at a time, with
 * the torch code's rules: the mosaic entry to align against (template.management.select_entries) and whether the
 * pose is near that entry's (TemplateConfig.clean_radius_deg), before the solve; after it, the confidence gating
 * and loss counters, the recovery schedule and whether the frame becomes a mosaic entry (pose_bins, has_bin,
 * within_reach); in the solve, the clean-frame rule (tracker.step._clean_streams). The tests compare each against
 * the torch code.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts: the mosaic's ypr (B, E, 3) degrees, bins (B, E, 2) int64, used (B, E) uint8; per stream (B,): ypr
 * (B, 3), entry int64, confidence, inside (REAL), failed, lost uint8, low_count, very_low_count, since int64.
 */

/* (yaw, pitch) distance of entry e of stream b to the pose ypr; infinite where the slot is unused. */
static inline REAL FN(entry_distance)(const TFManageProblem *p, int b, int e, const REAL *ypr) {
    if (!p->used[(size_t)b * p->E + e]) return (REAL)INFINITY;
    const REAL *ey = (const REAL *)p->mosaic_ypr + ((size_t)b * p->E + e) * 3;
    REAL dy = ey[0] - ypr[0], dp = ey[1] - ypr[1];
    return (REAL)sqrt((double)(dy * dy + dp * dp));
}

/* Before the solve, streams [b0, b1): select_entries (the nearest used entry, kept unless another is nearer by
 * the margin; the reference within its radius) and the clean-radius test of the chosen entry. Returns 0. */
int FN(tf_select_entries)(const TFManageProblem *p, int b0, int b1) {
    for (int b = b0; b < b1; ++b) {
        const REAL *ypr = (const REAL *)p->ypr + 3 * (size_t)b;
        const int64_t current = p->entry[b];
        int64_t best = 0;
        REAL d_best = (REAL)INFINITY;
        for (int e = 0; e < p->E; ++e) {
            REAL d = FN(entry_distance)(p, b, e, ypr);
            if (d < d_best) {
                d_best = d;
                best = e;
            }
        }
        REAL d_cur = FN(entry_distance)(p, b, (int)current, ypr);
        const REAL margin = (REAL)p->switch_margin_deg, radius = (REAL)p->reference_radius_deg;
        int64_t choice = d_best + margin < d_cur ? best : current;
        REAL d_ref = FN(entry_distance)(p, b, 0, ypr);
        int use_ref = d_ref <= radius && (current == 0 || d_ref <= radius - margin);
        int64_t chosen = use_ref ? 0 : choice;
        p->out_entry[b] = chosen;
        if (p->clean_radius_deg > 0) {
            const REAL *ey = (const REAL *)p->mosaic_ypr + ((size_t)b * p->E + chosen) * 3;
            REAL dy = ey[0] - ypr[0], dp = ey[1] - ypr[1];
            p->out_near[b] = (uint8_t)((REAL)sqrt((double)(dy * dy + dp * dp)) <= (REAL)p->clean_radius_deg);
        }
    }
    return 0;
}

/* After the confidence, streams [b0, b1): the gating, loss counters and recovery schedule of managed_step, and
 * whether the frame becomes a mosaic entry if no recovery changes the stream (its pose bin counted from the
 * reference entry's pose, near the bin's centre, a bin without an entry, within reach of one, room left).
 * Returns 0. */
int FN(tf_gate)(const TFManageProblem *p, int b0, int b1) {
    const REAL wy = (REAL)p->yaw_bin_deg, wp = (REAL)p->pitch_bin_deg;
    for (int b = b0; b < b1; ++b) {
        const REAL conf = ((const REAL *)p->confidence)[b], inside = ((const REAL *)p->inside)[b];
        const int failed = p->failed[b], was_lost = p->lost[b];
        const int outside = inside < (REAL)p->min_inside_fraction;
        int confident = conf >= (REAL)p->confidence_threshold && !failed && !outside;
        int64_t low = confident ? 0 : p->low_count[b] + 1;
        int very_low = conf < (REAL)p->very_low_confidence || failed || outside;
        int64_t vlow = very_low ? p->very_low_count[b] + 1 : 0;
        int lost = was_lost || failed || outside || low >= p->lost_after || vlow >= p->lost_after_very_low;
        lost = lost && !(conf >= (REAL)p->recover_confidence && !failed && !outside);
        int64_t since = lost ? p->since[b] + 1 : 0;
        if (lost && !was_lost) since = p->recovery_every;
        p->out_confident[b] = (uint8_t)confident;
        p->out_low_count[b] = low;
        p->out_very_low_count[b] = vlow;
        p->out_lost[b] = (uint8_t)lost;
        p->out_reverted[b] = (uint8_t)(lost && (failed || outside));
        p->out_since[b] = since;
        p->out_attempt[b] = (uint8_t)(lost && since >= p->recovery_every);
        /* a new mosaic entry */
        const REAL *ypr = (const REAL *)p->ypr + 3 * (size_t)b, *origin = (const REAL *)p->mosaic_ypr + (size_t)b * p->E * 3;
        REAL sy = (ypr[0] - origin[0]) / wy, sp = (ypr[1] - origin[1]) / wp;
        REAL by = (REAL)floor((double)(sy + (REAL)0.5)), bp = (REAL)floor((double)(sp + (REAL)0.5));
        const REAL frac = (REAL)p->bin_centre_fraction;
        int near = (REAL)fabs((double)(sy - by)) <= frac && (REAL)fabs((double)(sp - bp)) <= frac;
        const int64_t bin_y = (int64_t)by, bin_p = (int64_t)bp;
        p->out_bins[2 * (size_t)b] = bin_y;
        p->out_bins[2 * (size_t)b + 1] = bin_p;
        int has = 0, reach = 0, entries = 0;
        for (int e = 0; e < p->E; ++e) {
            if (!p->used[(size_t)b * p->E + e]) continue;
            ++entries;
            const int64_t *eb = p->bins + ((size_t)b * p->E + e) * 2;
            has |= eb[0] == bin_y && eb[1] == bin_p;
            const REAL *ey = (const REAL *)p->mosaic_ypr + ((size_t)b * p->E + e) * 3;
            REAL dy = (REAL)fabs((double)((ey[0] - ypr[0]) / wy)), dp = (REAL)fabs((double)((ey[1] - ypr[1]) / wp));
            reach |= (dy > dp ? dy : dp) <= (REAL)p->entry_reach;
        }
        int add = confident && !lost && conf >= (REAL)p->add_confidence && near && !has && reach &&
                  entries < p->max_entries;
        p->out_add[b] = (uint8_t)add;
    }
    return 0;
}

/* In the solve, after its coarser pose level, streams [b0, b1): the clean-frame rule of
 * TemplateConfig.clean_radius_deg (tracker.step._clean_streams at fast.robust_scale_of's scale of the level's
 * residuals r (B, N) over valid (B, N) uint8): a stream near its template's pose (near (B) uint8) is clean where
 * Tukey's loss at that scale rejects (weight exactly 0) fewer than `fraction` of its valid residuals. The torch
 * code's arithmetic, which the tests compare against: the scale is 1.4826 times the lower median of |r| over the
 * valid residuals that are not NaN (1 without any; an infinite median is the dtype's largest value, as nan_to_num
 * makes it), at least scale_floor, then at least min_scale (RobustLoss's floor on a scale); a residual is rejected
 * where ((r / s)^2) / c^2 is at least 1 (Tukey's weight (1 - min(t, 1))^2 is 0 exactly there: below 1, 1 - t is at
 * least half the dtype's epsilon, whose square is a normal number; NaN is never rejected); the rejected share in
 * float, or double with share_double (the integer counts' division gives torch's default dtype), against the
 * fraction in that dtype. out_clean (B) uint8. Returns 0, or -1 without memory. */
int FN(tf_clean_streams)(const TFCleanProblem *p, int b0, int b1) {
    const int N = p->N;
    REAL *scratch = (REAL *)malloc(sizeof(REAL) * (N > 0 ? (size_t)N : 1));
    if (!scratch) return -1;
    const REAL cc = (REAL)(p->c * p->c), fl = (REAL)p->scale_floor, tiny = (REAL)p->min_scale;
    const REAL largest = sizeof(REAL) == sizeof(float) ? (REAL)FLT_MAX : (REAL)DBL_MAX;
    for (int b = b0; b < b1; ++b) {
        const REAL *r = (const REAL *)p->r + (size_t)b * N;
        const uint8_t *valid = p->valid + (size_t)b * N;
        int k = 0;
        int64_t count = 0, rejected = 0;
        for (int n = 0; n < N; ++n) {
            if (!valid[n]) continue;
            ++count;
            if (r[n] == r[n]) scratch[k++] = (REAL)fabs((double)r[n]);
        }
        REAL med = k > 0 ? FN(select_kth)(scratch, k, (k - 1) / 2) : (REAL)1;
        med = med < largest ? med : largest;
        REAL s = (REAL)TF_MAD_TO_SIGMA * med; /* in REAL, as the torch code's product */
        s = s > fl ? s : fl;
        s = s > tiny ? s : tiny;
        for (int n = 0; n < N; ++n) {
            if (!valid[n]) continue;
            const REAL u = r[n] / s;
            rejected += (u * u) / cc >= (REAL)1;
        }
        const int64_t total = count > 0 ? count : 1;
        const int clean = p->share_double ? (double)rejected / (double)total < p->fraction
                                          : (float)rejected / (float)total < (float)p->fraction;
        p->out_clean[b] = (uint8_t)(p->near[b] && clean);
    }
    free(scratch);
    return 0;
}
