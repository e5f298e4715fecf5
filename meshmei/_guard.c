/* The step guard's per-candidate check (meshmei.validity.StepGuard), compiled: the float64 face frame with
 * the quality and turn rules. It repeats meshmei.validity.face_frame in float64 operation by operation, in
 * the torch code's order, so its normals and qualities are the torch code's bit for bit (tested). And the
 * guard's barrier with its gradient (guard_barrier), in float64, equal to the torch code to rounding. */

#include <math.h>
#include <stdint.h>
#include <float.h>
#include <stddef.h>

int meshmei_guard_abi(void) { return 2; }

/* The step guard's face frame (meshmei.validity.face_frame in float64) runs in two passes with torch's
 * square root between them: torch's CPU square root of float64 is not correctly rounded (about one value in
 * eighty is an ulp away from C's sqrt), so the norms are left to it.
 *
 * guard_frame_parts: for each face of F (m, 3) over V (n, 3), the cross product (T1 - T0) x (T2 - T0) into
 * C (m, 3), its squared length (c0^2 + c1^2) + c2^2, raised to DBL_MIN (safe_norm's clamp), into S (m) for
 * the caller's square root, and the summed squared edge lengths 0 + |T2 - T1|^2 + |T0 - T2|^2 + |T1 - T0|^2
 * into L2 (m), each (x^2 + y^2) + z^2. torch's cross product kernel fuses the first product into the
 * subtraction where it was compiled with fused multiply-add; the caller's probe says whether (`fused`).
 * Returns -1 where a coordinate of V is not finite, 1 where a squared cross product leaves float64's normal
 * range and the vector is not zero (the scaled path of meshmei.operators.safe_norm: the caller runs the
 * torch code), else 0: then a cross product is zero exactly where its square is. */
int guard_frame_parts(int64_t n, int64_t m, const double *V, const int64_t *F, int fused, double *C, double *S,
                      double *L2) {
    const double tiny = DBL_MIN, big = DBL_MAX;
    for (int64_t i = 0; i < 3 * n; i++)
        if (!isfinite(V[i])) return -1;
    int scaled = 0;
    for (int64_t f = 0; f < m; f++) {
        const double *T0 = V + 3 * F[3 * f], *T1 = V + 3 * F[3 * f + 1], *T2 = V + 3 * F[3 * f + 2];
        double a[3], b[3], d0[3], d1[3], *c = C + 3 * f, p, q, t;
        for (int k = 0; k < 3; k++) a[k] = T1[k] - T0[k], b[k] = T2[k] - T0[k];
        if (fused) {
            q = a[2] * b[1], c[0] = fma(a[1], b[2], -q);
            q = a[0] * b[2], c[1] = fma(a[2], b[0], -q);
            q = a[1] * b[0], c[2] = fma(a[0], b[1], -q);
        } else {
            p = a[1] * b[2], q = a[2] * b[1], c[0] = p - q;
            p = a[2] * b[0], q = a[0] * b[2], c[1] = p - q;
            p = a[0] * b[1], q = a[1] * b[0], c[2] = p - q;
        }
        for (int k = 0; k < 3; k++) d0[k] = T2[k] - T1[k], d1[k] = T0[k] - T2[k];
        double s0 = d0[0] * d0[0], s1 = d1[0] * d1[0], s2 = a[0] * a[0];
        t = d0[1] * d0[1], s0 = s0 + t, t = d0[2] * d0[2], s0 = s0 + t;
        t = d1[1] * d1[1], s1 = s1 + t, t = d1[2] * d1[2], s1 = s1 + t;
        t = a[1] * a[1], s2 = s2 + t, t = a[2] * a[2], s2 = s2 + t;
        double l2 = 0.0 + s0;
        l2 = l2 + s1;
        L2[f] = l2 + s2;
        double sq = c[0] * c[0];
        t = c[1] * c[1], sq = sq + t, t = c[2] * c[2], sq = sq + t;
        S[f] = sq < tiny ? tiny : sq;
        if ((sq < tiny || sq > big) && (c[0] != 0.0 || c[1] != 0.0 || c[2] != 0.0)) scaled = 1;
    }
    return scaled;
}

