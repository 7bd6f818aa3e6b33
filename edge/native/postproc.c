/* The pipeline's per-frame work in C, everything around the decoder and autoencoder calls: the frame's
 * features, 6D -> rotation, FK hung from the head, foot locks, two-bone limb IK, the plausibility
 * score around the autoencoder (SSI 3.1, 3.2.1), the SSI outlier test (3.2.2) and the look-ahead ring.
 *
 * The live frame is four calls (edge.pipeline.CompiledFrame): ep_frame_inputs, ep_frame_poses,
 * ep_frame_costs (after the autoencoder: the selection cost and the SSI decision), ep_emit; they read the pipeline's buffers through one core_context.
 * ep_forward, ep_post and ep_foot_locks are the same stages on given rows (tests/test_native.py holds
 * each to its numpy reference). Arguments come as the structs below, mirrored in edge/native/__init__.py;
 * the rotation and matrix helpers are quat.h, named for their edge.quat functions.
 *
 * Each function is the loop form of a numpy reference in edge/ (named in its comment) and is tested
 * against it (tests/test_native.py). Python's per-call overhead, not arithmetic, is what the numpy
 * versions pay at this size (a few hundred 3x3 products per frame), so one call here replaces a few
 * hundred numpy calls. Arrays are row-major float64 unless marked float; a *_stride argument is the
 * distance between rows in elements, 0 when every row shares one value.
 *
 * Built with -ffp-contract=off so no multiply-add is fused: results then match numpy, and x86 and
 * ARM match each other.
 *
 * The per-sample loops (FK, limb IK, the plausibility score) run LANES samples side by side: each
 * lane_* helper does one scalar operation for every lane, which the compiler turns into SIMD (2
 * doubles on NEON and SSE2, 8 with AVX-512), and independent samples hide each other's latency. Each
 * lane does exactly the one-sample arithmetic in the same order, and vector sqrt and division round
 * like scalar ones, so the results are bit for bit those of a plain loop over samples. A short last
 * block repeats its last sample in the spare lanes and stores only the real ones.
 */
#include <math.h>
#include <stdint.h>

#include "quat.h"       /* the rotation and matrix helpers, named for their edge.quat functions */


/* ------------------------------------------------------------------ samples side by side (LANES) */

#define LANES 8
#define MAX_JOINTS 32                   /* the lane functions keep a whole skeleton on the stack */
#define EACH for (int l = 0; l < LANES; l++)
typedef double lane[LANES];             /* one value for each of LANES samples */

/* The largest skeleton the lane functions take (edge.native checks edge.skeleton against it). */
int ep_max_joints(void) { return MAX_JOINTS; }
#define MAX_FEATURES 128
/* Facts shared with the Python side, defined there once and compiled in by edge.native.build as -D flags
 * (edge.native.shared_constants): edge.physics' FLOOR_ANKLE / FLOOR_TOE (the lowest an ankle and a toe
 * joint may go, m above the floor), ANKLE_HEIGHT and edge.skeleton's TOE_HEIGHT (the joints' rest
 * heights), LOCK_SNAP_M (FootLock's floor snap) and SUPPORT_FULL_M / SUPPORT_NONE_M (the support band). */
#if !defined(FLOOR_ANKLE) || !defined(FLOOR_TOE) || !defined(TOE_HEIGHT) || !defined(ANKLE_HEIGHT) || \
    !defined(LOCK_SNAP) || !defined(SUPPORT_FULL) || !defined(SUPPORT_NONE) || !defined(ELBOW_MIN_M) || \
    !defined(SHOULDER_PUSH_MAX_M) || !defined(REACH_START) || !defined(SHOULDER_REACH_MAX_M)
#error "build postproc.c with edge.native.build: it defines the constants shared with edge.physics"
#endif

/* dst[k][l] = src[row_l * stride + k] for k < n: row_l is r0 + l, or the block's last real row in a
 * spare lane (nl real rows). stride 0 gives every lane the same values. */
/* rows r0..r0+nl of an array (rows `stride` apart, 0: shared) into the lanes; a short block repeats its last row */
static inline void gather(lane *dst, int n, const double *src, int64_t stride, int r0, int nl) {
    EACH {
        const double *s = src + (int64_t)(r0 + (l < nl ? l : nl - 1)) * stride;
        for (int k = 0; k < n; k++) dst[k][l] = s[k];
    }
}

/* the inverse of gather, for the nl real lanes */
static inline void scatter(lane *src, int n, double *dst, int64_t stride, int r0, int nl) {
    for (int l = 0; l < nl; l++) {
        double *d = dst + (int64_t)(r0 + l) * stride;
        for (int k = 0; k < n; k++) d[k] = src[k][l];
    }
}

/* The lane forms of quat.h's helpers: the same arithmetic for every lane. */
/* dst = src */
static inline void lane_copy(lane *restrict dst, lane *restrict src, int n) {
    for (int k = 0; k < n; k++) EACH dst[k][l] = src[k][l];
}

/* a b, 3x3 */
/* mat3_mul: a @ b */
static inline void lane_matmul3(lane *restrict a, lane *restrict b, lane *restrict out) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++)
            EACH out[i * 3 + k][l] = a[i * 3 + 0][l] * b[0 * 3 + k][l] + a[i * 3 + 1][l] * b[1 * 3 + k][l] +
                                     a[i * 3 + 2][l] * b[2 * 3 + k][l];
}

/* a^T b, 3x3 */
/* a.T @ b (np.swapaxes(a, -1, -2) @ b) */
static inline void lane_matmul3_tn(lane *restrict a, lane *restrict b, lane *restrict out) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++)
            EACH out[i * 3 + k][l] = a[0 * 3 + i][l] * b[0 * 3 + k][l] + a[1 * 3 + i][l] * b[1 * 3 + k][l] +
                                     a[2 * 3 + i][l] * b[2 * 3 + k][l];
}

/* m v for a vector shared by all lanes (a bone offset) */
/* mat3_vec with one v for every lane */
static inline void lane_matvec3_shared_v(lane *restrict m, const double *v, lane *restrict out) {
    for (int i = 0; i < 3; i++) EACH out[i][l] = m[i * 3 + 0][l] * v[0] + m[i * 3 + 1][l] * v[1] + m[i * 3 + 2][l] * v[2];
}

/* m v for a matrix shared by all lanes */
/* mat3_vec with one m for every lane */
static inline void lane_matvec3_shared_m(const double *m, lane *restrict v, lane *restrict out) {
    for (int i = 0; i < 3; i++) EACH out[i][l] = m[i * 3 + 0] * v[0][l] + m[i * 3 + 1] * v[1][l] + m[i * 3 + 2] * v[2][l];
}


/* vec3_dot */
static inline void lane_dot3(const lane *a, const lane *b, double *restrict out) {
    EACH out[l] = a[0][l] * b[0][l] + a[1][l] * b[1][l] + a[2][l] * b[2][l];
}

/* quat_cross (edge.quat.cross) */
static inline void lane_cross3(lane *a, lane *b, lane *restrict out) {
    EACH {
        out[0][l] = a[1][l] * b[2][l] - a[2][l] * b[1][l];
        out[1][l] = a[2][l] * b[0][l] - a[0][l] * b[2][l];
        out[2][l] = a[0][l] * b[1][l] - a[1][l] * b[0][l];
    }
}

/* a - b */
static inline void lane_sub3(lane *a, lane *b, lane *restrict out) {
    for (int i = 0; i < 3; i++) EACH out[i][l] = a[i][l] - b[i][l];
}

/* edge.quat.matrix_from_6d of one float32 6D (columns a and b) into m [9] (row-major), in float32 as
 * numpy keeps it through the Gram-Schmidt. */
static inline void matrix_from_6d_f32(float a0, float a1, float a2, float b0, float b1, float b2, float *restrict m) {
    float na = sqrtf(a0 * a0 + a1 * a1 + a2 * a2);
    na = na > 1e-8f ? na : 1e-8f;
    float x0 = a0 / na, x1 = a1 / na, x2 = a2 / na;
    float d = x0 * b0 + x1 * b1 + x2 * b2;
    float c0 = b0 - d * x0, c1 = b1 - d * x1, c2 = b2 - d * x2;
    float nb = sqrtf(c0 * c0 + c1 * c1 + c2 * c2);
    nb = nb > 1e-8f ? nb : 1e-8f;
    float y0 = c0 / nb, y1 = c1 / nb, y2 = c2 / nb;
    m[0] = x0; m[1] = y0; m[2] = x1 * y2 - x2 * y1;
    m[3] = x1; m[4] = y1; m[5] = x2 * y0 - x0 * y2;
    m[6] = x2; m[7] = y2; m[8] = x0 * y1 - x1 * y0;
}

/* matrix_from_6d_f32 of the decoder's float32 output into double lanes: 6 floats per lane, `stride`
 * floats between lanes' rows. */
static inline void lane_matrix_from_6d_f32(const float *r6, int64_t stride, int r0, int nl, lane *restrict m) {
    float a0[LANES], a1[LANES], a2[LANES], b0[LANES], b1[LANES], b2[LANES];
    EACH {
        const float *q = r6 + (int64_t)(r0 + (l < nl ? l : nl - 1)) * stride;
        a0[l] = q[0]; a1[l] = q[1]; a2[l] = q[2]; b0[l] = q[3]; b1[l] = q[4]; b2[l] = q[5];
    }
    EACH {
        float t[9];
        matrix_from_6d_f32(a0[l], a1[l], a2[l], b0[l], b1[l], b2[l], t);
        for (int k = 0; k < 9; k++) m[k][l] = t[k];
    }
}

/* The same in float64 (the plausibility score casts the autoencoder's output first). */
/* quat_matrix_from_6d (edge.quat.matrix_from_6d) of the columns a, b */
static inline void lane_matrix_from_6d_f64(lane *a, lane *b, lane *restrict m) {
    lane na, d, nb;
    lane x[3], y[3], z[3], c[3];
    lane_dot3(a, a, na);
    EACH { na[l] = sqrt(na[l]); na[l] = na[l] > 1e-8 ? na[l] : 1e-8; }
    for (int i = 0; i < 3; i++) EACH x[i][l] = a[i][l] / na[l];
    lane_dot3(x, b, d);
    for (int i = 0; i < 3; i++) EACH c[i][l] = b[i][l] - d[l] * x[i][l];
    lane_dot3(c, c, nb);
    EACH { nb[l] = sqrt(nb[l]); nb[l] = nb[l] > 1e-8 ? nb[l] : 1e-8; }
    for (int i = 0; i < 3; i++) EACH y[i][l] = c[i][l] / nb[l];
    lane_cross3(x, y, z);
    for (int i = 0; i < 3; i++) EACH { m[i * 3 + 0][l] = x[i][l]; m[i * 3 + 1][l] = y[i][l]; m[i * 3 + 2][l] = z[i][l]; }
}

/* LANES poses side by side: local and world rotations and positions of every joint. */
typedef struct {
    lane L[MAX_JOINTS][9], W[MAX_JOINTS][9], P[MAX_JOINTS][3];
} block;

/* ------------------------------------------------------------------ what the calls are given */
/* Each struct is mirrored field for field by a ctypes Structure in edge/native/__init__.py. */

/* The skeleton: edge.skeleton.PARENTS [J] and OFFSETS [J,3], the limb chains (edge.pipeline.LIMB_CHAINS
 * [4,3]: legs, then arms) and their poles [4,3], the ankles [2], the head and neck joints. */
typedef struct {
    int J, head, neck;
    const int64_t *parents, *chains, *ankles;
    const double *offsets, *poles;
} skeleton;

/* Rows of poses [R,J,...]: local rotations [.,9], world rotations [.,9], positions [.,3]. An output
 * that is NULL is not written. */
typedef struct {
    double *local, *world, *pos;
} pose_rows;

/* NumpyFrame.forward's inputs: the decoder's 6D [R, rot6d_stride] float, the root (waist) rotation
 * [3,3], the tracked head joint's position [3] (each per row, or shared with stride 0), and the worn
 * IMUs' measured segments seg_m [J,9] with their flags seg_flag [J] (NULL: none). */
typedef struct {
    const float *rot6d;
    int rot6d_stride;
    const double *root_m;
    int root_stride;
    const double *anchor;
    int anchor_stride;
    const double *seg_m, *seg_flag;
} forward_inputs;

/* NumpyFrame.post's goals: the legs' foot goals [R,2,3] at weights [R,2] (foot_ik), the wrists [2,3]
 * and hand rotations [2,3,3] the arms reach for, the headset's rotation [3,3] (arm_ik; each per row or
 * shared); `lift` [R,2] (NULL: not wanted) receives how far the floor lifted each foot. */
typedef struct {
    const double *foot_goals, *foot_weights;
    int foot_ik, arm_ik;
    const double *wrists;
    int wrists_stride;
    const double *hand_m;
    int hand_stride;
    const double *head_m;
    int head_stride;
    double *lift;
    double swivel;          /* edge.ik.swivel_to_hands' gain (0: off) */
} limb_goals;

/* edge.ik.FootLock's state and settings (its arrays, one entry per foot of every sample). */
typedef struct {
    double release_frames, max_slip;
    double *lock_pos, *since, *weight;
    uint8_t *locked, *raw;
    double min_gap;
    /* edge.ik.guard_legs: the clearance it keeps (0: off), the most it moves a goal, and the legs'
     * segments [2 sides][2 segments][2 ends] as joint indices */
    double leg_guard, leg_guard_max;
    const int64_t *leg_segs;
} foot_locks;

/* edge.criteria.PhysicalPlausibility's settings: the legs' segments [2 sides][2 segments][2 ends] and
 * the feet [toe l, toe r, ankle l, ankle r] as joint indices; the leg gap and float heights, the toe
 * and ankle rest heights (m); the three terms' weights. */
typedef struct {
    const int64_t *segs, *feet;
    double gap, float_m, toe_h, ankle_h, w_floor, w_legs, w_support;
} physical_params;

/* edge.refine.Refiner.step's inputs besides the core context (ep_refine_step): the batch's decode
 * rot6d [R, rot6d_stride] float of R = L + 2 rows (the latent, its L steps of eps, the sample's own);
 * scratch pos [R,J,3], r [R, max_m], A [L,L], g [L], jt [L, max_m] (the Jacobian); the live terms: n_targets targets (joint, point
 * [3], radius, sqrt weight incl. the window's pull), KeepPose (keep [J] 0/1 and its sqrt weight, when
 * keep_on), FloorContact (sqrt weights of the floor and the planted feet; the shown sample's locks
 * FootLock's lock_pos [2,3] and weight [2] of row lock_row, when floor_on); the step's prior, continuity, damping and
 * largest step; and LegsApart (when legs_on: its sqrt weight, its clearance, and the legs' thigh and shin
 * segments legs_segs [2 sides][2 segments][2 ends] joint indices). */
