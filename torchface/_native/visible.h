/* Which surface points the camera sees (torchface.rendering.visibility.points_visible with a Coverage), point by
 * point with the torch code's arithmetic, so the same answer: the point's nearest pixel centre
 * (floor(X / Z * fx + cx + 0.5), likewise v), the triangle and facing the coverage has there, and the depth of that
 * triangle at the pixel centre by the rasterizer's arithmetic (Coverage.covered_depths: e = c_3 a + (c_7 b + c_11),
 * depth = c_12 / e) against the point's own depth.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts: points (B, N, 3); point_faces (B, N) int64, or (N) when faces_batched is 0; pix_to_face (B, H, W)
 * int64 and facing (B, H, W) int8, contiguous; coefficients (13, num_columns), the column of triangle f of
 * sample b being (b + batch_offset) F + f; ray_a (>= W), ray_b (>= H); out (B, N) uint8 (bool).
 */

int FN(tf_visible)(const TFVisibleProblem *p, int b0, int b1) {
    const int N = p->N, H = p->H, W = p->W;
    const REAL fx = (REAL)p->fx, fy = (REAL)p->fy, cx = (REAL)p->cx, cy = (REAL)p->cy, near = (REAL)p->near;
    const REAL keep = (REAL)p->keep, half = (REAL)0.5, wmax = (REAL)(W - 1), hmax = (REAL)(H - 1);
    const REAL *c = (const REAL *)p->coefficients, *ray_a = (const REAL *)p->ray_a, *ray_b = (const REAL *)p->ray_b;
    const size_t M = (size_t)p->num_columns;
    for (int b = b0; b < b1; ++b) {
        const REAL *pts = (const REAL *)p->points + (size_t)b * N * 3;
        const int64_t *own = p->point_faces + (p->faces_batched ? (size_t)b * N : 0);
        const int64_t *faces = p->pix_to_face + (size_t)b * H * W;
        const int8_t *facing = p->facing + (size_t)b * H * W;
        uint8_t *out = p->out + (size_t)b * N;
        const int64_t first = ((int64_t)b + p->batch_offset) * p->F;
        for (int n = 0; n < N; ++n) {
            const REAL X = pts[3 * n], Y = pts[3 * n + 1], Z = pts[3 * n + 2];
            const int front = Z > near;
            const REAL zs = front ? Z : (REAL)1;
            const REAL x = X / zs, y = Y / zs;
            const REAL xf = x * fx, yf = y * fy;
            const REAL u = xf + cx, v = yf + cy;
            const REAL col = (REAL)floor((double)(u + half)), row = (REAL)floor((double)(v + half));
            const int inside = front & (col >= (REAL)0) & (col <= wmax) & (row >= (REAL)0) & (row <= hmax);
            if (!inside) {
                out[n] = 0;
                continue;
            }
            const int64_t ci = (int64_t)col, ri = (int64_t)row, pix = ri * W + ci;
            const int64_t face = faces[pix];
            if (facing[pix] != 1) {
                out[n] = 0;
                continue;
            }
            int visible = face == own[n];
            if (!visible) {
                REAL depth = (REAL)INFINITY;
                if (face >= 0) {
                    const size_t k = (size_t)(first + face);
                    const REAL t1 = c[7 * M + k] * ray_b[ri], t2 = t1 + c[11 * M + k], t3 = c[3 * M + k] * ray_a[ci];
                    const REAL e = t3 + t2;
                    depth = c[12 * M + k] / e;
                }
                const REAL limit = Z * keep;
                visible = depth >= limit;
            }
            out[n] = (uint8_t)visible;
        }
    }
    return 0;
}
