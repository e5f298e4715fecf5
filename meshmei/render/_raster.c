/* The renderer's compiled kernels (see meshmei/render/native.py).
 *
 * front_*: the no-grad front of passes.run_passes (cull, z-buffer, contour segments, nearest-segment
 * buffer, soft pixels, samples and used faces), with the same operations in the same order on the same
 * dtype as the torch code (compiled with -ffp-contract=off: no fused multiply-add; no -ffast-math), so
 * that its decisions are the torch code's: bit for bit up to the square root of a segment distance, which
 * torch's CPU kernel does not round correctly and sqrt/sqrtf here do (see native.py).
 *
 * Keys are int64: (float32 bits of the depth or distance) << 32 | the face's or segment's slot, and each
 * pixel keeps the smallest (the packed-key "amin" of the torch code; the order of the pairs does not
 * matter for a minimum).
 *
 * sample_* and shade_*: the per-pixel arithmetic with hand-written backwards, equal to the torch code to
 * rounding.
 */
#include <stdint.h>
#include <string.h>
#include <math.h>

#define NONE INT64_MAX

static inline int64_t pack(float x, int64_t slot)
{
    int32_t bits;
    memcpy(&bits, &x, sizeof bits);
    /* the torch code views the float as int32 and widens it with its sign, then shifts */
    return (int64_t)((uint64_t)(int64_t)bits << 32) | slot;
}

/* ------------------------------------------------------------------------------------------------------
 * The differentiable per-pixel arithmetic: samples._SampleGeometry and shading._ShadeSamples, forward and
 * their hand-written backward, formula for formula (see their docstrings). Unlike the passes these need
 * not match torch bit for bit (sums may associate differently); the tests hold them to rounding.
 *
 * Sample geometry. u, v, z: (B * n) pixel coordinates and view depth of the vertices; ci: (3, U) rows of
 * the used faces' corners; covered samples (in_pix, in_slot), fringe samples (fr_pix, fr_slot, fr_k: the
 * contour edge k runs from corner k + 1 to corner k + 2, fr_sign: -1 outside, +1 inside), of which the
 * `out` ones (outside the surface) are shaded after the covered ones. Forward writes the face table
 * (21 values per used face: u0, v0, du[3], dv[3], the affine barycentrics a[3], bu[3], bv[3], iz[3],
 * tot), l and iz (3, Ni + No) and cov (Q). */
#define FT 21
/* A fringe sample's foot on its contour edge k (corners k + 1 and k + 2 of the face whose table row is
 * `row`), in coordinates relative to corner 0: the pixel centre Q, the edge's start a and direction d, its
 * squared length (and that floored at eps), the foot's parameter before and after clamping to [0, 1]. */
#define FOOT(T)                                                                                            \
    typedef struct {                                                                                       \
        int e0, e1;                                                                                        \
        T Qu, Qv, au, av, dx, dy, L2, L2c, t_raw, t;                                                       \
    } foot_##T;                                                                                            \
    static inline foot_##T foot_of_##T(const T *row, int64_t k, int64_t pix, int64_t S, T eps)             \
    {                                                                                                      \
        foot_##T f;                                                                                        \
        f.e0 = (int)((k + 1) % 3);                                                                         \
        f.e1 = (int)((k + 2) % 3);                                                                         \
        f.Qu = ((T)(pix % S) + (T)0.5) - row[0];                                                           \
        f.Qv = ((T)((pix / S) % S) + (T)0.5) - row[1];                                                     \
        f.au = row[2 + f.e0];                                                                              \
        f.av = row[5 + f.e0];                                                                              \
        f.dx = row[2 + f.e1] - f.au;                                                                       \
        f.dy = row[5 + f.e1] - f.av;                                                                       \
        f.L2 = f.dx * f.dx + f.dy * f.dy;                                                                  \
        f.L2c = f.L2 < eps ? eps : f.L2;                                                                   \
        f.t_raw = ((f.Qu - f.au) * f.dx + (f.Qv - f.av) * f.dy) / f.L2c;                                   \
        f.t = f.t_raw < 0 ? 0 : (f.t_raw > 1 ? 1 : f.t_raw);                                               \
        return f;                                                                                          \
    }

FOOT(float)
FOOT(double)