typedef struct {
    const float *rot6d;
    int rot6d_stride, L;
    double eps;
    double *pos, *r, *A, *g, *jt;
    int max_m, n_targets;
    const int64_t *target_joint;
    const double *target_pos, *target_radius, *target_w;
    int keep_on;
    const uint8_t *keep;
    double keep_w;
    int floor_on;
    double floor_w, planted_w;
    int lock_row;
    double prior, continuity, damping, max_step;
    int legs_on;
    double legs_w, legs_clear;
    const int64_t *legs_segs;
} refine_args;

/* What SSI's default selection cost reads besides the core context (ep_frame_costs): the autoencoder's
 * output [N, ae_rot_dim] float, the leg rows and leg joints of ep_leg_error, its result [N] (out), the
 * physical criterion's settings (NULL: none) and result [N] (out), the rows' world positions after IK
 * [rows,J,3] (the pipeline's _pos), and the ring's costs [slots, cost_stride] (out). */
typedef struct {
    const float *ae_out;
    int ae_rot_dim;
    const int64_t *leg_rows, *legs;
    double *leg_err;
    const physical_params *physical;
    double *physical_cost;
    const double *pos;
    double *ring_cost;
    int cost_stride;
} selection;

static void block_load(block *k, int r0, int nl, int J, const double *local, const double *world, const double *pos) {
    for (int j = 0; j < J; j++) {
        gather(k->L[j], 9, local + j * 9, (int64_t)J * 9, r0, nl);
        gather(k->W[j], 9, world + j * 9, (int64_t)J * 9, r0, nl);
        gather(k->P[j], 3, pos + j * 3, (int64_t)J * 3, r0, nl);
    }
}

/* Any of local, world and pos may be NULL: not wanted (each store is memory traffic the frame pays for). */
static void block_store(block *k, int r0, int nl, int J, double *local, double *world, double *pos) {
    for (int j = 0; j < J; j++) {
        if (local) scatter(k->L[j], 9, local + j * 9, (int64_t)J * 9, r0, nl);
        if (world) scatter(k->W[j], 9, world + j * 9, (int64_t)J * 9, r0, nl);
        if (pos) scatter(k->P[j], 3, pos + j * 3, (int64_t)J * 3, r0, nl);
    }
}

/* NumpyFrame.forward on one block: 6D -> local rotations (root from root_m), FK (edge.skeleton.fk,
 * parents[j] < j) and the body translated so joint `head` sits at `anchor`. A joint j with
 * seg_flag[j] > 0 (shared by every row; NULL: none) takes the world rotation its IMU measured,
 * seg_m [J,9], blended in 6D by the flag, and its local rotation follows. */
static void block_forward(block *k, int r0, int nl, const skeleton *sk, const forward_inputs *in) {
    const int J = sk->J, head = sk->head;
    const int64_t *parents = sk->parents;
    const double *offsets = sk->offsets, *seg_m = in->seg_m, *seg_flag = in->seg_flag;
    const float *rot6d = in->rot6d;
    const int rot6d_stride = in->rot6d_stride;
    lane v[3], shift[3];
    gather(k->L[0], 9, in->root_m, in->root_stride, r0, nl);
    lane_copy(k->W[0], k->L[0], 9);
    for (int i = 0; i < 3; i++) EACH k->P[0][i][l] = 0.0;
    for (int j = 1; j < J; j++) {
        int p = (int)parents[j];
        lane_matrix_from_6d_f32(rot6d + (j - 1) * 6, rot6d_stride, r0, nl, k->L[j]);
        lane_matmul3(k->W[p], k->L[j], k->W[j]);
        if (seg_flag && seg_flag[j] > 0.0) {    /* edge.pipeline.fk_with_segments: a worn IMU sets the segment */
            const double f = seg_flag[j], *m = seg_m + j * 9;
            lane a[3], b[3];
            for (int i = 0; i < 3; i++) EACH {
                a[i][l] = (1 - f) * k->W[j][i * 3][l] + f * m[i * 3];
                b[i][l] = (1 - f) * k->W[j][i * 3 + 1][l] + f * m[i * 3 + 1];
            }
            lane_matrix_from_6d_f64(a, b, k->W[j]);
            lane_matmul3_tn(k->W[p], k->W[j], k->L[j]);
        }
        lane_matvec3_shared_v(k->W[p], offsets + j * 3, v);
        for (int i = 0; i < 3; i++) EACH k->P[j][i][l] = k->P[p][i][l] + v[i][l];
    }
    gather(shift, 3, in->anchor, in->anchor_stride, r0, nl);
    for (int i = 0; i < 3; i++) EACH shift[i][l] = shift[i][l] - k->P[head][i][l];
    for (int j = 0; j < J; j++)
        for (int i = 0; i < 3; i++) EACH k->P[j][i][l] += shift[i][l];
}

/* edge.pipeline.NumpyFrame.forward: decoder 6D [R, (J-1)*6] float -> local rotations, world
 * rotations and positions of R rows (see block_forward). */
void ep_forward(const skeleton *sk, int R, const forward_inputs *in, const pose_rows *out) {
    block k;
    for (int r0 = 0; r0 < R; r0 += LANES) {
        int nl = R - r0 < LANES ? R - r0 : LANES;
        block_forward(&k, r0, nl, sk, in);
        block_store(&k, r0, nl, sk->J, out->local, out->world, out->pos);
    }
}

/* cos and sin of edge.ik._angle_between(u, v), an angle in [0, pi]: no acos needed downstream. */
static inline void lane_angle_between_cs(lane *u, lane *v, lane c, lane s) {
    lane uv, uu, vv;
    lane_dot3(u, v, uv);
    lane_dot3(u, u, uu);
    lane_dot3(v, v, vv);
    EACH {
        c[l] = clamp(uv[l] / sqrt(uu[l] * vv[l] + 1e-18), -1.0, 1.0);
        s[l] = sqrt(1.0 - c[l] * c[l]);
    }
}

/* edge.ik._normalize */
static inline void lane_normalize3(lane *v) {
    lane n;
    lane_dot3(v, v, n);
    EACH {
        n[l] = sqrt(n[l]);
        n[l] = n[l] > 1e-9 ? n[l] : 1e-9;
    }
    for (int i = 0; i < 3; i++) EACH v[i][l] /= n[l];
}

/* edge.ik._axis_angle_matrix (Rodrigues), from the angle's cosine and sine */
static inline void lane_axis_angle_matrix_cs(lane *axis, lane c, lane s, lane *restrict m) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++) EACH m[i * 3 + k][l] = axis[i][l] * axis[k][l] * (1.0 - c[l]);
    EACH {
        double x = axis[0][l], y = axis[1][l], z = axis[2][l];
        m[0][l] += c[l]; m[4][l] += c[l]; m[8][l] += c[l];
        m[1][l] -= s[l] * z; m[3][l] += s[l] * z;
        m[2][l] += s[l] * y; m[6][l] -= s[l] * y;
        m[5][l] -= s[l] * x; m[7][l] += s[l] * x;
    }
}

/* edge.ik.two_bone_ik for one chain a -> b -> c: new world rotations of a and b. The same rotations,
 * with each angle difference's cosine and sine taken from the angles' own (cos(x - y) = cx cy + sx sy)
 * instead of acos, cos and sin: trigonometry was most of this function's time. */
static void lane_two_bone_ik(lane *a, lane *b, lane *c, lane *t, lane *a_rot, lane *b_rot, lane *pole,
                             lane *a_new, lane *b_new) {
    lane ab[3], cb[3], ca[3], ta[3], nab[3], axis0[3], bent[3], axis1[3];
    lane_sub3(b, a, ab);
    lane_sub3(c, b, cb);
    lane_sub3(c, a, ca);
    lane_sub3(t, a, ta);
    for (int i = 0; i < 3; i++) EACH nab[i][l] = -ab[i][l];
    lane lab, lcb, lat, c0, s0, c1, s1, c_at, s_at, c0t, s0t, c1t, s1t, ca0, sa0, ca1, sa1, straight;
    lane_dot3(ab, ab, lab);
    lane_dot3(cb, cb, lcb);
    lane_dot3(ta, ta, lat);
    EACH {
        lab[l] = sqrt(lab[l]);
        lcb[l] = sqrt(lcb[l]);
        lat[l] = clamp(sqrt(lat[l]), 1e-4, (lab[l] + lcb[l]) * (1 - 1e-4));
    }
    lane_angle_between_cs(ca, ab, c0, s0);                    /* ac_ab_0 */
    lane_angle_between_cs(nab, cb, c1, s1);                   /* ba_bc_0 */
    lane_angle_between_cs(ca, ta, c_at, s_at);                /* ac_at_0 */
    EACH {
        c0t[l] = clamp((lcb[l] * lcb[l] - lab[l] * lab[l] - lat[l] * lat[l]) / (-2 * lab[l] * lat[l]), -1, 1);
        c1t[l] = clamp((lat[l] * lat[l] - lab[l] * lab[l] - lcb[l] * lcb[l]) / (-2 * lab[l] * lcb[l]), -1, 1);
        s0t[l] = sqrt(1.0 - c0t[l] * c0t[l]);
        s1t[l] = sqrt(1.0 - c1t[l] * c1t[l]);
        ca0[l] = c0t[l] * c0[l] + s0t[l] * s0[l];
        sa0[l] = s0t[l] * c0[l] - c0t[l] * s0[l];
        ca1[l] = c1t[l] * c1[l] + s1t[l] * s1[l];
        sa1[l] = s1t[l] * c1[l] - c1t[l] * s1[l];
    }
    lane_cross3(ca, ab, axis0);
    lane_cross3(ca, pole, bent);                              /* straight chain: bend towards the pole */
    lane_dot3(axis0, axis0, straight);
    for (int i = 0; i < 3; i++) EACH axis0[i][l] = straight[l] < 1e-12 ? bent[i][l] : axis0[i][l];
    lane_normalize3(axis0);
    lane_cross3(ca, ta, axis1);
    lane_normalize3(axis1);
    lane r0[9], r1[9], r2[9], r20[9], tmp[9];
    lane_axis_angle_matrix_cs(axis0, ca0, sa0, r0);
    lane_axis_angle_matrix_cs(axis0, ca1, sa1, r1);
    lane_axis_angle_matrix_cs(axis1, c_at, s_at, r2);
    lane_matmul3(r2, r0, r20);
    lane_matmul3(r20, a_rot, a_new);
    lane_matmul3(r1, b_rot, tmp);
    lane_matmul3(r20, tmp, b_new);
}

/* One chain of edge.ik.apply_limb_ik (with offsets) on a block: ends moved `w` of the way to the
 * target, world rotations and positions of the chain updated, then the positions of the end joint's
 * children (the toes). pole in the mid joint's frame; end_rot the end joint's new world rotation
 * (rows end_stride apart; NULL: keep the end joint's own). Targets tg rows tg_stride apart; w rows
 * w_stride apart (NULL: weight w_const). */
static void block_chain(block *k, int r0, int nl, int J, const int64_t *parents, const double *offsets,
                        const int64_t *chain, const double *tg, int64_t tg_stride, const double *w, int64_t w_stride,
                        double w_const, const double *pole_local, const double *end_rot, int64_t end_stride,
                        int floor, double *lift, int64_t lift_stride) {
    int ia = (int)chain[0], ib = (int)chain[1], ic = (int)chain[2], ip = (int)parents[ia];
    lane goal[3], wt[1], pole[3], v[3], end[9], a_new[9], b_new[9];
    gather(goal, 3, tg, tg_stride, r0, nl);
    if (w) gather(wt, 1, w, w_stride, r0, nl);
    else EACH wt[0][l] = w_const;
    for (int i = 0; i < 3; i++) EACH goal[i][l] = k->P[ic][i][l] + wt[0][l] * (goal[i][l] - k->P[ic][i][l]);
    if (floor) {                /* edge.pipeline.floor_lift: no ankle or toe below the floor */
        int it = ic + 1;
        while (it < J && parents[it] != ic) it++;
        const double *o = offsets + it * 3;
        lane up;
        EACH {
            double toe_drop = k->W[ic][3][l] * o[0] + k->W[ic][4][l] * o[1] + k->W[ic][5][l] * o[2];
            double a = FLOOR_ANKLE - goal[1][l], t = FLOOR_TOE - (goal[1][l] + toe_drop);
            up[l] = a > t ? a : t;
            up[l] = up[l] > 0.0 ? up[l] : 0.0;
            goal[1][l] += up[l];
        }
        if (lift) scatter(&up, 1, lift, lift_stride, r0, nl);
    }
    if (end_rot) gather(end, 9, end_rot, end_stride, r0, nl);
    else lane_copy(end, k->W[ic], 9);
    lane_matvec3_shared_v(k->W[ib], pole_local, pole);
    lane_two_bone_ik(k->P[ia], k->P[ib], k->P[ic], goal, k->W[ia], k->W[ib], pole, a_new, b_new);
    lane_matmul3_tn(k->W[ip], a_new, k->L[ia]);
    lane_matmul3_tn(a_new, b_new, k->L[ib]);
    lane_matmul3_tn(b_new, end, k->L[ic]);
    lane_copy(k->W[ia], a_new, 9);
    lane_copy(k->W[ib], b_new, 9);
    lane_copy(k->W[ic], end, 9);
    lane_matvec3_shared_v(a_new, offsets + ib * 3, v);
    for (int i = 0; i < 3; i++) EACH k->P[ib][i][l] = k->P[ia][i][l] + v[i][l];
    lane_matvec3_shared_v(b_new, offsets + ic * 3, v);
    for (int i = 0; i < 3; i++) EACH k->P[ic][i][l] = k->P[ib][i][l] + v[i][l];
    for (int j = ic + 1; j < J; j++) {
        if (parents[j] != ic) continue;
        lane_matvec3_shared_v(end, offsets + j * 3, v);
        for (int i = 0; i < 3; i++) EACH k->P[j][i][l] = k->P[ic][i][l] + v[i][l];
    }
}

static const int64_t TORSO[4] = {0, 1, 2, 3};   /* edge.ik.TORSO_LINE: pelvis, spine, chest, neck */

/* edge.ik.closest_on_polyline for one point per lane: the closest point q on the polyline through the
 * joints line[0..nline) of the block. */
