/* torchface's native kernels: the fast solver's level solve (level_solver.h) and the dissimilarity's smoothing
 * and patch tracking (dissimilarity.h), the normalised face without the z-buffer (normalised_face.h), and the
 * three together as template management's per-frame confidence (confidence.h), the rasterizer's coverage
 * (coverage.h), a template's candidate pixels (select_pixels.h), template management's per-frame decisions
 * (management.h), a template from its compact form (template_at.h), the top-k of its candidates
 * (top_pixels.h), a tracking step's gray crop pyramid (gray_pyramid.h) and which surface points the camera sees
 * (visible.h). Compiled at first use by torchface._native (the C compiler of the
 * machine, no other dependency) and called through ctypes; float and double variants. */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define TF_NEAR_PLANE_MM 1.0 /* torchface.conventions.NEAR_PLANE_MM */
#define TF_MAD_TO_SIGMA 1.482602218505602
#define TF_MAX_P 64
#define TF_BOUND_MARGIN 1e-6 /* torchface.tracker.fast.BOUND_MARGIN */
enum { TF_LOSS_NONE = 0, TF_LOSS_HUBER = 1, TF_LOSS_CAUCHY = 2, TF_LOSS_TUKEY = 3, TF_LOSS_GEMAN_MCCLURE = 4 };

/* Mirrored by torchface._native.LevelProblem (ctypes): keep the two in the same order. Arrays of the dtype are
 * void pointers; see level_solver.h for their shapes. */
typedef struct {
    int B, N, A, L, P, height, width, iterations, final_check;
    double fx, fy, cx, cy, scale_floor, damping, function_tolerance;
    const void *image, *points, *normals, *basis, *intensity, *neg_light_basis, *offsets;
    const uint8_t *mask, *free;
    void *R, *t, *alpha, *light;
    const void *alpha_lower, *alpha_upper, *alpha_mean;
    const double *alpha_prior, *loss_c, *step_tolerance;
    const int32_t *loss_kind;
    const void *start_r, *start_J;
    const uint8_t *start_valid;
    void *out_residual, *out_sampled, *out_J;
    uint8_t *out_valid, *out_converged, *out_finite;
    int64_t *out_iterations;
} TFLevelProblem;

/* Mirrored by torchface._native.LKProblem (ctypes): keep the two in the same order; see dissimilarity.h. */
typedef struct {
    int B, C, G, K, n, radius, iterations, project_out_bias, has_max_displacement;
    double eps, tolerance, max_displacement;
    const void *normalised, *mask, *kernel, *grid, *templ, *sd, *ref_weight, *ref_total;
    void *out_gray, *out_p, *out_support;
    uint8_t *out_converged, *out_valid;
    int radius_border; /* tf_reference_patches: the border (n: the patch size, iterations: the separation) */
} TFLKProblem;

/* Mirrored by torchface._native.FaceProblem (ctypes): keep the two in the same order; see normalised_face.h. */
typedef struct {
    int B, V, F, M, C, G, height, width;
    double fx, fy, cx, cy, min_facing_cos, min_gain, depth_eps;
    const void *verts, *normals;
    const uint8_t *back;
    const int64_t *faces, *face_index, *pixel_index;
    const void *bary, *frames, *illumination;
    void *out_image, *out_mask;
} TFFaceProblem;

/* Mirrored by torchface._native.ConfProblem (ctypes): keep the two in the same order; see confidence.h. */
typedef struct {
    int B, V, F, M, C, G, height, width, K, n, radius, iterations, project_out_bias, has_max_displacement,
        min_patches, S, A, E;
    double fx, fy, cx, cy, min_facing_cos, min_gain, depth_eps, eps, tolerance, max_displacement,
        max_displacement_or_inf, min_support, min_present_fraction, d0, trim_fraction;
    const void *mean, *shape_units, *anim_units;
    const int64_t *faces;
    const uint8_t *surface;
    const void *shape, *alpha, *R, *t, *ypr;
    const int64_t *face_index, *pixel_index;
    const void *bary, *frames, *illumination;
    const int64_t *rows;
    const void *mosaic_ypr;
    const uint8_t *used;
    const void *kernel;
    const uint8_t *patch_valid;
    const void *grid, *templ, *sd, *ref_weight, *ref_total;
    int64_t *out_entry;
    void *out_image, *out_mask, *out_p, *out_support;
    uint8_t *out_converged, *out_valid, *out_present;
    void *out_dissimilarity, *out_confidence, *out_inside;
} TFConfProblem;

