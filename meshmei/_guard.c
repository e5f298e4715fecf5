/* The step guard's per-candidate check (meshmei.validity.StepGuard), compiled: the float64 face frame with
 * the quality and turn rules. It repeats meshmei.validity.face_frame in float64 operation by operation, in
 * the torch code's order, so its normals and qualities are the torch code's bit for bit (tested). */

#include <math.h>
#include <stdint.h>
#include <float.h>

int meshmei_guard_abi(void) { return 1; }

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
