/* The normalised face of a posed mesh without the z-buffer test (torchface.normalise.face.normalised_face_posed
 * with zbuffer=False, as template management makes it every frame): each canonical pixel's surface point and
 * normal interpolated from its triangle's corners, projected, the frame sampled there (bilinear, border), kept
 * where in front of the near plane, inside the frame, on a front-facing triangle and facing the camera enough,
 * and its sampled value finite (a NaN frame pixel is missing data), and the illumination removed (paper Eq. 19
 * inverted). The same algorithm as the torch code, which the tests compare against.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order): verts, normals (B, V, 3) camera frame (unit vertex normals); back (B, F) uint8; faces (F, 3),
 * face_index (M,), pixel_index (M,) int64; bary (M, 3); frames (B, C, H, W); illumination (B, 5) or NULL;
 * out image (B, C, G * G) and mask (B, G * G), written only at the face pixels (the caller zeroes them).
 */

/* How many pixels ahead normalised_face_one asks for the frame rows it will read. */
#define TF_FACE_PREFETCH 32

static void FN(normalised_face_one)(const TFFaceProblem *p, int b) {
    const int V = p->V, F = p->F, M = p->M, C = p->C, H = p->height, W = p->width;
    const size_t GG = (size_t)p->G * p->G, HW = (size_t)H * W;
    const REAL *verts = (const REAL *)p->verts + (size_t)b * V * 3, *nrm = (const REAL *)p->normals + (size_t)b * V * 3;
    const uint8_t *back = p->back + (size_t)b * F;
    const REAL *bary = (const REAL *)p->bary, *img = (const REAL *)p->frames + (size_t)b * C * HW;
    const REAL *light = p->illumination ? (const REAL *)p->illumination + 5 * (size_t)b : NULL;
    REAL *out = (REAL *)p->out_image + (size_t)b * C * GG, *out_mask = (REAL *)p->out_mask + (size_t)b * GG;
    const REAL fx = (REAL)p->fx, fy = (REAL)p->fy, cx = (REAL)p->cx, cy = (REAL)p->cy;
    const REAL near = (REAL)TF_NEAR_PLANE_MM, zmin = (REAL)p->depth_eps, min_cos = (REAL)p->min_facing_cos;
    for (int m = 0; m < M; ++m) {
#if defined(__GNUC__) || defined(__clang__)
        /* Ask the memory for the frame rows that the pixel TF_FACE_PREFETCH ahead will read (its surface point's
         * projection, computed as below; nothing where it is outside the frame): the layout's pixels project all
         * over the face, and a frame just handed over is in memory, not in the caches, so waiting for each
         * pixel's rows was most of the kernel's time. A prefetch only: no value depends on it. (Here, not in a
         * function of its own: GCC takes a function that only prefetches for one without effects and drops its
         * calls.) */
        if (m + TF_FACE_PREFETCH < M) {
            const int64_t *tri_a = p->faces + 3 * p->face_index[m + TF_FACE_PREFETCH];
            const REAL *w_a = bary + 3 * (size_t)(m + TF_FACE_PREFETCH);
            REAL Xa[3] = {0, 0, 0};
            for (int i = 0; i < 3; ++i)
                for (int c = 0; c < 3; ++c) Xa[c] += w_a[i] * verts[3 * tri_a[i] + c];
            REAL za = Xa[2] > zmin ? Xa[2] : zmin;
            REAL ua = fx * Xa[0] / za + cx, va = fy * Xa[1] / za + cy;
            if (ua >= (REAL)0 && ua <= (REAL)(W - 1) && va >= (REAL)0 && va <= (REAL)(H - 1)) {
                size_t ia = (size_t)(int)va * W + (size_t)(int)ua;
                for (int c = 0; c < C; ++c) {
                    __builtin_prefetch(img + c * HW + ia);
                    __builtin_prefetch(img + c * HW + ia + ((int)va + 1 < H ? W : 0));
                }
            }
        }
#endif
        const int64_t f = p->face_index[m], *tri = p->faces + 3 * f;
        const REAL *w = bary + 3 * (size_t)m;
        REAL X[3] = {0, 0, 0}, N[3] = {0, 0, 0};
        for (int i = 0; i < 3; ++i)
            for (int c = 0; c < 3; ++c) {
                X[c] += w[i] * verts[3 * tri[i] + c];
                N[c] += w[i] * nrm[3 * tri[i] + c];
            }
        REAL nn = (REAL)sqrt((double)(N[0] * N[0] + N[1] * N[1] + N[2] * N[2]));
        nn = nn > (REAL)1e-12 ? nn : (REAL)1e-12;
        for (int c = 0; c < 3; ++c) N[c] /= nn;
        REAL z = X[2] > zmin ? X[2] : zmin;
        REAL u = fx * X[0] / z + cx, v = fy * X[1] / z + cy;
        int inside = u >= (REAL)0 && u <= (REAL)(W - 1) && v >= (REAL)0 && v <= (REAL)(H - 1);
        REAL xn = (REAL)sqrt((double)(X[0] * X[0] + X[1] * X[1] + X[2] * X[2]));
        xn = xn > (REAL)1e-12 ? xn : (REAL)1e-12;
        REAL facing = -(N[0] * X[0] + N[1] * X[1] + N[2] * X[2]) / xn;
        int keep = X[2] > near && inside && !back[f] && facing >= min_cos;
        const int64_t at = p->pixel_index[m];
        out_mask[at] = keep ? (REAL)1 : (REAL)0;
        if (!keep) {
            for (int c = 0; c < C; ++c) out[c * GG + at] = (REAL)0;
            continue;
        }
        REAL gain = 1, bias = 0;
        if (light) {
            gain = (REAL)1 + light[0] + N[0] * light[2] + N[1] * light[3] + N[2] * light[4];
            gain = gain > (REAL)p->min_gain ? gain : (REAL)p->min_gain;
            bias = light[1];
        }
        /* the bilinear weights once for every channel (sample_border's arithmetic) */
        REAL xc = u < (REAL)0 ? (REAL)0 : (u > (REAL)(W - 1) ? (REAL)(W - 1) : u);
        REAL yc = v < (REAL)0 ? (REAL)0 : (v > (REAL)(H - 1) ? (REAL)(H - 1) : v);
        int x0 = (int)xc, y0 = (int)yc;
        REAL ax = xc - (REAL)x0, ay = yc - (REAL)y0, bx = (REAL)1 - ax, by = (REAL)1 - ay;
        int right = x0 + 1 < W, down = y0 + 1 < H;
        size_t i00 = (size_t)y0 * W + x0, i10 = down ? i00 + W : i00;
        int finite = 1;
        for (int c = 0; c < C; ++c) {
            const REAL *q = img + c * HW;
            REAL h0 = bx * q[i00] + ax * (right ? q[i00 + 1] : (REAL)0);
            REAL h1 = bx * q[i10] + ax * (right ? q[i10 + 1] : (REAL)0);
            REAL val = by * h0 + ay * (down ? h1 : (REAL)0);
            val = light ? (val - bias) / gain : val;
            finite = finite && isfinite(val);
            out[c * GG + at] = val;
        }
        if (!finite) { /* a NaN (missing) frame pixel: not seen, as outside the frame */
            out_mask[at] = (REAL)0;
            for (int c = 0; c < C; ++c) out[c * GG + at] = (REAL)0;
        }
    }
}

/* Streams [b0, b1). Returns 0. */
int FN(tf_normalised_face)(const TFFaceProblem *p, int b0, int b1) {
    for (int b = b0; b < b1; ++b) FN(normalised_face_one)(p, b);
    return 0;
}
