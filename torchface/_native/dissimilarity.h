/* The dissimilarity measure's per-frame work (torchface.template.dissimilarity.dissimilarity): the masked, smoothed
 * gray image of a normalised face (_masked_gray) and the inverse-compositional Lucas-Kanade of the reference's
 * fiducial patches on it (inverse_compositional_lk, one gray channel, translation warp), one patch at a time; the
 * same algorithm as the torch code, which the tests compare against.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order): normalised (B, C, G, G); mask (B, 1, G, G) of 0 / 1; kernel (2 radius + 1) the normalised
 * Gaussian; gray (B, G, G) out; the reference's patches: grid (B, K, n, 2) pixel positions (u, v), template
 * (B, K, n), sd (B, K, n, 2) its gradient (steepest-descent images), ref_weight (B, K, n), ref_total (B, K);
 * out: p (B, K, 2), converged, valid (B, K) uint8, support (B, K).
 */

/* _masked_gray for one stream: the channel mean inside the mask, blurred by the separable Gaussian (replicated
 * border) and divided by the blurred mask (normalised convolution), 0 outside the mask. tmp: 3 G^2 REALs. */
static void FN(masked_gray)(const TFLKProblem *p, int b, REAL *gray, REAL *tmp) {
    const int C = p->C, G = p->G, R = p->radius;
    const size_t GG = (size_t)G * G;
    const REAL *img = (const REAL *)p->normalised + (size_t)b * C * GG;
    const REAL *restrict mask = (const REAL *)p->mask + (size_t)b * GG;
    const REAL *k = (const REAL *)p->kernel;
    REAL *restrict g0 = tmp, *restrict rows_g = tmp + GG, *restrict rows_m = tmp + 2 * GG;
    for (size_t i = 0; i < GG; ++i) {
        REAL s = img[i];
        for (int c = 1; c < C; ++c) s += img[c * GG + i];
        g0[i] = (s / (REAL)C) * mask[i];
    }
    if (R <= 0) {
        memcpy(gray, g0, sizeof(REAL) * GG);
        return;
    }
    /* along rows (x), replicated border: each output the taps' products added in order from 0; the pixels whose
     * taps are all inside the row a tap at a time over the row (vectorised, the same sums), the others with the
     * clamped indices */
    const int lo = R < G ? R : G, hi = G - R > lo ? G - R : lo; /* [lo, hi): the taps inside the row */
    for (int y = 0; y < G; ++y) {
        const REAL *restrict gr = g0 + (size_t)y * G, *restrict mr = mask + (size_t)y * G;
        REAL *restrict og = rows_g + (size_t)y * G, *restrict om = rows_m + (size_t)y * G;
        for (int x = 0; x < G; ++x) {
            if (x == lo) x = hi; /* (the inner pixels below) */
            if (x >= G) break;
            REAL sg = 0, sm = 0;
            for (int j = -R; j <= R; ++j) {
                int xx = x + j < 0 ? 0 : (x + j > G - 1 ? G - 1 : x + j);
                sg += k[j + R] * gr[xx];
                sm += k[j + R] * mr[xx];
            }
            og[x] = sg;
            om[x] = sm;
        }
        for (int x = lo; x < hi; ++x) og[x] = om[x] = (REAL)0;
        for (int j = -R; j <= R; ++j) {
            const REAL kj = k[j + R];
            for (int x = lo; x < hi; ++x) {
                og[x] += kj * gr[x + j];
                om[x] += kj * mr[x + j];
            }
        }
    }
    /* along columns (y): whole rows at a time (vectorised over x), then the normalisation */
    const REAL floor_ = (REAL)(1e3 * p->eps);
    REAL *restrict acc_g = g0, *restrict acc_m = g0 + G; /* g0 is no longer needed: two rows of accumulators */
    for (int y = 0; y < G; ++y) {
        for (int x = 0; x < G; ++x) acc_g[x] = acc_m[x] = (REAL)0;
        for (int j = -R; j <= R; ++j) {
            int yy = y + j < 0 ? 0 : (y + j > G - 1 ? G - 1 : y + j);
            const REAL kj = k[j + R];
            const REAL *restrict rg = rows_g + (size_t)yy * G, *restrict rm = rows_m + (size_t)yy * G;
            for (int x = 0; x < G; ++x) {
                acc_g[x] += kj * rg[x];
                acc_m[x] += kj * rm[x];
            }
        }
        REAL *restrict out = gray + (size_t)y * G;
        const REAL *restrict mrow = mask + (size_t)y * G;
        for (int x = 0; x < G; ++x) out[x] = (acc_m[x] > floor_ ? acc_g[x] / acc_m[x] : (REAL)0) * mrow[x];
    }
}