#define SAMPLE(NAME_F, NAME_B, T, SQRT, EXP)                                                               \
    void NAME_F(int64_t U, const T *u, const T *v, const T *z, const int64_t *ci, int64_t Ni,               \
                const int64_t *in_pix, const int64_t *in_slot, int64_t Q, const int64_t *fr_pix,             \
                const int64_t *fr_slot, const int64_t *fr_k, const T *fr_sign, int64_t No,                   \
                const int64_t *pos, int64_t S, double sigma_, double eps_, T *ft, T *l, T *iz, T *cov)      \
    {                                                                                                      \
        const T eps = (T)eps_, sigma = (T)sigma_;                                                          \
        for (int64_t s = 0; s < U; ++s) {                                                                  \
            T cu[3], cv[3], du[3], dv[3], a[3], eu[3], ev[3];                                              \
            T *row = ft + FT * s;                                                                          \
            for (int j = 0; j < 3; ++j) {                                                                  \
                int64_t c = ci[j * U + s];                                                                 \
                cu[j] = u[c];                                                                              \
                cv[j] = v[c];                                                                              \
                row[17 + j] = (T)1 / z[c];                                                                 \
            }                                                                                              \
            for (int j = 0; j < 3; ++j) {                                                                  \
                du[j] = cu[j] - cu[0];                                                                     \
                dv[j] = cv[j] - cv[0];                                                                     \
            }                                                                                              \
            for (int j = 0; j < 3; ++j) {                                                                  \
                T ua = du[(j + 1) % 3], va = dv[(j + 1) % 3];                                              \
                eu[j] = du[(j + 2) % 3] - ua;                                                              \
                ev[j] = dv[(j + 2) % 3] - va;                                                              \
                a[j] = ev[j] * ua - eu[j] * va;                                                            \
            }                                                                                              \
            T tot = a[0] + a[1];                                                                           \
            tot = tot + a[2];                                                                              \
            if (!(fabs((double)tot) > (double)eps))                                                        \
                tot = eps;                                                                                 \
            row[0] = cu[0];                                                                                \
            row[1] = cv[0];                                                                                \
            for (int j = 0; j < 3; ++j) {                                                                  \
                row[2 + j] = du[j];                                                                        \
                row[5 + j] = dv[j];                                                                        \
                row[8 + j] = a[j] / tot;                                                                   \
                row[11 + j] = -ev[j] / tot;                                                                \
                row[14 + j] = eu[j] / tot;                                                                 \
            }                                                                                              \
            row[20] = tot;                                                                                 \
        }                                                                                                  \
        const int64_t N = Ni + No;                                                                         \
        for (int64_t i = 0; i < Ni; ++i) {                                                                 \
            const T *row = ft + FT * in_slot[i];                                                           \
            T Pu = ((T)(in_pix[i] % S) + (T)0.5) - row[0];                                                 \
            T Pv = ((T)((in_pix[i] / S) % S) + (T)0.5) - row[1];                                           \
            for (int j = 0; j < 3; ++j) {                                                                  \
                T lj = row[8 + j] + row[11 + j] * Pu;                                                      \
                l[j * N + i] = lj + row[14 + j] * Pv;                                                      \
                iz[j * N + i] = row[17 + j];                                                               \
            }                                                                                              \
        }                                                                                                  \
        for (int64_t q = 0; q < Q; ++q) { /* pos[q]: the shaded sample's column - Ni (outside), or -1 */   \
            const T *row = ft + FT * fr_slot[q];                                                           \
            foot_##T f = foot_of_##T(row, fr_k[q], fr_pix[q], S, eps);                                     \
            T ex = f.au + f.t * f.dx - f.Qu, ey = f.av + f.t * f.dy - f.Qv;                                \
            T d2 = ex * ex + ey * ey;                                                                      \
            T d = SQRT(d2 < eps * eps ? eps * eps : d2);                                                   \
            cov[q] = (T)1 / ((T)1 + EXP(-(fr_sign[q] * d / sigma)));                                       \
            if (pos[q] < 0)                                                                                \
                continue;                                                                                  \
            for (int j = 0; j < 3; ++j) {                                                                  \
                l[j * N + Ni + pos[q]] = j == f.e0 ? (T)1 - f.t : (j == f.e1 ? f.t : (T)0);                \
                iz[j * N + Ni + pos[q]] = row[17 + j];                                                     \
            }                                                                                              \
        }                                                                                                  \
    }                                                                                                      \
    /* Backward: g_l, g_iz (3, Ni + No), g_cov (Q) -> g_u, g_v, g_z (B * n), accumulated (zeroed by the    \
     * caller); ft is the forward's table. */                                                              \
    void NAME_B(int64_t U, const T *z, const int64_t *ci, int64_t nv, int64_t Ni, const int64_t *in_pix,    \
                const int64_t *in_slot, int64_t Q, const int64_t *fr_pix, const int64_t *fr_slot,            \
                const int64_t *fr_k, const T *fr_sign, int64_t No, const int64_t *pos,                       \
                int64_t S, double sigma_, double eps_, const T *ft, const T *cov, const T *g_l,             \
                const T *g_iz, const T *g_cov, T *g_u, T *g_v, T *g_z)                                      \
    {                                                                                                      \
        const T eps = (T)eps_, sigma = (T)sigma_;                                                          \
        const int64_t N = Ni + No;                                                                         \
        for (int64_t i = 0; i < Ni; ++i) {                                                                 \
            int64_t s = in_slot[i];                                                                        \
            const T *row = ft + FT * s;                                                                    \
            T Pu = ((T)(in_pix[i] % S) + (T)0.5) - row[0];                                                 \
            T Pv = ((T)((in_pix[i] / S) % S) + (T)0.5) - row[1];                                           \
            T tot = row[20], gw[3], gll = 0;                                                               \
            for (int j = 0; j < 3; ++j) {                                                                  \
                T gl = g_l[j * N + i];                                                                     \
                T lj = row[8 + j] + row[11 + j] * Pu;                                                      \
                lj = lj + row[14 + j] * Pv;                                                                \
                gw[j] = gl / tot;                                                                          \
                gll += gl * lj;                                                                            \
            }                                                                                              \
            T gT = tot == eps ? (T)0 : -gll / tot;                                                         \
            for (int j = 0; j < 3; ++j) {                                                                  \
                int j1 = (j + 1) % 3, j2 = (j + 2) % 3;                                                    \
                T X1 = row[2 + j1], X2 = row[2 + j2], Y1 = row[5 + j1], Y2 = row[5 + j2];                  \
                T gx = gw[j2] * (Y1 - Pv) + gw[j1] * (Pv - Y2) + gT * (Y1 - Y2);                           \
                T gy = gw[j2] * (Pu - X1) + gw[j1] * (X2 - Pu) + gT * (X2 - X1);                           \
                int64_t c = ci[j * U + s];                                                                 \
                g_u[c] += gx;                                                                              \
                g_v[c] += gy;                                                                              \
                g_z[c] += g_iz[j * N + i];                                                                 \
            }                                                                                              \
        }                                                                                                  \
        for (int64_t q = 0; q < Q; ++q) {                                                                  \
            int64_t s = fr_slot[q], o = pos[q]; /* o: the shaded sample's column - Ni, or -1 */            \
            const T *row = ft + FT * s;                                                                    \
            foot_##T f = foot_of_##T(row, fr_k[q], fr_pix[q], S, eps);                                     \
            const int e0 = f.e0, e1 = f.e1;                                                                \
            const T Qu = f.Qu, Qv = f.Qv, au = f.au, av = f.av, dx = f.dx, dy = f.dy;                      \
            const T L2 = f.L2, L2c = f.L2c, t_raw = f.t_raw, t = f.t;                                      \
            T ex = au + t * dx - Qu, ey = av + t * dy - Qv;                                                \
            T d2 = ex * ex + ey * ey;                                                                      \
            T d = SQRT(d2 < eps * eps ? eps * eps : d2);                                                   \
            T c_ = cov[q];                                                                                 \
            T gd = d2 >= eps * eps ? g_cov[q] * c_ * ((T)1 - c_) * fr_sign[q] / sigma : (T)0;              \
            T gex = gd * ex / d, gey = gd * ey / d;                                                        \
            T gt = gex * dx + gey * dy;                                                                    \
            if (o >= 0)                                                                                    \
                gt += g_l[e1 * N + Ni + o] - g_l[e0 * N + Ni + o];                                         \
            if (!(t_raw >= 0 && t_raw <= 1))                                                               \
                gt = 0;                                                                                    \
            T gn = gt / L2c;                                                                               \
            T gL2 = L2 >= eps ? -gn * t_raw : (T)0;                                                        \
            T ru = Qu - au, rv = Qv - av;                                                                  \
            T ga_u = gex * ((T)1 - t) - gn * (dx + ru) - 2 * gL2 * dx;                                     \
            T gb_u = gex * t + gn * ru + 2 * gL2 * dx;                                                     \
            T ga_v = gey * ((T)1 - t) - gn * (dy + rv) - 2 * gL2 * dy;                                     \
            T gb_v = gey * t + gn * rv + 2 * gL2 * dy;                                                     \
            int64_t c0 = ci[e0 * U + s], c1 = ci[e1 * U + s];                                              \
            g_u[c0] += ga_u;                                                                               \
            g_v[c0] += ga_v;                                                                               \
            g_u[c1] += gb_u;                                                                               \
            g_v[c1] += gb_v;                                                                               \
            if (o >= 0)                                                                                    \
                for (int j = 0; j < 3; ++j)                                                                \
                    g_z[ci[j * U + s]] += g_iz[j * N + Ni + o];                                            \
        }                                                                                                  \
        for (int64_t k = 0; k < nv; ++k) /* d(1 / z) / dz */                                               \
            g_z[k] = -g_z[k] / (z[k] * z[k]);                                                              \
    }

