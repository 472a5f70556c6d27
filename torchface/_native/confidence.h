/* Template management's per-frame confidence in one pass per stream (torchface.tracker.managed._confidence): the
 * mesh at the estimate (the model's Eq. 1 deformation, turned and moved into the camera frame), the mosaic entry
 * nearest the estimate's (yaw, pitch) (template.management.nearest_entries), the posed mesh's vertex normals and
 * back-facing triangles (geometry.mesh.vertex_normals_and_backfacing), its normalised face without the z-buffer
 * (normalised_face.h), the dissimilarity against that entry's reference (dissimilarity.h, then dissimilarity()'s
 * mean displacement and confidence) and the fraction of surface vertices inside the frame
 * (template.management.face_inside_fraction). The same algorithms as the torch code, which the tests compare
 * against.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order): the model's mean (V, 3), shape_units (S, V, 3), anim_units (A, V, 3), faces (F, 3) int64,
 * surface (V) uint8; the estimate's shape (B, S), alpha (B, A), R (B, 3, 3), t (B, 3), illumination (B, 5) and
 * ypr (B, 3) degrees (NULL: entry 0); the layout's face_index, pixel_index (M) int64 and bary (M, 3); frames
 * (B, C, H, W); the mosaic's rows (B) int64 (each stream's row), entry poses mosaic_ypr (rows, E, 3), used
 * (rows, E) uint8 and references of its rows x E entries: patch_valid (rows E, K) uint8, grid (rows E, K, n, 2),
 * templ (rows E, K, n), sd (rows E, K, n, 2), ref_weight (rows E, K, n), ref_total (rows E, K); out: entry (B)
 * int64, image (B, C, G * G) and mask (B, G * G) zeroed by the caller, p (B, K, 2), support (B, K), converged,
 * valid, present (B, K) uint8, dissimilarity, confidence, inside (B).
 */

/* vertex_normals_and_backfacing for one stream: the triangles' cross products (v1 - v0) x (v2 - v0), back where
 * n . v0 >= 0, and per vertex the unit sum of its triangles' cross products (corner 0 of every triangle, then 1,
 * then 2, as the torch code adds them). */
static void FN(normals_and_back)(const REAL *verts, const int64_t *faces, int V, int F, REAL *normals, uint8_t *back,
                                 REAL *cross) {
    for (int f = 0; f < F; ++f) {
        const REAL *a = verts + 3 * faces[3 * f], *b = verts + 3 * faces[3 * f + 1], *c = verts + 3 * faces[3 * f + 2];
        REAL e1[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]}, e2[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
        REAL *x = cross + 3 * f;
        x[0] = e1[1] * e2[2] - e1[2] * e2[1];
        x[1] = e1[2] * e2[0] - e1[0] * e2[2];
        x[2] = e1[0] * e2[1] - e1[1] * e2[0];
        back[f] = (uint8_t)(x[0] * a[0] + x[1] * a[1] + x[2] * a[2] >= (REAL)0);
    }
    memset(normals, 0, sizeof(REAL) * 3 * V);
    for (int corner = 0; corner < 3; ++corner)
        for (int f = 0; f < F; ++f)
            for (int c = 0; c < 3; ++c) normals[3 * faces[3 * f + corner] + c] += cross[3 * f + c];
    const REAL eps = (REAL)TF_EPS(REAL);
    for (int v = 0; v < V; ++v) {
        REAL *n = normals + 3 * v;
        REAL sq = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
        sq = sq > eps * eps ? sq : eps * eps;
        REAL inv = (REAL)1 / (REAL)sqrt((double)sq);
        for (int c = 0; c < 3; ++c) n[c] *= inv;
    }
}

/* The model's vertices at shape and expression coefficients (Eq. 1: mean + sum_s sigma_s S_s + sum_a alpha_a A_a),
 * turned and moved into the camera frame: R X + t. */