/* Bilinear sample (zero outside, align_corners=True pixel coordinates) of gray and mask at (u, v); inside: the
 * point within [0, G - 1]^2. */
static inline void FN(sample_zero)(const REAL *gray, const REAL *mask, int G, REAL u, REAL v, REAL *val, REAL *m) {
    if (!(u > (REAL)-1 && u < (REAL)G && v > (REAL)-1 && v < (REAL)G)) { /* no neighbour inside (or NaN) */
        *val = *m = (REAL)0;
        return;
    }
    int x0 = (int)floor(u), y0 = (int)floor(v);
    REAL ax = u - (REAL)x0, ay = v - (REAL)y0, bx = (REAL)1 - ax, by = (REAL)1 - ay;
    REAL wts[4] = {bx * by, ax * by, bx * ay, ax * ay};
    int xs[4] = {x0, x0 + 1, x0, x0 + 1}, ys[4] = {y0, y0, y0 + 1, y0 + 1};
    REAL sv = 0, sm = 0;
    for (int q = 0; q < 4; ++q) {
        if (xs[q] < 0 || xs[q] >= G || ys[q] < 0 || ys[q] >= G) continue;
        size_t i = (size_t)ys[q] * G + xs[q];
        sv += wts[q] * gray[i];
        sm += wts[q] * mask[i];
    }
    *val = sv;
    *m = sm;
}

/* Weights of a patch's points at displacement (pu, pv) (weights_at): the reference weight times the image mask
 * sampled there (clamped to [0, 1]), zero where the point leaves the image; the errors warped - template. */
static double FN(patch_at)(const TFLKProblem *p, int b, int k, const REAL *gray, const REAL *mask, REAL pu, REAL pv,
                           REAL *err, REAL *w) {
    const int n = p->n, G = p->G;
    const size_t at = ((size_t)b * p->K + k) * n;
    const REAL *grid = (const REAL *)p->grid + 2 * at, *tpl = (const REAL *)p->templ + at;
    const REAL *rw = (const REAL *)p->ref_weight + at;
    const REAL gmax = (REAL)(G - 1);
    double total = 0.0;
    for (int i = 0; i < n; ++i) {
        REAL u = grid[2 * i] + pu, v = grid[2 * i + 1] + pv, val, m;
        FN(sample_zero)(gray, mask, G, u, v, &val, &m);
        int inside = u >= (REAL)0 && u <= gmax && v >= (REAL)0 && v <= gmax;
        m = m < (REAL)0 ? (REAL)0 : (m > (REAL)1 ? (REAL)1 : m);
        w[i] = inside ? m * rw[i] : (REAL)0;
        err[i] = val - tpl[i];
        total += w[i];
    }
    return total;
}