SAMPLE(sample_fwd_f32, sample_bwd_f32, float, sqrtf, expf)
SAMPLE(sample_fwd_f64, sample_bwd_f64, double, sqrt, exp)

/* Shading (shading._ShadeSamples). l, iz: (3, N); corners: (3, C, N), C = 6 (position, normal) or 7 (and
 * albedo); light: (3, N). Forward writes the shade (N); backward takes its gradient g (N) and writes g_l,
 * g_iz (3, N), g_corners (3, C, N) and g_light (3, N). */
#define SHADE_COMMON(T)                                                                                    \
    T q[3], bary[3], PN[7];                                                                                \
    for (int j = 0; j < 3; ++j)                                                                            \
        q[j] = l[j * N + i] * iz[j * N + i];                                                               \
    T s = q[0] + q[1];                                                                                     \
    s = s + q[2];                                                                                          \
    int pos = s > 0;                                                                                       \
    if (!pos)                                                                                              \
        s = 1;                                                                                             \
    const T inv_s = (T)1 / s;                                                                              \
    for (int j = 0; j < 3; ++j)                                                                            \
        bary[j] = q[j] * inv_s;                                                                            \
    for (int c = 0; c < C; ++c) {                                                                          \
        T p = bary[0] * corners[(0 * C + c) * N + i] + bary[1] * corners[(1 * C + c) * N + i];             \
        PN[c] = p + bary[2] * corners[(2 * C + c) * N + i];                                                \
    }                                                                                                      \
    T nv[3] = {PN[3], PN[4], PN[5]};                                                                       \
    T dv[3];                                                                                               \
    for (int k = 0; k < 3; ++k)                                                                            \
        dv[k] = light[k * N + i] - PN[k];                                                                  \
    T n_len = unit_len_##T(nv), d_len = unit_len_##T(dv);                                                  \
    T n_norm = n_len < eps ? eps : n_len, d_norm = d_len < eps ? eps : d_len;                              \
    const T inv_n = (T)1 / n_norm, inv_d = (T)1 / d_norm;                                                  \
    T n_hat[3], d_hat[3];                                                                                  \
    for (int k = 0; k < 3; ++k) {                                                                          \
        n_hat[k] = nv[k] * inv_n;                                                                          \
        d_hat[k] = dv[k] * inv_d;                                                                          \
    }                                                                                                      \
    T cth = n_hat[0] * d_hat[0] + n_hat[1] * d_hat[1];                                                     \
    cth = cth + n_hat[2] * d_hat[2];                                                                       \
    T lit = ambient + intensity * (cth < 0 ? (T)0 : cth);                                                  \
    T reflect = C == 7 ? PN[6] * albedo : albedo;

/* |x| taken on x over its largest component, held at the dtype's largest value: the rare branch of both
 * the shading's unit vectors (shading._unit, where a square overflowed: a light 1e20 away) and the normals'
 * lengths (operators.safe_norm, where a square left the normal range), as operators.scaled_norm. */
#define SCALED_LEN(T, SQRT, FABS, MAXV)                                                                    \
    static inline T scaled_len_##T(T x0, T x1, T x2)                                                       \
    {                                                                                                      \
        T mx = FABS(x0);                                                                                   \
        if (FABS(x1) > mx)                                                                                 \
            mx = FABS(x1);                                                                                 \
        if (FABS(x2) > mx)                                                                                 \
            mx = FABS(x2);                                                                                 \
        if (!(mx > 0))                                                                                     \
            return mx; /* NaN stays NaN, as in torch */                                                    \
        T a = x0 / mx, b = x1 / mx, c = x2 / mx;                                                           \
        T len = SQRT(a * a + b * b + c * c) * mx;                                                          \
        return len > MAXV ? MAXV : len;                                                                    \
    }                                                                                                      \
    static inline T unit_len_##T(const T *x)                                                               \
    {                                                                                                      \
        T d = x[0] * x[0] + x[1] * x[1];                                                                   \
        d = d + x[2] * x[2];                                                                               \
        T len = SQRT(d);                                                                                   \
        return len < (T)INFINITY ? len : scaled_len_##T(x[0], x[1], x[2]);                                 \
    }