/* guard_frame_finish: from guard_frame_parts' C and L2 and the square roots RS of its S (so the double
 * area dbl is RS where the cross product is not zero, else zero), the unit normals c / max(dbl, eps l2)
 * (zero where that is zero) into N (m, 3) and the qualities (qconst dbl) / max(l2, tiny) into Q (m);
 * the smallest quality into stats[0] and, with reference normals R (m, 3) (NULL: no turn rule), the number
 * of faces whose normal's cosine to its reference lies below cos_limit, both normals non-zero and the face
 * in `turn_faces` (NULL: every face), into stats[1]. */
void guard_frame_finish(int64_t m, const double *C, const double *RS, const double *L2, double eps, double qconst,
                        const double *R, double cos_limit, const uint8_t *turn_faces, double *N, double *Q,
                        double *stats) {
    const double tiny = DBL_MIN;
    double qmin = INFINITY, turned = 0.0, t;
    for (int64_t f = 0; f < m; f++) {
        const double *c = C + 3 * f;
        double *nf = N + 3 * f, l2 = L2[f];
        double dbl = (c[0] != 0.0 || c[1] != 0.0 || c[2] != 0.0) ? RS[f] : 0.0, floor_ = eps * l2;
        double den = dbl > floor_ ? dbl : floor_;
        if (den > 0.0) {
            for (int k = 0; k < 3; k++) nf[k] = c[k] / den;
        } else {
            nf[0] = nf[1] = nf[2] = 0.0;
        }
        double ql = qconst * dbl;
        Q[f] = ql / (l2 < tiny ? tiny : l2);
        if (Q[f] < qmin) qmin = Q[f];
        if (R && (!turn_faces || turn_faces[f])) {
            const double *r = R + 3 * f;
            double cs = nf[0] * r[0];
            t = nf[1] * r[1], cs = cs + t, t = nf[2] * r[2], cs = cs + t;
            double an = (fabs(nf[0]) + fabs(nf[1])) + fabs(nf[2]), ar = (fabs(r[0]) + fabs(r[1])) + fabs(r[2]);
            if (cs < cos_limit && an > 0.0 && ar > 0.0) turned += 1.0;
        }
    }
    stats[0] = qmin;
    stats[1] = turned;
}

/* incremental potential contact's barrier b(x) = -(x - h)^2 log(x / h) for x < h (x raised to `tiny`, the
 * caller's dtype's smallest normal number, as meshmei.contact.log_barrier clamps it), else 0; its slope into
 * *slope (0 where x was raised). The one copy of the formula in C: _contact.c's contact_energy calls it too. */
double meshmei_barrier(double x, double h, double tiny, double *slope) {
    if (!(x < h)) {
        *slope = 0.0;
        return 0.0;
    }
    double xc = x > tiny ? x : tiny, gap = xc - h, lg = log(xc / h);
    *slope = x > tiny ? -2.0 * gap * lg - gap * gap / xc : 0.0;
    return -gap * gap * lg;
}

/* The step guard's barrier (meshmei.validity.StepGuard.barrier) of B meshes V (B, n, 3) over the faces F
 * (m, 3), in float64, with its gradient in the same pass: per face, b(q - floor; q_band) on its quality
 * q = qconst |c| / l2 (c the cross product, l2 the summed squared edge lengths; q_band <= 0: none), and with
 * reference normals R (m, 3) (NULL: no turn energy), b(cos - cos_bound; band) on the cosine of its normal
 * c / max(|c|, eps l2) to its reference (band <= 0: none; turn_faces, NULL for every face, picks the faces
 * that have it). The energies go to energy[B]; with `grad` (else NULL) their gradients are added to grad
 * (B, n, 3). Returns -1 where a coordinate is not finite, 1 where a face inside a band has a squared cross
 * product outside float64's normal range (meshmei.operators.safe_norm's scaled path: the caller runs the
 * torch code), else 0. */