/* One patch's iterations (inverse_compositional_lk's iterate for a batch of one patch) and final state. */
static void FN(track_patch)(const TFLKProblem *p, int b, int k, const REAL *gray, const REAL *mask, REAL *err,
                            REAL *w) {
    const int n = p->n;
    const size_t at = ((size_t)b * p->K + k) * n, pk = (size_t)b * p->K + k;
    const REAL *sd = (const REAL *)p->sd + 2 * at;
    const double eps = p->eps, tol = p->tolerance, dmax = p->max_displacement;
    REAL pu = 0, pv = 0;
    int active = 1, converged = 0;
    for (int it = 0; it < p->iterations && active; ++it) {
        FN(patch_at)(p, b, k, gray, mask, pu, pv, err, w);
        /* weighted second moments of [sd_u, sd_v, e, 1] */
        double suu = 0, suv = 0, svv = 0, sue = 0, sve = 0, su1 = 0, sv1 = 0, se1 = 0, s11 = 0;
        for (int i = 0; i < n; ++i) {
            double wi = w[i], du = sd[2 * i], dv = sd[2 * i + 1], e = err[i];
            suu += wi * du * du;
            suv += wi * du * dv;
            svv += wi * dv * dv;
            sue += wi * du * e;
            sve += wi * dv * e;
            su1 += wi * du;
            sv1 += wi * dv;
            se1 += wi * e;
            s11 += wi;
        }
        double a = suu, bb = suv, c = svv, g0 = sue, g1 = sve;
        if (p->project_out_bias) { /* m_ij - m_i1 m_1j / m_11 */
            double d = s11 > eps ? s11 : eps;
            a -= su1 * (su1 / d);
            bb -= su1 * (sv1 / d);
            c -= sv1 * (sv1 / d);
            g0 -= su1 * (se1 / d);
            g1 -= sv1 * (se1 / d);
        }
        double det = a * c - bb * bb;
        int ok = det > 1e3 * eps * (a + c) * (a + c) && isfinite(det + g0 + g1);
        if (!ok) {
            active = 0; /* ill-posed: stops, not valid unless it had converged (it had not: it was active) */
            break;
        }
        double du = (c * g0 - bb * g1) / det, dv = (a * g1 - bb * g0) / det;
        pu = (REAL)((double)pu - du); /* compose with the inverse increment */
        pv = (REAL)((double)pv - dv);
        int small = sqrt(du * du + dv * dv) < tol;
        converged = small;
        active = !small;
        if (p->has_max_displacement && !(sqrt((double)pu * pu + (double)pv * pv) <= dmax)) active = 0;
    }
    double norm = sqrt((double)pu * pu + (double)pv * pv);
    int valid = active || converged;
    if (p->has_max_displacement) valid = valid && norm <= dmax;
    double total = FN(patch_at)(p, b, k, gray, mask, pu, pv, err, w);
    double ref_total = ((const REAL *)p->ref_total)[pk];
    double support = ref_total > 0 ? total / (ref_total > eps ? ref_total : eps) : 0.0;
    valid = valid && isfinite(pu) && isfinite(pv) && ref_total > 0;
    ((REAL *)p->out_p)[2 * pk] = pu;
    ((REAL *)p->out_p)[2 * pk + 1] = pv;
    p->out_converged[pk] = (uint8_t)converged;
    p->out_valid[pk] = (uint8_t)valid;
    ((REAL *)p->out_support)[pk] = (REAL)(support < 0 ? 0 : (support > 1 ? 1 : support));
}

/* Streams [b0, b1): the gray image (also written to out_gray) and every patch. Returns 0, or -1 without memory. */
int FN(tf_dissimilarity)(const TFLKProblem *p, int b0, int b1) {
    const size_t GG = (size_t)p->G * p->G;
    REAL *tmp = (REAL *)malloc(sizeof(REAL) * (3 * GG + 2 * (size_t)p->n + 8));
    if (!tmp) return -1;
    REAL *err = tmp + 3 * GG, *w = err + p->n;
    for (int b = b0; b < b1; ++b) {
        REAL *gray = (REAL *)p->out_gray + (size_t)b * GG;
        const REAL *mask = (const REAL *)p->mask + (size_t)b * GG;
        FN(masked_gray)(p, b, gray, tmp);
        for (int k = 0; k < p->K; ++k) FN(track_patch)(p, b, k, gray, mask, err, w);
    }
    free(tmp);
    return 0;
}

/* build_dissimilarity_reference's fiducial patches for streams [b0, b1): the masked, smoothed gray image (out_gray,
 * as masked_gray), its structure tensor summed over each patch window (central differences, zero at the image
 * border; avg_pool2d with zero padding times the window's area), the smaller eigenvalue as the texture score
 * where the whole patch (plus one pixel) is inside the mask and the image's inner part, -1 elsewhere, and the
 * greedy non-maximum suppression (the best remaining pixel, the first on a tie, then every pixel within the
 * separation along both axes cleared): out_p holds each pick's flat pixel index (as REAL) and out_support its
 * score. Returns 0, or -1 without memory. */
