/* One pyramid level's Levenberg-Marquardt solve of the tracker (paper Eq. 14-20), one stream at a time.
 *
 * The same algorithm as torchface.tracker.fast.solve_level (its torch implementation is the reference the tests
 * compare against): the residuals and local Jacobian of fast.linearise, IRLS weights at a robust scale
 * 1.4826 * median |r| (floored), a Gaussian prior on the animation units, box bounds on them (a unit at a bound
 * that the gradient pushes outward held out of the step, then the step clipped to the bounds), and step
 * acceptance with damping. Each stream iterates on its own until it has converged, which is what the torch code
 * does for a batch of one.
 *
 * Included twice by level_solver.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order, every array contiguous): image (B, h, w); points, normals (B, 3, N); basis (B, A, 3, N);
 * intensity, mask (B, N); neg_light_basis (B, L, N); offsets (B, 2); R (B, 3, 3); t (B, 3); alpha (B, A);
 * light (B, L); Jacobians (B, P, N) with P = 6 + A + L, columns d_omega (3), d_t (3), alpha (A), light (L);
 * alpha_prior (B, A) float64, the prior precision of each stream's animation units; alpha_lower, alpha_upper (B, A),
 * each stream's bounds on them.
 *
 * Inside, per-point quantities are rows of NP = N rounded up to a multiple of 8 values (the padding zero), and
 * every pass over the points that needs no gather is a plain loop over a row, which the compiler vectorises; only
 * the image sampling goes point by point.
 */

#define TF_PAD8(n) (((n) + 7) & ~7)
#define TF_PAD4(n) (((n) + 3) & ~3)
/* Rows of per-point temporaries of linearise: X or R^T g (3), R X (3), x, y, 1/Z, u, v, the five samples. */
#define TF_TMP_ROWS 16

typedef struct {
    REAL *J;        /* (P + 1, NP): the Jacobian, then the residuals as row P (the normal equations' last column) */
    REAL *r;        /* = J + P * NP: residuals (N), zero-padded */
    REAL *sampled;  /* (N) frame intensities at the points */
    uint8_t *valid; /* (N) */
    REAL *tmp;      /* (TF_TMP_ROWS, NP) */
} FN(Lin);

/* Bilinear interpolation of an (h, w) image at pixel (x, y) (pixel centres at integers), coordinates clamped to
 * the image first: grid_sample's mode="bilinear", padding_mode="border", align_corners=True. */
static inline REAL FN(sample_border)(const REAL *img, int h, int w, REAL x, REAL y) {
    REAL xmax = (REAL)(w - 1), ymax = (REAL)(h - 1);
    x = x < (REAL)0 ? (REAL)0 : (x > xmax ? xmax : x);
    y = y < (REAL)0 ? (REAL)0 : (y > ymax ? ymax : y);
    int x0 = (int)x, y0 = (int)y; /* floor: x, y >= 0 */
    REAL ax = x - (REAL)x0, ay = y - (REAL)y0, bx = (REAL)1 - ax, by = (REAL)1 - ay;
    /* a neighbour past the last row or column has weight 0 (x or y is clamped onto the last one) */
    const REAL *q0 = img + (size_t)y0 * w + x0, *q1 = y0 + 1 < h ? q0 + w : q0;
    int right = x0 + 1 < w;
    REAL h0 = bx * q0[0] + ax * (right ? q0[1] : (REAL)0);
    REAL h1 = bx * q1[0] + ax * (right ? q1[1] : (REAL)0);
    return by * h0 + ay * (y0 + 1 < h ? h1 : (REAL)0);
}

/* linearise's geometry, point by point (vectorised; the arrays are separate, as restrict says): R X, the
 * projection x = X_c / Z, y = Y_c / Z and pixel (u, v) in the crop, and inside (1 / 0): in front of the near plane,
 * inside the crop and facing the camera. (u, v) is the frame's pixel fx x + cx less the crop's offset (ox, oy),
 * integers: exact wherever the point lies right of and below the crop's corner, so that its pixel and fractions are
 * the whole frame's wherever the crop lies. (fx x + (cx - ox) rounded at the crop's scale, and the crop's size is
 * the batch's largest face's: a stream in a batch was tracked to the rounding apart from the same stream alone, and
 * in float32 an ICT Face Model track LOST on the background drifted up to 80 mm apart; test_other_models.py.) */
