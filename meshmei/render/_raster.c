/* The rasterizer's two no-grad enumeration passes, compiled (see meshmei/render/native.py).
 *
 * Each function is the loop body of its torch twin in meshmei/render/passes.py, pair by pair, with the
 * same operations in the same order on the same dtype, so that the keys come out bit for bit the same
 * (compiled with -ffp-contract=off: no fused multiply-add; no -ffast-math). The tables, box ranges and
 * pixel offsets are built by the torch code and passed in; the boxes are clipped to the image there.
 *
 * Keys are int64: (float32 bits of the depth or distance) << 32 | the face's or segment's slot, and each
 * pixel keeps the smallest (the packed-key "amin" of the torch code; the order of the pairs does not
 * matter for a minimum).
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

/* Pass 1 (passes._zbuffer). table: (15, K) row-major, rows ax[3], ay[3], dx[3], dy[3], iz[3] of the K
 * kept faces (edge k from a along d, canonical order); lo, hi: (K, 2) inclusive (column, row) ranges;
 * pix0: (K,) the flat offset of the face's batch member's image; zkey: (B * S * S,). */
#define ZBUFFER(NAME, T)                                                                                   \
    void NAME(int64_t K, const T *table, const int64_t *lo, const int64_t *hi, const int64_t *pix0,      \
              int64_t S, int64_t *zkey)                                                                 \
    {                                                                                                      \
        for (int64_t f = 0; f < K; ++f) {                                                                  \
            T ax[3], ay[3], dx[3], dy[3], iz[3];                                                           \
            for (int k = 0; k < 3; ++k) {                                                                  \
                ax[k] = table[(0 + k) * K + f];                                                            \
                ay[k] = table[(3 + k) * K + f];                                                            \
                dx[k] = table[(6 + k) * K + f];                                                            \
                dy[k] = table[(9 + k) * K + f];                                                            \
                iz[k] = table[(12 + k) * K + f];                                                           \
            }                                                                                              \
            int64_t *img = zkey + pix0[f];                                                                 \
            for (int64_t i = lo[2 * f + 1]; i <= hi[2 * f + 1]; ++i) {                                     \
                T py = (T)i + (T)0.5;                                                                      \
                for (int64_t j = lo[2 * f]; j <= hi[2 * f]; ++j) {                                         \
                    T px = (T)j + (T)0.5;                                                                  \
                    T w[3];                                                                                \
                    for (int k = 0; k < 3; ++k) {                                                          \
                        T a = dx[k] * (py - ay[k]);                                                        \
                        T b = dy[k] * (px - ax[k]);                                                        \
                        w[k] = a - b;                                                                      \
                    }                                                                                      \
                    T tot = w[0] + w[1];                                                                   \
                    tot = tot + w[2];                                                                      \
                    int inside;                                                                            \
                    if (tot > 0)                                                                           \
                        inside = w[0] >= 0 && w[1] >= 0 && w[2] >= 0;                                      \
                    else if (tot < 0)                                                                      \
                        inside = w[0] <= 0 && w[1] <= 0 && w[2] <= 0;                                      \
                    else                                                                                   \
                        inside = 0; /* zero or NaN */                                                      \
                    if (!inside)                                                                           \
                        continue;                                                                          \
                    T wz0 = w[0] * iz[0], wz1 = w[1] * iz[1], wz2 = w[2] * iz[2];                          \
                    T den = wz0 + wz1;                                                                     \
                    den = den + wz2;                                                                       \
                    float depth = (float)(tot / den);                                                      \
                    if (depth < 0)                                                                         \
                        depth = 0;                                                                         \
                    int64_t key = pack(depth, f);                                                          \
                    int64_t *px_key = img + i * S + j;                                                     \
                    if (key < *px_key)                                                                     \
                        *px_key = key;                                                                     \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
    }

ZBUFFER(zbuffer_f32, float)
ZBUFFER(zbuffer_f64, double)

/* Pass 2 (passes._segment_buffer with samples.seg_dist). table: (Q, 4) row-major, a = (ax, ay) and
 * b = (bx, by) of the Q contour segments; lo, hi, pix0 as above over the boxes grown by the margin;
 * a pair within the margin writes its distance's key. */
#define SEGBUFFER(NAME, T, SQRT)                                                                           \
    void NAME(int64_t Q, const T *table, const int64_t *lo, const int64_t *hi, const int64_t *pix0,      \
              int64_t S, double margin_, double eps_, int64_t *skey)                                    \
    {                                                                                                      \
        const T margin = (T)margin_, eps = (T)eps_;                                                        \
        for (int64_t q = 0; q < Q; ++q) {                                                                  \
            const T ax = table[4 * q], ay = table[4 * q + 1], bx = table[4 * q + 2], by = table[4 * q + 3]; \
            const T dx = bx - ax, dy = by - ay;                                                            \
            T L2 = dx * dx;                                                                                \
            L2 = L2 + dy * dy;                                                                             \
            const T L2c = L2 < eps ? eps : L2;                                                             \
            int64_t *img = skey + pix0[q];                                                                 \
            for (int64_t i = lo[2 * q + 1]; i <= hi[2 * q + 1]; ++i) {                                     \
                T py = (T)i + (T)0.5;                                                                      \
                for (int64_t j = lo[2 * q]; j <= hi[2 * q]; ++j) {                                         \
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
                    int64_t key = pack((float)d, q);                                                       \
                    int64_t *px_key = img + i * S + j;                                                     \
                    if (key < *px_key)                                                                     \
                        *px_key = key;                                                                     \
                }                                                                                          \
            }                                                                                              \
        }                                                                                                  \
    }

SEGBUFFER(segbuffer_f32, float, sqrtf)
SEGBUFFER(segbuffer_f64, double, sqrt)

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
#define SAMPLE(NAME_F, NAME_B, T, SQRT, EXP)                                                               \
    void NAME_F(int64_t U, const T *u, const T *v, const T *z, const int64_t *ci, int64_t Ni,               \
                const int64_t *in_pix, const int64_t *in_slot, int64_t Q, const int64_t *fr_pix,             \
                const int64_t *fr_slot, const int64_t *fr_k, const T *fr_sign, int64_t No,                   \
                const int64_t *out, int64_t S, double sigma_, double eps_, T *ft, T *l, T *iz, T *cov)      \
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
        for (int64_t q = 0; q < Q; ++q) {                                                                  \
            const T *row = ft + FT * fr_slot[q];                                                           \
            int e0 = (int)((fr_k[q] + 1) % 3), e1 = (int)((fr_k[q] + 2) % 3);                              \
            T Qu = ((T)(fr_pix[q] % S) + (T)0.5) - row[0];                                                 \
            T Qv = ((T)((fr_pix[q] / S) % S) + (T)0.5) - row[1];                                           \
            T au = row[2 + e0], bu = row[2 + e1], av = row[5 + e0], bv = row[5 + e1];                      \
            T dx = bu - au, dy = bv - av;                                                                  \
            T L2 = dx * dx + dy * dy;                                                                      \
            T t = ((Qu - au) * dx + (Qv - av) * dy) / (L2 < eps ? eps : L2);                               \
            t = t < 0 ? 0 : (t > 1 ? 1 : t);                                                               \
            T ex = au + t * dx - Qu, ey = av + t * dy - Qv;                                                \
            T d2 = ex * ex + ey * ey;                                                                      \
            T d = SQRT(d2 < eps * eps ? eps * eps : d2);                                                   \
            cov[q] = (T)1 / ((T)1 + EXP(-(fr_sign[q] * d / sigma)));                                       \
        }                                                                                                  \
        for (int64_t o = 0; o < No; ++o) {                                                                 \
            int64_t q = out[o], i = Ni + o;                                                                \
            const T *row = ft + FT * fr_slot[q];                                                           \
            int e0 = (int)((fr_k[q] + 1) % 3), e1 = (int)((fr_k[q] + 2) % 3);                              \
            T Qu = ((T)(fr_pix[q] % S) + (T)0.5) - row[0];                                                 \
            T Qv = ((T)((fr_pix[q] / S) % S) + (T)0.5) - row[1];                                           \
            T au = row[2 + e0], bu = row[2 + e1], av = row[5 + e0], bv = row[5 + e1];                      \
            T dx = bu - au, dy = bv - av;                                                                  \
            T L2 = dx * dx + dy * dy;                                                                      \
            T t = ((Qu - au) * dx + (Qv - av) * dy) / (L2 < eps ? eps : L2);                               \
            t = t < 0 ? 0 : (t > 1 ? 1 : t);                                                               \
            for (int j = 0; j < 3; ++j) {                                                                  \
                l[j * N + i] = j == e0 ? (T)1 - t : (j == e1 ? t : (T)0);                                  \
                iz[j * N + i] = row[17 + j];                                                               \
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
            int e0 = (int)((fr_k[q] + 1) % 3), e1 = (int)((fr_k[q] + 2) % 3);                              \
            T Qu = ((T)(fr_pix[q] % S) + (T)0.5) - row[0];                                                 \
            T Qv = ((T)((fr_pix[q] / S) % S) + (T)0.5) - row[1];                                           \
            T au = row[2 + e0], bu = row[2 + e1], av = row[5 + e0], bv = row[5 + e1];                      \
            T dx = bu - au, dy = bv - av;                                                                  \
            T L2 = dx * dx + dy * dy;                                                                      \
            T L2c = L2 < eps ? eps : L2;                                                                   \
            T t_raw = ((Qu - au) * dx + (Qv - av) * dy) / L2c;                                             \
            T t = t_raw < 0 ? 0 : (t_raw > 1 ? 1 : t_raw);                                                 \
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
#define SHADE_COMMON(T, SQRT)                                                                              \
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

#define UNIT_LEN(T, SQRT, FABS, MAXV)                                                                      \
    static inline T unit_len_##T(const T *x)                                                               \
    {                                                                                                      \
        T d = x[0] * x[0] + x[1] * x[1];                                                                   \
        d = d + x[2] * x[2];                                                                               \
        T len = SQRT(d);                                                                                   \
        if (len < (T)INFINITY)                                                                             \
            return len;                                                                                    \
        /* a square overflowed (a light 1e20 away): the norm of x over its largest component */           \
        T m = FABS(x[0]);                                                                                  \
        if (FABS(x[1]) > m)                                                                                \
            m = FABS(x[1]);                                                                                \
        if (FABS(x[2]) > m)                                                                                \
            m = FABS(x[2]);                                                                                \
        if (!(m > 0))                                                                                      \
            return len;                                                                                    \
        T a = x[0] / m, b = x[1] / m, c = x[2] / m;                                                        \
        len = SQRT(a * a + b * b + c * c) * m;                                                             \
        return len > MAXV ? MAXV : len;                                                                    \
    }

UNIT_LEN(float, sqrtf, fabsf, 3.4028234663852886e38f)
UNIT_LEN(double, sqrt, fabs, 1.7976931348623157e308)

#define SHADE(NAME_F, NAME_B, T, SQRT)                                                                     \
    void NAME_F(int64_t N, int64_t C, const T *l, const T *iz, const T *corners, const T *light,           \
                double ambient_, double intensity_, double albedo_, double eps_, T *shade)                 \
    {                                                                                                      \
        const T ambient = (T)ambient_, intensity = (T)intensity_, albedo = (T)albedo_, eps = (T)eps_;      \
        for (int64_t i = 0; i < N; ++i) {                                                                  \
            SHADE_COMMON(T, SQRT)                                                                          \
            shade[i] = reflect * lit;                                                                      \
        }                                                                                                  \
    }                                                                                                      \
    void NAME_B(int64_t N, int64_t C, const T *l, const T *iz, const T *corners, const T *light,           \
                double ambient_, double intensity_, double albedo_, double eps_, const T *g, T *g_l,        \
                T *g_iz, T *g_corners, T *g_light)                                                         \
    {                                                                                                      \
        const T ambient = (T)ambient_, intensity = (T)intensity_, albedo = (T)albedo_, eps = (T)eps_;      \
        for (int64_t i = 0; i < N; ++i) {                                                                  \
            SHADE_COMMON(T, SQRT)                                                                          \
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

SHADE(shade_fwd_f32, shade_bwd_f32, float, sqrtf)
SHADE(shade_fwd_f64, shade_bwd_f64, double, sqrt)

int meshmei_raster_abi(void) { return 2; }