static void lane_closest_on_polyline(block *k, const int64_t *line, int nline, lane *p, lane *q) {
    lane best;
    EACH best[l] = 1e300;
    for (int g = 0; g + 1 < nline; g++) {
        lane *a = k->P[line[g]], *b = k->P[line[g + 1]];
        EACH {
            double d[3], w[3], dd = 0, wd = 0;
            for (int i = 0; i < 3; i++) {
                d[i] = b[i][l] - a[i][l];
                w[i] = p[i][l] - a[i][l];
                dd += d[i] * d[i];
                wd += w[i] * d[i];
            }
            double t = clamp(wd / (dd > 1e-12 ? dd : 1e-12), 0.0, 1.0), x[3], r = 0;
            for (int i = 0; i < 3; i++) {
                x[i] = a[i][l] + t * d[i];
                r += (p[i][l] - x[i]) * (p[i][l] - x[i]);
            }
            if (r < best[l]) {
                best[l] = r;
                for (int i = 0; i < 3; i++) q[i][l] = x[i];
            }
        }
    }
}

/* edge.ik.swivel_to_hands for one arm chain (shoulder, elbow, wrist) on a block: the arm turned about
 * its shoulder-wrist line so the elbow sits on the far side from where the hand (the wrist's world
 * rotation, already the controller's) points, `gain` against the elbow's own side, and pushed out of
 * the torso (the polyline through torso[0..ntorso)) where it would come nearer than `clearance`. */
static void block_swivel(block *k, const int64_t *parents, const double *offsets, const int64_t *chain,
                         double gain, const int64_t *torso, int ntorso, double clearance, double guard_gain) {
    int ia = (int)chain[0], ib = (int)chain[1], ic = (int)chain[2], ip = (int)parents[ia];
    const double *o = offsets + ic * 3;
    double on = sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
    double axis[3] = {o[0] / on, o[1] / on, o[2] / on};
    lane n[3], e[3], u[3], h[3], t[3], x[3], centre[3], elbow[3], q[3], away[3];
    lane along, hn, ul, tl, c, s, dist, an, turn[9], a_new[9], b_new[9], v[3];
    lane_sub3(k->P[ic], k->P[ia], n);
    lane_normalize3(n);
    lane_sub3(k->P[ib], k->P[ia], e);
    lane_dot3(e, n, along);
    for (int i = 0; i < 3; i++) EACH u[i][l] = e[i][l] - along[l] * n[i][l];
    lane_matvec3_shared_v(k->W[ic], axis, h);
    lane_dot3(h, n, hn);
    lane_dot3(u, u, ul);
    EACH ul[l] = sqrt(ul[l]);
    for (int i = 0; i < 3; i++) EACH {
        u[i][l] /= ul[l] > 1e-9 ? ul[l] : 1e-9;
        t[i][l] = u[i][l] - gain * (h[i][l] - hn[l] * n[i][l]);
    }
    lane_normalize3(t);
    for (int i = 0; i < 3; i++) EACH {
        centre[i][l] = k->P[ia][i][l] + along[l] * n[i][l];
        elbow[i][l] = centre[i][l] + ul[l] * t[i][l];
    }
    lane_closest_on_polyline(k, torso, ntorso, elbow, q);
    lane_sub3(elbow, q, away);
    lane_dot3(away, away, dist);
    /* out along the circle's own way from the torso (its centre's, across the arm): the elbow's own
     * way out can run along the arm when the hand reaches across the chest */
    lane_closest_on_polyline(k, torso, ntorso, centre, q);
    lane_sub3(centre, q, away);
    lane_dot3(away, n, an);
    for (int i = 0; i < 3; i++) EACH away[i][l] -= an[l] * n[i][l];
    lane_normalize3(away);
    EACH {
        double push = clearance - sqrt(dist[l]);
        push = guard_gain * (push > 0.0 ? push : 0.0) / clearance;
        for (int i = 0; i < 3; i++) t[i][l] += push * away[i][l];
    }
    lane_dot3(t, t, tl);
    EACH tl[l] = sqrt(tl[l]);
    for (int i = 0; i < 3; i++) EACH t[i][l] /= tl[l] > 1e-9 ? tl[l] : 1e-9;
    lane_dot3(u, t, c);
    lane_cross3(u, t, x);
    lane_dot3(x, n, s);
    EACH {                  /* a straight arm, or no side to prefer: keep the elbow */
        int keep = ul[l] < 1e-6 || tl[l] < 1e-6;
        c[l] = keep ? 1.0 : clamp(c[l], -1.0, 1.0);
        s[l] = keep ? 0.0 : s[l];
        double r = sqrt(c[l] * c[l] + s[l] * s[l]);    /* atan2's angle: (c, s) on the unit circle */
        c[l] /= r;
        s[l] /= r;
    }
    lane_axis_angle_matrix_cs(n, c, s, turn);
    lane_matmul3(turn, k->W[ia], a_new);
    lane_matmul3(turn, k->W[ib], b_new);
    for (int i = 0; i < 3; i++)
        EACH v[i][l] = turn[i * 3][l] * e[0][l] + turn[i * 3 + 1][l] * e[1][l] + turn[i * 3 + 2][l] * e[2][l];
    for (int i = 0; i < 3; i++) EACH k->P[ib][i][l] = k->P[ia][i][l] + v[i][l];
    lane_matmul3_tn(k->W[ip], a_new, k->L[ia]);
    lane_matmul3_tn(a_new, b_new, k->L[ib]);
    lane_matmul3_tn(b_new, k->W[ic], k->L[ic]);
    lane_copy(k->W[ia], a_new, 9);
    lane_copy(k->W[ib], b_new, 9);
}

/* out = m v for a matrix and a vector per lane */
static inline void lane_matvec3(lane *restrict m, lane *restrict v, lane *restrict out) {
    for (int i = 0; i < 3; i++)
        EACH out[i][l] = m[i * 3][l] * v[0][l] + m[i * 3 + 1][l] * v[1][l] + m[i * 3 + 2][l] * v[2][l];
}

/* edge.ik._swing_matrix: the shortest-arc rotation taking a's direction to b's (identity where they agree) */
static inline void lane_swing_matrix(lane *a, lane *b, lane *restrict m) {
    lane axis[3], c, s;
    lane_cross3(a, b, axis);
    lane_dot3(a, b, c);
    lane_dot3(axis, axis, s);
    EACH {
        s[l] = sqrt(s[l]);
        double r = sqrt(c[l] * c[l] + s[l] * s[l]);     /* atan2's angle: (c, s) on the unit circle */
        c[l] = r > 0.0 ? c[l] / r : 1.0;
        s[l] = r > 0.0 ? s[l] / r : 0.0;
    }
    lane_normalize3(axis);
    lane_axis_angle_matrix_cs(axis, c, s, m);
}

/* The collar of an arm chain (shoulder ia, elbow ib, wrist ic; collar ip) swung by collar_turn so the
 * shoulder goes to co + new_bone, the arm turned by arm_turn about the new shoulder (elbow and wrist
 * positions, shoulder and elbow world rotations) and the collar's local rotation set. Carried along
 * (arm_turn = collar_turn: edge.ik.shoulders_to_reach) the wrist's world rotation turns too and the arm's
 * locals stay; re_aimed at the wrist (edge.ik.shoulders_out_of_torso) the wrist keeps the hand's world
 * rotation and the shoulder's and wrist's locals are set. */
static void lane_move_shoulder(block *k, const int64_t *parents, int ia, int ib, int ic, lane *new_bone,
                               lane *collar_turn, lane *arm_turn, int re_aimed) {
    int ip = (int)parents[ia], ipp = (int)parents[ip], below[2] = {ib, ic};
    lane v[3], w[3], tmp[9];
    for (int m = 0; m < 2; m++) {               /* elbow, wrist: about the shoulder, turned */
        int j = below[m];
        lane_sub3(k->P[j], k->P[ia], v);
        lane_matvec3(arm_turn, v, w);
        for (int i = 0; i < 3; i++) EACH k->P[j][i][l] = k->P[ip][i][l] + new_bone[i][l] + w[i][l];
    }
    for (int i = 0; i < 3; i++) EACH k->P[ia][i][l] = k->P[ip][i][l] + new_bone[i][l];
    lane_matmul3(collar_turn, k->W[ip], tmp);
    lane_copy(k->W[ip], tmp, 9);
    lane_matmul3(arm_turn, k->W[ia], tmp);
    lane_copy(k->W[ia], tmp, 9);
    lane_matmul3(arm_turn, k->W[ib], tmp);
    lane_copy(k->W[ib], tmp, 9);
    lane_matmul3_tn(k->W[ipp], k->W[ip], k->L[ip]);
    if (re_aimed) {
        lane_matmul3_tn(k->W[ip], k->W[ia], k->L[ia]);
        lane_matmul3_tn(k->W[ib], k->W[ic], k->L[ic]);
    } else {
        lane_matmul3(arm_turn, k->W[ic], tmp);
        lane_copy(k->W[ic], tmp, 9);
    }
}

/* The collar's new bone: bone + step (per lane, `step` scaled by `by`), at the bone's own length. */
static inline void lane_collar_toward(block *k, int ip, int ia, lane *dir, lane by, lane *bone, lane *new_bone) {
    lane len;
    lane_sub3(k->P[ia], k->P[ip], bone);
    lane_dot3(bone, bone, len);
    for (int i = 0; i < 3; i++) EACH new_bone[i][l] = bone[i][l] + by[l] * dir[i][l];
    lane_normalize3(new_bone);
    for (int i = 0; i < 3; i++) EACH new_bone[i][l] *= sqrt(len[l]);
}

/* edge.ik.shoulders_to_reach for one arm chain on a block, before its IK: where the wrist's target (tg,
 * rows tg_stride apart) is farther from the shoulder than `start` of the arm's length, the collar swings
 * the shoulder toward it by the excess (at most max_move), the arm coming along as it is. */
static void block_reach(block *k, int r0, int nl, const int64_t *parents, const double *offsets, const int64_t *chain,
                        const double *tg, int64_t tg_stride, double start, double max_move) {
    int ia = (int)chain[0], ib = (int)chain[1], ic = (int)chain[2], ip = (int)parents[ia];
    const double *ob = offsets + ib * 3, *oc = offsets + ic * 3;
    double length = sqrt(ob[0] * ob[0] + ob[1] * ob[1] + ob[2] * ob[2]) + sqrt(oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2]);
    lane goal[3], to[3], bone[3], new_bone[3], turn[9], d, by, tb;
    int any = 0;
    gather(goal, 3, tg, tg_stride, r0, nl);
    lane_sub3(goal, k->P[ia], to);
    lane_dot3(to, to, d);
    EACH {
        d[l] = sqrt(d[l]);
        by[l] = clamp(d[l] - start * length, 0.0, max_move);
        any |= by[l] > 0.0;
    }
    if (!any) return;       /* most frames: every sample's controller within reach */
    lane_normalize3(to);
    lane_sub3(k->P[ia], k->P[ip], bone);                 /* the collar moves the shoulder across its bone */
    lane_normalize3(bone);
    lane_dot3(to, bone, tb);
    for (int i = 0; i < 3; i++) EACH to[i][l] -= tb[l] * bone[i][l];
    lane_collar_toward(k, ip, ia, to, by, bone, new_bone);
    lane_swing_matrix(bone, new_bone, turn);
    lane_move_shoulder(k, parents, ia, ib, ic, new_bone, turn, turn, 0);
}

/* edge.ik.shoulders_out_of_torso for one arm chain on a block, after block_swivel: where the elbow is
 * still nearer than min_gap to the torso's line (a straight arm), the collar moves the shoulder out across
 * the arm (at most max_push) and the arm is re-aimed at the wrist, the hand's rotation kept. */
static void block_push_shoulder(block *k, const int64_t *parents, const int64_t *chain, const int64_t *torso,
                                int ntorso, double min_gap, double max_push) {
    int ia = (int)chain[0], ib = (int)chain[1], ic = (int)chain[2], ip = (int)parents[ia];
    lane q[3], gap[3], n[3], step[3], bone[3], new_bone[3], arm[3], to[3], collar_turn[9], aim[9], arm_turn[9];
    lane dist, out, we, ws, by;
    int any = 0;
    lane_closest_on_polyline(k, torso, ntorso, k->P[ib], q);
    lane_sub3(k->P[ib], q, gap);
    lane_dot3(gap, gap, dist);
    EACH {
        dist[l] = sqrt(dist[l]);
        any |= dist[l] < min_gap;
    }
    if (!any) return;       /* most frames: every elbow clear of the torso */
    /* the shoulder steps across both its collar bone and the arm, to the elbow's side away from the
     * torso; re-aimed at the wrist, the elbow moves |wrist-elbow|/|wrist-shoulder| of the step */
    lane_sub3(k->P[ic], k->P[ia], n);
    lane_dot3(n, n, ws);
    lane_normalize3(n);
    lane_sub3(k->P[ia], k->P[ip], bone);
    lane_cross3(bone, n, step);
    lane_normalize3(step);
    lane_dot3(step, gap, out);
    lane_sub3(k->P[ic], k->P[ib], arm);
    lane_dot3(arm, arm, we);
    EACH {
        double sign = (out[l] > 0.0) - (out[l] < 0.0), w = sqrt(ws[l]), d = dist[l];
        for (int i = 0; i < 3; i++) step[i][l] *= sign;
        double lever = sqrt(we[l]) / (w > 1e-9 ? w : 1e-9);
        double gain = lever * fabs(out[l]) / (d > 1e-9 ? d : 1e-9);
        double short_ = min_gap - d > 0.0 ? min_gap - d : 0.0, move = short_ / (gain > 1e-3 ? gain : 1e-3);
        by[l] = move < max_push ? move : max_push;
    }
    lane_collar_toward(k, ip, ia, step, by, bone, new_bone);
    lane_swing_matrix(bone, new_bone, collar_turn);
    lane_sub3(k->P[ic], k->P[ia], arm);
    lane_matvec3(collar_turn, arm, to);
    for (int i = 0; i < 3; i++) EACH arm[i][l] = k->P[ic][i][l] - (k->P[ip][i][l] + new_bone[i][l]);
    lane_swing_matrix(to, arm, aim);
    lane_matmul3(aim, collar_turn, arm_turn);
    lane_move_shoulder(k, parents, ia, ib, ic, new_bone, collar_turn, arm_turn, 1);
}

