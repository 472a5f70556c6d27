/* The rasterizer's coverage (torchface.rendering.rasterizer._cover): which triangle each pixel centre sees, by
 * the same ray test with the same arithmetic as the torch code, so the same triangles bit for bit. Candidate
 * pixels are every pixel of each triangle's bounding box (the torch code's path for small boxes; its scanline
 * spans for large ones keep a superset of the covered pixels, so they decide the same); the z-buffer keeps the
 * nearest hit and, on an exact depth tie, the lower face index.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts: coefficients (13, B F) (rasterizer._face_coefficients: row j + 4 i, function j times ray component i;
 * row 12 k = n . v0; oriented); tri (B F, 3, 3) the triangles' corners (corner, xyz) in the camera frame; usable
 * (B F) uint8, the rows that may be tested; ray_a (W), ray_b (H); out: pix_to_face (B, H, W) int64 and facing
 * (B, H, W) int8 from front (B F) uint8; depth (B, H, W) REAL workspace.
 * Each row's pixel box is rasterizer._project_corners' and _cover's (its corners projected through fx, fy, cx, cy,
 * widened by margin; the whole image where a corner is at or behind the near plane, or projects beyond
 * max_projected or to a non-finite position; not tested where every corner is at or behind it), with the same
 * operations in the same order, so the same boxes: made here, not by some 70 small torch operations of the caller.
 * Windows (sizes not NULL): stream b's image is only the top-left sizes[2 b] x sizes[2 b + 1] (height x width) of
 * the H x W one, written at element starts[b] of the outputs (C order, that size): the same triangles at its
 * pixels as without them, the rest of the image neither tested nor written (rasterizer._cover's windows).
 */

