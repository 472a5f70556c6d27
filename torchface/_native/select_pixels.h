/* A template's candidate pixels and their selection scores (torchface.template.points.select_pixels_posed up to
 * its top-k): pixels seen on a front-facing triangle whose erosion keeps them, with a gray-level gradient of at
 * least the threshold, and, on the triangles whose bound does not settle it, whose interpolated normal faces the
 * pixel's ray enough; the score is the pixel's selection key there, -1 elsewhere. The same tests with the same
 * arithmetic as the torch code, which the tests compare against.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order): gray (B, H, W) the windows; pix_to_face (B, H, W) int64 and facing (B, H, W) int8 their
 * coverage; coefficients (13, N) the coverage's ray-test table (stream b's triangle f is column
 * (b + batch_offset) F + f), ray_a (W), ray_b (H); verts, normals (B, V, 3) the posed mesh (camera frame, unit
 * normals); faces (F, 3) int64; offsets (B, 2) the windows' top-left pixel (REAL, full image of the level);
 * keys (full_h full_w) float32 the level's selection keys; out: score (B, H W) float32.
 */

/* Streams [b0, b1). Returns 0, or -1 without memory.
 * Two passes over a window: the row erosion of the coverage mask (each row's mask made into a row buffer), then,
 * per pixel, the column erosion and the tests in the torch code's order, each only where the previous ones passed,
 * and the score (one pass per test, each over the whole window, took twice the time). */