/* NumpyFrame.post on one block (see ep_post): every array is the whole batch's, read at the block's rows. */
static void block_post(block *k, int r0, int nl, const skeleton *sk, const limb_goals *g) {
    const int J = sk->J;
    for (int c = 0; c < 2; c++)
        block_chain(k, r0, nl, J, sk->parents, sk->offsets, sk->chains + c * 3, g->foot_goals + c * 3, 6,
                    g->foot_ik ? g->foot_weights + c : 0, 2, 0.0, sk->poles + c * 3, 0, 0, g->foot_ik,
                    g->lift ? g->lift + c : 0, 2);
    if (g->arm_ik)
        for (int c = 2; c < 4; c++)
            block_reach(k, r0, nl, sk->parents, sk->offsets, sk->chains + c * 3, g->wrists + (c - 2) * 3,
                        g->wrists_stride, REACH_START, SHOULDER_REACH_MAX_M);
    for (int c = 2; c < 4; c++)
        block_chain(k, r0, nl, J, sk->parents, sk->offsets, sk->chains + c * 3, g->wrists + (c - 2) * 3,
                    g->wrists_stride, 0, 0, g->arm_ik ? 1.0 : 0.0, sk->poles + c * 3,
                    g->arm_ik ? g->hand_m + (c - 2) * 9 : 0, g->hand_stride, 0, 0, 0);
    if (g->arm_ik && g->swivel > 0)
        for (int c = 2; c < 4; c++)
            block_swivel(k, sk->parents, sk->offsets, sk->chains + c * 3, g->swivel, TORSO, 4, ELBOW_CLEARANCE_M,
                         GUARD_GAIN);
    if (g->arm_ik && g->swivel > 0)
        for (int c = 2; c < 4; c++)
            block_push_shoulder(k, sk->parents, sk->chains + c * 3, TORSO, 4, ELBOW_MIN_M, SHOULDER_PUSH_MAX_M);
    if (g->arm_ik) {
        gather(k->W[sk->head], 9, g->head_m, g->head_stride, r0, nl);
        lane_matmul3_tn(k->W[sk->neck], k->W[sk->head], k->L[sk->head]);
    }
}

/* edge.pipeline.NumpyFrame.post: the legs (chains 0, 1) to their foot goals at the lock weights (0
 * without foot IK), lifted so no ankle or toe is below the floor, keeping the ankles' orientation; the
 * arms (chains 2, 3) onto the controllers with the hands turned to them; the head turned to the
 * headset. Without arm IK the arms and head are left alone. Updates the R rows in place. */
void ep_post(const skeleton *sk, int R, const limb_goals *g, const pose_rows *rows) {
    block k;
    for (int r0 = 0; r0 < R; r0 += LANES) {
        int nl = R - r0 < LANES ? R - r0 : LANES;
        block_load(&k, r0, nl, sk->J, rows->local, rows->world, rows->pos);
        block_post(&k, r0, nl, sk, g);
        block_store(&k, r0, nl, sk->J, rows->local, rows->world, rows->pos);
    }
}

/* edge.proportions.UserBody.on_user: one pose's local rotations local_in [J,9] on the skeleton sk (the
 * user's limb lengths in sk->offsets), hung so joint sk->head sits where the pose's positions pos_in
 * [J,3] have it; each arm (chains 2, 3) solved again so its wrist is where pos_in has it, the hand's
 * world rotation kept; and, where an ankle or toe is then under the floor, both legs (chains 0, 1)
 * solved to lift it onto the floor (the other leg's goal its own ankle), the toes following. Writes
 * out's local, world and pos (any of them NULL: not wanted). */
static inline int toe_of(const skeleton *sk, int f);

static int below_floor(const block *k, const skeleton *sk) {
    for (int f = 0; f < 2; f++)
        if (k->P[sk->ankles[f]][1][0] < FLOOR_ANKLE || k->P[toe_of(sk, f)][1][0] < FLOOR_TOE) return 1;
    return 0;
}

void ep_on_user(const skeleton *sk, const double *local_in, const double *pos_in, const pose_rows *out) {
    const int J = sk->J, head = sk->head;
    const int64_t *parents = sk->parents;
    block k;
    lane v[3], shift[3];
    for (int j = 0; j < J; j++) gather(k.L[j], 9, local_in + j * 9, 0, 0, 1);
    lane_copy(k.W[0], k.L[0], 9);                       /* edge.skeleton.fk from the origin */
    for (int i = 0; i < 3; i++) EACH k.P[0][i][l] = 0.0;
    for (int j = 1; j < J; j++) {
        int p = (int)parents[j];
        lane_matmul3(k.W[p], k.L[j], k.W[j]);
        lane_matvec3_shared_v(k.W[p], sk->offsets + j * 3, v);
        for (int i = 0; i < 3; i++) EACH k.P[j][i][l] = k.P[p][i][l] + v[i][l];
    }
    gather(shift, 3, pos_in + head * 3, 0, 0, 1);
    for (int i = 0; i < 3; i++) EACH shift[i][l] = shift[i][l] - k.P[head][i][l];
    for (int j = 0; j < J; j++)
        for (int i = 0; i < 3; i++) EACH k.P[j][i][l] += shift[i][l];
    for (int c = 2; c < 4; c++)                         /* the wrists back on the controllers */
        block_chain(&k, 0, 1, J, parents, sk->offsets, sk->chains + c * 3, pos_in + sk->chains[c * 3 + 2] * 3, 0,
                    0, 0, 1.0, sk->poles + c * 3, 0, 0, 0, 0, 0);
    if (below_floor(&k, sk))                            /* longer legs bent reach under the floor */
        for (int c = 0; c < 2; c++)
            block_chain(&k, 0, 1, J, parents, sk->offsets, sk->chains + c * 3, pos_in, 0, 0, 0, 0.0,
                        sk->poles + c * 3, 0, 0, 1, 0, 0);
    block_store(&k, 0, 1, J, out->local, out->world, out->pos);
}

/* The transpose of edge.plausibility.yaw_matrix of a pelvis rotation R. */
static void yaw_transpose(const double *R, double *yt) {
    double theta = atan2(R[2], R[8]), c = cos(theta), s = sin(theta);
    /* yaw = [[c,0,s],[0,1,0],[-s,0,c]] */
    yt[0] = c; yt[1] = 0.0; yt[2] = -s;
    yt[3] = 0.0; yt[4] = 1.0; yt[5] = 0.0;
    yt[6] = s; yt[7] = 0.0; yt[8] = c;
}

/* edge.plausibility.local_pose: world positions [B,J,3] and pelvis rotations (rows pelvis_stride
 * apart) -> positions in the character frame (float64 `local`, and float for the autoencoder's
 * input) and the pelvis rotation in it. */
void ep_local_pose(int B, int J, const double *pos, const double *pelvis, int pelvis_stride, double *local,
                   float *ae_in, double *root_local) {
    for (int r = 0; r < B; r++) {
        const double *P = pos + (int64_t)r * J * 3, *R = pelvis + (int64_t)r * pelvis_stride;
        double yt[9];
        yaw_transpose(R, yt);
        double *Lr = local + (int64_t)r * J * 3;
        float *A = ae_in + (int64_t)r * J * 3;
        for (int j = 0; j < J; j++) {
            double rel[3] = {P[j * 3] - P[0] * 1.0, P[j * 3 + 1] - P[1] * 0.0, P[j * 3 + 2] - P[2] * 1.0};
            mat3_vec(yt, rel, Lr + j * 3);
            for (int i = 0; i < 3; i++) A[j * 3 + i] = (float)Lr[j * 3 + i];
        }
        mat3_mul(yt, R, root_local + (int64_t)r * 9);
    }
}

/* edge.plausibility.PlausibilityScorer.lower_body_error after the autoencoder: its 6D output
 * [B,rot_dim] float -> leg rotations (rows leg_rows [2,3]), leg FK (edge.skeleton.fk_legs) from the
 * pelvis, and the mean distance to the input's leg joints legs [2,4]. */
void ep_leg_error(int B, int J, const float *ae_out, int rot_dim, const int64_t *leg_rows, const int64_t *legs,
                  const double *offsets, const double *local, const double *root_local, double *err) {
    for (int r0 = 0; r0 < B; r0 += LANES) {
        int nl = B - r0 < LANES ? B - r0 : LANES;
        lane total, d2;
        EACH total[l] = 0.0;
        for (int s = 0; s < 2; s++) {
            lane rot[9], next[9], leg[9], base[3], joint[3], v[3], a6[6];
            gather(rot, 9, root_local, 9, r0, nl);
            gather(base, 3, local, (int64_t)J * 3, r0, nl);
            for (int k = 0; k < 4; k++) {
                int jk = (int)legs[s * 4 + k];
                lane_matvec3_shared_v(rot, offsets + jk * 3, v);
                gather(joint, 3, local + jk * 3, (int64_t)J * 3, r0, nl);
                EACH d2[l] = 0.0;
                for (int i = 0; i < 3; i++)
                    EACH {
                        base[i][l] = base[i][l] + v[i][l];
                        double d = base[i][l] - joint[i][l];
                        d2[l] += d * d;
                    }
                EACH total[l] += sqrt(d2[l]);
                if (k < 3) {
                    const float *r6 = ae_out + leg_rows[s * 3 + k] * 6;
                    EACH {
                        const float *q = r6 + (int64_t)(r0 + (l < nl ? l : nl - 1)) * rot_dim;
                        for (int i = 0; i < 6; i++) a6[i][l] = (double)q[i];
                    }
                    lane_matrix_from_6d_f64(a6, a6 + 3, leg);
                    lane_matmul3(rot, leg, next);
                    lane_copy(rot, next, 9);
                }
            }
        }
        EACH total[l] = total[l] / 8.0;
        scatter(&total, 1, err, 1, r0, nl);
    }
}

/* edge.physics.segment_closest: the closest points a (on p0-p1) and b (on q0-q1) of two segments, at
 * *s and *t along them (Ericson, Real-Time Collision Detection 5.1.9); returns their distance. */
static double segment_closest(const double *p0, const double *p1, const double *q0, const double *q1,
                              double *pa, double *pb, double *s, double *t) {
    double d1[3], d2[3], r[3];
    for (int i = 0; i < 3; i++) { d1[i] = p1[i] - p0[i]; d2[i] = q1[i] - q0[i]; r[i] = p0[i] - q0[i]; }
    double a = vec3_dot(d1, d1), e = vec3_dot(d2, d2), f = vec3_dot(d2, r), c = vec3_dot(d1, r), b = vec3_dot(d1, d2);
    double denom = a * e - b * b;
    double sc = denom > 1e-12 ? clamp((b * f - c * e) / denom, 0, 1) : 0.0;
    double tc = (b * sc + f) / (e > 1e-12 ? e : 1e-12);
    double am = a > 1e-12 ? a : 1e-12;
    if (tc < 0) sc = clamp(-c / am, 0, 1);
    else if (tc > 1) sc = clamp((b - c) / am, 0, 1);
    tc = clamp(tc, 0, 1);
    double dd[3];
    for (int i = 0; i < 3; i++) {
        pa[i] = p0[i] + d1[i] * sc;
        pb[i] = q0[i] + d2[i] * tc;
        dd[i] = pa[i] - pb[i];
    }
    *s = sc;
    *t = tc;
    return sqrt(vec3_dot(dd, dd));
}

/* edge.physics.support of a foot's lowest point h above the floor */
static double support(double h) { return clamp((SUPPORT_NONE - h) / (SUPPORT_NONE - SUPPORT_FULL), 0.0, 1.0); }

/* edge.physics.lowest_point */
static double lowest_point(double ankle_y, double toe_drop) {
    double t = ankle_y + toe_drop - TOE_HEIGHT, a = ankle_y - ANKLE_HEIGHT;
    return t < a ? t : a;
}

/* edge.ik.FootLock.update for foot i (state arrays FootLock's; locked and raw are numpy bools) at
 * this ankle position (toe_drop: its toe's height relative to it, for the floor snap; NULL: none), and the foot goal the pipeline hands the leg IK: the ankle drawn towards its
 * lock by the lock's weight (edge.pipeline.NumpyFrame.foot_goals). */
static int foot_lock(int i, double p, const double *ankle, const double *toe_drop, const foot_locks *st,
                     double *goal) {
    const double release_frames = st->release_frames, max_slip = st->max_slip;
    double *since = st->since, *weight = st->weight;
    uint8_t *locked = st->locked, *raw = st->raw;
    double *lock = st->lock_pos + (int64_t)i * 3;
    int contact = toe_drop ? p * support(lowest_point(ankle[1], *toe_drop)) > 0.5 : p > 0.5;
    double d[3] = {ankle[0] - lock[0], ankle[1] - lock[1], ankle[2] - lock[2]};
    int slipped = locked[i] && sqrt(d[0] * d[0] + d[2] * d[2]) > max_slip;
    int start = contact && !locked[i] && (!raw[i] || weight[i] == 0.0);
    if (start) {
        for (int k = 0; k < 3; k++) lock[k] = ankle[k] + weight[i] * (lock[k] - ankle[k]);
        if (toe_drop) {         /* onto the floor when within LOCK_SNAP of it */
            double h = lowest_point(lock[1], *toe_drop);
            if (fabs(h) <= LOCK_SNAP) lock[1] -= h;
        }
    }
    locked[i] = (locked[i] && contact && !slipped) || start;
    raw[i] = contact;
    since[i] = locked[i] ? 0.0 : since[i] + 1.0;
    double x = clamp(since[i] / release_frames, 0.0, 1.0);
    weight[i] = locked[i] ? 1.0 : 1.0 - x * x * (3 - 2 * x);
    for (int k = 0; k < 3; k++) goal[(int64_t)i * 3 + k] = (lock[k] - ankle[k]) * weight[i] + ankle[k];
    return start;
}

/* edge.ik.FootLock.separate for one row (feet i0 = 2 r, i0 + 1): two locked feet whose locks are closer
 * across the floor than st->min_gap, one of them locked this frame (started[f]), are moved apart to it
 * along the line between them, the new lock or both halfway; a moved foot's goal is its lock (weight 1). */
static void separate_locks(int64_t i0, const int *started, const foot_locks *st, double *goal) {
    if (!(started[0] || started[1]) || !st->locked[i0] || !st->locked[i0 + 1]) return;
    double *a = st->lock_pos + i0 * 3, *b = a + 3;
    double dx = b[0] - a[0], dz = b[2] - a[2], d = sqrt(dx * dx + dz * dz);
    if (d >= st->min_gap) return;
    double push = st->min_gap - d, ux = 1.0, uz = 0.0;      /* on top of each other: apart along x */
    if (d > 1e-9) { ux = dx / d; uz = dz / d; }
    double wa = started[0] ? (started[1] ? 0.5 : 1.0) : 0.0, wb = 1.0 - wa;
    a[0] -= wa * push * ux; a[2] -= wa * push * uz;
    b[0] += wb * push * ux; b[2] += wb * push * uz;
    for (int k = 0; k < 3; k++) { goal[i0 * 3 + k] = a[k]; goal[(i0 + 1) * 3 + k] = b[k]; }
}