SCALED_LEN(float, sqrtf, fabsf, 3.4028234663852886e38f)
SCALED_LEN(double, sqrt, fabs, 1.7976931348623157e308)

#define SHADE(NAME_F, NAME_B, T)                                                                           \
    void NAME_F(int64_t N, int64_t C, const T *l, const T *iz, const T *corners, const T *light,           \
                double ambient_, double intensity_, double albedo_, double eps_, T *shade)                 \
    {                                                                                                      \
        const T ambient = (T)ambient_, intensity = (T)intensity_, albedo = (T)albedo_, eps = (T)eps_;      \
        for (int64_t i = 0; i < N; ++i) {                                                                  \
            SHADE_COMMON(T)                                                                                \
            shade[i] = reflect * lit;                                                                      \
        }                                                                                                  \
    }                                                                                                      \
    void NAME_B(int64_t N, int64_t C, const T *l, const T *iz, const T *corners, const T *light,           \
                double ambient_, double intensity_, double albedo_, double eps_, const T *g, T *g_l,        \
                T *g_iz, T *g_corners, T *g_light)                                                         \
    {                                                                                                      \
        const T ambient = (T)ambient_, intensity = (T)intensity_, albedo = (T)albedo_, eps = (T)eps_;      \
        for (int64_t i = 0; i < N; ++i) {                                                                  \
            SHADE_COMMON(T)                                                                                \
            T gc = cth >= 0 ? g[i] * reflect * intensity : (T)0;                                           \
            T gx[3], gy[3], gN[3], gD[3];                                                                  \
            for (int k = 0; k < 3; ++k) {                                                                  \
                gx[k] = gc * d_hat[k];                                                                     \
                gy[k] = gc * n_hat[k];                                                                     \
            }                                                                                              \
            T pn = n_hat[0] * gx[0] + n_hat[1] * gx[1] + n_hat[2] * gx[2];                                 \
            T pd = d_hat[0] * gy[0] + d_hat[1] * gy[1] + d_hat[2] * gy[2];                                 \
            if (!(n_len > eps))                                                                            \
                pn = 0;                                                                                    \
            if (!(d_len > eps))                                                                            \
                pd = 0;                                                                                    \
            for (int k = 0; k < 3; ++k) {                                                                  \
                gN[k] = (gx[k] - pn * n_hat[k]) * inv_n;                                                   \
                gD[k] = (gy[k] - pd * d_hat[k]) * inv_d;                                                   \
            }                                                                                              \
            T gPN[7] = {-gD[0], -gD[1], -gD[2], gN[0], gN[1], gN[2], C == 7 ? g[i] * lit * albedo : (T)0}; \
            T gb[3];                                                                                       \
            for (int j = 0; j < 3; ++j) {                                                                  \
                T acc = 0;                                                                                 \
                for (int c = 0; c < C; ++c) {                                                              \
                    g_corners[(j * C + c) * N + i] = bary[j] * gPN[c];                                     \
                    acc += corners[(j * C + c) * N + i] * gPN[c];                                          \
                }                                                                                          \
                gb[j] = acc;                                                                               \
            }                                                                                              \
            T gbb = gb[0] * bary[0] + gb[1] * bary[1] + gb[2] * bary[2];                                   \
            for (int j = 0; j < 3; ++j) {                                                                  \
                T gq = pos ? (gb[j] - gbb) * inv_s : gb[j];                                                \
                g_l[j * N + i] = gq * iz[j * N + i];                                                       \
                g_iz[j * N + i] = gq * l[j * N + i];                                                       \
            }                                                                                              \
            for (int k = 0; k < 3; ++k)                                                                    \
                g_light[k * N + i] = gD[k];                                                                \
        }                                                                                                  \
    }

SHADE(shade_fwd_f32, shade_bwd_f32, float)
SHADE(shade_fwd_f64, shade_bwd_f64, double)

/* ------------------------------------------------------------------------------------------------------
 * The whole no-grad front of passes.run_passes in one call: cull (passes._cull), z-buffer, contour
 * segments (passes._contour_segments), nearest-segment buffer, soft pixels (passes._soft_pixels), the
 * covered and fringe samples and the used faces (samples.used_faces), with the same arithmetic as the
 * torch code, so every decision is the same (up to the square root's last bit: see the top).
 *
 * Inputs: U, Vv, Z (B, n) pixel coordinates and depth (1 where outside [znear, zfar]), ok (B, n) in depth
 * range; F (m, 3); et (m, 15) the topology's edge table. Work arrays (caller-allocated): keep, front
 * (B * m) uint8; slot_of, kept (B * m) int64; seg (9 * B * m) int64, (slot, k, b) per contour segment;
 * zkey, skey (B * S * S) int64; box (4 * B * m) T, the kept faces' screen boxes; integral (B * (S + 1)^2)
 * int32.
 * Outputs (caller-allocated at their largest): face_id (B*S*S); in_pix, in_b, in_f, in_slot (B*S*S);
 * fr_pix, fr_b, fr_f, fr_k, fr_slot (B*S*S); used (B * m); corner_index (3, B * m) read as (3, U) with the
 * row stride B * m; counts[4] = {K kept faces, Ni covered, Nf fringe, U used}.
 */
static inline void keep_min(int64_t *pixel_key, int64_t key)
{
    if (key < *pixel_key)
        *pixel_key = key;
}

