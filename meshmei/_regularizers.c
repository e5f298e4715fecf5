/* The three default regularizers of meshmei.regularizers, compiled: the uniform Laplacian, edge-length and
 * triangle-area losses of B meshes V (B, n, 3) sharing one connectivity, each with its gradient, in one
 * float64 pass (the torch code is their reference, equal to rounding; tested). Each writes the loss of every
 * mesh into value (B) and, where grad is not NULL, its gradient into grad (B, n, 3), and returns 0; or 1 where
 * a nonzero vector's squared length leaves float64's normal range or a value is not finite (the caller then
 * runs the torch code, whose safe norms rescale such vectors); reg_losses returns -1 where the scratch memory
 * they share cannot be had.
 * The edge and area losses, which take square roots, measure each mesh divided by a power of two near its
 * extent (exact) and bring the loss and its gradient back, as the torch code does. */

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

int meshmei_regularizers_abi(void) { return 1; }

/* X (n, 3) divided by 2^k into Y, with 2^k a power of two near its extent (meshmei.regularizers._pow2_extent:
 * the extent over [2^k, 2^(k+1)), k = 0 for a mesh without extent); returns k. Exact: the squares of a mesh
 * 1e-160 across left float64's range (the torch code's gradient of the area loss was NaN there). */
static int unit_scale(int64_t n, const double *X, double *Y) {
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY}, ext = 0.0;
    for (int64_t i = 0; i < n; i++)
        for (int c = 0; c < 3; c++) lo[c] = fmin(lo[c], X[3 * i + c]), hi[c] = fmax(hi[c], X[3 * i + c]);
    for (int c = 0; c < 3; c++) ext = fmax(ext, hi[c] - lo[c]);
    int e = 1;
    if (ext > 0.0) frexp(ext, &e);
    for (int64_t i = 0; i < 3 * n; i++) Y[i] = ldexp(X[i], 1 - e);
    return e - 1;
}

/* a nonzero vector u whose squared length s is outside [DBL_MIN, DBL_MAX] (or underflowed to 0): its root, or
 * the root's gradient, is not right */
static int out_of_range(const double *u, double s) {
    return (u[0] != 0.0 || u[1] != 0.0 || u[2] != 0.0) && !(s >= DBL_MIN && s <= DBL_MAX);
}

/* mean_i |v_i - mean_{j in N(i)} v_j|^2 over the vertices with neighbours (the 1-rings in CSR: the neighbours
 * of i are idx[ptr[i]:ptr[i+1]], symmetric). With d_i that umbrella vector and L the number of such vertices,
 * the gradient at k is (2 / L) (d_k - sum_{i in N(k)} d_i / deg_i). */
static int reg_uniform_laplacian(int64_t B, int64_t n, const double *V, const int64_t *ptr, const int64_t *idx,
                                 double *value, double *grad, double *D /* scratch, 3 n */) {
    int64_t live = 0;
    for (int64_t i = 0; i < n; i++) live += ptr[i + 1] > ptr[i];
    const double scale = live > 0 ? 1.0 / (double)live : 0.0;
    for (int64_t b = 0; b < B; b++) {
        const double *X = V + 3 * n * b;
        double e = 0.0;
        for (int64_t i = 0; i < n; i++) {
            const int64_t deg = ptr[i + 1] - ptr[i];
            double *d = D + 3 * i, s[3] = {0.0, 0.0, 0.0};
            if (deg == 0) {
                d[0] = d[1] = d[2] = 0.0;
                continue;
            }
            for (int64_t p = ptr[i]; p < ptr[i + 1]; p++)
                for (int k = 0; k < 3; k++) s[k] += X[3 * idx[p] + k];
            for (int k = 0; k < 3; k++) d[k] = X[3 * i + k] - s[k] / (double)deg;
            e += d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        }
        value[b] = e * scale;
        if (!isfinite(value[b])) return 1;
        if (!grad) continue;
        double *G = grad + 3 * n * b;
        for (int64_t i = 0; i < n; i++) {
            const int64_t deg = ptr[i + 1] - ptr[i];
            if (deg == 0) continue;
            double g[3];
            for (int k = 0; k < 3; k++) g[k] = D[3 * i + k];
            for (int64_t p = ptr[i]; p < ptr[i + 1]; p++) {
                const int64_t j = idx[p];
                const double w = 1.0 / (double)(ptr[j + 1] - ptr[j]);
                for (int k = 0; k < 3; k++) g[k] -= w * D[3 * j + k];
            }
            for (int k = 0; k < 3; k++) G[3 * i + k] = 2.0 * scale * g[k];
        }
    }
    return 0;
}

/* mean_e (|e| - mean |e|)^2 over the unique edges E (nE, 2). The mean's own slope sums to zero over the edges,
 * so the gradient of edge e's length is 2 (|e| - mean) / nE; a zero-length edge passes none (safe_norm). */