/* edge.ik.guard_legs for one row (its feet i0 = 2 r, i0 + 1), given its legs' segment ends `legs`
 * [2 sides][2 segments (thigh, shin)][2 ends][3] before the IK: where a left and a right segment come
 * closer than st->leg_guard, the free feet's goals move apart across the floor, the shortfall shared by
 * how free each is and divided by how much of an ankle's move reaches the closest point (0.5 s on a
 * thigh, 0.5 + 0.5 s on a shin, at least 0.3), at most st->leg_guard_max. */
static void guard_legs(const double legs[2][2][2][3], int64_t i0, const foot_locks *st, double *goal) {
    double free_l = 1.0 - st->weight[i0], free_r = 1.0 - st->weight[i0 + 1], total = free_l + free_r;
    if (st->leg_guard <= 0.0 || total < 1e-3) return;
    double gap = INFINITY, on_l[3], on_r[3], along_l = 0.0, along_r = 0.0;
    int shin_l = 0, shin_r = 0;
    for (int a = 0; a < 2; a++)
        for (int b = 0; b < 2; b++) {
            double pa[3], pb[3], s, t;
            double d = segment_closest(legs[0][a][0], legs[0][a][1], legs[1][b][0], legs[1][b][1], pa, pb, &s, &t);
            if (d < gap) {
                gap = d; shin_l = a; shin_r = b; along_l = s; along_r = t;
                for (int i = 0; i < 3; i++) { on_l[i] = pa[i]; on_r[i] = pb[i]; }
            }
        }
    double short_m = st->leg_guard - gap;
    if (!(short_m > 0.0)) return;
    double apart[3] = {on_l[0] - on_r[0], 0.0, on_l[2] - on_r[2]};
    if (!(sqrt(apart[0] * apart[0] + apart[2] * apart[2]) > 0.01)) {     /* on top of each other: the body's left */
        apart[0] = legs[0][0][0][0] - legs[1][0][0][0];
        apart[2] = legs[0][0][0][2] - legs[1][0][0][2];
    }
    double n = sqrt(vec3_dot(apart, apart));
    n = n > 1e-9 ? n : 1e-9;
    double reach_l = shin_l ? 0.5 + 0.5 * along_l : 0.5 * along_l, reach_r = shin_r ? 0.5 + 0.5 * along_r : 0.5 * along_r;
    double push_l = short_m * (free_l / total) / (reach_l > 0.3 ? reach_l : 0.3);
    double push_r = short_m * (free_r / total) / (reach_r > 0.3 ? reach_r : 0.3);
    push_l = push_l < st->leg_guard_max ? push_l : st->leg_guard_max;
    push_r = push_r < st->leg_guard_max ? push_r : st->leg_guard_max;
    for (int i = 0; i < 3; i++) {
        goal[i0 * 3 + i] += apart[i] / n * push_l;
        goal[(i0 + 1) * 3 + i] -= apart[i] / n * push_r;
    }
}

/* edge.ik.FootLock.update for B samples' two feet from the decoder's contacts [B,2] float and the FK
 * positions [B,J,3] (the ankles'), with each toe's drop below its ankle [B,2] (NULL: no floor snap);
 * the foot goals [B,2,3] as NumpyFrame.foot_goals draws them. */
void ep_foot_locks(const skeleton *sk, int B, const float *contacts, const double *pos, const double *toe_drop,
                   const foot_locks *st, double *goal) {
    for (int r = 0; r < B; r++) {
        int started[2];
        for (int f = 0; f < 2; f++)
            started[f] = foot_lock(r * 2 + f, contacts[r * 2 + f], pos + ((int64_t)r * sk->J + sk->ankles[f]) * 3,
                                   toe_drop ? toe_drop + r * 2 + f : 0, st, goal);
        separate_locks((int64_t)r * 2, started, st, goal);
        if (st->leg_guard > 0.0) {
            double legs[2][2][2][3];
            for (int q = 0; q < 8; q++)
                for (int i = 0; i < 3; i++) legs[q >> 2][(q >> 1) & 1][q & 1][i] = pos[((int64_t)r * sk->J + st->leg_segs[q]) * 3 + i];
            guard_legs(legs, (int64_t)r * 2, st, goal);
        }
    }
}

/* ------------------------------------------------------------------ the live frame in one call */

/* What stays the same from frame to frame: the skeleton, the pipeline's buffers, FootLock's state and
 * the look-ahead ring (edge.pipeline.Pipeline builds one; field order matches its ctypes mirror,
 * native.CoreContext). */
typedef struct {
    skeleton sk;
    foot_locks locks;                         /* the N samples' (FootLock's arrays) */
    int foot_ik, arm_ik, rot6d_stride;
    const float *rot6d, *contacts;            /* the decoder's outputs, [rows,...] */
    double *goals, *weights;                  /* leg IK goals [rows,2,3] and weights [rows,2], out */
    /* edge.pipeline.LookaheadBuffer's arrays, [slots, ...] with ring_rows pose rows (samples + 1) per
     * slot: the frame's tracker inputs, and what it keeps of each row's pose. */
    int ring_rows;
    double *ring_waist, *ring_anchor, *ring_wrists, *ring_hand, *ring_head;   /* [3,3] [3] [2,3] [2,3,3] [3,3] */
    float *ring_rot6d, *ring_contacts;        /* [rows, rot6d_stride], [rows, 2] */
    double *ring_goal, *ring_weight, *ring_lock_weight;     /* [rows,2,3], [rows,2], [rows - 1,2] */
    double *out_local, *out_world, *out_pos;  /* ep_emit's pose [J,3,3], scratch [J,3,3], [J,3] */
    /* edge.plausibility.PlausibilityScorer's buffers, filled for the N samples when ae_in is not NULL:
     * the autoencoder's input [N,J*3] float, the positions in the character frame [N,J,3] and the
     * pelvis rotation in it [N,3,3] (ep_local_pose's outputs). */
    float *ae_in;
    double *ae_local, *ae_root_local;
    /* ep_frame_inputs: this frame's tracker signals [25 (+ imus * 5)] and ep_frame_features' offsets
     * [4,3], last frame's points [4,3] (updated), the frame rate; the features go to the ring
     * [slots,n_features] and to every one of the decoder's dec_rows input rows. */
    const double *frame_in, *frame_offsets;
    double *prev, fps;
    float *ring_features, *dec_features;
    int dec_rows;
    /* the GRU state each sample's step read, kept for a transition's recompute: [slots, ring_rows - 1, hidden] */
    float *ring_hidden;
    int hidden;
    double *out_contacts;                     /* ep_emit's foot contacts [2] */
    /* the decoder's input width: 24 point features, or 24 + imus * 7 with the extra IMUs (frame_in then
     * carries their orientations and flags after the 25 tracker values) */
    int n_features, imus;
    double *floor_lift;                       /* how far the floor lifted each row's feet [rows,2], out */
    /* the worn IMUs' segments: ep_frame_inputs writes each one's measured world rotation [J,9] and flag
     * [J] (0 for joints without one, or when segments is 0) for ring slot s; imu_joints [imus] */
    double *ring_seg_m, *ring_seg_flag;
    const int64_t *imu_joints;
    int segments;
    /* ep_frame_inputs' sanity test: frame_in's length, the largest |position| it accepts (m), and where
     * a frame that passes is kept (good_in [frame_len]) to stand in for one that does not */
    double *good_in;
    int frame_len;
    double position_limit;
    /* the decoder's latent input [dec_rows, latent_dim] float and the samples' own latents [N, latent_dim]
     * float, for a move's spare row (ep_frame_inputs) */
    float *dec_latent;
    const float *latents;
    int latent_dim;
    /* a live target on a foot of row target_row (-1: none; edge.refine): for each foot f with
     * target_weight[f] > 0, its leg goal moves that far towards where the ankle must be for joint
     * target_joint[f] (the ankle or the toe) to be at target_goal[f] [2,3] */
    int target_row;
    const int64_t *target_joint;
    const double *target_goal, *target_weight;
    double swivel;                            /* edge.ik.swivel_to_hands' gain (0: off) */
    /* edge.smooth.UpperBodySmoother's state, per decoder row: the last filtered value [rows, 11, 6] and
     * the filtered speed [rows, 11] (smooth_prev NULL: off); smooth_keep [11] 1 for a joint that passes
     * through; the cut-off's floor (Hz), its rise per unit/s of speed, and the speed's own weight */
    double *smooth_prev, *smooth_speed;
    double *smooth_before, *smooth_before_speed;  /* the samples' state before each slot's frame [slots, ring_rows, ...] */
    const double *smooth_keep;
    double smooth_min_cut, smooth_beta, smooth_speed_weight;
    /* Present-frame output (look-ahead 0, keep_shown 1): ep_frame_poses writes the pose of the row the
     * frame will show (shown_row of ring slot shown_slot; -1: none) straight into ep_emit's arrays, and
     * ep_emit takes it from there instead of making it again. Anything that rewrites that row of the ring
     * in between sets shown_row to -1 (edge.frame_compiled.CompiledFrame.ring_changed). */
    int keep_shown, shown_slot, shown_row;
} core_context;

/* The layout of the structs above, for the loader to hold the ctypes mirrors against (edge.native.load):
 * out[0..8) the sizes of skeleton, pose_rows, forward_inputs, limb_goals, foot_locks, physical_params,
 * selection, refine_args; out[8] sizeof(core_context), then the offset of each of its fields in order. Returns how many it wrote. */
#include <stddef.h>
#define CORE_FIELDS(X) X(sk) X(locks) X(foot_ik) X(arm_ik) X(rot6d_stride) X(rot6d) X(contacts) X(goals) X(weights) \
    X(ring_rows) X(ring_waist) X(ring_anchor) X(ring_wrists) X(ring_hand) X(ring_head) X(ring_rot6d) X(ring_contacts) \
    X(ring_goal) X(ring_weight) X(ring_lock_weight) X(out_local) X(out_world) X(out_pos) X(ae_in) X(ae_local) \
    X(ae_root_local) X(frame_in) X(frame_offsets) X(prev) X(fps) X(ring_features) X(dec_features) X(dec_rows) \
    X(ring_hidden) X(hidden) X(out_contacts) X(n_features) X(imus) X(floor_lift) X(ring_seg_m) X(ring_seg_flag) \
    X(imu_joints) X(segments) X(good_in) X(frame_len) X(position_limit) X(dec_latent) X(latents) X(latent_dim) \
    X(target_row) X(target_joint) X(target_goal) X(target_weight) X(swivel) X(smooth_prev) X(smooth_speed) \
    X(smooth_before) X(smooth_before_speed) X(smooth_keep) X(smooth_min_cut) X(smooth_beta) X(smooth_speed_weight) \
    X(keep_shown) X(shown_slot) X(shown_row)
int ep_layout(int64_t *out, int n) {
    int64_t v[128];
    int k = 0;
    v[k++] = sizeof(skeleton); v[k++] = sizeof(pose_rows); v[k++] = sizeof(forward_inputs);
    v[k++] = sizeof(limb_goals); v[k++] = sizeof(foot_locks); v[k++] = sizeof(physical_params);
    v[k++] = sizeof(selection); v[k++] = sizeof(refine_args); v[k++] = sizeof(core_context);
#define OFFSET(f) v[k++] = offsetof(core_context, f);
    CORE_FIELDS(OFFSET)
#undef OFFSET
    for (int i = 0; i < k && i < n; i++) out[i] = v[i];
    return k;
}

static void copy_f32(float *dst, const float *src, int64_t n) { for (int64_t i = 0; i < n; i++) dst[i] = src[i]; }
static void copy_f64(double *dst, const double *src, int64_t n) { for (int64_t i = 0; i < n; i++) dst[i] = src[i]; }

/* The toe joint of foot f: the child of ankles[f] (edge.skeleton.TOES). */
static inline int toe_of(const skeleton *sk, int f) {
    int a = (int)sk->ankles[f], toe = a + 1;
    while (toe < sk->J && sk->parents[toe] != a) toe++;
    return toe;
}

/* 1 when the n floats are all finite: x * 0 is 0 for a finite x and NaN otherwise, and a NaN stays in
 * its lane's sum. Sixteen independent lanes, so the compiler vectorises it without reassociating. */
static int all_finite_f32(const float *x, int64_t n) {
    float acc[16] = {0};
    int64_t i = 0;
    for (; i + 16 <= n; i += 16)
        for (int l = 0; l < 16; l++) acc[l] += x[i + l] * 0.0f;
    for (; i < n; i++) acc[0] += x[i] * 0.0f;
    float all = 0.0f;
    for (int l = 0; l < 16; l++) all += acc[l];
    return all == 0.0f;
}

/* edge.smooth.UpperBodySmoother.apply: the one-euro filter (Casiez et al. 2012) on the first 11 joints'
 * 6D values of rows 0..R-1 of rot [R, stride], in place, with the state of rows first..first+R-1, in
 * the numpy reference's order of operations. */
#define SMOOTH_JOINTS 11
static void smooth_rows(const core_context *x, float *rot, int stride, int R, int first) {
    enum { C = SMOOTH_JOINTS * 6 };
    double k = x->fps / (2.0 * M_PI), d[C], sq[SMOOTH_JOINTS], joint_alpha[SMOOTH_JOINTS], alpha[C];
    for (int r = 0; r < R; r++) {       /* in passes over a row's 66 values and 11 joints, so each vectorises */
        double *prev = x->smooth_prev + (int64_t)(first + r) * C;
        double *speed = x->smooth_speed + (int64_t)(first + r) * SMOOTH_JOINTS;
        float *v = rot + (int64_t)r * stride;
        for (int i = 0; i < C; i++)
            d[i] = (double)v[i] - prev[i];
        for (int j = 0; j < SMOOTH_JOINTS; j++) {
            const double *dj = d + j * 6;
            double s = dj[0] * dj[0];
            for (int i = 1; i < 6; i++)
                s += dj[i] * dj[i];
            sq[j] = s;
        }
        for (int j = 0; j < SMOOTH_JOINTS; j++) {
            double now = sqrt(sq[j]) * x->fps;
            now -= speed[j];
            now *= x->smooth_speed_weight;
            speed[j] += now;
            double cut = speed[j] * x->smooth_beta;
            cut += x->smooth_min_cut;
            double a = cut / (cut + k);
            joint_alpha[j] = x->smooth_keep[j] > a ? x->smooth_keep[j] : a;
        }
        for (int i = 0; i < C; i++)
            alpha[i] = joint_alpha[i / 6];
        for (int i = 0; i < C; i++) {
            prev[i] += d[i] * alpha[i];
            v[i] = (float)prev[i];
        }
    }
}

/* smooth_rows on R rows of another buffer (a move's recompute: rot [R, stride]) with the state of rows
 * first..first+R-1 (UpperBodySmoother.apply_to). */