__attribute__((noinline)) static void FN(geometry)(int N, const REAL *restrict X0, const REAL *restrict X1, const REAL *restrict X2,
                         const REAL *restrict n0, const REAL *restrict n1, const REAL *restrict n2, const REAL *R,
                         const REAL *t, REAL fx, REAL fy, REAL cx, REAL cy, REAL ox, REAL oy, REAL umax, REAL vmax,
                         REAL *restrict Xr0, REAL *restrict Xr1, REAL *restrict Xr2, REAL *restrict xs, REAL *restrict ys,
                         REAL *restrict izs, REAL *restrict us, REAL *restrict vs, REAL *restrict inside) {
    const REAL r00 = R[0], r01 = R[1], r02 = R[2], r10 = R[3], r11 = R[4], r12 = R[5], r20 = R[6], r21 = R[7],
               r22 = R[8], t0 = t[0], t1 = t[1], t2 = t[2], near = (REAL)TF_NEAR_PLANE_MM;
    for (int n = 0; n < N; ++n) {
        REAL a0 = r00 * X0[n] + r01 * X1[n] + r02 * X2[n];
        REAL a1 = r10 * X0[n] + r11 * X1[n] + r12 * X2[n];
        REAL a2 = r20 * X0[n] + r21 * X1[n] + r22 * X2[n];
        Xr0[n] = a0;
        Xr1[n] = a1;
        Xr2[n] = a2;
        REAL c0 = a0 + t0, c1 = a1 + t1, Z = a2 + t2;
        REAL iz = (REAL)1 / (Z > near ? Z : near);
        REAL x = c0 * iz, y = c1 * iz;
        REAL u = (fx * x + cx) - ox, v = (fy * y + cy) - oy;
        xs[n] = x;
        ys[n] = y;
        izs[n] = iz;
        us[n] = u;
        vs[n] = v;
        REAL facing = (r00 * n0[n] + r01 * n1[n] + r02 * n2[n]) * c0 + (r10 * n0[n] + r11 * n1[n] + r12 * n2[n]) * c1
                      + (r20 * n0[n] + r21 * n1[n] + r22 * n2[n]) * Z;
        int in = (Z > near) & (u >= (REAL)0) & (u <= umax) & (v >= (REAL)0) & (v <= vmax) & (facing < (REAL)0);
        inside[n] = in ? (REAL)1 : (REAL)0;
    }
}

/* linearise's pose Jacobian columns, point by point (vectorised): g = dI/dX_cam from the central differences
 * (s1 - s3) / 2 and (s2 - s4) / 2 of the samples one pixel either side, d_omega = (R X) x g, d_t = g, and R^T g for
 * the animation units' columns; zero where ok is 0. */
__attribute__((noinline)) static void FN(gradients)(int N, const REAL *restrict ok, const REAL *restrict s1, const REAL *restrict s2,
                          const REAL *restrict s3, const REAL *restrict s4, const REAL *restrict izs,
                          const REAL *restrict xs, const REAL *restrict ys, const REAL *restrict Xr0,
                          const REAL *restrict Xr1, const REAL *restrict Xr2, const REAL *R, REAL hfx, REAL hfy,
                          REAL *restrict Jr0, REAL *restrict Jr1, REAL *restrict Jr2, REAL *restrict Jt0,
                          REAL *restrict Jt1, REAL *restrict Jt2, REAL *restrict gm0, REAL *restrict gm1,
                          REAL *restrict gm2) {
    const REAL r00 = R[0], r01 = R[1], r02 = R[2], r10 = R[3], r11 = R[4], r12 = R[5], r20 = R[6], r21 = R[7],
               r22 = R[8];
    for (int n = 0; n < N; ++n) {
        REAL m = ok[n], iz = izs[n];
        REAL gx = m != (REAL)0 ? (s1[n] - s3[n]) * hfx * iz : (REAL)0;
        REAL gy = m != (REAL)0 ? (s2[n] - s4[n]) * hfy * iz : (REAL)0;
        REAL gz = -(gx * xs[n] + gy * ys[n]);
        REAL a0 = Xr0[n], a1 = Xr1[n], a2 = Xr2[n];
        Jr0[n] = m != (REAL)0 ? a1 * gz - a2 * gy : (REAL)0;
        Jr1[n] = m != (REAL)0 ? a2 * gx - a0 * gz : (REAL)0;
        Jr2[n] = m != (REAL)0 ? a0 * gy - a1 * gx : (REAL)0;
        Jt0[n] = gx;
        Jt1[n] = gy;
        Jt2[n] = gz;
        gm0[n] = r00 * gx + r10 * gy + r20 * gz;
        gm1[n] = r01 * gx + r11 * gy + r21 * gz;
        gm2[n] = r02 * gx + r12 * gy + r22 * gz;
    }
}

/* fast.linearise for one stream: residuals, validity, sampled intensities and (with jac) the Jacobian, whose
 * columns are zero at the points that are not valid or whose residual is not finite (the solve leaves those out;
 * zero columns keep a non-finite value there out of the normal equations). */