static int reg_edge(int64_t B, int64_t n, int64_t nE, const double *V, const int64_t *E, double *value, double *grad,
                    double *Ln /* scratch, nE + 3 n */) {
    double *X = Ln + nE;
    for (int64_t b = 0; b < B; b++) {
        const int k = unit_scale(n, V + 3 * n * b, X);
        double mean = 0.0, e = 0.0;
        for (int64_t q = 0; q < nE; q++) {
            const double *P = X + 3 * E[2 * q], *Q = X + 3 * E[2 * q + 1];
            const double u[3] = {Q[0] - P[0], Q[1] - P[1], Q[2] - P[2]}, s = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
            if (out_of_range(u, s)) return 1;
            Ln[q] = sqrt(s);
            mean += Ln[q];
        }
        mean = nE > 0 ? mean / (double)nE : 0.0;
        for (int64_t q = 0; q < nE; q++) e += (Ln[q] - mean) * (Ln[q] - mean);
        value[b] = ldexp(nE > 0 ? e / (double)nE : 0.0, 2 * k);  /* units of length^2 */
        if (!isfinite(value[b])) return 1;
        if (!grad) continue;
        double *G = grad + 3 * n * b;
        for (int64_t q = 0; q < nE; q++) {
            if (Ln[q] == 0.0) continue;
            const int64_t i = E[2 * q], j = E[2 * q + 1];
            const double w = 2.0 * (Ln[q] - mean) / (double)nE / Ln[q];
            for (int c = 0; c < 3; c++) {
                const double t = w * (X[3 * j + c] - X[3 * i + c]);
                G[3 * j + c] += t;
                G[3 * i + c] -= t;
            }
        }
        for (int64_t i = 0; i < 3 * n; i++) G[i] = ldexp(G[i], k);
    }
    return 0;
}

/* mean_t (A_t - mean A)^2 over the faces F (m, 3), A_t = |(T1 - T0) x (T2 - T0)| / 2. The gradient of A_t at
 * corner c is u x d_c / 2, u the unit normal and d_c the edge opposite c (T2 - T1, T0 - T2, T1 - T0); a face
 * of zero area passes none (safe_norm). */
static int reg_area(int64_t B, int64_t n, int64_t m, const double *V, const int64_t *F, double *value, double *grad,
                    double *A /* scratch, 4 m + 3 n */) {
    double *N = A + m, *X = A + 4 * m;
    for (int64_t b = 0; b < B; b++) {
        const int k = unit_scale(n, V + 3 * n * b, X);
        double mean = 0.0, e = 0.0;
        for (int64_t f = 0; f < m; f++) {
            const double *T0 = X + 3 * F[3 * f], *T1 = X + 3 * F[3 * f + 1], *T2 = X + 3 * F[3 * f + 2];
            double a[3], c[3], *u = N + 3 * f;
            for (int j = 0; j < 3; j++) a[j] = T1[j] - T0[j], c[j] = T2[j] - T0[j];
            u[0] = a[1] * c[2] - a[2] * c[1];
            u[1] = a[2] * c[0] - a[0] * c[2];
            u[2] = a[0] * c[1] - a[1] * c[0];
            const double s = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
            if (out_of_range(u, s)) return 1;
            const double len = sqrt(s);
            A[f] = 0.5 * len;
            mean += A[f];
            for (int j = 0; j < 3; j++) u[j] = len > 0.0 ? u[j] / len : 0.0;
        }
        mean /= (double)m;
        for (int64_t f = 0; f < m; f++) e += (A[f] - mean) * (A[f] - mean);
        value[b] = ldexp(e / (double)m, 4 * k);  /* units of length^4 */
        if (!isfinite(value[b])) return 1;
        if (!grad) continue;
        double *G = grad + 3 * n * b;
        for (int64_t f = 0; f < m; f++) {
            const double *u = N + 3 * f, w = (A[f] - mean) / (double)m;  /* 2 (A - mean) / m times the 1/2 of A */
            const int64_t *t = F + 3 * f;
            for (int c = 0; c < 3; c++) {
                const double *P = X + 3 * t[(c + 1) % 3], *Q = X + 3 * t[(c + 2) % 3];
                const double d[3] = {Q[0] - P[0], Q[1] - P[1], Q[2] - P[2]};
                double *g = G + 3 * t[c];
                g[0] += w * (u[1] * d[2] - u[2] * d[1]);
                g[1] += w * (u[2] * d[0] - u[0] * d[2]);
                g[2] += w * (u[0] * d[1] - u[1] * d[0]);
            }
        }
        for (int64_t i = 0; i < 3 * n; i++) G[i] = ldexp(G[i], 3 * k);
    }
    return 0;
}

/* The losses picked by `which` (1: uniform Laplacian, 2: edge, 4: area), in that order, into value (k, B) and,
 * where grad is not NULL, grad (k, B, n, 3) (zeros on entry): the three in one call, sharing one scratch
 * buffer. Returns as they do, or -1 where the buffer cannot be had. */
int reg_losses(int64_t B, int64_t n, int64_t m, int64_t nE, const double *V, const int64_t *F, const int64_t *E,
               const int64_t *ptr, const int64_t *idx, int which, double *value, double *grad) {
    const int64_t size = (nE > 4 * m ? nE : 4 * m) + 3 * n;  /* the largest any of them takes */
    double *scratch = malloc((size_t)size * sizeof(double));
    if (!scratch) return -1;
    int64_t k = 0;
    int rc = 0;
    if (which & 1) {
        rc = reg_uniform_laplacian(B, n, V, ptr, idx, value + k * B, grad ? grad + 3 * n * B * k : NULL, scratch);
        k++;
    }
    if (!rc && (which & 2)) {
        rc = reg_edge(B, n, nE, V, E, value + k * B, grad ? grad + 3 * n * B * k : NULL, scratch);
        k++;
    }
    if (!rc && (which & 4)) rc = reg_area(B, n, m, V, F, value + k * B, grad ? grad + 3 * n * B * k : NULL, scratch);
    free(scratch);
    return rc;
}