void ep_smooth_rows(const core_context *x, float *rot, int stride, int R, int first) {
    if (x->smooth_prev)
        smooth_rows(x, rot, stride, R, first);
}

/* lane l of a block's local and world rotations and positions into one pose's [J,9], [J,9] and [J,3] */
static void block_store_lane(const block *k, int l, int J, double *local, double *world, double *pos) {
    for (int j = 0; j < J; j++) {
        for (int i = 0; i < 9; i++) {
            local[j * 9 + i] = k->L[j][i][l];
            world[j * 9 + i] = k->W[j][i][l];
        }
        for (int i = 0; i < 3; i++) pos[j * 3 + i] = k->P[j][i][l];
    }
}

/* edge.pipeline.NumpyFrame.poses (Pipeline.step between the decoder and the criteria), for R rows: N samples and, when R = N + 1,
 * the transition row from sample c to sample n at blend weight a (when R = N, c is the sample the frame
 * shows). With keep_shown, the row the frame shows (the transition row, or sample c) also goes to
 * ep_emit's arrays, as row_pose would make it (see core_context's shown_row). Per block of LANES rows, kept on
 * the stack throughout: _forward; the samples' foot locks (_foot_goals: goals drawn by the locks, IK
 * weight 1); the transition row's goals blended from c's and n's (at IK weight 1 too) (c, n < N, so their
 * blocks came first or are this one); _post. The tracker inputs are ring slot `slot`'s, shared by
 * every row; world rotations and positions [R,J,...] go to world and pos (world skipped when NULL).
 * Then what the ring keeps of each row goes to slot `slot`: the decoder's 6D and contacts, the leg
 * IK's goals and weights, the samples' lock weights, and the GRU state their step read (hidden_read,
 * the decoder's input buffer, which its step does not write). Returns 1, or 0 with nothing done but
 * the kept pose forgotten when a value of the decoder's dec_rows rows (its output or the state it
 * wrote, hidden_written) is not finite (NumpyFrame.finite). */
int ep_frame_poses(core_context *x, int slot, int R, int N, int c, int n, double a, double *world,
                   double *pos, const float *hidden_read, const float *hidden_written, int dec_rows) {
    x->shown_row = -1;
    if (!all_finite_f32(hidden_written, (int64_t)dec_rows * x->hidden)
            || !all_finite_f32(x->rot6d, (int64_t)dec_rows * x->rot6d_stride))
        return 0;                       /* NumpyFrame.finite: Pipeline._heal first, then call again */
    int shown = !x->keep_shown ? -1 : R > N ? N : c;
    if (x->smooth_prev) {               /* UpperBodySmoother.remember, then apply: on the decoder's own output */
        int64_t n6 = (int64_t)SMOOTH_JOINTS * 6, at = (int64_t)slot * x->ring_rows;
        copy_f64(x->smooth_before + at * n6, x->smooth_prev, N * n6);
        copy_f64(x->smooth_before_speed + at * SMOOTH_JOINTS, x->smooth_speed, (int64_t)N * SMOOTH_JOINTS);
        smooth_rows(x, (float *)x->rot6d, x->rot6d_stride, R, 0);
    }
    block k;
    const skeleton *sk = &x->sk;
    int J = sk->J, S = x->ring_rows;
    const double *root_m = x->ring_waist + slot * 9, *anchor = x->ring_anchor + slot * 3;
    const double *wrists = x->ring_wrists + slot * 6, *hand_m = x->ring_hand + slot * 18, *head_m = x->ring_head + slot * 9;
    double yt[9], root_local[9];        /* every sample's pelvis is the waist's rotation: one yaw for all */
    yaw_transpose(root_m, yt);
    mat3_mul(yt, root_m, root_local);
    const forward_inputs fin = {x->rot6d, x->rot6d_stride, root_m, 0, anchor, 0, x->ring_seg_m + (int64_t)slot * J * 9,
                                x->ring_seg_flag + (int64_t)slot * J};
    const limb_goals goals = {x->goals, x->weights, x->foot_ik, x->arm_ik, wrists, 0, hand_m, 0, head_m, 0, x->floor_lift,
                              x->swivel};
    for (int r0 = 0; r0 < R; r0 += LANES) {
        int nl = R - r0 < LANES ? R - r0 : LANES;
        block_forward(&k, r0, nl, sk, &fin);
        if (x->foot_ik) {
            for (int l = 0; l < nl && r0 + l < N; l++) {
                int started[2];
                for (int f = 0; f < 2; f++) {
                    int i = (r0 + l) * 2 + f;
                    int a = (int)sk->ankles[f], toe = toe_of(sk, f);
                    const double *o = sk->offsets + toe * 3;
                    double ankle[3] = {k.P[a][0][l], k.P[a][1][l], k.P[a][2][l]};
                    double drop = k.W[a][3][l] * o[0] + k.W[a][4][l] * o[1] + k.W[a][5][l] * o[2];
                    started[f] = foot_lock(i, x->contacts[i], ankle, &drop, &x->locks, x->goals);
                    x->weights[i] = 1.0;
                }
                separate_locks((int64_t)(r0 + l) * 2, started, &x->locks, x->goals);
                if (x->locks.leg_guard > 0.0) {
                    double legs[2][2][2][3];
                    for (int q = 0; q < 8; q++)
                        for (int i = 0; i < 3; i++) legs[q >> 2][(q >> 1) & 1][q & 1][i] = k.P[x->locks.leg_segs[q]][i][l];
                    guard_legs(legs, (int64_t)(r0 + l) * 2, &x->locks, x->goals);
                }
                for (int f = 0; f < 2; f++) {
                    int i = (r0 + l) * 2 + f, a = (int)sk->ankles[f];
                    double tw = r0 + l == x->target_row ? x->target_weight[f] : 0.0;
                    if (tw > 0.0) {             /* NumpyFrame.foot_goals: the target's pull on the leg goal */
                        int tj = (int)x->target_joint[f];
                        for (int c3 = 0; c3 < 3; c3++) {
                            double want = x->target_goal[f * 3 + c3] - (k.P[tj][c3][l] - k.P[a][c3][l]);
                            x->goals[i * 3 + c3] += tw * (want - x->goals[i * 3 + c3]);
                        }
                    }
                }
            }
            if (R > N && r0 + nl > N)
                for (int f = 0; f < 2; f++) {
                    for (int i = 0; i < 3; i++)
                        x->goals[(N * 2 + f) * 3 + i] = (1 - a) * x->goals[(c * 2 + f) * 3 + i] + a * x->goals[(n * 2 + f) * 3 + i];
                    x->weights[N * 2 + f] = 1.0;   /* as the samples': their goals carry the locks' pull */
                }
        }
        block_post(&k, r0, nl, sk, &goals);
        block_store(&k, r0, nl, J, 0, world, pos);
        if (shown >= r0 && shown < r0 + nl)
            block_store_lane(&k, shown - r0, J, x->out_local, x->out_world, x->out_pos);
        int ns = N - r0 < nl ? N - r0 : nl;     /* sample rows in this block (not the transition row) */
        if (x->ae_in && ns > 0) {                /* ep_local_pose on the block, for the plausibility score */
            lane rel[3], loc[3];
            for (int j = 0; j < J; j++) {
                EACH {
                    rel[0][l] = k.P[j][0][l] - k.P[0][0][l] * 1.0;
                    rel[1][l] = k.P[j][1][l] - k.P[0][1][l] * 0.0;
                    rel[2][l] = k.P[j][2][l] - k.P[0][2][l] * 1.0;
                }
                lane_matvec3_shared_m(yt, rel, loc);
                scatter(loc, 3, x->ae_local + j * 3, (int64_t)J * 3, r0, ns);
                for (int l = 0; l < ns; l++)
                    for (int i = 0; i < 3; i++) x->ae_in[((int64_t)(r0 + l) * J + j) * 3 + i] = (float)loc[i][l];
            }
            for (int l = 0; l < ns; l++) copy_f64(x->ae_root_local + (int64_t)(r0 + l) * 9, root_local, 9);
        }
    }
    int64_t row0 = (int64_t)slot * S;
    copy_f32(x->ring_rot6d + row0 * x->rot6d_stride, x->rot6d, (int64_t)R * x->rot6d_stride);
    copy_f32(x->ring_contacts + row0 * 2, x->contacts, (int64_t)R * 2);
    copy_f64(x->ring_goal + row0 * 6, x->goals, (int64_t)R * 6);
    copy_f64(x->ring_weight + row0 * 2, x->weights, (int64_t)R * 2);
    copy_f64(x->ring_lock_weight + (int64_t)slot * (S - 1) * 2, x->locks.weight, (int64_t)N * 2);
    copy_f32(x->ring_hidden + (int64_t)slot * (S - 1) * x->hidden, hidden_read, (int64_t)N * x->hidden);
    if (shown >= 0) {
        x->shown_slot = slot;
        x->shown_row = shown;
    }
    return 1;
}

void ep_physical_cost(int N, int J, const double *pos, const float *contacts, const double *lift,
                      const physical_params *pp, double *cost);
int ep_switch_to(int N, const double *cost, int c, double margin);

/* edge.criteria.Composite of the default criteria, Plausibility (SSI 3.2.1) at weight w_plaus and
 * PhysicalPlausibility at w_phys (skipped when sel->physical is NULL), for the N samples of the live
 * frame, into ring slot `slot`'s costs, summed in Composite.cost's order; then, when c >= 0,
 * ep_switch_to from sample c on those costs (SSI eq. 2, 3.2.2): the sample to move to, or -1. The
 * autoencoder has run on what ep_frame_poses prepared (x->ae_*). One call for the whole judgement. */
int ep_frame_costs(const core_context *x, const selection *sel, int slot, int N, double w_plaus, double w_phys,
                   int c, double margin) {
    const int J = x->sk.J;
    double *cost = sel->ring_cost + (int64_t)slot * sel->cost_stride;
    ep_leg_error(N, J, sel->ae_out, sel->ae_rot_dim, sel->leg_rows, sel->legs, x->sk.offsets, x->ae_local,
                 x->ae_root_local, sel->leg_err);
    int physical = sel->physical != 0 && w_phys != 0.0;
    if (physical)
        ep_physical_cost(N, J, sel->pos, x->contacts, x->floor_lift, sel->physical, sel->physical_cost);
    for (int r = 0; r < N; r++) {
        double total = w_plaus != 0.0 ? w_plaus * sel->leg_err[r] : 0.0;
        if (physical) total = total + w_phys * sel->physical_cost[r];
        cost[r] = total;
    }
    return c >= 0 ? ep_switch_to(N, cost, c, margin) : -1;
}

/* One row's pose again from what the look-ahead ring keeps of it in slot `slot`: its decoder 6D
 * (float), its leg goals [2,3] and IK weights [2], and the slot's tracker inputs; block_forward then
 * block_post, so the result is bit for bit the row's pose in ep_frame_poses (NumpyFrame.row_pose). */
static void row_pose(const core_context *x, int slot, int row, const pose_rows *out) {
    const skeleton *sk = &x->sk;
    int64_t r = (int64_t)slot * x->ring_rows + row;
    const forward_inputs fin = {x->ring_rot6d + r * x->rot6d_stride, 0, x->ring_waist + slot * 9, 0,
                                x->ring_anchor + slot * 3, 0, x->ring_seg_m + (int64_t)slot * sk->J * 9,
                                x->ring_seg_flag + (int64_t)slot * sk->J};
    const limb_goals goals = {x->ring_goal + r * 6, x->ring_weight + r * 2, x->foot_ik, x->arm_ik,
                              x->ring_wrists + slot * 6, 0, x->ring_hand + slot * 18, 0, x->ring_head + slot * 9, 0, 0,
                              x->swivel};
    block k;
    block_forward(&k, 0, 1, sk, &fin);
    block_post(&k, 0, 1, sk, &goals);
    block_store(&k, 0, 1, sk->J, out->local, out->world, out->pos);
}

/* edge.pipeline.NumpyFrame.emit: row_pose of row `row` of ring slot `slot` into out_local and out_pos
 * (unless ep_frame_poses already put it there: shown_row), and its foot contacts, as far as each foot is
 * on the floor to bear them (edge.pipeline.supported_contacts), into out_contacts. */
void ep_emit(core_context *x, int slot, int row) {
    const skeleton *sk = &x->sk;
    int64_t r = (int64_t)slot * x->ring_rows + row;
    const pose_rows out = {x->out_local, x->out_world, x->out_pos};
    if (row != x->shown_row || slot != x->shown_slot)
        row_pose(x, slot, row, &out);
    x->shown_row = -1;                  /* taken: a second emit of this frame makes it again */
    for (int f = 0; f < 2; f++) {
        int a = (int)sk->ankles[f], toe = toe_of(sk, f);
        double h = lowest_point(x->out_pos[a * 3 + 1], x->out_pos[toe * 3 + 1] - x->out_pos[a * 3 + 1]);
        x->out_contacts[f] = x->ring_contacts[r * 2 + f] * support(h);
    }
}

/* The inverse of the character's heading (edge.features.heading): the yaw of the waist's forward
 * axis, as a quaternion about +Y, conjugated, in numpy's order of operations. */
static void heading_inverse(const double *waist_rot, double *inv) {
    const double forward[3] = {0.0, 0.0, 1.0};
    double fwd[3];
    quat_rotate(waist_rot, forward, fwd);
    double half = atan2(fwd[0], fwd[2]) / 2, c = cos(half), s = sin(half);
    inv[0] = c * 1.0; inv[1] = (s * 0.0) * -1.0; inv[2] = (s * 1.0) * -1.0; inv[3] = (s * 0.0) * -1.0;
}

/* One frame of tracker signals -> the decoder's 24 point features and what the pipeline keeps of the
 * frame: edge.features.body_points, heading and features (the same arithmetic, in numpy's order, so
 * the result is bit-identical to the numpy path training used), and the tracker rotations as matrices.
 * in [25]: head_pos 3, head_rot 4, hand_pos 2x3, hand_rot 2x4, waist_rot 4; offsets [4,3]: eye,
 * left grip, right grip, pelvis-to-head (scaled); prev [4,3]: last frame's points.
 * Out: points [4,3] (head, wrists, waist), features (float, the decoder's input), mats [4,9]
 * (waist, left hand, right hand, head). */