int FN(tf_select_pixels)(const TFSelectProblem *p, int b0, int b1) {
    const int H = p->H, W = p->W, V = p->V, F = p->F, r = p->erode;
    const size_t HW = (size_t)H * W, N = (size_t)p->num_columns;
    uint8_t *rows = (uint8_t *)malloc(HW + (size_t)W + (size_t)F);
    if (!rows) return -1;
    uint8_t *mask = rows + HW, *unsure = mask + W;
    const REAL *coef = (const REAL *)p->coefficients, *ray_a = (const REAL *)p->ray_a, *ray_b = (const REAL *)p->ray_b;
    const REAL threshold = (REAL)p->gradient_threshold, min_cos = (REAL)p->min_facing_cos;
    const REAL bound_ok = (REAL)((p->min_facing_cos > 0 ? p->min_facing_cos : 0.0) + p->facing_margin);
    for (int b = b0; b < b1; ++b) {
        const REAL *g = (const REAL *)p->gray + (size_t)b * HW;
        const int64_t *face = p->pix_to_face + (size_t)b * HW;
        const int8_t *facing = p->facing + (size_t)b * HW;
        const REAL *verts = (const REAL *)p->verts + (size_t)b * V * 3, *nrm = (const REAL *)p->normals + (size_t)b * V * 3;
        const REAL *off = (const REAL *)p->offsets + 2 * (size_t)b;
        float *score = p->out_score + (size_t)b * HW;
        /* each triangle's lower bound on the facing cosine: the smallest -n_i . r_j over its corners' unit normals
         * and unit directions from the camera; a triangle whose bound clears the threshold passes whole */
        for (int f = 0; f < F; ++f) {
            REAL rays[3][3];
            for (int j = 0; j < 3; ++j) {
                const REAL *x = verts + 3 * p->faces[3 * f + j];
                REAL nn = (REAL)sqrt((double)(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]));
                nn = nn > (REAL)1e-12 ? nn : (REAL)1e-12;
                for (int c = 0; c < 3; ++c) rays[j][c] = x[c] / nn;
            }
            REAL mx = -(REAL)INFINITY;
            int nan = 0;
            for (int i = 0; i < 3; ++i) {
                const REAL *n = nrm + 3 * p->faces[3 * f + i];
                for (int j = 0; j < 3; ++j) {
                    REAL d = n[0] * rays[j][0] + n[1] * rays[j][1] + n[2] * rays[j][2];
                    nan |= d != d;
                    mx = d > mx ? d : mx;
                }
            }
            unsure[f] = (uint8_t)(nan || !(-mx >= bound_ok));
        }
        /* _erode along the rows: a pixel of the mask (seen on a front-facing triangle) stays where its r
         * neighbours either side along the row are set (outside the image counts as set) */
        for (int y = 0; y < H; ++y) {
            const size_t row = (size_t)y * W;
            for (int x = 0; x < W; ++x) mask[x] = (uint8_t)(face[row + x] >= 0 && facing[row + x] > 0);
            for (int x = 0; x < W; ++x) {
                uint8_t v = mask[x];
                for (int d = 1; d <= r && v; ++d) {
                    if (x - d >= 0) v &= mask[x - d];
                    if (x + d < W) v &= mask[x + d];
                }
                rows[row + x] = v;
            }
        }
        const int64_t ox = (int64_t)off[0], oy = (int64_t)off[1];
        for (int y = 0; y < H; ++y)
            for (int x = 0; x < W; ++x) {
                const size_t i = (size_t)y * W + x;
                score[i] = -1.0f;
                /* _erode along the columns */
                uint8_t v = rows[i];
                for (int d = 1; d <= r && v; ++d) {
                    if (y - d >= 0) v &= rows[i - (size_t)d * W];
                    if (y + d < H) v &= rows[i + (size_t)d * W];
                }
                if (!v) continue;
                /* the gradient magnitude (image_with_gradients: central differences, one-sided at the border) */
                REAL gu = x == 0 ? g[i + 1] - g[i] : (x == W - 1 ? g[i] - g[i - 1] : g[i + 1] - g[i - 1]);
                REAL gv = y == 0 ? g[i + W] - g[i] : (y == H - 1 ? g[i] - g[i - W] : g[i + W] - g[i - W]);
                gu *= (REAL)0.5;
                gv *= (REAL)0.5;
                REAL mag = (REAL)sqrt((double)(gu * gu + gv * gv));
                if (!(mag >= threshold && isfinite(mag) && isfinite(g[i]))) continue;  /* non-finite: no point */
                if (unsure[face[i]]) {
                    /* the interpolated normal against the pixel's ray */
                    const int64_t f = face[i], col = ((int64_t)b + p->batch_offset) * F + f;
                    REAL a = ray_a[x], bb = ray_b[y];
                    REAL e0 = coef[0 * N + col] * a + (coef[4 * N + col] * bb + coef[8 * N + col]);
                    REAL e1 = coef[1 * N + col] * a + (coef[5 * N + col] * bb + coef[9 * N + col]);
                    REAL e2 = coef[2 * N + col] * a + (coef[6 * N + col] * bb + coef[10 * N + col]);
                    REAL sum = e0 + e1 + e2;
                    REAL w[3] = {e0 / sum, e1 / sum, e2 / sum};
                    REAL n[3] = {0, 0, 0};
                    for (int k = 0; k < 3; ++k) {
                        const REAL *nk = nrm + 3 * p->faces[3 * f + k];
                        for (int c = 0; c < 3; ++c) n[c] += w[k] * nk[c];
                    }
                    REAL ray[3] = {((REAL)x + off[0] - (REAL)p->cx) / (REAL)p->fx,
                                   ((REAL)y + off[1] - (REAL)p->cy) / (REAL)p->fy, (REAL)1};
                    REAL nn = (REAL)sqrt((double)(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]));
                    REAL rn = (REAL)sqrt((double)(ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2]));
                    nn = nn > (REAL)1e-12 ? nn : (REAL)1e-12;
                    rn = rn > (REAL)1e-12 ? rn : (REAL)1e-12;
                    REAL c = -((n[0] / nn) * (ray[0] / rn) + (n[1] / nn) * (ray[1] / rn) + (n[2] / nn) * (ray[2] / rn));
                    if (!(c >= min_cos)) continue;
                }
                /* the score: the whole image's key at the window's pixel */
                score[i] = p->keys[(size_t)(oy + y) * p->full_w + (size_t)(ox + x)];
            }
    }
    free(rows);
    return 0;
}