static void FN(linearise)(const TFLevelProblem *p, int b, const REAL *R, const REAL *t, const REAL *alpha,
                          const REAL *light, int jac, FN(Lin) *out) {
    const int N = p->N, A = p->A, L = p->L, P = p->P, h = p->height, w = p->width;
    const size_t NP = (size_t)TF_PAD8(N);
    const REAL *img = (const REAL *)p->image + (size_t)b * h * w;
    const REAL *pts = (const REAL *)p->points + (size_t)b * 3 * N;
    const REAL *nrm = (const REAL *)p->normals + (size_t)b * 3 * N;
    const REAL *basis = (const REAL *)p->basis + (size_t)b * A * 3 * N;
    const REAL *tint = (const REAL *)p->intensity + (size_t)b * N;
    const REAL *nlb = (const REAL *)p->neg_light_basis + (size_t)b * L * N;
    const uint8_t *mask = p->mask + (size_t)b * N;
    const REAL *off = (const REAL *)p->offsets + 2 * b;
    const REAL fx = (REAL)p->fx, fy = (REAL)p->fy;
    const REAL cx = (REAL)p->cx, cy = (REAL)p->cy;
    const REAL hfx = (REAL)0.5 * fx, hfy = (REAL)0.5 * fy;
    const REAL umax = (REAL)(w - 1), vmax = (REAL)(h - 1);
    REAL *restrict X0 = out->tmp, *restrict X1 = X0 + NP, *restrict X2 = X1 + NP;
    REAL *restrict Xr0 = X2 + NP, *restrict Xr1 = Xr0 + NP, *restrict Xr2 = Xr1 + NP;
    REAL *restrict xs = Xr2 + NP, *restrict ys = xs + NP, *restrict izs = ys + NP, *restrict us = izs + NP;
    REAL *restrict vs = us + NP, *restrict s0 = vs + NP, *restrict s1 = s0 + NP, *restrict s2 = s1 + NP;
    REAL *restrict s3 = s2 + NP, *restrict s4 = s3 + NP;
    REAL *restrict r = out->r, *restrict sampled = out->sampled;
    uint8_t *restrict valid = out->valid;

    /* the points with the expression: X = points + sum_a alpha_a basis_a (head frame) */
    REAL *X[3] = {X0, X1, X2};
    for (int c = 0; c < 3; ++c) {
        REAL *restrict Xc = X[c];
        const REAL *restrict pc = pts + (size_t)c * N;
        for (int n = 0; n < N; ++n) Xc[n] = pc[n];
        for (int a = 0; a < A; ++a) {
            const REAL *restrict ba = basis + ((size_t)a * 3 + c) * N;
            const REAL al = alpha[a];
            for (int n = 0; n < N; ++n) Xc[n] += al * ba[n];
        }
    }
    /* turned and moved into the camera frame, projected; validity but for the sampled values (as 0 / 1 in s0,
     * a REAL row, for a vectorised loop) */
    FN(geometry)(N, X0, X1, X2, nrm, nrm + N, nrm + 2 * N, R, t, fx, fy, cx, cy, off[0], off[1], umax, vmax, Xr0, Xr1,
                 Xr2, xs, ys, izs, us, vs, s0);
    for (int n = 0; n < N; ++n) valid[n] = (uint8_t)((mask[n] != 0) & (s0[n] != (REAL)0));
    /* the image at the points (and one pixel either side along u and v), point by point */
    for (int n = 0; n < N; ++n) {
        REAL u = us[n], v = vs[n];
        if (!(isfinite(u) && isfinite(v))) {
            s0[n] = s1[n] = s2[n] = s3[n] = s4[n] = (REAL)NAN;
            continue;
        }
        if (jac && u >= (REAL)1 && u < (REAL)(w - 2) && v >= (REAL)1 && v < (REAL)(h - 2)) {
            int x0 = (int)u, y0 = (int)v; /* floor: u, v >= 1; x0 + 2 <= w - 1, y0 + 2 <= h - 1 */
            /* away from the border the five samples share their fractions: one 4x4 neighbourhood */
            REAL ax = u - (REAL)x0, ay = v - (REAL)y0, bx = (REAL)1 - ax, by = (REAL)1 - ay;
            const REAL *q0 = img + (size_t)y0 * w + x0, *qm = q0 - w, *q1 = q0 + w, *q2 = q1 + w;
            REAL h0m = bx * q0[-1] + ax * q0[0], h00 = bx * q0[0] + ax * q0[1], h0p = bx * q0[1] + ax * q0[2];
            REAL h1m = bx * q1[-1] + ax * q1[0], h10 = bx * q1[0] + ax * q1[1], h1p = bx * q1[1] + ax * q1[2];
            REAL hm0 = bx * qm[0] + ax * qm[1], h20 = bx * q2[0] + ax * q2[1];
            s0[n] = by * h00 + ay * h10;
            s1[n] = by * h0p + ay * h1p;
            s2[n] = by * h10 + ay * h20;
            s3[n] = by * h0m + ay * h1m;
            s4[n] = by * hm0 + ay * h00;
            continue;
        }
        {
            s0[n] = FN(sample_border)(img, h, w, u, v);
            if (jac) {
                s1[n] = FN(sample_border)(img, h, w, u + 1, v);
                s2[n] = FN(sample_border)(img, h, w, u, v + 1);
                s3[n] = FN(sample_border)(img, h, w, u - 1, v);
                s4[n] = FN(sample_border)(img, h, w, u, v - 1);
            }
        }
    }
    /* residuals r = I(x) - T + sum_l light_l (-B_l) (paper Eq. 19-20) */
    for (int n = 0; n < N; ++n) {
        sampled[n] = s0[n];
        r[n] = s0[n] - tint[n];
    }
    for (int l = 0; l < L; ++l) {
        const REAL *bl = nlb + (size_t)l * N, ll = light[l];
        for (int n = 0; n < N; ++n) r[n] += ll * bl[n];
    }
    for (size_t n = N; n < NP; ++n) r[n] = (REAL)0;
    if (!jac) return;
    /* Jacobian columns: d_omega = (R X) x g, d_t = g, alpha_a = g . (R B_a), light_l = -B_l, with g = dI/dX_cam;
     * zero where the point is left out (ok: 1 where valid and r finite, as a REAL for a vectorised select) */
    REAL *restrict ok = s0; /* s0 is no longer needed: it is in sampled */
    for (int n = 0; n < N; ++n) {
        /* a point whose gradient stencil touches a non-finite pixel is left out (as fast.linearise) */
        const REAL stencil = s1[n] + s2[n] + s3[n] + s4[n];
        valid[n] = (uint8_t)((valid[n] != 0) & (fabs(stencil) < (REAL)INFINITY));
        ok[n] = ((valid[n] != 0) & (fabs(r[n]) < (REAL)INFINITY)) ? (REAL)1 : (REAL)0;
    }
    REAL *J = out->J;
    REAL *restrict Jr0 = J, *restrict Jr1 = J + NP, *restrict Jr2 = J + 2 * NP;
    REAL *restrict Jt0 = J + 3 * NP, *restrict Jt1 = J + 4 * NP, *restrict Jt2 = J + 5 * NP;
    REAL *restrict gm0 = X0, *restrict gm1 = X1, *restrict gm2 = X2; /* R^T g, the gradient in the head frame */
    FN(gradients)(N, ok, s1, s2, s3, s4, izs, xs, ys, Xr0, Xr1, Xr2, R, hfx, hfy, Jr0, Jr1, Jr2, Jt0, Jt1, Jt2, gm0, gm1,
                  gm2);
    for (int a = 0; a < A; ++a) {
        const REAL *restrict b0 = basis + (size_t)a * 3 * N, *restrict b1 = b0 + N, *restrict b2 = b1 + N;
        REAL *restrict Ja = J + (size_t)(6 + a) * NP;
        for (int n = 0; n < N; ++n) Ja[n] = b0[n] * gm0[n] + b1[n] * gm1[n] + b2[n] * gm2[n];
    }
    for (int l = 0; l < L; ++l) {
        const REAL *restrict bl = nlb + (size_t)l * N;
        REAL *restrict Jl = J + (size_t)(6 + A + l) * NP;
        for (int n = 0; n < N; ++n) Jl[n] = ok[n] != (REAL)0 ? bl[n] : (REAL)0;
    }
    for (int i = 0; i < P; ++i)
        for (size_t n = N; n < NP; ++n) J[i * NP + n] = (REAL)0;
}