static inline void pix_range(double lo_, double hi_, int64_t S, int64_t *lo, int64_t *hi, int is_f32)
{
    /* passes._ranges: ceil(clamp(lo, -2, S + 2) - 0.5) clamped to [0, S], floor(clamp(hi, ...) - 0.5)
     * clamped to [-1, S - 1], in the dtype of the coordinates */
    double a = lo_ < -2.0 ? -2.0 : (lo_ > S + 2.0 ? S + 2.0 : lo_);
    double b = hi_ < -2.0 ? -2.0 : (hi_ > S + 2.0 ? S + 2.0 : hi_);
    double la, hb;
    if (is_f32) {
        la = ceilf((float)a - 0.5f);
        hb = floorf((float)b - 0.5f);
    } else {
        la = ceil(a - 0.5);
        hb = floor(b - 0.5);
    }
    int64_t l = (int64_t)la, h = (int64_t)hb;
    *lo = l < 0 ? 0 : (l > S ? S : l);
    *hi = h < -1 ? -1 : (h > S - 1 ? S - 1 : h);
}

#define FRONT(NAME, T, IS_F32, SQRT)                                                                       \
    void NAME(int64_t B, int64_t n, int64_t m, const T *U, const T *Vv, const T *Z, const uint8_t *ok,     \
              const int64_t *F, const int64_t *et, int64_t S, double margin_, double eps_, uint8_t *keep,    \
              uint8_t *front, int64_t *slot_of, int64_t *kept, int64_t *seg, int64_t *zkey, int64_t *skey,   \
              T *box, int32_t *integral, int64_t *face_id, int64_t *in_pix, int64_t *in_b, int64_t *in_f,    \
              int64_t *in_slot, int64_t *fr_pix, int64_t *fr_b, int64_t *fr_f, int64_t *fr_k,                \
              int64_t *fr_slot, int64_t *used, int64_t *corner_index, int64_t *counts)                       \
    {                                                                                                      \
        const T margin = (T)margin_, eps = (T)eps_;                                                        \
        /* the torch code compares with the Python floats -margin and S + margin, cast to the dtype */     \
        const T lo_m = (T)(-margin_), hi_m = (T)((double)S + margin_);                                     \
        const int64_t P = S * S, BM = B * m;                                                               \
        /* cull: keep faces with every corner in depth range whose box reaches the grown image */          \
        int64_t K = 0;                                                                                     \
        for (int64_t b = 0; b < B; ++b)                                                                    \
            for (int64_t f = 0; f < m; ++f) {                                                              \
                const int64_t *c = F + 3 * f, g = b * m + f;                                               \
                const T *u = U + b * n, *v = Vv + b * n;                                                   \
                T u0 = u[c[0]], u1 = u[c[1]], u2 = u[c[2]], v0 = v[c[0]], v1 = v[c[1]], v2 = v[c[2]];      \
                T umin = u0 < u1 ? u0 : u1, umax = u0 > u1 ? u0 : u1;                                      \
                umin = umin < u2 ? umin : u2;                                                              \
                umax = umax > u2 ? umax : u2;                                                              \
                T vmin = v0 < v1 ? v0 : v1, vmax = v0 > v1 ? v0 : v1;                                      \
                vmin = vmin < v2 ? vmin : v2;                                                              \
                vmax = vmax > v2 ? vmax : v2;                                                              \
                const uint8_t *o = ok + b * n;                                                             \
                int k_ = o[c[0]] && o[c[1]] && o[c[2]] && umax >= lo_m && umin <= hi_m && vmax >= lo_m &&  \
                         vmin <= hi_m;                                                                     \
                T area2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0);                                   \
                keep[g] = (uint8_t)k_;                                                                     \
                front[g] = area2 < 0;                                                                      \
                slot_of[g] = -1;                                                                           \
                if (k_) {                                                                                  \
                    T *row = box + 4 * K;                                                               \
                    row[0] = umin;                                                                         \
                    row[1] = umax;                                                                         \
                    row[2] = vmin;                                                                         \
                    row[3] = vmax;                                                                         \
                    kept[K++] = g;                                                                         \
                }                                                                                          \
            }                                                                                              \
        counts[0] = K;                                                                                     \
        for (int64_t i = 0; i < B * P; ++i)                                                                \
            zkey[i] = skey[i] = NONE;                                                                      \
        /* z-buffer (passes._zbuffer): edge k from corner k + 1 to k + 2 in canonical order */             \
        for (int64_t s = 0; s < K; ++s) {                                                                  \
            int64_t g = kept[s], b = g / m, f = g % m;                                                     \
            const int64_t *c = F + 3 * f;                                                                  \
            const T *u = U + b * n, *v = Vv + b * n, *zz = Z + b * n;                                      \
            const T *row = box + 4 * s;                                                                 \
            T ax[3], ay[3], dx[3], dy[3], iz[3];                                                           \
            for (int k = 0; k < 3; ++k) {                                                                  \
                int64_t p1 = c[(k + 1) % 3], p2 = c[(k + 2) % 3];                                          \
                int flip = et[15 * f + 12 + k] != 0;                                                       \
                T u1 = u[p1], u2 = u[p2], v1 = v[p1], v2 = v[p2];                                          \
                T sg = flip ? (T)-1 : (T)1;                                                                \
                ax[k] = flip ? u2 : u1;                                                                    \
                ay[k] = flip ? v2 : v1;                                                                    \
                dx[k] = sg * ((flip ? u1 : u2) - ax[k]);                                                   \
                dy[k] = sg * ((flip ? v1 : v2) - ay[k]);                                                   \
                iz[k] = (T)1 / zz[c[k]];                                                                   \
            }                                                                                              \
            int64_t lo[2], hi[2];                                                                          \
            pix_range((double)row[0], (double)row[1], S, &lo[0], &hi[0], IS_F32);                          \
            pix_range((double)row[2], (double)row[3], S, &lo[1], &hi[1], IS_F32);                          \
            int64_t *img = zkey + b * P;                                                                   \
            for (int64_t i = lo[1]; i <= hi[1]; ++i) {                                                     \
                T py = (T)i + (T)0.5;                                                                      \
                for (int64_t j = lo[0]; j <= hi[0]; ++j) {                                                 \
                    T px = (T)j + (T)0.5;                                                                  \
                    T w[3];                                                                                \
                    for (int k = 0; k < 3; ++k) {                                                          \
                        T a = dx[k] * (py - ay[k]);                                                        \
                        T bb = dy[k] * (px - ax[k]);                                                       \
                        w[k] = a - bb;                                                                     \
                    }                                                                                      \
                    T tot = w[0] + w[1];                                                                   \
                    tot = tot + w[2];                                                                      \
                    int inside;                                                                            \
                    if (tot > 0)                                                                           \
                        inside = w[0] >= 0 && w[1] >= 0 && w[2] >= 0;                                      \
                    else if (tot < 0)                                                                      \
                        inside = w[0] <= 0 && w[1] <= 0 && w[2] <= 0;                                      \
                    else                                                                                   \
                        inside = 0;                                                                        \
                    if (!inside)                                                                           \
                        continue;                                                                          \
                    T wz0 = w[0] * iz[0], wz1 = w[1] * iz[1], wz2 = w[2] * iz[2];                          \
                    T den = wz0 + wz1;                                                                     \
                    den = den + wz2;                                                                       \
                    float depth = (float)(tot / den);                                                      \
                    if (depth < 0)                                                                         \
                        depth = 0;                                                                         \
                    keep_min(img + i * S + j, pack(depth, s));                                             \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
        /* contour segments (passes._contour_segments), slot-major then k, and their buffer */             \
        int64_t Q = 0;                                                                                     \
        for (int64_t s = 0; s < K; ++s) {                                                                  \
            int64_t g = kept[s], b = g / m, f = g % m;                                                     \
            const int64_t *c = F + 3 * f, *e = et + 15 * f;                                                \
            const T *u = U + b * n, *v = Vv + b * n;                                                       \
            for (int k = 0; k < 3; ++k) {                                                                  \
                int64_t tf = e[9 + k];                                                                     \
                int tkeep = tf >= 0 && keep[b * m + tf];                                                   \
                int contour = 1;                                                                           \
                if (tkeep) {                                                                               \
                    T Lu = u[e[k]], Lv = v[e[k]], Hu = u[e[3 + k]], Hv = v[e[3 + k]];                      \
                    T Ou = u[e[6 + k]], Ov = v[e[6 + k]], Ku = u[c[k]], Kv = v[c[k]];                      \
                    T side_f = (Hu - Lu) * (Kv - Lv) - (Hv - Lv) * (Ku - Lu);                              \
                    T side_g = (Hu - Lu) * (Ov - Lv) - (Hv - Lv) * (Ou - Lu);                              \
                    contour = !(side_f * side_g < 0);                                                      \
                }                                                                                          \
                if (!contour)                                                                              \
                    continue;                                                                              \
                int fr = front[g], gfr = tf >= 0 ? front[b * m + tf] : 0;                                  \
                int owner = !tkeep || (fr && !gfr) || (fr == gfr && f < tf);                               \
                if (!owner)                                                                                \
                    continue;                                                                              \
                seg[3 * Q] = s;                                                                            \
                seg[3 * Q + 1] = k;                                                                        \
                seg[3 * Q + 2] = b;                                                                        \
                ++Q;                                                                                       \
            }                                                                                              \
        }                                                                                                  \
        for (int64_t q = 0; q < Q; ++q) {                                                                  \
            int64_t s = seg[3 * q], k = seg[3 * q + 1], b = seg[3 * q + 2], f = kept[s] % m;               \
            const int64_t *c = F + 3 * f;                                                                  \
            const T *u = U + b * n, *v = Vv + b * n;                                                       \
            const T ax = u[c[(k + 1) % 3]], ay = v[c[(k + 1) % 3]];                                        \
            const T bx = u[c[(k + 2) % 3]], by = v[c[(k + 2) % 3]];                                        \
            int64_t lo[2], hi[2];                                                                          \
            pix_range((double)((ax < bx ? ax : bx) - margin), (double)((ax > bx ? ax : bx) + margin), S,   \
                      &lo[0], &hi[0], IS_F32);                                                             \
            pix_range((double)((ay < by ? ay : by) - margin), (double)((ay > by ? ay : by) + margin), S,   \
                      &lo[1], &hi[1], IS_F32);                                                             \
            const T dx = bx - ax, dy = by - ay;                                                            \
            T L2 = dx * dx;                                                                                \
            L2 = L2 + dy * dy;                                                                             \
            const T L2c = L2 < eps ? eps : L2;                                                             \
            int64_t *img = skey + b * P;                                                                   \
            for (int64_t i = lo[1]; i <= hi[1]; ++i) {                                                     \
                T py = (T)i + (T)0.5;                                                                      \
                for (int64_t j = lo[0]; j <= hi[0]; ++j) {                                                 \
                    T px = (T)j + (T)0.5;                                                                  \
                    T num = (px - ax) * dx;                                                                \
                    num = num + (py - ay) * dy;                                                            \
                    T t = num / L2c;                                                                       \
                    t = t < 0 ? 0 : (t > 1 ? 1 : t);                                                       \
                    T ex = ax + t * dx;                                                                    \
                    ex = ex - px;                                                                          \
                    T ey = ay + t * dy;                                                                    \
                    ey = ey - py;                                                                          \
                    T d2 = ex * ex;                                                                        \
                    d2 = d2 + ey * ey;                                                                     \
                    T d = SQRT(d2);                                                                        \
                    if (!(d <= margin))                                                                    \
                        continue;                                                                          \
                    keep_min(img + i * S + j, pack((float)d, q));                                          \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
        /* face ids, covered samples (pixel order) */                                                      \
        int64_t Ni = 0;                                                                                    \
        for (int64_t p = 0; p < B * P; ++p) {                                                              \
            if (zkey[p] == NONE) {                                                                         \
                face_id[p] = -1;                                                                           \
                continue;                                                                                  \
            }                                                                                              \
            int64_t g = kept[zkey[p] & 0xFFFFFFFF];                                                        \
            face_id[p] = g % m;                                                                            \
            in_pix[Ni] = p;                                                                                \
            in_b[Ni] = p / P;                                                                              \
            in_f[Ni] = g % m;                                                                              \
            ++Ni;                                                                                          \
            slot_of[g] = 0;                                                                                \
        }                                                                                                  \
        /* soft pixels (passes._soft_pixels): near a segment, and if covered, within reach of the          \
         * background (an integral image of uncovered pixels, the box clipped to the image) */             \
        const int64_t reach = (int64_t)ceil((double)margin_ + 1.5), W = S + 1;                             \
        for (int64_t b = 0; b < B; ++b) {                                                                  \
            int32_t *tab = integral + b * W * W;                                                           \
            for (int64_t j = 0; j < W; ++j)                                                                \
                tab[j] = 0;                                                                                \
            for (int64_t i = 0; i < S; ++i) {                                                              \
                int32_t run = 0;                                                                           \
                tab[(i + 1) * W] = 0;                                                                      \
                for (int64_t j = 0; j < S; ++j) {                                                          \
                    run += zkey[b * P + i * S + j] == NONE;                                                \
                    tab[(i + 1) * W + j + 1] = tab[i * W + j + 1] + run;                                   \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
        int64_t Nf = 0;                                                                                    \
        for (int64_t p = 0; p < B * P; ++p) {                                                              \
            if (skey[p] == NONE)                                                                           \
                continue;                                                                                  \
            if (zkey[p] != NONE) {                                                                         \
                int64_t b = p / P, i = (p / S) % S, j = p % S;                                             \
                int64_t i0 = i - reach < 0 ? 0 : i - reach, i1 = i + reach + 1 > S ? S : i + reach + 1;    \
                int64_t j0 = j - reach < 0 ? 0 : j - reach, j1 = j + reach + 1 > S ? S : j + reach + 1;    \
                const int32_t *tab = integral + b * W * W;                                                 \
                int32_t cnt = tab[i1 * W + j1] - tab[i0 * W + j1] - tab[i1 * W + j0] + tab[i0 * W + j0];   \
                if (cnt <= 0)                                                                              \
                    continue;                                                                              \
            }                                                                                              \
            int64_t q = skey[p] & 0xFFFFFFFF, s = seg[3 * q], g = kept[s];                                 \
            fr_pix[Nf] = p;                                                                                \
            fr_b[Nf] = g / m;                                                                              \
            fr_f[Nf] = g % m;                                                                              \
            fr_k[Nf] = seg[3 * q + 1];                                                                     \
            ++Nf;                                                                                          \
            slot_of[g] = 0;                                                                                \
        }                                                                                                  \
        /* used faces (samples.used_faces): marked (b, f) in increasing b * m + f, with their corners */   \
        int64_t Uc = 0;                                                                                    \
        for (int64_t g = 0; g < BM; ++g)                                                                   \
            if (slot_of[g] == 0) {                                                                         \
                slot_of[g] = Uc;                                                                           \
                used[Uc++] = g;                                                                            \
            }                                                                                              \
        for (int64_t t = 0; t < Uc; ++t) {                                                                 \
            int64_t g = used[t], b = g / m, f = g % m;                                                     \
            for (int j = 0; j < 3; ++j)                                                                    \
                corner_index[j * BM + t] = b * n + F[3 * f + j];                                           \
        }                                                                                                  \
        for (int64_t i = 0; i < Ni; ++i)                                                                   \
            in_slot[i] = slot_of[in_b[i] * m + in_f[i]];                                                   \
        for (int64_t i = 0; i < Nf; ++i)                                                                   \
            fr_slot[i] = slot_of[fr_b[i] * m + fr_f[i]];                                                   \
        counts[1] = Ni;                                                                                    \
        counts[2] = Nf;                                                                                    \
        counts[3] = Uc;                                                                                    \
    }

FRONT(front_f32, float, 1, sqrtf)
FRONT(front_f64, double, 0, sqrt)

/* ------------------------------------------------------------------------------------------------------
 * Area-weighted vertex normals (operators.vertex_normals_from_corners): per face the cross product
 * c = (b - a) x (c - a) and its length, summed at the face's corners into acc (B, n, 4); the normal is
 * acc[:3] / max(|acc[:3]|, eps * acc[3]), zero where both vanish. Lengths as operators.safe_norm: the plain
 * sqrt where the square is in range, else taken on the vector over its largest component. Backward takes
 * the normals' gradient (B, n, 3) and the forward's acc and accumulates into gV (B, n, 3, zeroed); work:
 * (B, n, 4). */
#define NORMALS(NAME_F, NAME_B, T, SQRT, TINY, MAXV)                                                  \
    static inline T snorm_##T(T x0, T x1, T x2)                                                            \
    {                                                                                                      \
        T sq = x0 * x0 + x1 * x1;                                                                          \
        sq = sq + x2 * x2;                                                                                 \
        if ((sq < TINY || sq > MAXV) && (x0 != 0 || x1 != 0 || x2 != 0))                                  \
            return scaled_len_##T(x0, x1, x2);                                                             \
        return sq > 0 ? SQRT(sq < TINY ? TINY : sq) : (T)0;                                                \
    }                                                                                                      \
    static inline void face_cross_##T(const T *V, const int64_t *f, T *e1, T *e2, T *cr)                   \
    {                                                                                                      \
        const T *a = V + 3 * f[0], *b = V + 3 * f[1], *c = V + 3 * f[2];                                   \
        for (int k = 0; k < 3; ++k) {                                                                      \
            e1[k] = b[k] - a[k];                                                                           \
            e2[k] = c[k] - a[k];                                                                           \
        }                                                                                                  \
        cr[0] = e1[1] * e2[2] - e1[2] * e2[1];                                                             \
        cr[1] = e1[2] * e2[0] - e1[0] * e2[2];                                                             \
        cr[2] = e1[0] * e2[1] - e1[1] * e2[0];                                                             \
    }                                                                                                      \
    void NAME_F(int64_t B, int64_t n, int64_t m, const T *V, const int64_t *F, double eps_, T *acc, T *out) \
    {                                                                                                      \
        const T eps = (T)eps_;                                                                             \
        for (int64_t i = 0; i < B * n * 4; ++i)                                                            \
            acc[i] = 0;                                                                                    \
        for (int64_t b = 0; b < B; ++b) {                                                                  \
            const T *Vb = V + b * n * 3;                                                                   \
            T *ab = acc + b * n * 4;                                                                       \
            for (int64_t f = 0; f < m; ++f) {                                                              \
                T e1[3], e2[3], cr[3];                                                                     \
                face_cross_##T(Vb, F + 3 * f, e1, e2, cr);                                                 \
                T w = snorm_##T(cr[0], cr[1], cr[2]);                                                      \
                for (int k = 0; k < 3; ++k) {                                                              \
                    T *r = ab + 4 * F[3 * f + k];                                                          \
                    r[0] += cr[0];                                                                         \
                    r[1] += cr[1];                                                                         \
                    r[2] += cr[2];                                                                         \
                    r[3] += w;                                                                             \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
        for (int64_t v = 0; v < B * n; ++v) {                                                              \
            const T *r = acc + 4 * v;                                                                      \
            T L = snorm_##T(r[0], r[1], r[2]), fl = eps * r[3];                                            \
            T den = L > fl ? L : fl;                                                                       \
            for (int k = 0; k < 3; ++k)                                                                    \
                out[3 * v + k] = den > 0 ? r[k] / den : (T)0;                                              \
        }                                                                                                  \
    }                                                                                                      \
    void NAME_B(int64_t B, int64_t n, int64_t m, const T *V, const int64_t *F, double eps_, const T *acc,  \
                const T *g, T *work, T *gV)                                                                \
    {                                                                                                      \
        const T eps = (T)eps_;                                                                             \
        for (int64_t v = 0; v < B * n; ++v) {                                                              \
            const T *r = acc + 4 * v, *gv = g + 3 * v;                                                     \
            T *wk = work + 4 * v;                                                                          \
            T L = snorm_##T(r[0], r[1], r[2]), fl = eps * r[3];                                            \
            wk[0] = wk[1] = wk[2] = wk[3] = 0;                                                             \
            if (L >= fl && L > 0) { /* x / |x| */                                                          \
                T inv = (T)1 / L, d = (r[0] * gv[0] + r[1] * gv[1] + r[2] * gv[2]) * inv * inv;            \
                for (int k = 0; k < 3; ++k)                                                                \
                    wk[k] = (gv[k] - d * r[k]) * inv;                                                      \
            } else if (fl > L) { /* x / (eps w): the floor of a vertex whose normals cancel */             \
                T inv = (T)1 / fl;                                                                         \
                for (int k = 0; k < 3; ++k)                                                                \
                    wk[k] = gv[k] * inv;                                                                   \
                wk[3] = -eps * (r[0] * gv[0] + r[1] * gv[1] + r[2] * gv[2]) * inv * inv;                   \
            }                                                                                              \
        }                                                                                                  \
        for (int64_t b = 0; b < B; ++b) {                                                                  \
            const T *Vb = V + b * n * 3;                                                                   \
            const T *wb = work + b * n * 4;                                                                \
            T *gb = gV + b * n * 3;                                                                        \
            for (int64_t f = 0; f < m; ++f) {                                                              \
                const int64_t *c = F + 3 * f;                                                              \
                T e1[3], e2[3], cr[3], gc[3] = {0, 0, 0}, gw = 0;                                          \
                for (int k = 0; k < 3; ++k) {                                                              \
                    const T *wk = wb + 4 * c[k];                                                           \
                    gc[0] += wk[0];                                                                        \
                    gc[1] += wk[1];                                                                        \
                    gc[2] += wk[2];                                                                        \
                    gw += wk[3];                                                                           \
                }                                                                                          \
                if (gc[0] == 0 && gc[1] == 0 && gc[2] == 0 && gw == 0)                                     \
                    continue;                                                                              \
                face_cross_##T(Vb, c, e1, e2, cr);                                                         \
                T len = snorm_##T(cr[0], cr[1], cr[2]);                                                    \
                if (len > 0 && gw != 0)                                                                    \
                    for (int k = 0; k < 3; ++k)                                                            \
                        gc[k] += gw * (cr[k] / len);                                                       \
                /* c = e1 x e2: g_e1 = e2 x gc, g_e2 = gc x e1 */                                          \
                T g1[3] = {e2[1] * gc[2] - e2[2] * gc[1], e2[2] * gc[0] - e2[0] * gc[2],                   \
                           e2[0] * gc[1] - e2[1] * gc[0]};                                                 \
                T g2[3] = {gc[1] * e1[2] - gc[2] * e1[1], gc[2] * e1[0] - gc[0] * e1[2],                   \
                           gc[0] * e1[1] - gc[1] * e1[0]};                                                 \
                for (int k = 0; k < 3; ++k) {                                                              \
                    gb[3 * c[0] + k] -= g1[k] + g2[k];                                                     \
                    gb[3 * c[1] + k] += g1[k];                                                             \
                    gb[3 * c[2] + k] += g2[k];                                                             \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
    }

NORMALS(normals_fwd_f32, normals_bwd_f32, float, sqrtf, 1.17549435082228751e-38f, 3.4028234663852886e38f)
NORMALS(normals_fwd_f64, normals_bwd_f64, double, sqrt, 2.2250738585072014e-308, 1.7976931348623157e308)

int meshmei_raster_abi(void) { return 5; }
