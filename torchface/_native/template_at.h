/* A template from its compact form (torchface.template.points.template_at): at each point, given by its triangle
 * and barycentric coordinates, the person's neutral position, the expression basis and the unit normal, each the
 * barycentric combination of the triangle's corners (Eq. 3-9), written both point-first (Template's fields) and
 * point-last (Template.point_last, what the fast solver reads). The same arithmetic as the torch code, which the
 * tests compare against.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts (C order): verts, vertex_normals (B, V, 3); anim_units (A, V, 3); faces (F, 3) int64; face_index (B, N)
 * int64 (a negative index counts as 0); bary (B, N, 3); out: points (B, N, 3), basis (B, N, 3, A), normals
 * (B, N, 3), points_t (B, 3, N), normals_t (B, 3, N), basis_t (B, A, 3, N); with out_rows (B) int64 (not NULL),
 * stream b's values go to row out_rows[b] of outputs of any number of rows (a tracker state's templates, written in
 * place).
 */

int FN(tf_template_at)(const TFTemplateProblem *p, int b0, int b1) {
    const int V = p->V, A = p->A, N = p->N;
    const REAL *au = (const REAL *)p->anim_units;
    for (int b = b0; b < b1; ++b) {
        const REAL *verts = (const REAL *)p->verts + (size_t)b * V * 3;
        const REAL *vn = (const REAL *)p->vertex_normals + (size_t)b * V * 3;
        const int64_t *fi = p->face_index + (size_t)b * N;
        const REAL *bary = (const REAL *)p->bary + (size_t)b * N * 3;
        const size_t o = p->out_rows ? (size_t)p->out_rows[b] : (size_t)b;
        REAL *pts = (REAL *)p->out_points + o * N * 3, *nrm = (REAL *)p->out_normals + o * N * 3;
        REAL *basis = (REAL *)p->out_basis + o * N * 3 * A;
        REAL *pts_t = (REAL *)p->out_points_t + o * 3 * N, *nrm_t = (REAL *)p->out_normals_t + o * 3 * N;
        REAL *basis_t = (REAL *)p->out_basis_t + o * A * 3 * N;
        for (int n = 0; n < N; ++n) {
            const int64_t f = fi[n] < 0 ? 0 : fi[n];
            const int64_t *tri = p->faces + 3 * f;
            const REAL *w = bary + 3 * (size_t)n;
            REAL P[3], Nn[3];
            for (int c = 0; c < 3; ++c) {
                /* (w0 x0 + w1 x1) + w2 x2, the products first: (vals * w).sum(2) */
                P[c] = w[0] * verts[3 * tri[0] + c] + w[1] * verts[3 * tri[1] + c];
                P[c] = P[c] + w[2] * verts[3 * tri[2] + c];
                Nn[c] = w[0] * vn[3 * tri[0] + c] + w[1] * vn[3 * tri[1] + c];
                Nn[c] = Nn[c] + w[2] * vn[3 * tri[2] + c];
            }
            REAL norm = (REAL)sqrt((double)(Nn[0] * Nn[0] + Nn[1] * Nn[1] + Nn[2] * Nn[2]));
            norm = norm > (REAL)1e-12 ? norm : (REAL)1e-12;
            for (int c = 0; c < 3; ++c) {
                REAL u = Nn[c] / norm;
                pts[3 * (size_t)n + c] = P[c];
                nrm[3 * (size_t)n + c] = u;
                pts_t[(size_t)c * N + n] = P[c];
                nrm_t[(size_t)c * N + n] = u;
                for (int a = 0; a < A; ++a) {
                    const REAL *ua = au + (size_t)a * V * 3;
                    REAL v = w[0] * ua[3 * tri[0] + c] + w[1] * ua[3 * tri[1] + c];
                    v = v + w[2] * ua[3 * tri[2] + c];
                    basis[((size_t)n * 3 + c) * A + a] = v;
                    basis_t[((size_t)a * 3 + c) * N + n] = v;
                }
            }
        }
    }
    return 0;
}
