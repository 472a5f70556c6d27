/* A tracking step's gray crop pyramid (torchface.tracker.step.gray_crop_pyramid): each stream's window of its
 * colour frame turned gray (appearance.sampling.to_gray), then each level made from the one before by
 * appearance.sampling.pyr_down. The same arithmetic as the torch code, so the same values bit for bit: the gray
 * value is r * w_r, then g * w_g and b * w_b added by fused multiply-adds (addcmul_), and each pyramid pass is the
 * first tap's product, then the other five taps' fused multiply-adds in order (add_ with alpha), rows first; torch's
 * vectorised CPU kernels (AVX2, AVX-512, NEON) fuse these, as the tests check. A stream's levels are made one
 * after the other, so that a level is still in the cache when the next reads it; the torch code streamed the
 * whole batch's levels, their padded copies and their row passes through memory.
 *
 * Included twice by kernels.c: REAL is float or double and FN(name) appends the dtype to a name.
 * Layouts: frames (T, 3, H, W) with element strides (frame, channel, row, column); rows (B) int64, the frame of
 * each stream (NULL: stream b's is frame b); offsets (B, 2) int64 (x0, y0), each window inside its frame;
 * out: levels pointers, level l contiguous (B, 1, height >> l, width >> l), level 0 the gray window.
 */

/* pyr_down of one (h, w) image into (h / 2, w / 2) (h, w >= 3); tmp: w + 4 REALs, one row of the row pass with
 * its reflected border (F.pad(mode="reflect") of two pixels). */
static void FN(pyr_down_one)(const REAL *in, int h, int w, REAL *out, REAL *tmp) {
    const REAL t0 = (REAL)1 / 32, t1 = (REAL)5 / 32, t2 = (REAL)10 / 32; /* appearance.sampling._PYR_TAPS */
    const int h2 = h / 2, w2 = w / 2;
    for (int y = 0; y < h2; ++y) {
        const REAL *q[6];
        for (int k = 0; k < 6; ++k) {
            int i = 2 * y + k - 2;
            i = i < 0 ? -i : (i >= h ? 2 * (h - 1) - i : i);
            q[k] = in + (size_t)i * w;
        }
        const REAL *restrict q0 = q[0], *restrict q1 = q[1], *restrict q2 = q[2], *restrict q3 = q[3],
                            *restrict q4 = q[4], *restrict q5 = q[5];
        REAL *restrict row = tmp + 2;
        for (int x = 0; x < w; ++x) {
            REAL acc = q0[x] * t0;
            acc = TF_FMA(q1[x], t1, acc);
            acc = TF_FMA(q2[x], t2, acc);
            acc = TF_FMA(q3[x], t2, acc);
            acc = TF_FMA(q4[x], t1, acc);
            row[x] = TF_FMA(q5[x], t0, acc);
        }
        /* the reflected columns -2, -1, w, w + 1 are columns 2, 1, w - 2, w - 3: the same values */
        tmp[0] = tmp[4];
        tmp[1] = tmp[3];
        tmp[w + 2] = tmp[w];
        tmp[w + 3] = tmp[w - 1];
        REAL *restrict o = out + (size_t)y * w2;
        for (int x = 0; x < w2; ++x) {
            const REAL *c = tmp + 2 * x;
            REAL acc = c[0] * t0;
            acc = TF_FMA(c[1], t1, acc);
            acc = TF_FMA(c[2], t2, acc);
            acc = TF_FMA(c[3], t2, acc);
            acc = TF_FMA(c[4], t1, acc);
            o[x] = TF_FMA(c[5], t0, acc);
        }
    }
}

/* Streams [b0, b1); returns 0, or -1 when the row buffer could not be allocated. */
int FN(tf_gray_pyramid)(const TFPyramidProblem *p, int b0, int b1) {
    const int ch = p->height, cw = p->width;
    const REAL wr = (REAL)0.299, wg = (REAL)0.587, wb = (REAL)0.114; /* appearance.sampling._BT601 */
    REAL *tmp = (REAL *)malloc(sizeof(REAL) * ((size_t)cw + 4));
    if (!tmp) return -1;
    for (int b = b0; b < b1; ++b) {
        const int64_t frame = p->rows ? p->rows[b] : b, x0 = p->offsets[2 * b], y0 = p->offsets[2 * b + 1];
        const REAL *base = (const REAL *)p->frames + frame * p->stride_frame;
        REAL *level = (REAL *)p->out[0] + (size_t)b * ch * cw;
        for (int y = 0; y < ch; ++y) {
            const REAL *restrict r = base + (y0 + y) * p->stride_row + x0 * p->stride_col;
            const REAL *restrict g = r + p->stride_channel, *restrict bl = g + p->stride_channel;
            REAL *restrict o = level + (size_t)y * cw;
            if (p->stride_col == 1) {
                for (int x = 0; x < cw; ++x) o[x] = TF_FMA(bl[x], wb, TF_FMA(g[x], wg, r[x] * wr));
            } else {
                const int64_t s = p->stride_col;
                for (int x = 0; x < cw; ++x) o[x] = TF_FMA(bl[x * s], wb, TF_FMA(g[x * s], wg, r[x * s] * wr));
            }
        }
        int h = ch, w = cw;
        for (int l = 1; l < p->levels; ++l) {
            REAL *next = (REAL *)p->out[l] + (size_t)b * (h / 2) * (w / 2);
            FN(pyr_down_one)(level, h, w, next, tmp);
            level = next;
            h /= 2;
            w /= 2;
        }
    }
    free(tmp);
    return 0;
}