/* rho(r; s) and the IRLS weight of a robust loss (torchface.solver.robust.RobustLoss). */
static inline void FN(robust)(int kind, double c, double s, double r, double *rho, double *weight) {
    if (kind == TF_LOSS_NONE) {
        *rho = 0.5 * r * r;
        *weight = 1.0;
        return;
    }
    double u = r / s, u2 = u * u, ss = s * s;
    switch (kind) {
    case TF_LOSS_HUBER: {
        double a = fabs(u);
        *rho = ss * (a <= c ? 0.5 * u2 : c * ((a > c ? a : c) - 0.5 * c));
        *weight = c / (a > c ? a : c);
        break;
    }
    case TF_LOSS_CAUCHY:
        *rho = ss * 0.5 * c * c * log1p(u2 / (c * c));
        *weight = 1.0 / (1.0 + u2 / (c * c));
        break;
    case TF_LOSS_TUKEY: {
        double q = u2 / (c * c);
        q = q > 1.0 ? 1.0 : q;
        double m = 1.0 - q;
        *rho = ss * (c * c / 6.0) * (1.0 - m * m * m);
        *weight = m * m;
        break;
    }
    default: { /* Geman-McClure */
        double d = 1.0 + u2 / (c * c);
        *rho = ss * 0.5 * u2 / d;
        *weight = 1.0 / (d * d);
        break;
    }
    }
}

static int FN(cmp)(const void *a, const void *b) {
    REAL x = *(const REAL *)a, y = *(const REAL *)b;
    return (x > y) - (x < y);
}

/* The k-th smallest of x[0..n) (0-based; x is reordered): quickselect, exact. */
static REAL FN(select_kth)(REAL *x, int n, int k) {
    int lo = 0, hi = n - 1;
    while (hi - lo > 16) {
        int mid = lo + (hi - lo) / 2;
        /* median of three as the pivot */
        REAL a = x[lo], b = x[mid], c = x[hi];
        REAL pivot = a < b ? (b < c ? b : (a < c ? c : a)) : (a < c ? a : (b < c ? c : b));
        int i = lo, j = hi;
        while (i <= j) {
            while (x[i] < pivot) ++i;
            while (x[j] > pivot) --j;
            if (i <= j) {
                REAL tmp = x[i];
                x[i] = x[j];
                x[j] = tmp;
                ++i;
                --j;
            }
        }
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else return x[k];
    }
    qsort(x + lo, (size_t)(hi - lo + 1), sizeof(REAL), FN(cmp));
    return x[k];
}

/* fast.robust_scale_of: max(1.4826 * (lower) median |r| over valid points, floor); 1.4826 when none is valid. */
static double FN(robust_scale)(const REAL *r, const uint8_t *valid, int N, double floor_, REAL *scratch) {
    int k = 0;
    for (int n = 0; n < N; ++n)
        if (valid[n]) scratch[k++] = (REAL)fabs((double)r[n]);
    REAL med = k > 0 ? FN(select_kth)(scratch, k, (k - 1) / 2) : (REAL)1;
    REAL s = (REAL)TF_MAD_TO_SIGMA * med, fl = (REAL)floor_; /* in REAL, as the torch code's product */
    return (double)(s > fl ? s : fl);
}