int guard_barrier(int64_t B, int64_t n, int64_t m, const double *V, const int64_t *F, const double *R,
                  const uint8_t *turn_faces, double floor_q, double q_band, double cos_bound, double band, double eps,
                  double qconst, double tiny, double *energy, double *grad) {
    for (int64_t i = 0; i < 3 * n * B; i++)
        if (!isfinite(V[i])) return -1;
    for (int64_t it = 0; it < B; it++) {
        const double *X = V + 3 * n * it;
        double *G = grad ? grad + 3 * n * it : NULL, e = 0.0;
        for (int64_t f = 0; f < m; f++) {
            const int64_t *t = F + 3 * f;
            const double *T0 = X + 3 * t[0], *T1 = X + 3 * t[1], *T2 = X + 3 * t[2];
            double a[3], b[3], e0[3], e1[3], c[3];
            for (int k = 0; k < 3; k++)
                a[k] = T1[k] - T0[k], b[k] = T2[k] - T0[k], e0[k] = T2[k] - T1[k], e1[k] = T0[k] - T2[k];
            c[0] = a[1] * b[2] - a[2] * b[1];
            c[1] = a[2] * b[0] - a[0] * b[2];
            c[2] = a[0] * b[1] - a[1] * b[0];
            double sq = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
            double l2 = (e0[0] * e0[0] + e0[1] * e0[1] + e0[2] * e0[2]) + (e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
                        + (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
            double dbl = sq > 0.0 ? sqrt(sq > DBL_MIN ? sq : DBL_MIN) : 0.0, L = l2 > DBL_MIN ? l2 : DBL_MIN;
            double q = qconst * dbl / L, sq_, sl_q = 0.0, sl_t = 0.0, cs = 0.0, den = 0.0;
            int inside = 0;
            if (q_band > 0.0 && q - floor_q < q_band) {
                e += meshmei_barrier(q - floor_q, q_band, tiny, &sq_);
                sl_q = sq_, inside = 1;
            }
            int turn = R && band > 0.0 && (!turn_faces || turn_faces[f]);
            if (turn) {
                const double *r = R + 3 * f;
                den = dbl > eps * l2 ? dbl : eps * l2;
                cs = den > 0.0 ? (c[0] * r[0] + c[1] * r[1] + c[2] * r[2]) / den : 0.0;
                if (cs - cos_bound < band) {
                    e += meshmei_barrier(cs - cos_bound, band, tiny, &sq_);
                    sl_t = sq_, inside = 1;
                }
            }
            if (!inside) continue;
            if ((sq < DBL_MIN || sq > DBL_MAX) && (c[0] != 0.0 || c[1] != 0.0 || c[2] != 0.0)) return 1;
            if (G == NULL || (sl_q == 0.0 && sl_t == 0.0)) continue;
            /* the energy's derivatives in c (gc) and in l2 (gl) */
            double gc[3] = {0.0, 0.0, 0.0}, gl = 0.0;
            if (sl_q != 0.0 && dbl > 0.0 && sq > DBL_MIN) {
                for (int k = 0; k < 3; k++) gc[k] += sl_q * qconst * c[k] / (dbl * L);
                if (l2 > DBL_MIN) gl -= sl_q * q / L;
            }
            if (sl_t != 0.0 && den > 0.0) {
                const double *r = R + 3 * f;
                if (dbl > eps * l2) { /* c / |c| */
                    for (int k = 0; k < 3; k++) gc[k] += sl_t * (r[k] - cs * c[k] / dbl) / dbl;
                } else { /* c / (eps l2) */
                    for (int k = 0; k < 3; k++) gc[k] += sl_t * r[k] / den;
                    gl -= sl_t * cs / l2;
                }
            }
            /* c = a x b: d(gc . c)/da = b x gc, /db = gc x a; l2's: 2 (e1 - a), 2 (a - e0), 2 (e0 - e1) */
            double ga[3] = {b[1] * gc[2] - b[2] * gc[1], b[2] * gc[0] - b[0] * gc[2], b[0] * gc[1] - b[1] * gc[0]};
            double gb[3] = {gc[1] * a[2] - gc[2] * a[1], gc[2] * a[0] - gc[0] * a[2], gc[0] * a[1] - gc[1] * a[0]};
            double *G0 = G + 3 * t[0], *G1 = G + 3 * t[1], *G2 = G + 3 * t[2];
            for (int k = 0; k < 3; k++) {
                G0[k] += -ga[k] - gb[k] + 2.0 * gl * (e1[k] - a[k]);
                G1[k] += ga[k] + 2.0 * gl * (a[k] - e0[k]);
                G2[k] += gb[k] + 2.0 * gl * (e0[k] - e1[k]);
            }
        }
        energy[it] = e;
    }
    return 0;
}
