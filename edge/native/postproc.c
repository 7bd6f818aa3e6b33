/* The pipeline's per-sample post-processing in C: 6D -> rotation, FK hung from the head, two-bone
 * limb IK, and the plausibility score around the autoencoder (SSI 3.1, 3.2.1).
 *
 * Each function is the loop form of a numpy reference in edge/ (named in its comment) and is tested
 * against it (tests/test_native.py). Python's per-call overhead, not arithmetic, is what the numpy
 * versions pay at this size (a few hundred 3x3 products per frame), so one call here replaces a few
 * hundred numpy calls. Arrays are row-major float64 unless marked float; a *_stride argument is the
 * distance between rows in elements, 0 when every row shares one value.
 *
 * Built with -ffp-contract=off so no multiply-add is fused: results then match numpy, and x86 and
 * ARM match each other.
 */
#include <math.h>
#include <stdint.h>

typedef double mat3[9];

static void matmul3(const double *a, const double *b, double *out) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++)
            out[i * 3 + k] = a[i * 3 + 0] * b[0 * 3 + k] + a[i * 3 + 1] * b[1 * 3 + k] + a[i * 3 + 2] * b[2 * 3 + k];
}

/* a^T b */
static void matmul3_tn(const double *a, const double *b, double *out) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++)
            out[i * 3 + k] = a[0 * 3 + i] * b[0 * 3 + k] + a[1 * 3 + i] * b[1 * 3 + k] + a[2 * 3 + i] * b[2 * 3 + k];
}

static void matvec3(const double *m, const double *v, double *out) {
    for (int i = 0; i < 3; i++)
        out[i] = m[i * 3 + 0] * v[0] + m[i * 3 + 1] * v[1] + m[i * 3 + 2] * v[2];
}

static void copy9(const double *src, double *dst) {
    for (int i = 0; i < 9; i++) dst[i] = src[i];
}