int FN(tf_reference_patches)(const TFLKProblem *p, int b0, int b1) {
    const int G = p->G, h = p->n, r = h / 2, K = p->K, s = p->iterations, border = p->radius_border;
    const size_t GG = (size_t)G * G;
    REAL *tmp = (REAL *)malloc(sizeof(REAL) * 6 * GG); /* masked_gray's 3 GG, then gu, gv, score */
    if (!tmp) return -1;
    REAL *gu = tmp + 3 * GG, *gv = gu + GG, *score = gv + GG;
    for (int b = b0; b < b1; ++b) {
        REAL *gray = (REAL *)p->out_gray + (size_t)b * GG;
        const REAL *mask = (const REAL *)p->mask + (size_t)b * GG;
        FN(masked_gray)(p, b, gray, tmp);
        for (int y = 0; y < G; ++y)
            for (int x = 0; x < G; ++x) {
                size_t i = (size_t)y * G + x;
                gu[i] = (x > 0 && x < G - 1) ? (REAL)0.5 * (gray[i + 1] - gray[i - 1]) : (REAL)0;
                gv[i] = (y > 0 && y < G - 1) ? (REAL)0.5 * (gray[i + G] - gray[i - G]) : (REAL)0;
            }
        /* the window sums (zero outside), as avg_pool2d's mean times the window's area, at the pixels that may be
         * eligible (those at least edge = r + 1 + border >= r + 1 from the image border: their windows, and the
         * mask's one pixel wider, are inside the image); every other pixel scores -1 whatever its sums. Each sum
         * adds its terms row by row as the window reads them, a window position at a time over the row
         * (vectorised over the pixels, the same sums). tmp's first 4 G REALs (masked_gray's, no longer used). */
        const REAL area = (REAL)(h * h), area_m = (REAL)((h + 2) * (h + 2));
        const int edge = r + 1 + (border > 0 ? border : 0), lo = edge, hi = G - edge;
        REAL *restrict sa = tmp, *restrict sb = tmp + G, *restrict sc = tmp + 2 * G, *restrict sm = tmp + 3 * G;
        for (size_t i = 0; i < GG; ++i) score[i] = (REAL)-1;
        for (int y = lo; y < hi; ++y) {
            for (int x = lo; x < hi; ++x) sa[x] = sb[x] = sc[x] = sm[x] = (REAL)0;
            for (int dy = -r; dy <= r; ++dy)
                for (int dx = -r; dx <= r; ++dx) {
                    const REAL *restrict u = gu + (size_t)(y + dy) * G, *restrict v = gv + (size_t)(y + dy) * G;
                    for (int x = lo; x < hi; ++x) {
                        const REAL ux = u[x + dx], vx = v[x + dx];
                        sa[x] += ux * ux;
                        sb[x] += ux * vx;
                        sc[x] += vx * vx;
                    }
                }
            for (int dy = -r - 1; dy <= r + 1; ++dy)
                for (int dx = -r - 1; dx <= r + 1; ++dx) {
                    const REAL *restrict mk = mask + (size_t)(y + dy) * G;
                    for (int x = lo; x < hi; ++x) sm[x] += mk[x + dx];
                }
            for (int x = lo; x < hi; ++x) {
                REAL a = sa[x] / area * area, bb = sb[x] / area * area, c = sc[x] / area * area;
                REAL half = (REAL)0.5 * (a - c);
                REAL min_eig = (REAL)0.5 * (a + c) - (REAL)sqrt((double)(half * half + bb * bb));
                int eligible = sm[x] / area_m > (REAL)(1.0 - 1e-6);
                score[(size_t)y * G + x] = eligible ? (min_eig > (REAL)0 ? min_eig : (REAL)0) : (REAL)-1;
            }
        }
        REAL *idx_out = (REAL *)p->out_p + (size_t)b * K, *best_out = (REAL *)p->out_support + (size_t)b * K;
        for (int k = 0; k < K; ++k) {
            size_t best_i = 0;
            REAL best = score[0];
            for (size_t i = 1; i < GG; ++i)
                if (score[i] > best) {
                    best = score[i];
                    best_i = i;
                }
            idx_out[k] = (REAL)best_i;
            best_out[k] = best;
            int v = (int)(best_i / G), u = (int)(best_i % G);
            for (int dy = -s; dy <= s; ++dy) {
                int yy = v + dy < 0 ? 0 : (v + dy > G - 1 ? G - 1 : v + dy);
                for (int dx = -s; dx <= s; ++dx) {
                    int xx = u + dx < 0 ? 0 : (u + dx > G - 1 ? G - 1 : u + dx);
                    score[(size_t)yy * G + xx] = (REAL)-1;
                }
            }
        }
    }
    free(tmp);
    return 0;
}