/* Robust cost sum rho(r; s) over valid points (rho(0) = 0 elsewhere). */
static double FN(cost)(const REAL *r, const uint8_t *valid, int N, int kind, double c, double s) {
    double total = 0.0, rho, wgt;
    for (int n = 0; n < N; ++n) {
        if (!valid[n]) continue;
        FN(robust)(kind, c, s, (double)r[n], &rho, &wgt);
        total += rho;
    }
    return total;
}

/* In-place Cholesky of the (n, n) matrix a (lower triangle); 0 on success, else the failing column + 1. */
static int FN(cholesky)(double *a, int n) {
    for (int j = 0; j < n; ++j) {
        double d = a[j * n + j];
        for (int k = 0; k < j; ++k) d -= a[j * n + k] * a[j * n + k];
        if (!(d > 0.0)) return j + 1;
        d = sqrt(d);
        a[j * n + j] = d;
        for (int i = j + 1; i < n; ++i) {
            double v = a[i * n + j];
            for (int k = 0; k < j; ++k) v -= a[i * n + k] * a[j * n + k];
            a[i * n + j] = v / d;
        }
    }
    return 0;
}

/* Solve (L L^T) x = rhs in place. */
static void FN(cholesky_solve)(const double *l, int n, double *x) {
    for (int i = 0; i < n; ++i) {
        double v = x[i];
        for (int k = 0; k < i; ++k) v -= l[i * n + k] * x[k];
        x[i] = v / l[i * n + i];
    }
    for (int i = n - 1; i >= 0; --i) {
        double v = x[i];
        for (int k = i + 1; k < n; ++k) v -= l[k * n + i] * x[k];
        x[i] = v / l[i * n + i];
    }
}

/* R <- exp(hat(w)) R (so3.axis_angle_to_matrix: R = I + a K + b K^2, a = sin t / t, b = (1 - cos t) / t^2). */
static void FN(rotate)(REAL *R, const double *w) {
    double tt = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    double th = sqrt(tt > 1e-300 ? tt : 1e-300);
    double a = th < 1e-8 ? 1.0 - tt / 6.0 : sin(th) / th;
    double hs = 0.5 * th, sh = hs < 1e-8 ? 1.0 - hs * hs / 6.0 : sin(hs) / hs;
    double bb = 0.5 * sh * sh;
    double K[9] = {0, -w[2], w[1], w[2], 0, -w[0], -w[1], w[0], 0};
    double E[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            double k2 = K[3 * i] * K[j] + K[3 * i + 1] * K[3 + j] + K[3 * i + 2] * K[6 + j];
            E[3 * i + j] = (i == j ? 1.0 : 0.0) + a * K[3 * i + j] + bb * k2;
        }
    REAL D[9];
    for (int i = 0; i < 9; ++i) D[i] = (REAL)E[i];
    REAL out[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) out[3 * i + j] = D[3 * i] * R[j] + D[3 * i + 1] * R[3 + j] + D[3 * i + 2] * R[6 + j];
    memcpy(R, out, sizeof(out));
}

/* The workspace of one stream's solve, in REALs (see solve_one for how it is cut up). */
static size_t FN(workspace_reals)(int P, int N) {
    size_t NP = (size_t)TF_PAD8(N);
    return (size_t)(P + 1) * NP + (size_t)TF_PAD4(P) * NP + (3 + TF_TMP_ROWS) * NP + (size_t)N / sizeof(REAL) + 16;
}

/* The sum of eight partial sums, in double. */
static inline double FN(lanes)(const REAL *x) {
    return (((double)x[0] + x[4]) + ((double)x[1] + x[5])) + (((double)x[2] + x[6]) + ((double)x[3] + x[7]));
}

/* Normal equations of the weighted, linearised problem at lin: H = J^T W J (+ prior), grad = J^T W r (+ prior).
 * Jw = W J (P rounded up to 4 rows; rows of fixed parameters and the padding rows zero); every entry is then a
 * dot product of a row of Jw with a row of lin->J (whose row P is r), four rows of Jw against two of J at a
 * time, in eight lanes of partial sums (vectorised; eight independent sums per lane). The Jacobian's columns are
 * zero at the points left out, whose weights are zero too. */