/* Mirrored by torchface._native.CoverProblem (ctypes): keep the two in the same order; see coverage.h. */
typedef struct {
    int B, F, H, W;
    double near, fx, fy, cx, cy, margin, max_projected;
    const void *coefficients, *ray_a, *ray_b, *tri;
    const uint8_t *usable, *front;
    int64_t *pix_to_face;
    int8_t *facing;
    void *depth;
    const int64_t *sizes, *starts;
} TFCoverProblem;

/* Mirrored by torchface._native.CoeffProblem (ctypes): keep the two in the same order; see coverage.h. */
typedef struct {
    int N;
    double large, eps;
    const void *tri;
    void *coefficients;
    uint8_t *front, *usable, *scaled;
} TFCoeffProblem;

/* Mirrored by torchface._native.SelectProblem (ctypes): keep the two in the same order; see select_pixels.h. */
typedef struct {
    int B, H, W, V, F, erode, full_w, batch_offset, num_columns;
    double gradient_threshold, min_facing_cos, facing_margin, fx, fy, cx, cy;
    const void *gray;
    const int64_t *pix_to_face;
    const int8_t *facing;
    const void *coefficients, *ray_a, *ray_b, *verts, *normals;
    const int64_t *faces;
    const void *offsets;
    const float *keys;
    float *out_score;
} TFSelectProblem;

/* Mirrored by torchface._native.ManageProblem (ctypes): keep the two in the same order; see management.h. */
typedef struct {
    int B, E, lost_after, lost_after_very_low, recovery_every, max_entries;
    double switch_margin_deg, reference_radius_deg, clean_radius_deg, min_inside_fraction, confidence_threshold,
        very_low_confidence, recover_confidence, yaw_bin_deg, pitch_bin_deg, bin_centre_fraction, entry_reach,
        add_confidence;
    const void *mosaic_ypr;
    const int64_t *bins;
    const uint8_t *used;
    const void *ypr;
    const int64_t *entry;
    const void *confidence, *inside;
    const uint8_t *failed, *lost;
    const int64_t *low_count, *very_low_count, *since;
    int64_t *out_entry;
    uint8_t *out_near, *out_confident;
    int64_t *out_low_count, *out_very_low_count;
    uint8_t *out_lost, *out_reverted;
    int64_t *out_since;
    uint8_t *out_attempt;
    int64_t *out_bins;
    uint8_t *out_add;
} TFManageProblem;

/* Mirrored by torchface._native.CleanProblem (ctypes): keep the two in the same order; see management.h. */
typedef struct {
    int B, N, share_double;
    double scale_floor, min_scale, c, fraction;
    const void *r;
    const uint8_t *valid, *near;
    uint8_t *out_clean;
} TFCleanProblem;

/* Mirrored by torchface._native.TemplateProblem (ctypes): keep the two in the same order; see template_at.h. */
typedef struct {
    int B, V, A, N;
    const void *verts, *vertex_normals, *anim_units;
    const int64_t *faces, *face_index;
    const void *bary;
    void *out_points, *out_basis, *out_normals, *out_points_t, *out_normals_t, *out_basis_t;
    const int64_t *out_rows;
} TFTemplateProblem;

/* Mirrored by torchface._native.TopProblem (ctypes): keep the two in the same order; see top_pixels.h. */
typedef struct {
    int B;
    int64_t N, k;
    const void *score;
    int64_t *out_index;
    void *out_value;
} TFTopProblem;