/* Streams [b0, b1). Returns 0. */
int FN(tf_coverage)(const TFCoverProblem *p, int b0, int b1) {
    const int F = p->F;
    const size_t N = (size_t)p->B * F;
    const REAL *c = (const REAL *)p->coefficients, *ray_a = (const REAL *)p->ray_a, *ray_b = (const REAL *)p->ray_b;
    const REAL near = (REAL)p->near, fx = (REAL)p->fx, fy = (REAL)p->fy, cx = (REAL)p->cx, cy = (REAL)p->cy;
    const REAL margin = (REAL)p->margin, max_projected = (REAL)p->max_projected;
    const REAL *tri = (const REAL *)p->tri;
    for (int b = b0; b < b1; ++b) {
        const int64_t H = p->sizes ? p->sizes[2 * (size_t)b] : p->H, W = p->sizes ? p->sizes[2 * (size_t)b + 1] : p->W;
        const size_t HW = (size_t)H * W, start = p->sizes ? (size_t)p->starts[b] : (size_t)b * HW;
        int64_t *face = p->pix_to_face + start;
        int8_t *facing = p->facing + start;
        REAL *depth = (REAL *)p->depth + start;
        for (size_t i = 0; i < HW; ++i) {
            face[i] = -1;
            depth[i] = (REAL)INFINITY;
        }
        for (int f = 0; f < F; ++f) {
            const size_t r = (size_t)b * F + f;
            if (!p->usable[r]) continue;
            /* The box, as _project_corners and _cover compute it (the canvas's H x W: a window clamps it below). */
            const REAL *t = tri + 9 * r;
            REAL u[3], v[3];
            int crosses = 0, behind = 1, far = 0;
            for (int i = 0; i < 3; ++i) {
                const REAL z = t[3 * i + 2];
                const int at_or_behind = z <= near;
                const REAL z_safe = at_or_behind ? (REAL)1 : z;
                u[i] = t[3 * i] / z_safe * fx + cx;
                v[i] = t[3 * i + 1] / z_safe * fy + cy;
                /* beyond the limit or not finite (NaN fails <=) */
                far |= !((u[i] < 0 ? -u[i] : u[i]) <= max_projected && (v[i] < 0 ? -v[i] : v[i]) <= max_projected);
                crosses |= at_or_behind;
                behind &= at_or_behind;
            }
            if (behind) continue;
            int64_t x_first = 0, x_last = p->W - 1, y_first = 0, y_last = p->H - 1;
            if (!(crosses || far)) {  /* finite corners: amin / amax in any order */
                const REAL u_min = u[0] < u[1] ? (u[0] < u[2] ? u[0] : u[2]) : (u[1] < u[2] ? u[1] : u[2]);
                const REAL u_max = u[0] > u[1] ? (u[0] > u[2] ? u[0] : u[2]) : (u[1] > u[2] ? u[1] : u[2]);
                const REAL v_min = v[0] < v[1] ? (v[0] < v[2] ? v[0] : v[2]) : (v[1] < v[2] ? v[1] : v[2]);
                const REAL v_max = v[0] > v[1] ? (v[0] > v[2] ? v[0] : v[2]) : (v[1] > v[2] ? v[1] : v[2]);
                const REAL u_lo = u_min - margin, u_hi = u_max + margin, v_lo = v_min - margin, v_hi = v_max + margin;
                x_first = (int64_t)ceil((double)u_lo);  /* (in double: the same integers as torch's ceil, floor) */
                x_last = (int64_t)floor((double)u_hi);
                y_first = (int64_t)ceil((double)v_lo);
                y_last = (int64_t)floor((double)v_hi);
            }
            const REAL a0 = c[0 * N + r], a1 = c[1 * N + r], a2 = c[2 * N + r], a3 = c[3 * N + r];
            const REAL b0c = c[4 * N + r], b1c = c[5 * N + r], b2c = c[6 * N + r], b3c = c[7 * N + r];
            const REAL c0 = c[8 * N + r], c1 = c[9 * N + r], c2 = c[10 * N + r], c3 = c[11 * N + r];
            const REAL k = c[12 * N + r];
            /* clamped into the image (a box wholly outside it is empty; the caller's skip rows were those) */
            const int64_t x0 = x_first > 0 ? x_first : 0, y0 = y_first > 0 ? y_first : 0;
            const int64_t x1 = x_last < W - 1 ? x_last : W - 1, y1 = y_last < H - 1 ? y_last : H - 1;
            for (int64_t y = y0; y <= y1; ++y) {
                const REAL by = ray_b[y];
                /* the per-row part (c[4:8] b + c[8:12]), as both torch paths compute it */
                const REAL r0 = b0c * by + c0, r1 = b1c * by + c1, r2 = b2c * by + c2, r3 = b3c * by + c3;
                for (int64_t x = x0; x <= x1; ++x) {
                    const REAL ax = ray_a[x];
                    REAL e0 = a0 * ax + r0, e1 = a1 * ax + r1, e2 = a2 * ax + r2, e3 = a3 * ax + r3;
                    if (!(e0 >= (REAL)0 && e1 >= (REAL)0 && e2 >= (REAL)0 && e3 > (REAL)0)) continue;
                    REAL z = k / e3;
                    if (!(z > near)) continue;
                    size_t i = (size_t)y * W + x;
                    if (z < depth[i] || (z == depth[i] && f < face[i])) {
                        depth[i] = z;
                        face[i] = f;
                    }
                }
            }
        }
        for (size_t i = 0; i < HW; ++i)
            facing[i] = face[i] < 0 ? 0 : (p->front[(size_t)b * F + face[i]] ? 1 : -1);
    }
    return 0;
}

