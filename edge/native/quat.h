/* Rotation and 3x3 matrix helpers of the compiled core, one sample at a time, each named for the
 * edge.quat function it computes (same arithmetic, same order of operations, so the results match
 * numpy's). Row-major 3x3 matrices as double[9]; quaternions (w, x, y, z) as double[4].
 *
 *   quat_mul             edge.quat.mul
 *   quat_rotate          edge.quat.rotate
 *   quat_to_matrix       edge.quat.to_matrix
 *   quat_cross           edge.quat.cross (of 3-vectors)
 *   quat_matrix_from_6d  edge.quat.matrix_from_6d (of the two columns u, v)
 *   quat_from_matrix     edge.quat.from_matrix
 *   mat3_mul, mat3_vec, vec3_dot    a @ b, m @ v, a . b (numpy's operators)
 *
 * The SIMD forms that run LANES samples side by side are lane_* in postproc.c. */
#ifndef EDGEPOSE_QUAT_H
#define EDGEPOSE_QUAT_H
#include <math.h>

static inline double clamp(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* a @ b */
static inline void mat3_mul(const double *a, const double *b, double *out) {
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 3; k++)
            out[i * 3 + k] = a[i * 3 + 0] * b[0 * 3 + k] + a[i * 3 + 1] * b[1 * 3 + k] + a[i * 3 + 2] * b[2 * 3 + k];
}

/* m @ v */
static inline void mat3_vec(const double *m, const double *v, double *out) {
    for (int i = 0; i < 3; i++)
        out[i] = m[i * 3 + 0] * v[0] + m[i * 3 + 1] * v[1] + m[i * 3 + 2] * v[2];
}

/* a . b */
static inline double vec3_dot(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* edge.quat.cross */
static inline void quat_cross(const double *a, const double *b, double *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* edge.quat.mul */
static inline void quat_mul(const double *a, const double *b, double *out) {
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

/* edge.quat.rotate, in its order of operations: t = 2 (u x v); v + w t + u x t. */
static inline void quat_rotate(const double *q, const double *v, double *out) {
    double c[3], t[3], c2[3];
    quat_cross(q + 1, v, c);
    for (int i = 0; i < 3; i++) t[i] = 2.0 * c[i];
    quat_cross(q + 1, t, c2);
    for (int i = 0; i < 3; i++) out[i] = v[i] + q[0] * t[i] + c2[i];
}

/* edge.quat.to_matrix */
static inline void quat_to_matrix(const double *q, double *m) {
    double w = q[0], x = q[1], y = q[2], z = q[3];
    m[0] = 1 - 2 * (y * y + z * z); m[1] = 2 * (x * y - w * z); m[2] = 2 * (x * z + w * y);
    m[3] = 2 * (x * y + w * z); m[4] = 1 - 2 * (x * x + z * z); m[5] = 2 * (y * z - w * x);
    m[6] = 2 * (x * z - w * y); m[7] = 2 * (y * z + w * x); m[8] = 1 - 2 * (x * x + y * y);
}

/* edge.quat.matrix_from_6d of the 6D (u, v): u normalised, v made orthogonal to it and normalised,
 * their cross product; the three as the matrix's columns. */
static inline void quat_matrix_from_6d(const double *u, const double *v_in, double *out) {
    double v[3], x[3], y[3];
    double nu = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    nu = nu > 1e-8 ? nu : 1e-8;
    for (int i = 0; i < 3; i++) x[i] = u[i] / nu;
    double d = x[0] * v_in[0] + x[1] * v_in[1] + x[2] * v_in[2];
    for (int i = 0; i < 3; i++) v[i] = v_in[i] - d * x[i];
    double nv = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    nv = nv > 1e-8 ? nv : 1e-8;
    for (int i = 0; i < 3; i++) y[i] = v[i] / nv;
    double z[3] = {x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]};
    for (int i = 0; i < 3; i++) {
        out[i * 3] = x[i];
        out[i * 3 + 1] = y[i];
        out[i * 3 + 2] = z[i];
    }
}

/* edge.quat.from_matrix of one row-major m: Shepperd's method (the branch numpy's masks pick), then
 * normalised, in numpy's order of operations. x < lo ? lo : x is np.maximum's (a NaN stays NaN). */
static inline void quat_from_matrix(const double *m, double *q) {
    double tr = m[0] + m[4] + m[8], s;
    if (tr > 0) {
        s = tr + 1.0;
        s = sqrt(s < 1e-12 ? 1e-12 : s) * 2;
        q[0] = 0.25 * s; q[1] = (m[7] - m[5]) / s; q[2] = (m[2] - m[6]) / s; q[3] = (m[3] - m[1]) / s;
    } else if (m[0] > m[4] && m[0] > m[8]) {
        s = 1.0 + m[0] - m[4] - m[8];
        s = sqrt(s < 1e-12 ? 1e-12 : s) * 2;
        q[0] = (m[7] - m[5]) / s; q[1] = 0.25 * s; q[2] = (m[1] + m[3]) / s; q[3] = (m[2] + m[6]) / s;
    } else if (m[4] > m[8]) {
        s = 1.0 + m[4] - m[0] - m[8];
        s = sqrt(s < 1e-12 ? 1e-12 : s) * 2;
        q[0] = (m[2] - m[6]) / s; q[1] = (m[1] + m[3]) / s; q[2] = 0.25 * s; q[3] = (m[5] + m[7]) / s;
    } else {
        s = 1.0 + m[8] - m[0] - m[4];
        s = sqrt(s < 1e-12 ? 1e-12 : s) * 2;
        q[0] = (m[3] - m[1]) / s; q[1] = (m[2] + m[6]) / s; q[2] = (m[5] + m[7]) / s; q[3] = 0.25 * s;
    }
    double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    n = n < 1e-8 ? 1e-8 : n;
    for (int i = 0; i < 4; i++) q[i] /= n;
}

#endif