void ep_frame_features(const double *in, const double *offsets, const double *prev, double fps, double *points,
                       float *features, double *mats) {
    const double *head_pos = in, *head_rot = in + 3, *hand_pos = in + 7, *hand_rot = in + 13, *waist_rot = in + 21;
    const double *rots[4] = {head_rot, hand_rot, hand_rot + 4, waist_rot};
    double turned[4][3];
    for (int k = 0; k < 4; k++) quat_rotate(rots[k], offsets + k * 3, turned[k]);
    for (int i = 0; i < 3; i++) {
        points[i] = head_pos[i] - turned[0][i];
        points[3 + i] = hand_pos[i] - turned[1][i];
        points[6 + i] = hand_pos[3 + i] - turned[2][i];
        points[9 + i] = points[i] - turned[3][i];
    }
    const double xz[3] = {1.0, 0.0, 1.0};
    double inv[4];
    heading_inverse(waist_rot, inv);
    for (int k = 0; k < 8; k++) {
        double v[3], r[3];
        for (int i = 0; i < 3; i++)
            v[i] = k < 4 ? points[k * 3 + i] - points[9 + i] * xz[i] : (points[(k - 4) * 3 + i] - prev[(k - 4) * 3 + i]) * fps;
        quat_rotate(inv, v, r);
        for (int i = 0; i < 3; i++) features[k * 3 + i] = (float)r[i];
    }
    quat_to_matrix(waist_rot, mats);
    quat_to_matrix(hand_rot, mats + 9);
    quat_to_matrix(hand_rot + 4, mats + 18);
    quat_to_matrix(head_rot, mats + 27);
}

/* edge.features.imu_features: the K extra IMUs' orientations imu_rot [K,4] (world) and presence
 * flags [K] -> features [K*6 + K]: the 6D (first two matrix columns) of each orientation in the
 * character frame of waist_rot's heading, times its flag, then the flags. Bit-identical to numpy. */
void ep_imu_features(int K, const double *imu_rot, const double *imu_flag, const double *waist_rot, float *features) {
    double inv[4], local[4], m[9];
    heading_inverse(waist_rot, inv);
    for (int k = 0; k < K; k++) {
        quat_mul(inv, imu_rot + k * 4, local);
        quat_to_matrix(local, m);
        const double f = imu_flag[k];
        const double six[6] = {m[0], m[3], m[6], m[1], m[4], m[7]};
        for (int i = 0; i < 6; i++) features[k * 6 + i] = (float)(six[i] * f);
        features[K * 6 + k] = (float)f;
    }
}

/* edge.features.orientation_features: the headset's and the two controllers' orientations (frame_in's
 * head_rot at 3, hand_rot at 13 and 17) -> features [18]: the 6D of each in the character frame of
 * waist_rot's heading (what the decoder's upper-body head reads). Bit-identical to numpy. */
void ep_orientation_features(const double *in, float *features) {
    const double *rots[3] = {in + 3, in + 13, in + 17};
    double inv[4], local[4], m[9];
    heading_inverse(in + 21, inv);
    for (int k = 0; k < 3; k++) {
        quat_mul(inv, rots[k], local);
        quat_to_matrix(local, m);
        const double six[6] = {m[0], m[3], m[6], m[1], m[4], m[7]};
        for (int i = 0; i < 6; i++) features[k * 6 + i] = (float)six[i];
    }
}

/* edge.physics.segment_distance: closest distance between segments p0-p1 and q0-q1. */
static double segment_distance(const double *p0, const double *p1, const double *q0, const double *q1) {
    double a[3], b[3], s, t;
    return segment_closest(p0, p1, q0, q1, a, b, &s, &t);
}

/* edge.criteria.PhysicalPlausibility.cost for N rows of world positions pos [N,J,3]: w_floor times how
 * far the floor lifted the feet (lift [N,2]), w_legs times how far the legs' thigh/shin segments come
 * inside `gap` of each other (segs [2 sides][2 segments][2 ends] joint indices), and w_support times how
 * far above `float_m` a foot is while the sample says it is in contact (contacts [N,2] float, > 0.5;
 * the foot's height: edge.physics.foot_height with the rest heights toe_h and ankle_h of joints feet
 * [toe l, toe r, ankle l, ankle r]). -> cost [N]. */
void ep_physical_cost(int N, int J, const double *pos, const float *contacts, const double *lift,
                      const physical_params *pp, double *cost) {
    const int64_t *segs = pp->segs, *feet = pp->feet;
    const double gap = pp->gap, float_m = pp->float_m, toe_h = pp->toe_h, ankle_h = pp->ankle_h;
    for (int r = 0; r < N; r++) {
        const double *P = pos + (int64_t)r * J * 3;
        double closest = 1e300;
        for (int a = 0; a < 2; a++)
            for (int b = 0; b < 2; b++) {
                const int64_t *L = segs + a * 2, *R = segs + 4 + b * 2;
                double d = segment_distance(P + L[0] * 3, P + L[1] * 3, P + R[0] * 3, P + R[1] * 3);
                closest = d < closest ? d : closest;
            }
        double legs = gap - closest > 0 ? gap - closest : 0.0, support = 0.0;
        for (int f = 0; f < 2; f++) {
            double toe = P[feet[f] * 3 + 1] - toe_h, ankle = P[feet[2 + f] * 3 + 1] - ankle_h;
            double h = (toe < ankle ? toe : ankle) - float_m;
            if (contacts[r * 2 + f] > 0.5f && h > 0) support += h;
        }
        cost[r] = pp->w_floor * (lift[r * 2] + lift[r * 2 + 1]) + pp->w_legs * legs + pp->w_support * support;
    }
}


/* edge.pipeline.NumpyFrame.sane: 1 when the frame's n signal values are all finite and its
 * head and controller positions (in[0..3), in[7..13)) lie within `limit` metres of the origin. */
int ep_frame_sane(const double *in, int n, double limit) {
    for (int i = 0; i < n; i++)
        if (!(in[i] - in[i] == 0.0)) return 0;
    for (int i = 0; i < 13; i++)
        if ((i < 3 || i >= 7) && !(in[i] > -limit && in[i] < limit)) return 0;
    return 1;
}

/* The k-th smallest of x[0..n) (x is reordered), np.partition(x, k)[k]: Hoare's quickselect. */
static double kth_smallest(double *x, int n, int k) {
    int lo = 0, hi = n - 1;
    while (lo < hi) {
        double pivot = x[(lo + hi) / 2];
        int i = lo, j = hi;
        while (i <= j) {
            while (x[i] < pivot) i++;
            while (x[j] > pivot) j--;
            if (i <= j) {
                double t = x[i]; x[i] = x[j]; x[j] = t;
                i++; j--;
            }
        }
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else break;
    }
    return x[k];
}

/* edge.ssi.switch_to (is_outlier and best_other) in one call (SSI eq. 2, 3.2.2): the sample to switch to
 * from c, or -1 when c's cost is not an outlier (its excess over the best must also exceed margin;
 * or a cost is NaN, where numpy's test is false too).
 * N <= 1024. */
int ep_switch_to(int N, const double *cost, int c, double margin) {
    double x[1024], lo = cost[0];
    if (N < 2 || N > 1024) return -1;
    for (int i = 0; i < N; i++) {
        if (cost[i] != cost[i]) return -1;
        lo = cost[i] < lo ? cost[i] : lo;
        x[i] = cost[i];
    }
    int k = N / 2;
    double median = kth_smallest(x, N, k);
    if (N % 2 == 0) {                       /* the mean of the two middle values, as np.median */
        double below = x[0];
        for (int i = 1; i < k; i++) below = x[i] > below ? x[i] : below;
        median = (below + median) / 2.0;
    }
    double spread = 2.0 * (median - lo);
    if (!(cost[c] - lo > (spread > margin ? spread : margin))) return -1;
    int best = -1;
    for (int i = 0; i < N; i++)
        if (i != c && (best < 0 || cost[i] < cost[best])) best = i;
    return best;
}

/* edge.pipeline.midway_rotation: the rotation halfway between a and b [9] (row-major), as the mean of
 * their 6D (first two columns) Gram-Schmidt-ed back, in edge.quat.matrix_from_6d's order. */
static void midway_rotation(const double *a, const double *b, double *out) {
    double u[3], v[3];
    for (int i = 0; i < 3; i++) {
        u[i] = 0.5 * (a[i * 3] + b[i * 3]);
        v[i] = 0.5 * (a[i * 3 + 1] + b[i * 3 + 1]);
    }
    quat_matrix_from_6d(u, v, out);
}

int ep_frame_sane(const double *in, int n, double limit);

/* dst = (1 - a) * from + a * to over n floats, in double and rounded once, as numpy computes it with a
 * float64 weight (SSI 3.2.3: a move eases the latent and the GRU state). */
static void ease_f32(float *dst, const float *from, const float *to, int n, double a) {
    for (int i = 0; i < n; i++) dst[i] = (float)((1 - a) * (double)from[i] + a * (double)to[i]);
}

/* edge.pipeline.NumpyFrame.inputs for the live frame, straight into ring slot `slot` and the decoder's
 * input. First ep_frame_sane on frame_in: a frame that fails returns 0 and changes nothing (the
 * pipeline stands the last good one in and calls again); one that passes is kept in good_in. Then
 * ep_frame_features (first: no previous frame, velocity 0), the points, features and tracker matrices
 * where Pipeline.step keeps them, and, when c >= 0 (a move from sample c to n is live at weight a), the
 * spare row N's latent and GRU state (in `state`, the buffer the decoder reads next) eased between
 * the two samples'. Returns 1. */
int ep_frame_inputs(const core_context *x, int slot, int first, int N, int c, int n, double a, float *state) {
    if (!ep_frame_sane(x->frame_in, x->frame_len, x->position_limit))
        return 0;
    copy_f64(x->good_in, x->frame_in, x->frame_len);
    if (c >= 0) {
        const int L = x->latent_dim, H = x->hidden;
        ease_f32(x->dec_latent + (int64_t)N * L, x->latents + (int64_t)c * L, x->latents + (int64_t)n * L, L, a);
        ease_f32(state + (int64_t)N * H, state + (int64_t)c * H, state + (int64_t)n * H, H, a);
    }
    double points[12], mats[36];
    float feat[MAX_FEATURES];
    const int F = x->n_features;
    ep_frame_features(x->frame_in, x->frame_offsets, first ? points : x->prev, x->fps, points, feat, mats);
    if (F > 24)                 /* the extra IMUs: frame_in[25..] holds their orientations [K,4] and flags [K] */
        ep_imu_features(x->imus, x->frame_in + 25, x->frame_in + 25 + 4 * x->imus, x->frame_in + 21, feat + 24);
    if (F > 24 + 49)            /* the upper-body head's orientations (v0.5 on) */
        ep_orientation_features(x->frame_in, feat + 24 + 49);
    if (x->segments) {
        double *seg = x->ring_seg_m + (int64_t)slot * x->sk.J * 9, *flag = x->ring_seg_flag + (int64_t)slot * x->sk.J;
        for (int k = 0; k < x->imus; k++) {
            int64_t j = x->imu_joints[k];
            quat_to_matrix(x->frame_in + 25 + 4 * k, seg + j * 9);
            flag[j] = x->frame_in[25 + 4 * x->imus + k];
        }
        /* edge.pipeline.torso_segments: with the chest measured, the spine segment halfway between the
         * waist and the chest, the neck's halfway between the chest and the headset */
        const int spine = 1, chest = 2, neck = 3;
        flag[spine] = flag[neck] = flag[chest];
        if (flag[chest] > 0.0) {
            midway_rotation(mats, seg + chest * 9, seg + spine * 9);
            midway_rotation(seg + chest * 9, mats + 27, seg + neck * 9);
        }
    }
    copy_f64(x->prev, points, 12);
    copy_f64(x->ring_anchor + slot * 3, points, 3);
    copy_f64(x->ring_wrists + slot * 6, points + 3, 6);
    copy_f64(x->ring_waist + slot * 9, mats, 9);
    copy_f64(x->ring_hand + slot * 18, mats + 9, 18);
    copy_f64(x->ring_head + slot * 9, mats + 27, 9);
    copy_f32(x->ring_features + slot * F, feat, F);
    for (int r = 0; r < x->dec_rows; r++) copy_f32(x->dec_features + (int64_t)r * F, feat, F);
    return 1;
}


/* The dot product of a and b [n] in 8 partial sums (so it vectorises), added pairwise. */
static inline double dot_lanes(const double *a, const double *b, int n) {
    double acc[8] = {0};
    int i = 0;
    for (; i + 8 <= n; i += 8)
        for (int l = 0; l < 8; l++) acc[l] += a[i + l] * b[i + l];
    for (; i < n; i++) acc[0] += a[i] * b[i];
    return ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
}

/* ------------------------------------------------------------------ the refiner's FK in float32 */

/* The refiner's Jacobian comes from differences of mm to cm between rows: float32 (0.1 um at 1 m)
 * carries them, at twice the lanes per vector of block_forward's float64. */
#define LANES32 16
#define EACH32 for (int l = 0; l < LANES32; l++)
typedef float lane32[LANES32];

/* matrix_from_6d_f32 in float lanes; a and b each [3] lanes (the matrix's first two columns). */
static inline void lane32_matrix_from_6d(lane32 *a, lane32 *b, lane32 *restrict m) {
    EACH32 {
        float t[9];
        matrix_from_6d_f32(a[0][l], a[1][l], a[2][l], b[0][l], b[1][l], b[2][l], t);
        for (int k = 0; k < 9; k++) m[k][l] = t[k];
    }
}

/* lane_matmul3 in float lanes: out = a b */
static inline void lane32_matmul3(const lane32 *restrict a, const lane32 *restrict b, lane32 *restrict out) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++)
            EACH32 out[i * 3 + k][l] = a[i * 3][l] * b[k][l] + a[i * 3 + 1][l] * b[3 + k][l] + a[i * 3 + 2][l] * b[6 + k][l];
}

/* block_forward's world positions, in float32, for rows r0..r0+nl (nl <= LANES32) into pos [R,J,3]
 * (float64): the same FK (root, 6D, worn IMUs' segments, the head at the anchor) without the local
 * rotations. The root and anchor are the frame's, shared by every row (the refiner's batch). */