static void FN(posed_vertices)(const TFConfProblem *p, int b, REAL *verts) {
    const int V = p->V, S = p->S, A = p->A;
    const REAL *mean = (const REAL *)p->mean, *su = (const REAL *)p->shape_units, *au = (const REAL *)p->anim_units;
    const REAL *sigma = (const REAL *)p->shape + (size_t)b * S, *alpha = (const REAL *)p->alpha + (size_t)b * A;
    const REAL *R = (const REAL *)p->R + 9 * (size_t)b, *t = (const REAL *)p->t + 3 * (size_t)b;
    for (int i = 0; i < 3 * V; ++i) verts[i] = mean[i];
    for (int s = 0; s < S; ++s)
        if (sigma[s] != (REAL)0)
            for (int i = 0; i < 3 * V; ++i) verts[i] += sigma[s] * su[(size_t)s * 3 * V + i];
    for (int a = 0; a < A; ++a)
        if (alpha[a] != (REAL)0)
            for (int i = 0; i < 3 * V; ++i) verts[i] += alpha[a] * au[(size_t)a * 3 * V + i];
    for (int v = 0; v < V; ++v) {
        REAL x = verts[3 * v], y = verts[3 * v + 1], z = verts[3 * v + 2];
        for (int r = 0; r < 3; ++r) verts[3 * v + r] = R[3 * r] * x + R[3 * r + 1] * y + R[3 * r + 2] * z + t[r];
    }
}

/* nearest_entries: the used entry nearest the pose in (yaw, pitch), the lowest index on a tie. */
static int64_t FN(nearest_entry)(const TFConfProblem *p, int b) {
    if (!p->ypr) return 0;
    const int E = p->E;
    const int64_t row = p->rows[b];
    const REAL *ypr = (const REAL *)p->ypr + 3 * (size_t)b, *ey = (const REAL *)p->mosaic_ypr + (size_t)row * E * 3;
    const uint8_t *used = p->used + (size_t)row * E;
    int64_t best = 0;
    REAL d_best = (REAL)INFINITY;
    for (int e = 0; e < E; ++e) {
        if (!used[e]) continue;
        REAL dy = ey[3 * e] - ypr[0], dp = ey[3 * e + 1] - ypr[1];
        REAL d = (REAL)sqrt((double)(dy * dy + dp * dp));
        if (d < d_best) {
            d_best = d;
            best = e;
        }
    }
    return best;
}