/* Mirrored by torchface._native.PickProblem (ctypes): keep the two in the same order; see top_pixels.h. */
typedef struct {
    int B, H, W, F, batch_offset;
    int64_t k, num_columns;
    const int64_t *index;
    const float *value;
    const int64_t *pix_to_face;
    const void *gray, *coefficients, *ray_a, *ray_b;
    int64_t *out_face;
    void *out_bary, *out_intensity;
    uint8_t *out_valid;
} TFPickProblem;

/* Mirrored by torchface._native.PyramidProblem (ctypes): keep the two in the same order; see gray_pyramid.h. */
typedef struct {
    int B, height, width, levels;
    int64_t stride_frame, stride_channel, stride_row, stride_col;
    const void *frames;
    const int64_t *rows, *offsets;
    void *const *out;
} TFPyramidProblem;

/* Mirrored by torchface._native.VisibleProblem (ctypes): keep the two in the same order; see visible.h. */
typedef struct {
    int B, N, H, W, F, batch_offset, faces_batched;
    int64_t num_columns;
    double fx, fy, cx, cy, near, keep;
    const void *points;
    const int64_t *point_faces, *pix_to_face;
    const int8_t *facing;
    const void *coefficients, *ray_a, *ray_b;
    uint8_t *out;
} TFVisibleProblem;

#define TF_EPS(T) (sizeof(T) == sizeof(float) ? (double)FLT_EPSILON : DBL_EPSILON)

/* Each thread's workspace (see tf_solve_level), kept between calls. */
static _Thread_local void *tf_workspace = NULL;
static _Thread_local size_t tf_workspace_size = 0;

int tf_abi_version(void) { return 20; }

/* A kernel's streams on OpenMP's threads (at most threads of them), where built with -fopenmp: the runtime torch's
 * own threads use (torchface._native.run_chunks). The streams go in chunks of about batch / (8 threads) (at least
 * one), each handed to the next thread that is free: streams differ in cost (a level solve's iterations and
 * points), and on a busy machine one thread may be held up; with one fixed half of the batch per thread, the other
 * then waited for it. Each stream's result does not depend on the chunks. */
typedef int (*tf_kernel_fn)(const void *, int, int);
#ifdef _OPENMP
#include <omp.h>
int tf_has_openmp(void) { return 1; }
int tf_parallel(tf_kernel_fn fn, const void *problem, int batch, int threads) {
    int status = 0;
    const int grain = threads > 0 && batch / (8 * threads) > 1 ? batch / (8 * threads) : 1;
    const int chunks = (batch + grain - 1) / grain;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1) reduction(| : status)
    for (int c = 0; c < chunks; ++c) {
        const int b0 = c * grain, b1 = batch - b0 > grain ? b0 + grain : batch;
        status |= fn(problem, b0, b1) != 0;
    }
    return status;
}
#else
int tf_has_openmp(void) { return 0; }
int tf_parallel(tf_kernel_fn fn, const void *problem, int batch, int threads) {
    (void)threads;
    return fn(problem, 0, batch);
}
#endif
int tf_max_parameters(void) { return TF_MAX_P; }

#define REAL float
#define TF_FMA fmaf
#define FN(name) name##_f32
#include "level_solver.h"
#include "dissimilarity.h"
#include "normalised_face.h"
#include "confidence.h"
#include "coverage.h"
#include "select_pixels.h"
#include "management.h"
#include "template_at.h"
#include "top_pixels.h"
#include "gray_pyramid.h"
#include "visible.h"
#undef REAL
#undef TF_FMA
#undef FN

#define REAL double
#define TF_FMA fma
#define FN(name) name##_f64
#include "level_solver.h"
#include "dissimilarity.h"
#include "normalised_face.h"
#include "confidence.h"
#include "coverage.h"
#include "select_pixels.h"
#include "management.h"
#include "template_at.h"
#include "top_pixels.h"
#include "gray_pyramid.h"
#include "visible.h"
#undef REAL
#undef TF_FMA
#undef FN