static void block_positions_f32(int r0, int nl, const skeleton *sk, const forward_inputs *in, double *pos) {
    const int J = sk->J, head = sk->head;
    lane32 W[MAX_JOINTS][9], P[MAX_JOINTS][3], a[3], b[3];
    for (int k = 0; k < 9; k++) EACH32 W[0][k][l] = (float)in->root_m[k];
    for (int i = 0; i < 3; i++) EACH32 P[0][i][l] = 0.0f;
    for (int j = 1; j < J; j++) {
        const int p = (int)sk->parents[j];
        EACH32 {
            const float *o = in->rot6d + (int64_t)(r0 + (l < nl ? l : nl - 1)) * in->rot6d_stride + (j - 1) * 6;
            a[0][l] = o[0]; a[1][l] = o[1]; a[2][l] = o[2];
            b[0][l] = o[3]; b[1][l] = o[4]; b[2][l] = o[5];
        }
        lane32 Lj[9];
        lane32_matrix_from_6d(a, b, Lj);
        lane32_matmul3(W[p], Lj, W[j]);
        if (in->seg_flag && in->seg_flag[j] > 0.0) {     /* a worn IMU sets the segment (blended in 6D) */
            const float f = (float)in->seg_flag[j];
            const double *m = in->seg_m + j * 9;
            for (int i = 0; i < 3; i++) EACH32 {
                a[i][l] = (1 - f) * W[j][i * 3][l] + f * (float)m[i * 3];
                b[i][l] = (1 - f) * W[j][i * 3 + 1][l] + f * (float)m[i * 3 + 1];
            }
            lane32_matrix_from_6d(a, b, W[j]);
        }
        const double *off = sk->offsets + j * 3;
        for (int i = 0; i < 3; i++)
            EACH32 P[j][i][l] = P[p][i][l] + (W[p][i * 3][l] * (float)off[0] + W[p][i * 3 + 1][l] * (float)off[1] +
                                              W[p][i * 3 + 2][l] * (float)off[2]);
    }
    for (int j = 0; j < J; j++)
        for (int i = 0; i < 3; i++)
            for (int l = 0; l < nl; l++)
                pos[((int64_t)(r0 + l) * J + j) * 3 + i] = in->anchor[i] + (double)(P[j][i][l] - P[head][i][l]);
}

/* One row's residuals of the live terms (edge.refine's TargetReach, KeepPose, FloorContact, LegsApart,
 * in that order) from its positions P [J,3] and the reference row's ref [J,3], into r; returns how many. */
static int refine_residuals(const core_context *x, const refine_args *a, const double *P, const double *ref, double *r) {
    const skeleton *sk = &x->sk;
    int m = 0;
    for (int i = 0; i < a->n_targets; i++) {
        const double *p = P + a->target_joint[i] * 3, *t = a->target_pos + i * 3;
        double d[3] = {p[0] - t[0], p[1] - t[1], p[2] - t[2]};
        double dist = sqrt(vec3_dot(d, d));
        double beyond = 1.0 - a->target_radius[i] / (dist > 1e-9 ? dist : 1e-9);
        beyond = beyond > 0.0 ? beyond : 0.0;
        for (int c = 0; c < 3; c++) r[m++] = a->target_w[i] * d[c] * beyond;
    }
    if (a->keep_on)
        for (int j = 0; j < sk->J; j++)
            if (a->keep[j])
                for (int c = 0; c < 3; c++) r[m++] = a->keep_w * (P[j * 3 + c] - ref[j * 3 + c]);
    if (a->floor_on) {
        for (int f = 0; f < 4; f++) {           /* toes at FLOOR_TOE, ankles at FLOOR_ANKLE */
            int j = f < 2 ? toe_of(sk, f) : (int)sk->ankles[f - 2];
            double under = P[j * 3 + 1] - (f < 2 ? FLOOR_TOE : FLOOR_ANKLE);
            r[m++] = a->floor_w * (under < 0.0 ? under : 0.0);
        }
        const double *lock_pos = x->locks.lock_pos + (int64_t)a->lock_row * 6, *lock_weight = x->locks.weight + (int64_t)a->lock_row * 2;
        for (int f = 0; f < 2; f++) {
            int j = (int)sk->ankles[f];
            for (int c = 0; c < 3; c++)
                r[m++] = (P[j * 3 + c] - lock_pos[f * 3 + c]) * (a->planted_w * lock_weight[f]);
        }
    }
    if (a->legs_on)                             /* each left segment against each right one */
        for (int i = 0; i < 2; i++)
            for (int k = 0; k < 2; k++) {
                const int64_t *Ls = a->legs_segs + i * 2, *Rs = a->legs_segs + 4 + k * 2;
                double inside = a->legs_clear - segment_distance(P + Ls[0] * 3, P + Ls[1] * 3, P + Rs[0] * 3, P + Rs[1] * 3);
                r[m++] = a->legs_w * (inside > 0.0 ? inside : 0.0);
            }
    return m;
}

/* edge.quat.from_matrix of n row-major matrices m [n,3,3] into q [n,4]: the pose stream's rotations. */
void ep_from_matrix(int n, const double *m, double *q) {
    for (int i = 0; i < n; i++) quat_from_matrix(m + i * 9, q + i * 4);
}

/* edge.refine.Refiner._fill_batch(z, steps) before the batch's decode: its first L + 1 latent rows
 * [L+1, L] float32 are z rounded to float32, then + steps [L, L] (float32) from row 1 on, added in float32
 * as numpy adds them (the same bits). */
void ep_refine_fill(int L, const double *z, const float *steps, float *latent) {
    for (int k = 0; k < L; k++) latent[k] = (float)z[k];
    for (int r = 1; r <= L; r++)
        for (int k = 0; k < L; k++) latent[r * L + k] = latent[k] + steps[(r - 1) * L + k];
}

/* edge.refine.Refiner.step after the batch's decode: FK of the R = L + 2 rows against ring slot
 * `slot`'s inputs (with the worn IMUs' segments), the live terms' residuals of each, the forward-
 * difference Jacobian J [L,m] = (r_k - r_0) / eps, and one Levenberg-Marquardt step on z [L] in place:
 * (J J^T + (prior + continuity + damping) I) dz = -(J r_0 + prior (z - zp) + continuity (z - z_prev)),
 * dz scaled to at most max_step, by Cholesky. Returns the constraints' cost r_0 . r_0, or -1 when the
 * residuals would not fit max_m (nothing changed). */
double ep_refine_step(const core_context *x, const refine_args *a, int slot, double *z, const double *z_prev,
                      const double *zp) {
    const skeleton *sk = &x->sk;
    const int J = sk->J, L = a->L, R = L + 2;
    int m = a->n_targets * 3 + (a->floor_on ? 10 : 0) + (a->legs_on ? 4 : 0);
    if (a->keep_on)
        for (int j = 0; j < J; j++) m += a->keep[j] ? 3 : 0;
    if (((m + 7) & ~7) > a->max_m || L > 64)
        return -1.0;
    const forward_inputs fin = {a->rot6d, a->rot6d_stride, x->ring_waist + slot * 9, 0, x->ring_anchor + slot * 3, 0,
                                x->ring_seg_m + (int64_t)slot * J * 9, x->ring_seg_flag + (int64_t)slot * J};
    for (int r0 = 0; r0 < R; r0 += LANES32)
        block_positions_f32(r0, R - r0 < LANES32 ? R - r0 : LANES32, sk, &fin, a->pos);
    const double *ref = a->pos + (int64_t)(R - 1) * J * 3;
    for (int row = 0; row <= L; row++)
        refine_residuals(x, a, a->pos + (int64_t)row * J * 3, ref, a->r + (int64_t)row * a->max_m);
    double *r0 = a->r, cost = 0.0;
    for (int i = 0; i < m; i++) cost += r0[i] * r0[i];
    /* the Jacobian J [L][m], J[p][i] = (r_{p+1}[i] - r_0[i]) / eps, row by row (contiguous), and r_0,
     * zero-padded to m8 (a multiple of 8) so the dot products below have no scalar tail */
    const int m8 = (m + 7) & ~7;
    const double inv_eps = 1.0 / a->eps;
    double *jt = a->jt;
    for (int i = m; i < m8; i++) r0[i] = 0.0;
    for (int p = 0; p < L; p++) {
        const double *rp = a->r + (int64_t)(p + 1) * a->max_m;
        double *jp = jt + (int64_t)p * a->max_m;
        for (int i = 0; i < m; i++) jp[i] = (rp[i] - r0[i]) * inv_eps;
        for (int i = m; i < m8; i++) jp[i] = 0.0;
    }
    /* A = J J^T + lambda I (its lower triangle, mirrored) and g = J r_0 + prior (z - zp) + continuity (z - z_prev) */
    const double lambda = a->prior + a->continuity + a->damping;
    double *A = a->A, *g = a->g;
    for (int p = 0; p < L; p++) {
        const double *jp = jt + (int64_t)p * a->max_m;
        for (int q = 0; q <= p; q++)
            A[p * L + q] = A[q * L + p] = dot_lanes(jp, jt + (int64_t)q * a->max_m, m8);
        g[p] = dot_lanes(jp, r0, m8);
    }
    for (int p = 0; p < L; p++) {
        A[p * L + p] += lambda;
        g[p] += a->prior * (z[p] - zp[p]) + a->continuity * (z[p] - z_prev[p]);
    }
    /* Cholesky A = C C^T (lower, in A), then C y = -g, C^T dz = y */
    double y[64], dz[64], inv[64];      /* inv: 1 / C's diagonal (a multiply, not a divide, per entry) */
    for (int p = 0; p < L; p++) {
        for (int q = 0; q < p; q++)
            A[p * L + q] = (A[p * L + q] - dot_lanes(A + p * L, A + q * L, q)) * inv[q];
        double s = A[p * L + p] - dot_lanes(A + p * L, A + p * L, p);
        A[p * L + p] = sqrt(s > 1e-300 ? s : 1e-300);
        inv[p] = 1.0 / A[p * L + p];
    }
    for (int p = 0; p < L; p++)
        y[p] = (-g[p] - dot_lanes(A + p * L, y, p)) * inv[p];
    for (int p = L - 1; p >= 0; p--) {
        double s = y[p];
        for (int t = p + 1; t < L; t++) s -= A[t * L + p] * dz[t];
        dz[p] = s * inv[p];
    }
    double n2 = 0.0;
    for (int p = 0; p < L; p++) n2 += dz[p] * dz[p];
    double scale = sqrt(n2) > a->max_step ? a->max_step / sqrt(n2) : 1.0;
    for (int p = 0; p < L; p++) z[p] += dz[p] * scale;
    return cost;
}

/* ---- POSE_FRAME on the wire (firmware_bridge/wire/protocol.md): the board's one message a tick.
 * firmware_bridge.wire.messages.encode_pose_frame is the reference; PoseEncoder calls this and is
 * tested to write the same bytes. Layout: header <BBHI (version, type, seq, t_us), POSE_RECORD
 * (root mm <i2[3], Q14 quaternions <i2[J][4], contacts u1[2], N u1, SSI flags u1, lost <u2),
 * CRC-16/CCITT-FALSE <H over both, all COBS-encoded, then the 0x00 delimiter. Rounding is numpy's
 * np.round: half to even (nearbyint in the default rounding mode). Returns the bytes written, or
 * -1 (a non-finite root or contact), -2 (a quaternion NaN, infinite or zero), -3 (out too small). */
static void put_i16(uint8_t *p, double v) {
    int16_t x = (int16_t)v;
    p[0] = (uint8_t)(x & 0xFF);
    p[1] = (uint8_t)((uint16_t)x >> 8);
}

static uint16_t crc_table[256];         /* CRC-16/CCITT-FALSE of each byte value, made on first use */

static uint16_t crc_ccitt_false(const uint8_t *d, int n) {
    if (!crc_table[1])
        for (int v = 0; v < 256; v++) {
            uint16_t c = (uint16_t)(v << 8);
            for (int b = 0; b < 8; b++) c = (c & 0x8000) ? (uint16_t)((c << 1) ^ 0x1021) : (uint16_t)(c << 1);
            crc_table[v] = c;
        }
    uint16_t crc = 0xFFFF;
    for (int i = 0; i < n; i++) crc = (uint16_t)((crc << 8) ^ crc_table[((crc >> 8) ^ d[i]) & 0xFF]);
    return crc;
}

static double clip16(double v) { return v < -32767.0 ? -32767.0 : v > 32767.0 ? 32767.0 : v; }

int ep_encode_pose(int version, int msg_type, int seq, unsigned int t_us, const double *root, const double *quats,
                   int joints, const double *contacts, int num_samples, int ssi_flags, int trackers_lost,
                   unsigned char *out, int cap) {
    uint8_t body[8 + 6 + 8 * MAX_JOINTS + 6 + 2];
    int n = 0;
    if (joints > MAX_JOINTS) return -3;
    for (int k = 0; k < 3; k++) if (!isfinite(root[k])) return -1;
    for (int k = 0; k < 2; k++) if (!isfinite(contacts[k])) return -1;
    body[n++] = (uint8_t)version;
    body[n++] = (uint8_t)msg_type;
    body[n++] = (uint8_t)(seq & 0xFF); body[n++] = (uint8_t)((seq >> 8) & 0xFF);
    for (int k = 0; k < 4; k++) body[n++] = (uint8_t)((t_us >> (8 * k)) & 0xFF);
    for (int k = 0; k < 3; k++, n += 2) put_i16(body + n, clip16(nearbyint(root[k] * 1000.0)));
    for (int j = 0; j < joints; j++) {
        const double *q = quats + 4 * j;
        for (int k = 0; k < 4; k++) if (!isfinite(q[k])) return -2;
        double norm = sqrt(((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3]);
        if (norm < 1e-6) return -2;
        for (int k = 0; k < 4; k++, n += 2) put_i16(body + n, clip16(nearbyint(q[k] / norm * 16384.0)));
    }
    for (int k = 0; k < 2; k++) {
        double c = contacts[k] < 0.0 ? 0.0 : contacts[k] > 1.0 ? 1.0 : contacts[k];
        body[n++] = (uint8_t)nearbyint(c * 255.0);
    }
    body[n++] = (uint8_t)num_samples;
    body[n++] = (uint8_t)ssi_flags;
    body[n++] = (uint8_t)(trackers_lost & 0xFF); body[n++] = (uint8_t)((trackers_lost >> 8) & 0xFF);
    uint16_t crc = crc_ccitt_false(body, n);
    body[n++] = (uint8_t)(crc & 0xFF); body[n++] = (uint8_t)(crc >> 8);
    /* COBS as framing.cobs_encode does it: each zero-free run (len + 1, run), runs of 254 or more cut
       into 0xFF blocks of 254 that carry no implied zero. */
    if (cap < n + n / 254 + 2) return -3;
    int o = 0, start = 0;
    for (int i = 0; i <= n; i++) {
        if (i < n && body[i] != 0) continue;
        int len = i - start;
        const uint8_t *run = body + start;
        while (len >= 254) {
            out[o++] = 0xFF;
            for (int k = 0; k < 254; k++) out[o++] = run[k];
            run += 254; len -= 254;
        }
        out[o++] = (uint8_t)(len + 1);
        for (int k = 0; k < len; k++) out[o++] = run[k];
        start = i + 1;
    }
    out[o++] = 0;
    return o;
}