static void FN(confidence_one)(const TFConfProblem *p, int b, REAL *work) {
    const int V = p->V, F = p->F, K = p->K, n = p->n, G = p->G;
    const size_t GG = (size_t)G * G;
    REAL *verts = work, *normals = verts + 3 * (size_t)V, *cross = normals + 3 * (size_t)V, *gray = cross + 3 * (size_t)F;
    REAL *tmp = gray + GG, *err = tmp + 3 * GG, *w = err + n;
    uint8_t *back = (uint8_t *)(w + n);
    FN(posed_vertices)(p, b, verts);
    FN(normals_and_back)(verts, p->faces, V, F, normals, back, cross);
    const int64_t entry = FN(nearest_entry)(p, b);
    p->out_entry[b] = entry;

    /* the normalised face: normalised_face.h's kernel on this stream alone */
    REAL *image = (REAL *)p->out_image + (size_t)b * p->C * GG, *mask = (REAL *)p->out_mask + (size_t)b * GG;
    TFFaceProblem face = {1, V, F, p->M, p->C, G, p->height, p->width, p->fx, p->fy, p->cx, p->cy,
                          p->min_facing_cos, p->min_gain, p->depth_eps, verts, normals, back, p->faces,
                          p->face_index, p->pixel_index, p->bary,
                          (const REAL *)p->frames + (size_t)b * p->C * p->height * p->width,
                          p->illumination ? (const REAL *)p->illumination + 5 * (size_t)b : NULL, image, mask};
    FN(normalised_face_one)(&face, 0);

    /* the dissimilarity against the entry's reference: dissimilarity.h's kernels on this stream alone */
    const size_t ek = ((size_t)p->rows[b] * p->E + (size_t)entry) * K, ekn = ek * n;
    TFLKProblem lk = {1, p->C, G, K, n, p->radius, p->iterations, p->project_out_bias, p->has_max_displacement,
                      p->eps, p->tolerance, p->max_displacement, image, mask, p->kernel,
                      (const REAL *)p->grid + 2 * ekn, (const REAL *)p->templ + ekn, (const REAL *)p->sd + 2 * ekn,
                      (const REAL *)p->ref_weight + ekn, (const REAL *)p->ref_total + ek, gray,
                      (REAL *)p->out_p + 2 * (size_t)b * K, (REAL *)p->out_support + (size_t)b * K,
                      p->out_converged + (size_t)b * K, p->out_valid + (size_t)b * K, 0};
    FN(masked_gray)(&lk, 0, gray, tmp);
    for (int k = 0; k < K; ++k) FN(track_patch)(&lk, 0, k, gray, mask, err, w);

    /* dissimilarity(): mean of min(|p|, d_max) over the present patches less the largest floor(trim_fraction *
     * count) of them (trimmed_mean; at least one kept), confidence exp(-(d / d0)^2) */
    const uint8_t *patch_valid = p->patch_valid + ek;
    const REAL *pk = (const REAL *)p->out_p + 2 * (size_t)b * K, *support = (const REAL *)p->out_support + (size_t)b * K;
    const double dmax = p->max_displacement_or_inf;
    int count = 0, valid_patches = 0;
    REAL kept[K > 0 ? K : 1]; /* the present patches' displacements, ascending */
    for (int k = 0; k < K; ++k) {
        valid_patches += patch_valid[k] != 0;
        int present = patch_valid[k] && (double)support[k] >= p->min_support;
        p->out_present[(size_t)b * K + k] = (uint8_t)present;
        if (!present) continue;
        double d = sqrt((double)pk[2 * k] * pk[2 * k] + (double)pk[2 * k + 1] * pk[2 * k + 1]);
        if (!(d == d)) d = dmax; /* NaN */
        d = d < dmax ? d : dmax;
        if (!lk.out_valid[k]) d = dmax;
        /* insertion into the ascending list of the present patches' displacements */
        int i = count++;
        for (; i > 0 && kept[i - 1] > (REAL)d; --i) kept[i] = kept[i - 1];
        kept[i] = (REAL)d;
    }
    int enough = count >= p->min_patches && (double)count >= p->min_present_fraction * valid_patches;
    int keep = count - (int)floor((double)count * p->trim_fraction);
    if (keep < 1) keep = 1;
    double sum = 0.0;
    for (int i = 0; i < keep && i < count; ++i) sum += (double)kept[i];
    double mean = sum / keep;
    double d = enough ? mean : dmax;
    ((REAL *)p->out_dissimilarity)[b] = (REAL)d;
    ((REAL *)p->out_confidence)[b] = enough ? (REAL)exp(-(d / p->d0) * (d / p->d0)) : (REAL)0;

    /* face_inside_fraction: surface vertices in front of the camera and projecting inside the frame */
    int surface = 0, inside = 0;
    const REAL zmin = (REAL)p->depth_eps;
    for (int v = 0; v < V; ++v) {
        if (!p->surface[v]) continue;
        ++surface;
        const REAL *x = verts + 3 * v;
        REAL z = x[2] > zmin ? x[2] : zmin;
        REAL u = (REAL)p->fx * x[0] / z + (REAL)p->cx, vv = (REAL)p->fy * x[1] / z + (REAL)p->cy;
        inside += x[2] > (REAL)1 && u >= (REAL)0 && u <= (REAL)(p->width - 1) && vv >= (REAL)0 &&
                  vv <= (REAL)(p->height - 1);
    }
    ((REAL *)p->out_inside)[b] = (REAL)((double)inside / (surface > 0 ? surface : 1));
}

/* Streams [b0, b1). Returns 0, or -1 without memory. */
int FN(tf_confidence)(const TFConfProblem *p, int b0, int b1) {
    const size_t GG = (size_t)p->G * p->G;
    size_t reals = 6 * (size_t)p->V + 3 * (size_t)p->F + 4 * GG + 2 * (size_t)p->n + (size_t)p->F / sizeof(REAL) + 16;
    REAL *work = (REAL *)malloc(sizeof(REAL) * reals);
    if (!work) return -1;
    for (int b = b0; b < b1; ++b) FN(confidence_one)(p, b, work);
    free(work);
    return 0;
}