static double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static void cross3(const double *a, const double *b, double *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static double clamp(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* edge.quat.matrix_from_6d on float32 input: numpy keeps float32 through the Gram-Schmidt. */
static void matrix_from_6d_f32(const float *r6, double *m) {
    float a0 = r6[0], a1 = r6[1], a2 = r6[2], b0 = r6[3], b1 = r6[4], b2 = r6[5];
    float na = sqrtf(a0 * a0 + a1 * a1 + a2 * a2);
    na = na > 1e-8f ? na : 1e-8f;
    float x0 = a0 / na, x1 = a1 / na, x2 = a2 / na;
    float d = x0 * b0 + x1 * b1 + x2 * b2;
    b0 = b0 - d * x0;
    b1 = b1 - d * x1;
    b2 = b2 - d * x2;
    float nb = sqrtf(b0 * b0 + b1 * b1 + b2 * b2);
    nb = nb > 1e-8f ? nb : 1e-8f;
    float y0 = b0 / nb, y1 = b1 / nb, y2 = b2 / nb;
    float z0 = x1 * y2 - x2 * y1, z1 = x2 * y0 - x0 * y2, z2 = x0 * y1 - x1 * y0;
    m[0] = x0; m[1] = y0; m[2] = z0;
    m[3] = x1; m[4] = y1; m[5] = z1;
    m[6] = x2; m[7] = y2; m[8] = z2;
}

/* The same in float64 (the plausibility score casts the autoencoder's output first). */
static void matrix_from_6d_f64(const double *a, const double *bin, double *m) {
    double na = sqrt(dot3(a, a));
    na = na > 1e-8 ? na : 1e-8;
    double x[3] = {a[0] / na, a[1] / na, a[2] / na};
    double d = dot3(x, bin);
    double b[3] = {bin[0] - d * x[0], bin[1] - d * x[1], bin[2] - d * x[2]};
    double nb = sqrt(dot3(b, b));
    nb = nb > 1e-8 ? nb : 1e-8;
    double y[3] = {b[0] / nb, b[1] / nb, b[2] / nb}, z[3];
    cross3(x, y, z);
    for (int i = 0; i < 3; i++) {
        m[i * 3 + 0] = x[i];
        m[i * 3 + 1] = y[i];
        m[i * 3 + 2] = z[i];
    }
}

/* edge.pipeline.Pipeline._forward: decoder 6D [R, (J-1)*6] float -> local rotations (root from root_m),
 * FK (edge.skeleton.fk, parents[j] < j) and the body translated so joint `head` sits at `anchor`. */
void ep_forward(int R, int J, const int64_t *parents, const double *offsets, int head,
                const float *rot6d, int rot6d_stride, const double *root_m, int root_stride,
                const double *anchor, int anchor_stride, double *local, double *world, double *pos) {
    for (int r = 0; r < R; r++) {
        double *L = local + (int64_t)r * J * 9, *W = world + (int64_t)r * J * 9, *P = pos + (int64_t)r * J * 3;
        const float *r6 = rot6d + (int64_t)r * rot6d_stride;
        copy9(root_m + (int64_t)r * root_stride, L);
        for (int j = 1; j < J; j++) matrix_from_6d_f32(r6 + (j - 1) * 6, L + j * 9);
        copy9(L, W);
        P[0] = P[1] = P[2] = 0.0;
        for (int j = 1; j < J; j++) {
            int p = (int)parents[j];
            double v[3];
            matmul3(W + p * 9, L + j * 9, W + j * 9);
            matvec3(W + p * 9, offsets + j * 3, v);
            for (int i = 0; i < 3; i++) P[j * 3 + i] = P[p * 3 + i] + v[i];
        }
        const double *an = anchor + (int64_t)r * anchor_stride;
        double shift[3] = {an[0] - P[head * 3], an[1] - P[head * 3 + 1], an[2] - P[head * 3 + 2]};
        for (int j = 0; j < J; j++)
            for (int i = 0; i < 3; i++) P[j * 3 + i] += shift[i];
    }
}

/* cos and sin of edge.ik._angle_between(u, v), an angle in [0, pi]: no acos needed downstream. */
static void angle_between_cs(const double *u, const double *v, double *c, double *s) {
    *c = clamp(dot3(u, v) / sqrt(dot3(u, u) * dot3(v, v) + 1e-18), -1.0, 1.0);
    *s = sqrt(1.0 - *c * *c);
}

/* edge.ik._normalize */
static void normalize3(double *v) {
    double n = sqrt(dot3(v, v));
    n = n > 1e-9 ? n : 1e-9;
    v[0] /= n; v[1] /= n; v[2] /= n;
}

/* edge.ik._axis_angle_matrix (Rodrigues), from the angle's cosine and sine */
static void axis_angle_matrix_cs(const double *axis, double c, double s, double *m) {
    double x = axis[0], y = axis[1], z = axis[2];
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++) m[i * 3 + k] = axis[i] * axis[k] * (1.0 - c);
    m[0] += c; m[4] += c; m[8] += c;
    m[1] -= s * z; m[3] += s * z;
    m[2] += s * y; m[6] -= s * y;
    m[5] -= s * x; m[7] += s * x;
}

/* edge.ik.two_bone_ik for one chain a -> b -> c: new world rotations of a and b. The same rotations,
 * with each angle difference's cosine and sine taken from the angles' own (cos(x - y) = cx cy + sx sy)
 * instead of acos, cos and sin: trigonometry was most of this function's time. */
static void two_bone_ik(const double *a, const double *b, const double *c, const double *t, const double *a_rot,
                        const double *b_rot, const double *pole, double *a_new, double *b_new) {
    double ab[3], cb[3], ca[3], ta[3], nab[3];
    for (int i = 0; i < 3; i++) {
        ab[i] = b[i] - a[i];
        cb[i] = c[i] - b[i];
        ca[i] = c[i] - a[i];
        ta[i] = t[i] - a[i];
        nab[i] = -ab[i];
    }
    double lab = sqrt(dot3(ab, ab)), lcb = sqrt(dot3(cb, cb));
    double lat = clamp(sqrt(dot3(ta, ta)), 1e-4, (lab + lcb) * (1 - 1e-4));
    double c0, s0, c1, s1, c_at, s_at;                         /* ac_ab_0, ba_bc_0, ac_at_0 */
    angle_between_cs(ca, ab, &c0, &s0);
    angle_between_cs(nab, cb, &c1, &s1);
    angle_between_cs(ca, ta, &c_at, &s_at);
    double c0t = clamp((lcb * lcb - lab * lab - lat * lat) / (-2 * lab * lat), -1, 1);   /* ac_ab_1 */
    double c1t = clamp((lat * lat - lab * lab - lcb * lcb) / (-2 * lab * lcb), -1, 1);   /* ba_bc_1 */
    double s0t = sqrt(1.0 - c0t * c0t), s1t = sqrt(1.0 - c1t * c1t);
    double axis0[3], axis1[3];
    cross3(ca, ab, axis0);
    if (dot3(axis0, axis0) < 1e-12) cross3(ca, pole, axis0);   /* straight chain: bend towards the pole */
    normalize3(axis0);
    cross3(ca, ta, axis1);
    normalize3(axis1);
    mat3 r0, r1, r2, r20, tmp;
    axis_angle_matrix_cs(axis0, c0t * c0 + s0t * s0, s0t * c0 - c0t * s0, r0);
    axis_angle_matrix_cs(axis0, c1t * c1 + s1t * s1, s1t * c1 - c1t * s1, r1);
    axis_angle_matrix_cs(axis1, c_at, s_at, r2);
    matmul3(r2, r0, r20);
    matmul3(r20, a_rot, a_new);
    matmul3(r1, b_rot, tmp);
    matmul3(r20, tmp, b_new);
}

/* One chain of edge.ik.apply_limb_ik (with offsets) on one pose: ends moved `w` of the way to the
 * target, world rotations and positions of the chain updated, then the positions of the end joint's
 * children (the toes). pole in the mid joint's frame; end_rot the end joint's new world rotation. */
static void solve_chain(double *L, double *W, double *P, int J, const int64_t *parents, const double *offsets,
                        const int64_t *chain, const double *tg, double w, const double *pole_local,
                        const double *end_rot) {
    int ia = (int)chain[0], ib = (int)chain[1], ic = (int)chain[2];
    double goal[3], pole[3], a[3], v[3];
    for (int i = 0; i < 3; i++) {
        goal[i] = P[ic * 3 + i] + w * (tg[i] - P[ic * 3 + i]);
        a[i] = P[ia * 3 + i];
    }
    matvec3(W + ib * 9, pole_local, pole);
    mat3 a_new, b_new, end;
    copy9(end_rot, end);
    two_bone_ik(P + ia * 3, P + ib * 3, P + ic * 3, goal, W + ia * 9, W + ib * 9, pole, a_new, b_new);
    matmul3_tn(W + (int)parents[ia] * 9, a_new, L + ia * 9);
    matmul3_tn(a_new, b_new, L + ib * 9);
    matmul3_tn(b_new, end, L + ic * 9);
    copy9(a_new, W + ia * 9);
    copy9(b_new, W + ib * 9);
    copy9(end, W + ic * 9);
    matvec3(a_new, offsets + ib * 3, v);
    for (int i = 0; i < 3; i++) P[ib * 3 + i] = a[i] + v[i];
    matvec3(b_new, offsets + ic * 3, v);
    for (int i = 0; i < 3; i++) P[ic * 3 + i] = P[ib * 3 + i] + v[i];
    for (int j = ic + 1; j < J; j++) {
        if (parents[j] != ic) continue;
        matvec3(W + ic * 9, offsets + j * 3, v);
        for (int i = 0; i < 3; i++) P[j * 3 + i] = P[ic * 3 + i] + v[i];
    }
}

/* edge.pipeline.Pipeline._post: the legs (chains 0, 1) to their foot goals [R,2,3] at the lock
 * weights [R,2] (0 without foot IK), keeping the ankles' orientation; the arms (chains 2, 3) onto the
 * controllers (wrists [2,3], hand rotations [2,3,3] per row or shared) with the hands turned to them;
 * the head turned to the headset (head_m [3,3]). Without arm IK the arms and head are left alone. */
void ep_post(int R, int J, const int64_t *parents, const double *offsets, const int64_t *chains,
             const double *poles, const double *foot_goals, const double *foot_weights, int foot_ik, int arm_ik,
             const double *wrists, int wrists_stride, const double *hand_m, int hand_stride, const double *head_m,
             int head_stride, int neck, int head, double *local, double *world, double *pos) {
    for (int r = 0; r < R; r++) {
        double *L = local + (int64_t)r * J * 9, *W = world + (int64_t)r * J * 9, *P = pos + (int64_t)r * J * 3;
        for (int k = 0; k < 2; k++)
            solve_chain(L, W, P, J, parents, offsets, chains + k * 3, foot_goals + ((int64_t)r * 2 + k) * 3,
                        foot_ik ? foot_weights[(int64_t)r * 2 + k] : 0.0, poles + k * 3, W + chains[k * 3 + 2] * 9);
        for (int k = 2; k < 4; k++)
            solve_chain(L, W, P, J, parents, offsets, chains + k * 3, wrists + (int64_t)r * wrists_stride + (k - 2) * 3,
                        arm_ik ? 1.0 : 0.0, poles + k * 3,
                        arm_ik ? hand_m + (int64_t)r * hand_stride + (k - 2) * 9 : W + chains[k * 3 + 2] * 9);
        if (arm_ik) {
            const double *hm = head_m + (int64_t)r * head_stride;
            copy9(hm, W + head * 9);
            matmul3_tn(W + neck * 9, hm, L + head * 9);
        }
    }
}

/* edge.plausibility.local_pose: world positions [B,J,3] and pelvis rotations (rows pelvis_stride
 * apart) -> positions in the character frame (float64 `local`, and float for the autoencoder's
 * input) and the pelvis rotation in it. */
void ep_local_pose(int B, int J, const double *pos, const double *pelvis, int pelvis_stride, double *local,
                   float *ae_in, double *root_local) {
    for (int r = 0; r < B; r++) {
        const double *P = pos + (int64_t)r * J * 3, *R = pelvis + (int64_t)r * pelvis_stride;
        double theta = atan2(R[2], R[8]), c = cos(theta), s = sin(theta);
        /* yaw = [[c,0,s],[0,1,0],[-s,0,c]]; we apply its transpose */
        double yt[9] = {c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c};
        double *Lr = local + (int64_t)r * J * 3;
        float *A = ae_in + (int64_t)r * J * 3;
        for (int j = 0; j < J; j++) {
            double rel[3] = {P[j * 3] - P[0] * 1.0, P[j * 3 + 1] - P[1] * 0.0, P[j * 3 + 2] - P[2] * 1.0};
            matvec3(yt, rel, Lr + j * 3);
            for (int i = 0; i < 3; i++) A[j * 3 + i] = (float)Lr[j * 3 + i];
        }
        matmul3(yt, R, root_local + (int64_t)r * 9);
    }
}

/* edge.plausibility.PlausibilityScorer.lower_body_error after the autoencoder: its 6D output
 * [B,rot_dim] float -> leg rotations (rows leg_rows [2,3]), leg FK (edge.skeleton.fk_legs) from the
 * pelvis, and the mean distance to the input's leg joints legs [2,4]. */
void ep_leg_error(int B, int J, const float *ae_out, int rot_dim, const int64_t *leg_rows, const int64_t *legs,
                  const double *offsets, const double *local, const double *root_local, double *err) {
    for (int r = 0; r < B; r++) {
        const float *o = ae_out + (int64_t)r * rot_dim;
        const double *Lr = local + (int64_t)r * J * 3;
        double total = 0.0;
        for (int s = 0; s < 2; s++) {
            mat3 rot, next, leg;
            double base[3] = {Lr[0], Lr[1], Lr[2]}, v[3];
            copy9(root_local + (int64_t)r * 9, rot);
            for (int k = 0; k < 4; k++) {
                matvec3(rot, offsets + legs[s * 4 + k] * 3, v);
                double d2 = 0.0;
                for (int i = 0; i < 3; i++) {
                    base[i] = base[i] + v[i];
                    double d = base[i] - Lr[legs[s * 4 + k] * 3 + i];
                    d2 += d * d;
                }
                total += sqrt(d2);
                if (k < 3) {
                    const float *r6 = o + leg_rows[s * 3 + k] * 6;
                    double a6[6];
                    for (int i = 0; i < 6; i++) a6[i] = (double)r6[i];
                    matrix_from_6d_f64(a6, a6 + 3, leg);
                    matmul3(rot, leg, next);
                    copy9(next, rot);
                }
            }
        }
        err[r] = total / 8.0;
    }
}

/* edge.ik.FootLock.update for B samples and F feet, and the foot goals the pipeline hands the leg IK:
 * each foot's ankle drawn towards its lock by the lock's weight (edge.pipeline.Pipeline.step).
 * State arrays are FootLock's (locked and raw are numpy bools); goal [B,F,3] out. */
void ep_foot_locks(int B, int F, const float *contacts, const double *pos, int J, const int64_t *ankles,
                   double release_frames, double max_slip, double *lock_pos, uint8_t *locked, uint8_t *raw,
                   double *since, double *weight, double *goal) {
    for (int r = 0; r < B; r++) {
        for (int f = 0; f < F; f++) {
            int i = r * F + f;
            const double *ankle = pos + ((int64_t)r * J + ankles[f]) * 3;
            double *lock = lock_pos + (int64_t)i * 3;
            int contact = contacts[i] > 0.5f;
            double d[3] = {ankle[0] - lock[0], ankle[1] - lock[1], ankle[2] - lock[2]};
            int slipped = locked[i] && sqrt(dot3(d, d)) > max_slip;
            int start = contact && !locked[i] && (!raw[i] || weight[i] == 0.0);
            if (start)
                for (int k = 0; k < 3; k++) lock[k] = ankle[k] + weight[i] * (lock[k] - ankle[k]);
            locked[i] = (locked[i] && contact && !slipped) || start;
            raw[i] = contact;
            since[i] = locked[i] ? 0.0 : since[i] + 1.0;
            double x = clamp(since[i] / release_frames, 0.0, 1.0);
            weight[i] = locked[i] ? 1.0 : 1.0 - x * x * (3 - 2 * x);
            for (int k = 0; k < 3; k++) goal[(int64_t)i * 3 + k] = (lock[k] - ankle[k]) * weight[i] + ankle[k];
        }
    }
}

/* edge.quat.rotate, in its order of operations: t = 2 (u x v); v + w t + u x t. */
static void quat_rotate(const double *q, const double *v, double *out) {
    double c[3], t[3], c2[3];
    cross3(q + 1, v, c);
    for (int i = 0; i < 3; i++) t[i] = 2.0 * c[i];
    cross3(q + 1, t, c2);
    for (int i = 0; i < 3; i++) out[i] = v[i] + q[0] * t[i] + c2[i];
}

/* edge.quat.to_matrix */
static void quat_to_matrix(const double *q, double *m) {
    double w = q[0], x = q[1], y = q[2], z = q[3];
    m[0] = 1 - 2 * (y * y + z * z); m[1] = 2 * (x * y - w * z); m[2] = 2 * (x * z + w * y);
    m[3] = 2 * (x * y + w * z); m[4] = 1 - 2 * (x * x + z * z); m[5] = 2 * (y * z - w * x);
    m[6] = 2 * (x * z - w * y); m[7] = 2 * (y * z + w * x); m[8] = 1 - 2 * (x * x + y * y);
}

/* One frame of tracker signals -> the decoder's 24 features and what the pipeline keeps of the frame:
 * edge.features.body_points, heading and features (the same arithmetic, in numpy's order, so the
 * result is bit-identical to the numpy path training used), and the tracker rotations as matrices.
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
    /* heading: yaw of the waist's forward axis, as a quaternion about +Y; then its inverse */
    const double forward[3] = {0.0, 0.0, 1.0}, xz[3] = {1.0, 0.0, 1.0};
    double fwd[3];
    quat_rotate(waist_rot, forward, fwd);
    double half = atan2(fwd[0], fwd[2]) / 2, c = cos(half), s = sin(half);
    double inv[4] = {c * 1.0, (s * 0.0) * -1.0, (s * 1.0) * -1.0, (s * 0.0) * -1.0};
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