static void FN(normal_equations)(const TFLevelProblem *p, const FN(Lin) *lin, const REAL *wgt, const double *prior,
                                 const double *d_alpha, REAL *Jw, double *H, double *grad) {
    const int P = p->P, A = p->A, P4 = TF_PAD4(P);
    const size_t NP = (size_t)TF_PAD8(p->N);
    const uint8_t *freep = p->free;
    const REAL *J = lin->J;
    for (int i = 0; i < P4; ++i) {
        REAL *wi = Jw + (size_t)i * NP;
        if (i >= P || !freep[i]) {
            memset(wi, 0, sizeof(REAL) * NP);
            continue;
        }
        const REAL *ji = J + (size_t)i * NP;
        for (size_t n = 0; n < NP; ++n) wi[n] = ji[n] * wgt[n];
    }
    double G[TF_MAX_P + 4][TF_MAX_P + 1]; /* G[i][j] = Jw_i . J_j for j <= i, and j = P (the residuals) */
    for (int i0 = 0; i0 < P4; i0 += 4) {
        const REAL *w0 = Jw + (size_t)i0 * NP, *w1 = w0 + NP, *w2 = w1 + NP, *w3 = w2 + NP;
        int cols[TF_MAX_P + 2], nc = 0;
        for (int j = 0; j <= i0 + 3 && j < P; ++j) cols[nc++] = j;
        cols[nc++] = P;
        if (nc % 2) cols[nc] = P; /* pairs: an odd one out is paired with the residual row again */
        for (int q = 0; q < nc; q += 2) {
            const REAL *c = J + (size_t)cols[q] * NP, *d = J + (size_t)cols[q + 1] * NP;
            REAL a0[8] = {0}, a1[8] = {0}, a2[8] = {0}, a3[8] = {0};
            REAL e0[8] = {0}, e1[8] = {0}, e2[8] = {0}, e3[8] = {0};
            for (size_t n = 0; n < NP; n += 8)
                for (int k = 0; k < 8; ++k) {
                    REAL cv = c[n + k], dv = d[n + k];
                    REAL x0 = w0[n + k], x1 = w1[n + k], x2 = w2[n + k], x3 = w3[n + k];
                    a0[k] = TF_FMA(x0, cv, a0[k]);
                    a1[k] = TF_FMA(x1, cv, a1[k]);
                    a2[k] = TF_FMA(x2, cv, a2[k]);
                    a3[k] = TF_FMA(x3, cv, a3[k]);
                    e0[k] = TF_FMA(x0, dv, e0[k]);
                    e1[k] = TF_FMA(x1, dv, e1[k]);
                    e2[k] = TF_FMA(x2, dv, e2[k]);
                    e3[k] = TF_FMA(x3, dv, e3[k]);
                }
            int j = cols[q], k = cols[q + 1];
            G[i0][j] = FN(lanes)(a0);
            G[i0 + 1][j] = FN(lanes)(a1);
            G[i0 + 2][j] = FN(lanes)(a2);
            G[i0 + 3][j] = FN(lanes)(a3);
            G[i0][k] = FN(lanes)(e0);
            G[i0 + 1][k] = FN(lanes)(e1);
            G[i0 + 2][k] = FN(lanes)(e2);
            G[i0 + 3][k] = FN(lanes)(e3);
        }
    }
    for (int i = 0; i < P; ++i) {
        for (int j = 0; j <= i; ++j) H[i * P + j] = H[j * P + i] = freep[i] && freep[j] ? G[i][j] : 0.0;
        H[i * P + i] += prior[i];
        grad[i] = G[i][P];
    }
    for (int a = 0; a < A; ++a) grad[6 + a] += prior[6 + a] * d_alpha[a];
}