/* The rasterizer's per-triangle coefficients (torchface.rendering.rasterizer._face_coefficients) of rows [r0, r1)
 * of tri (N, 3, 3) (corner, xyz): the cross products c0 = v1 x e12, c1 = v2 x e20, c2 = v0 x e01 and
 * n = e01 x e02 (component i: a_{i+1} b_{i+2} - a_{i+2} b_{i+1}), k = n . v0, all times sign(n . v0), in table
 * (13, N) row j + 4 i (function j, component i), then k; front (N) uint8 (k < 0) and usable (N) uint8 (finite,
 * |n| > eps max_edge^2, |k| > eps |n| |v0|), with the torch code's operations in its order (a sum of three
 * terms as (x + y) + z), so the same values bit for bit. A row with a non-finite corner is all zeros and not
 * usable (the torch code zeroes its corners); a row with a coordinate beyond `large` is not computed and flagged
 * in scaled (N) uint8: the torch code scales those (the caller runs it instead). */
static inline void FN(tf_cross)(const REAL *a, const REAL *b, REAL *out) {
    for (int i = 0; i < 3; ++i) out[i] = a[(i + 1) % 3] * b[(i + 2) % 3] - a[(i + 2) % 3] * b[(i + 1) % 3];
}

int FN(tf_face_coefficients)(const TFCoeffProblem *p, int r0, int r1) {
    const size_t N = (size_t)p->N;
    const REAL *tri = (const REAL *)p->tri, large = (REAL)p->large, eps = (REAL)p->eps;
    REAL *out = (REAL *)p->coefficients;
    for (int r = r0; r < r1; ++r) {
        const REAL *t = tri + 9 * (size_t)r;
        int finite = 1;
        REAL largest = 0;
        for (int i = 0; i < 9; ++i) {
            finite &= isfinite(t[i]) != 0;
            REAL a = t[i] < 0 ? -t[i] : t[i];
            largest = a > largest ? a : largest;
        }
        p->scaled[r] = 0;
        if (!finite) {
            for (int j = 0; j < 13; ++j) out[(size_t)j * N + r] = (REAL)0;
            p->front[r] = 0;
            p->usable[r] = 0;
            continue;
        }
        if (largest > large) {
            p->scaled[r] = 1;
            continue;
        }
        const REAL *v0 = t, *v1 = t + 3, *v2 = t + 6;
        REAL e01[3], e02[3], e12[3], e20[3], cr[4][3];
        for (int i = 0; i < 3; ++i) {
            e01[i] = v1[i] - v0[i];
            e02[i] = v2[i] - v0[i];
            e12[i] = v2[i] - v1[i];
            e20[i] = v0[i] - v2[i];
        }
        FN(tf_cross)(v1, e12, cr[0]);
        FN(tf_cross)(v2, e20, cr[1]);
        FN(tf_cross)(v0, e01, cr[2]);
        FN(tf_cross)(e01, e02, cr[3]);
        const REAL *n = cr[3];
        const REAL k = (n[0] * v0[0] + n[1] * v0[1]) + n[2] * v0[2];
        const int front = k < (REAL)0;
        const REAL sign = front ? (REAL)-1 : (REAL)1;
        const REAL n_norm = (REAL)sqrt((double)((n[0] * n[0] + n[1] * n[1]) + n[2] * n[2]));
        const REAL *edges[3] = {e01, e02, e12};
        REAL max_edge_sq = 0;
        for (int e = 0; e < 3; ++e) {
            const REAL *x = edges[e];
            REAL sq = (x[0] * x[0] + x[1] * x[1]) + x[2] * x[2];
            max_edge_sq = e == 0 || sq > max_edge_sq ? sq : max_edge_sq;
        }
        const REAL v0_norm = (REAL)sqrt((double)((v0[0] * v0[0] + v0[1] * v0[1]) + v0[2] * v0[2]));
        const REAL k_abs = k < (REAL)0 ? -k : k;
        p->front[r] = (uint8_t)front;
        p->usable[r] = (uint8_t)(n_norm > eps * max_edge_sq && k_abs > eps * n_norm * v0_norm);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 4; ++j) out[(size_t)(j + 4 * i) * N + r] = cr[j][i] * sign;
        out[12 * N + r] = k * sign;
    }
    return 0;
}