/* One stream's solve (fast.solve_level for a batch of one); work: FN(workspace_reals) REALs. */
static void FN(solve_one)(const TFLevelProblem *p, int b, REAL *work) {
    const int N = p->N, A = p->A, L = p->L, P = p->P;
    REAL *R = (REAL *)p->R + 9 * (size_t)b, *t = (REAL *)p->t + 3 * (size_t)b;
    REAL *alpha = (REAL *)p->alpha + (size_t)A * b, *light = (REAL *)p->light + (size_t)L * b;
    const REAL *lo = (const REAL *)p->alpha_lower + (size_t)A * b, *hi = (const REAL *)p->alpha_upper + (size_t)A * b;
    const REAL *amean = p->alpha_mean ? (const REAL *)p->alpha_mean + (size_t)A * b : NULL;
    const int kind = p->loss_kind[b];
    const double c = p->loss_c[b];

    /* workspace */
    const size_t NP = (size_t)TF_PAD8(N);
    REAL *J = work, *r = J + (size_t)P * NP, *Jw = r + NP, *sampled = Jw + (size_t)TF_PAD4(P) * NP;
    REAL *wgt = sampled + NP, *scratch = wgt + NP, *tmp = scratch + NP;
    uint8_t *valid = (uint8_t *)(tmp + (size_t)TF_TMP_ROWS * NP);
    FN(Lin) lin = {J, r, sampled, valid, tmp};

    double H[TF_MAX_P * TF_MAX_P], grad[TF_MAX_P], Hd[TF_MAX_P * TF_MAX_P], delta[TF_MAX_P];
    double bestH[TF_MAX_P * TF_MAX_P], best_grad[TF_MAX_P];
    double prior[TF_MAX_P], d_alpha[TF_MAX_P];
    REAL bestR[9], bestt[3], best_alpha[TF_MAX_P], best_light[TF_MAX_P];
    double best_cost = 0.0, best_s = 1.0;
    int have_best = 0, all_free = 1;
    for (int i = 0; i < P; ++i) {
        prior[i] = (i >= 6 && i < 6 + A && p->free[i]) ? p->alpha_prior[(size_t)b * A + (i - 6)] : 0.0;
        all_free &= p->free[i] != 0;
    }
    double lam = p->damping;
    int64_t iters = 0;
    int active = 1, finite = 1;

    for (int it = 0; it < p->iterations; ++it) {
        if (it == 0 && p->start_r) { /* the linearisation handed on by a pass that ended at this estimate */
            const REAL *sr = (const REAL *)p->start_r + (size_t)b * N, *sJ = (const REAL *)p->start_J + (size_t)b * P * N;
            const uint8_t *sv = p->start_valid + (size_t)b * N;
            for (int n = 0; n < N; ++n) {
                r[n] = sr[n];
                valid[n] = sv[n];
            }
            for (int i = 0; i < P; ++i) {
                REAL *Ji = J + (size_t)i * NP;
                const REAL *si = sJ + (size_t)i * N;
                for (int n = 0; n < N; ++n) Ji[n] = valid[n] && isfinite(r[n]) ? si[n] : (REAL)0;
                for (size_t n = N; n < NP; ++n) Ji[n] = (REAL)0;
            }
        } else {
            FN(linearise)(p, b, R, t, alpha, light, 1, &lin);
        }
        int n_valid = 0;
        for (int n = 0; n < N; ++n) {
            valid[n] = valid[n] && isfinite(r[n]);
            if (!valid[n]) r[n] = (REAL)0;
            n_valid += valid[n];
        }
        for (size_t n = N; n < NP; ++n) r[n] = (REAL)0;
        double prior_cost = 0.0;
        for (int a = 0; a < A; ++a) {
            d_alpha[a] = amean ? (double)(alpha[a] - amean[a]) : (double)alpha[a];
            prior_cost += 0.5 * prior[6 + a] * d_alpha[a] * d_alpha[a];
        }
        int accept = 1;
        if (have_best) {
            double judged = FN(cost)(r, valid, N, kind, c, best_s) + prior_cost;
            accept = judged <= best_cost && isfinite(judged);
        }
        double s = FN(robust_scale)(r, valid, N, p->scale_floor, scratch);
        double cost = prior_cost, rho, wt;
        for (size_t n = N; n < NP; ++n) wgt[n] = (REAL)0;
        for (int n = 0; n < N; ++n) {
            if (!valid[n]) {
                wgt[n] = (REAL)0;
                continue;
            }
            FN(robust)(kind, c, s, (double)r[n], &rho, &wt);
            cost += rho;
            wgt[n] = (REAL)wt;
        }
        FN(normal_equations)(p, &lin, wgt, prior, d_alpha, Jw, H, grad);
        if (accept) { /* always the first point; later, a step that did not raise the cost */
            if (have_best) lam = lam / 3.0 > 1e-6 ? lam / 3.0 : 1e-6;
            memcpy(bestR, R, sizeof(bestR));
            memcpy(bestt, t, sizeof(bestt));
            memcpy(best_alpha, alpha, sizeof(REAL) * A);
            memcpy(best_light, light, sizeof(REAL) * L);
            memcpy(bestH, H, sizeof(double) * P * P);
            memcpy(best_grad, grad, sizeof(double) * P);
            best_cost = cost;
            best_s = s;
            have_best = 1;
        } else { /* undo the rejected step */
            memcpy(R, bestR, sizeof(bestR));
            memcpy(t, bestt, sizeof(bestt));
            memcpy(alpha, best_alpha, sizeof(REAL) * A);
            memcpy(light, best_light, sizeof(REAL) * L);
            memcpy(H, bestH, sizeof(double) * P * P);
            memcpy(grad, best_grad, sizeof(double) * P);
            cost = best_cost;
            s = best_s;
            lam *= 10.0;
        }

        double dmax = 1e-12;
        for (int i = 0; i < P; ++i) dmax = H[i * P + i] > dmax ? H[i * P + i] : dmax;
        double floor_ = 1e-6 * dmax;
        memcpy(Hd, H, sizeof(double) * P * P);
        for (int i = 0; i < P; ++i) {
            Hd[i * P + i] += (H[i * P + i] + floor_) * lam;
            if (!all_free && !p->free[i]) Hd[i * P + i] += 1.0;
        }
        /* The active set: an animation unit at a bound (within TF_BOUND_MARGIN of its range) that the gradient
         * pushes outward (-grad points past the bound) is held there, out of the system (its row and column of
         * the damped matrix zero, 1 on the diagonal, 0 on the right-hand side: its step is 0), so that the
         * others' step is the one with that unit fixed; a unit that the step then takes past a bound is clipped
         * below. */
        uint8_t held[TF_MAX_P];
        for (int i = 0; i < P; ++i) held[i] = 0;
        for (int a = 0; a < A; ++a) {
            const int i = 6 + a;
            /* no margin for an infinite range (a bound at -inf or inf): an infinite one put the other bound's inner
             * edge at -inf or inf, holding every unit the gradient pushed towards it */
            const REAL span = hi[a] - lo[a];
            const REAL margin = isfinite(span) ? span * (REAL)TF_BOUND_MARGIN : (REAL)0;
            const REAL lo_in = lo[a] + margin, hi_in = hi[a] - margin;
            const int outward = (alpha[a] <= lo_in && grad[i] > 0.0) || (alpha[a] >= hi_in && grad[i] < 0.0);
            held[i] = (uint8_t)(p->free[i] && outward);
            if (!held[i]) continue;
            for (int j = 0; j < P; ++j) Hd[i * P + j] = Hd[j * P + i] = 0.0;
            Hd[i * P + i] = 1.0;
        }
        int info = FN(cholesky)(Hd, P);
        int good = info == 0;
        if (good) {
            for (int i = 0; i < P; ++i) delta[i] = held[i] ? 0.0 : grad[i];
            FN(cholesky_solve)(Hd, P, delta);
            double sum = 0.0;
            for (int i = 0; i < P; ++i) {
                delta[i] = -delta[i];
                sum += delta[i];
            }
            good = isfinite(sum) && n_valid >= P;
        }
        finite = finite && (good || !active);
        int step = active && good;
        for (int i = 0; i < P; ++i) {
            if (!step || !p->free[i] || held[i]) delta[i] = 0.0;
            /* the increment as the torch code applies it: rounded to REAL */
            delta[i] = (double)(REAL)delta[i];
        }
        FN(rotate)(R, delta);
        for (int i = 0; i < 3; ++i) t[i] += (REAL)delta[3 + i];
        for (int a = 0; a < A; ++a) {
            REAL v = alpha[a] + (REAL)delta[6 + a];
            v = v < lo[a] ? lo[a] : v;
            v = v > hi[a] ? hi[a] : v;
            /* the convergence tests read the change made: a unit the data pushes against its bound moves by 0 */
            delta[6 + a] = (double)(v - alpha[a]);
            alpha[a] = v;
        }
        for (int l = 0; l < L; ++l) light[l] += (REAL)delta[6 + A + l];
        iters += active;
        int small = 1;
        for (int i = 0; i < P; ++i) small &= fabs(delta[i]) < p->step_tolerance[i];
        active = active && good && !small;
        if (p->function_tolerance > 0) {
            double pred = 0.0;
            for (int i = 0; i < P; ++i) {
                double hd = 0.0;
                for (int j = 0; j < P; ++j) hd += H[i * P + j] * delta[j];
                pred += delta[i] * (grad[i] + 0.5 * hd);
            }
            pred = -pred;
            /* a negative prediction (a step that clipping at the bounds took away from the model's minimum, or
             * rounding) does not stop the level: the model is not trusted there (the iteration cap still ends it) */
            active = active && !(pred >= 0.0 && pred < p->function_tolerance * cost);
        }
        if (!active) break;
    }

    REAL *out_r = (REAL *)p->out_residual + (size_t)b * N;
    REAL *out_sampled = (REAL *)p->out_sampled + (size_t)b * N;
    uint8_t *out_valid = p->out_valid + (size_t)b * N;
    p->out_iterations[b] = iters;
    p->out_converged[b] = (uint8_t)(!active && finite);
    p->out_finite[b] = (uint8_t)finite;
    if (!p->final_check) { /* the last linearisation of the loop, masked */
        if (p->iterations > 0) {
            memcpy(out_r, r, sizeof(REAL) * N);
            memcpy(out_valid, valid, N);
        } else {
            memset(out_r, 0, sizeof(REAL) * N);
            memset(out_valid, 0, N);
        }
        memset(out_sampled, 0, sizeof(REAL) * N);
        return;
    }
    int keep = p->out_J != NULL;
    FN(linearise)(p, b, R, t, alpha, light, keep, &lin);
    if (have_best) { /* the last step is kept only where it did not raise the cost */
        double cost = FN(cost)(r, valid, N, kind, c, best_s); /* NaN where a valid point's residual is */
        for (int a = 0; a < A; ++a) {
            double d = amean ? (double)(alpha[a] - amean[a]) : (double)alpha[a];
            cost += 0.5 * prior[6 + a] * d * d;
        }
        int accept = cost <= best_cost && isfinite(cost);
        if (!accept) {
            memcpy(R, bestR, sizeof(bestR));
            memcpy(t, bestt, sizeof(bestt));
            memcpy(alpha, best_alpha, sizeof(REAL) * A);
            memcpy(light, best_light, sizeof(REAL) * L);
            FN(linearise)(p, b, R, t, alpha, light, keep, &lin);
        }
    }
    memcpy(out_r, r, sizeof(REAL) * N);
    memcpy(out_sampled, sampled, sizeof(REAL) * N);
    memcpy(out_valid, valid, N);
    if (keep)
        for (int i = 0; i < P; ++i) memcpy((REAL *)p->out_J + ((size_t)b * P + i) * N, J + (size_t)i * NP, sizeof(REAL) * N);
}

/* Streams [b0, b1) of the problem; returns 0, or -1 when the workspace could not be allocated. The workspace is
 * kept per thread and grows as needed: a fresh one per call was mapped and zeroed by the kernel every time. */
int FN(tf_solve_level)(const TFLevelProblem *p, int b0, int b1) {
    size_t bytes = FN(workspace_reals)(p->P, p->N) * sizeof(REAL);
    if (bytes > tf_workspace_size) {
        void *grown = realloc(tf_workspace, bytes);
        if (!grown) return -1;
        tf_workspace = grown;
        tf_workspace_size = bytes;
    }
    for (int b = b0; b < b1; ++b) FN(solve_one)(p, b, (REAL *)tf_workspace);
    return 0;
}
