/* The contact barrier's broad phase (meshmei.contact.ContactBarrier), compiled: every (vertex, face) pair,
 * the vertex not in the face, and every (edge, edge) pair, sharing no vertex, that may lie within `reach`.
 *
 * A uniform grid over the vertices' bounding box (counting sort, no hashing): the vertices go into one cell
 * each, the edges into every cell their box overlaps; a face or an edge looks in the cells its box,
 * widened by `reach`, overlaps. A pair found there is kept when this file's own distance (the formulas of
 * meshmei.contact._point_triangle and _segment_segment, in double) is below `lim` (the caller's reach^2 with
 * a relative slack of 1e-6), so the kept pairs hold every pair whose distance, as the torch code measures
 * it, is below reach; their squared distances are written beside them.
 *
 * Cost: O(n + pairs found in the cells); the grid's cells are sized to the primitives and to `reach`, at
 * most 8 per primitive, and an edge whose box covers more than 64 cells (one stretched far beyond the
 * others) is kept in a list that every edge's query checks instead.
 *
 * Each search returns how many pairs it found (-1 for a non-finite coordinate, -2 for no memory) and
 * writes the first `cap` of them; the caller calls again with room for all where that was too few.
 *
 * Also here, sharing the distances and the angles: the exact distances of given pairs (the separation
 * certificate's) and the rules of meshmei.certify's certificates (the separation certificate's fans, the graph
 * certificate's check); and the contact energy of given pairs with its gradient (contact_energy). */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <float.h>

int meshmei_contact_abi(void) { return 6; }

/* the barrier and its slope (_guard.c, built into the same library) */
double meshmei_barrier(double x, double h, double tiny, double *slope);

static double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static void cross3(const double *a, const double *b, double *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static double clamp01(double x) { return x < 0.0 ? 0.0 : (x > 1.0 ? 1.0 : x); }

/* squared distance from P to the triangle ABC: the projection onto the plane where it falls inside, else the
 * nearest edge's closest point (a degenerate triangle: its edges); that closest point's weights on the
 * corners into wt[0..2] */
static double point_triangle_weights(const double *P, const double *A, const double *B, const double *C, double *wt) {
    const double tiny = DBL_MIN;
    double ab[3], ac[3], ap[3], n[3], w[3];
    for (int k = 0; k < 3; k++) {
        ab[k] = B[k] - A[k];
        ac[k] = C[k] - A[k];
        ap[k] = P[k] - A[k];
    }
    cross3(ab, ac, n);
    double nn = dot3(n, n);
    cross3(ap, ac, w);
    double u = dot3(w, n);
    cross3(ab, ap, w);
    double v = dot3(w, n);
    if (u >= 0.0 && v >= 0.0 && u + v <= nn && nn > tiny) {
        double s = dot3(ap, n);
        wt[1] = u / nn, wt[2] = v / nn, wt[0] = 1.0 - wt[1] - wt[2];
        return s * s / nn;
    }
    const double *X[3] = {A, B, C}, *Y[3] = {B, C, A};
    double best = INFINITY, tb = 0.0;
    int eb = 0;
    for (int e = 0; e < 3; e++) {
        double D[3], PX[3];
        for (int k = 0; k < 3; k++) {
            D[k] = Y[e][k] - X[e][k];
            PX[k] = P[k] - X[e][k];
        }
        double dd = dot3(D, D);
        double t = clamp01(dot3(PX, D) / (dd > tiny ? dd : tiny));
        for (int k = 0; k < 3; k++) w[k] = PX[k] - D[k] * t;
        double d = dot3(w, w);
        if (d < best) best = d, tb = t, eb = e;
    }
    wt[0] = wt[1] = wt[2] = 0.0;
    wt[eb] = 1.0 - tb, wt[(eb + 1) % 3] = tb;
    return best;
}

/* squared distance between the segments P1 Q1 and P2 Q2 (Ericson, 5.1.9, as the torch code clamps it), and
 * the closest points' parameters s, t into st[0..1] */
static double segment_params(const double *P1, const double *Q1, const double *P2, const double *Q2, double *st) {
    const double tiny = DBL_MIN;
    double d1[3], d2[3], r[3], w[3];
    for (int k = 0; k < 3; k++) {
        d1[k] = Q1[k] - P1[k];
        d2[k] = Q2[k] - P2[k];
        r[k] = P1[k] - P2[k];
    }
    double a = dot3(d1, d1), e = dot3(d2, d2), b = dot3(d1, d2), c = dot3(d1, r), f = dot3(d2, r);
    double den = a * e - b * b;
    double s = den > 1e-12 * a * e ? clamp01((b * f - c * e) / den) : 0.0;
    double t = (b * s + f) / (e > tiny ? e : tiny);
    double ac = a > tiny ? a : tiny;
    if (t < 0.0) s = clamp01(-c / ac);
    else if (t > 1.0) s = clamp01((b - c) / ac);
    t = clamp01(t);
    if (e <= tiny) {
        s = clamp01(-c / ac);
        t = 0.0;
    }
    for (int k = 0; k < 3; k++) w[k] = r[k] + d1[k] * s - d2[k] * t;
    st[0] = s, st[1] = t;
    return dot3(w, w);
}

/* squared distance from P to the triangle ABC (point_triangle_weights without the weights) */
static double point_triangle(const double *P, const double *A, const double *B, const double *C) {
    double w[3];
    return point_triangle_weights(P, A, B, C, w);
}

/* squared distance between the segments P1 Q1 and P2 Q2 (segment_params without the parameters) */
static double segment_segment(const double *P1, const double *Q1, const double *P2, const double *Q2) {
    double st[2];
    return segment_params(P1, Q1, P2, Q2, st);
}

typedef struct {
    double lo[3], inv;
    int64_t dim[3];
    int64_t *start; /* (cells + 1): the points of cell c are items[start[c] .. start[c + 1]) */
    int64_t *items;
} grid_t;

static int all_finite(int64_t n, const double *V) {
    for (int64_t i = 0; i < 3 * n; i++)
        if (!isfinite(V[i])) return 0;
    return 1;
}

static int64_t cell_of(const grid_t *g, int k, double x) {
    double c = floor((x - g->lo[k]) * g->inv);
    if (c < 0.0) return 0;
    if (c > (double)(g->dim[k] - 1)) return g->dim[k] - 1;
    return (int64_t)c;
}

static int64_t cell_index(const grid_t *g, int64_t x, int64_t y, int64_t z) {
    return (x * g->dim[1] + y) * g->dim[2] + z;
}

/* the points P (n, 3) sorted into cells of side h (or larger: at most 2 n + 64 cells) over their box;
 * returns 0, or -2 for no memory */
static int grid_build(grid_t *g, int64_t n, const double *P, double h) {
    double hi[3], cap = 2.0 * (double)n + 64.0;
    g->start = g->items = NULL;
    for (int k = 0; k < 3; k++) g->lo[k] = hi[k] = n ? P[k] : 0.0;
    for (int64_t i = 1; i < n; i++)
        for (int k = 0; k < 3; k++) {
            double x = P[3 * i + k];
            if (x < g->lo[k]) g->lo[k] = x;
            if (x > hi[k]) hi[k] = x;
        }
    double ext = 0.0;
    for (int k = 0; k < 3; k++)
        if (hi[k] - g->lo[k] > ext) ext = hi[k] - g->lo[k];
    if (!(h > 0.0)) h = ext > 0.0 ? ext : 1.0;
    for (;;) {
        double cells = 1.0;
        for (int k = 0; k < 3; k++) cells *= floor((hi[k] - g->lo[k]) / h) + 1.0;
        if (cells <= cap) break;
        h *= 1.25 * cbrt(cells / cap);
    }
    g->inv = 1.0 / h;
    for (int k = 0; k < 3; k++) g->dim[k] = (int64_t)floor((hi[k] - g->lo[k]) / h) + 1;
    int64_t cells = g->dim[0] * g->dim[1] * g->dim[2];
    g->start = calloc((size_t)cells + 1, sizeof(int64_t));
    g->items = malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    int64_t *cell = malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    if (!g->start || !g->items || !cell) {
        free(g->start), free(g->items), free(cell);
        g->start = g->items = NULL;
        return -2;
    }
    for (int64_t i = 0; i < n; i++) {
        const double *x = P + 3 * i;
        cell[i] = cell_index(g, cell_of(g, 0, x[0]), cell_of(g, 1, x[1]), cell_of(g, 2, x[2]));
        g->start[cell[i] + 1]++;
    }
    for (int64_t c = 0; c < cells; c++) g->start[c + 1] += g->start[c];
    for (int64_t i = 0; i < n; i++) g->items[g->start[cell[i]]++] = i; /* start[c] now ends cell c */
    for (int64_t c = cells; c > 0; c--) g->start[c] = g->start[c - 1];
    g->start[0] = 0;
    free(cell);
    return 0;
}

static void grid_free(grid_t *g) { free(g->start), free(g->items); }

/* the cells a box [lo, hi] overlaps: for each (x, y), the cells z0..z1 follow each other, so their points are
 * items[from .. to) of one range (cell_rows gives its bounds for row r of nx * ny) */
typedef struct {
    int64_t x0, y0, z0, z1, nx, ny;
} boxcells_t;

static boxcells_t box_cells(const grid_t *g, const double *lo, const double *hi) {
    boxcells_t b;
    b.x0 = cell_of(g, 0, lo[0]), b.y0 = cell_of(g, 1, lo[1]), b.z0 = cell_of(g, 2, lo[2]);
    b.z1 = cell_of(g, 2, hi[2]);
    b.nx = cell_of(g, 0, hi[0]) - b.x0 + 1, b.ny = cell_of(g, 1, hi[1]) - b.y0 + 1;
    return b;
}

static void cell_row(const grid_t *g, const boxcells_t *b, int64_t r, int64_t *from, int64_t *to) {
    int64_t x = b->x0 + r / b->ny, y = b->y0 + r % b->ny;
    *from = g->start[cell_index(g, x, y, b->z0)];
    *to = g->start[cell_index(g, x, y, b->z1) + 1];
}

static void box_of(const double *V, const int64_t *idx, int k, double widen, double *lo, double *hi) {
    for (int a = 0; a < 3; a++) {
        lo[a] = hi[a] = V[3 * idx[0] + a];
        for (int j = 1; j < k; j++) {
            double x = V[3 * idx[j] + a];
            if (x < lo[a]) lo[a] = x;
            if (x > hi[a]) hi[a] = x;
        }
        lo[a] -= widen;
        hi[a] += widen;
    }
}

static void emit(int64_t *found, int64_t cap, int64_t *out_a, int64_t *out_b, double *out_d, int64_t a, int64_t b,
                 double d) {
    if (*found < cap) {
        out_a[*found] = a;
        out_b[*found] = b;
        out_d[*found] = d;
    }
    (*found)++;
}

/* The broad phases' box tests pass about one candidate in five: a branch on each was mispredicted at every
 * turn, and it was most of a search (a 10k sphere: 1.25 million edge-box tests for 227,000 that pass). They are
 * made without a branch, SCAN_CHUNK candidates at a time, the passing ones written into a list in their order
 * and then tested as before: the same pairs in the same order, measured the same way (tested against the
 * branching code), in about 0.7 times the time (a 10k sphere, one thread: vertex-face 4.6 against 6.7 ms,
 * edge-edge 12-14 against 17-18). */
#define SCAN_CHUNK 64

/* (vertex, face) pairs: out_v, out_f and their squared distances out_d (room for `cap`). The vertices in a
 * grid of cells about the size of a face's box widened by reach; each face looks in the cells that box
 * overlaps (mostly 8). */
int64_t contact_vertex_face(int64_t n, const double *V, int64_t m, const int64_t *F, double lim, int64_t cap,
                            int64_t *out_v, int64_t *out_f, double *out_d) {
    if (!all_finite(n, V)) return -1;
    double widen = sqrt(lim), mean = 0.0, lo[3], hi[3];
    for (int64_t f = 0; f < m; f++) {
        box_of(V, F + 3 * f, 3, 0.0, lo, hi);
        for (int a = 0; a < 3; a++) mean += hi[a] - lo[a];
    }
    mean = m ? mean / (3.0 * (double)m) : 0.0;
    grid_t g;
    if (grid_build(&g, n, V, mean + 2.0 * widen)) return -2;
    double *gp = malloc((size_t)(n > 0 ? n : 1) * 3 * sizeof(double)); /* the points in the grid's order */
    if (!gp) {
        grid_free(&g);
        return -2;
    }
    for (int64_t q = 0; q < n; q++)
        for (int a = 0; a < 3; a++) gp[3 * q + a] = V[3 * g.items[q] + a];
    int64_t found = 0, hit[SCAN_CHUNK];
    for (int64_t f = 0; f < m; f++) {
        const int64_t *tri = F + 3 * f;
        const double *A = V + 3 * tri[0], *B = V + 3 * tri[1], *C = V + 3 * tri[2];
        box_of(V, tri, 3, widen, lo, hi);
        boxcells_t bc = box_cells(&g, lo, hi);
        for (int64_t r = 0, from, to; r < bc.nx * bc.ny; r++) {
            cell_row(&g, &bc, r, &from, &to);
            for (int64_t q0 = from; q0 < to; q0 += SCAN_CHUNK) {
                int64_t q1 = q0 + SCAN_CHUNK < to ? q0 + SCAN_CHUNK : to, nhit = 0;
                for (int64_t q = q0; q < q1; q++) { /* the box test, without a branch (SCAN_CHUNK) */
                    const double *P = gp + 3 * q;
                    int miss = (P[0] < lo[0]) | (P[0] > hi[0]) | (P[1] < lo[1]) | (P[1] > hi[1]) | (P[2] < lo[2]) |
                               (P[2] > hi[2]);
                    hit[nhit] = q;
                    nhit += !miss;
                }
                for (int64_t h = 0; h < nhit; h++) {
                    int64_t v = g.items[hit[h]];
                    if (v == tri[0] || v == tri[1] || v == tri[2]) continue;
                    double d = point_triangle(V + 3 * v, A, B, C);
                    if (d < lim) emit(&found, cap, out_v, out_f, out_d, v, f, d);
                }
            }
        }
    }
    grid_free(&g);
    free(gp);
    return found;
}

/* test the edges i and j (no shared vertex; j's box against i's widened box [lo, hi]) and write the pair
 * where they lie within lim: (a, b) with a < b, except where `first` marks one edge and not the other */
static void edge_pair(const double *V, const int64_t *E, const uint8_t *first, int64_t i, int64_t j,
                      const double *lo, const double *hi, double lim, int64_t *found, int64_t cap, int64_t *out_a,
                      int64_t *out_b, double *out_d) {
    const int64_t *ei = E + 2 * i, *ej = E + 2 * j;
    if (ei[0] == ej[0] || ei[0] == ej[1] || ei[1] == ej[0] || ei[1] == ej[1]) return;
    const double *P2 = V + 3 * ej[0], *Q2 = V + 3 * ej[1];
    for (int a = 0; a < 3; a++)
        if ((P2[a] < Q2[a] ? Q2[a] : P2[a]) < lo[a] || (P2[a] < Q2[a] ? P2[a] : Q2[a]) > hi[a]) return;
    double d = segment_segment(V + 3 * ei[0], V + 3 * ei[1], P2, Q2);
    if (!(d < lim)) return;
    int64_t a = i < j ? i : j, b = i < j ? j : i;
    if (first && first[b] && !first[a]) {
        int64_t t = a;
        a = b, b = t;
    }
    emit(found, cap, out_a, out_b, out_d, a, b, d);
}

typedef struct {
    double x; /* the lower x of the edge's box */
    int64_t e;
} sweep_t;

static int by_x(const void *a, const void *b) {
    double x = ((const sweep_t *)a)->x, y = ((const sweep_t *)b)->x;
    if (x != y) return x < y ? -1 : 1;
    int64_t i = ((const sweep_t *)a)->e, j = ((const sweep_t *)b)->e;
    return (i > j) - (i < j);
}

/* (edge, edge) pairs: out_a, out_b and their squared distances out_d (room for `cap`; the order within a pair
 * as edge_pair writes it, the distance as measured from edge i to edge j: from the short edge of a short and a
 * long one, else from the one the search below starts from). The
 * short edges' midpoints in a grid; a short edge looks for the short edges after it in the grid's order
 * whose midpoints lie within its half-extent, the largest short half-extent and reach (the cells that box
 * overlaps; two edges within reach of each other each lie in the other's box, so the pair is found from the
 * one the grid holds first). A long edge (half-extent above twice the mean: stretched ones, not in the grid)
 * looks in the grid the same way for every short edge (a box about its own length: the cost of a long edge is
 * its length, not the edge count); pairs of long edges come from a sweep along x. Each pair once. */
int64_t contact_edge_edge(int64_t n, const double *V, int64_t k, const int64_t *E, const uint8_t *first,
                          double lim, int64_t cap, int64_t *out_a, int64_t *out_b, double *out_d) {
    if (!all_finite(n, V)) return -1;
    size_t room = (size_t)(k > 0 ? k : 1);
    double widen = sqrt(lim), mean = 0.0, lo[3], hi[3];
    double *box = malloc(room * 6 * sizeof(double)); /* per edge: midpoint, half-extents */
    double *P = calloc(room * 3, sizeof(double)), *packed = malloc(room * 6 * sizeof(double));
    int64_t *longs = malloc(room * sizeof(int64_t)), *slot = malloc(room * sizeof(int64_t));
    sweep_t *sweep = malloc(room * sizeof(sweep_t));
    int64_t *ids = malloc(room * sizeof(int64_t)), *pos = malloc(room * sizeof(int64_t)); /* grid order <-> edge */
    double *size = malloc(room * sizeof(double)); /* the largest half-extent */
    grid_t g = {0};
    int64_t found = -2, nlong = 0, nshort = 0;
    if (!box || !P || !packed || !longs || !sweep || !slot || !ids || !pos || !size) goto done;
    for (int64_t e = 0; e < k; e++) {
        box_of(V, E + 2 * e, 2, 0.0, lo, hi);
        size[e] = 0.0;
        for (int a = 0; a < 3; a++) {
            box[6 * e + a] = 0.5 * (lo[a] + hi[a]);
            box[6 * e + 3 + a] = 0.5 * (hi[a] - lo[a]);
            if (box[6 * e + 3 + a] > size[e]) size[e] = box[6 * e + 3 + a];
        }
        mean += size[e];
    }
    mean = k ? mean / (double)k : 0.0;
    double largest[3] = {0.0, 0.0, 0.0}; /* the largest half-extents of a short edge */
    for (int64_t e = 0; e < k; e++) {
        if (size[e] > 2.0 * mean) {
            longs[nlong++] = e;
            continue;
        }
        for (int a = 0; a < 3; a++) {
            if (box[6 * e + 3 + a] > largest[a]) largest[a] = box[6 * e + 3 + a];
            P[3 * nshort + a] = box[6 * e + a];
        }
        slot[nshort++] = e; /* the grid's point nshort is this edge */
    }
    double cell = mean + widen + 0.5 * (largest[0] + largest[1] + largest[2]); /* about a query's half-size */
    if (grid_build(&g, nshort, P, cell)) goto done;
    for (int64_t q = 0; q < nshort; q++) { /* the short edges' boxes in the grid's order: read in sequence */
        ids[q] = slot[g.items[q]];
        pos[ids[q]] = q;
        for (int a = 0; a < 6; a++) packed[6 * q + a] = box[6 * ids[q] + a];
    }
    found = 0;
    int64_t hit[SCAN_CHUNK];
    /* The short edges in the grid's order, then the long ones: neighbouring queries read the same cells in turn
     * (a 10k fit of the teapot: 26.3 ms against 28.8 in edge order, medians of 30 alternated calls). The same
     * pairs, each found and measured from the same edge as in edge order; only the order they are written in
     * differs, and the caller sorts them. */
    for (int64_t t = 0; t < k; t++) {
        int64_t i = t < nshort ? ids[t] : longs[t - nshort];
        const double *bi = box + 6 * i;
        box_of(V, E + 2 * i, 2, widen, lo, hi);
        int long_i = size[i] > 2.0 * mean;
        double qlo[3], qhi[3], jlo[3], jhi[3];
        for (int a = 0; a < 3; a++) {
            double r = bi[3 + a] + largest[a] + widen;
            qlo[a] = bi[a] - r, qhi[a] = bi[a] + r;
        }
        boxcells_t bc = box_cells(&g, qlo, qhi);
        for (int64_t row = 0, from, to; row < bc.nx * bc.ny; row++) {
            cell_row(&g, &bc, row, &from, &to);
            if (!long_i && from <= pos[i]) from = pos[i] + 1; /* the grid's earlier edges found their pairs with i */
            for (int64_t q0 = from; q0 < to; q0 += SCAN_CHUNK) {
                int64_t q1 = q0 + SCAN_CHUNK < to ? q0 + SCAN_CHUNK : to, nhit = 0;
                for (int64_t q = q0; q < q1; q++) { /* the box test, without a branch (SCAN_CHUNK) */
                    const double *bj = packed + 6 * q;
                    int miss = (fabs(bi[0] - bj[0]) > bi[3] + bj[3] + widen) |
                               (fabs(bi[1] - bj[1]) > bi[4] + bj[4] + widen) |
                               (fabs(bi[2] - bj[2]) > bi[5] + bj[5] + widen);
                    hit[nhit] = q;
                    nhit += !miss;
                }
                for (int64_t h = 0; h < nhit; h++) {
                    int64_t q = hit[h];
                    if (!long_i) {
                        edge_pair(V, E, first, i, ids[q], lo, hi, lim, &found, cap, out_a, out_b, out_d);
                    } else { /* a short and a long edge: measured from the short one */
                        box_of(V, E + 2 * ids[q], 2, widen, jlo, jhi);
                        edge_pair(V, E, first, ids[q], i, jlo, jhi, lim, &found, cap, out_a, out_b, out_d);
                    }
                }
            }
        }
    }
    /* two long edges: swept in the order of their boxes' lower x, each against those that start before its box
     * (widened twice: generous, edge_pair decides) ends; measured from the lower index */
    for (int64_t t = 0; t < nlong; t++) sweep[t].x = box[6 * longs[t]] - box[6 * longs[t] + 3], sweep[t].e = longs[t];
    qsort(sweep, (size_t)nlong, sizeof(sweep_t), by_x);
    for (int64_t p = 0; p < nlong; p++) {
        int64_t i = sweep[p].e;
        double ilo[3], ihi[3], jlo[3], jhi[3];
        box_of(V, E + 2 * i, 2, widen, ilo, ihi);
        for (int64_t s = p + 1; s < nlong && sweep[s].x <= ihi[0] + widen; s++) {
            int64_t j = sweep[s].e;
            if (i < j) {
                edge_pair(V, E, first, i, j, ilo, ihi, lim, &found, cap, out_a, out_b, out_d);
            } else {
                box_of(V, E + 2 * j, 2, widen, jlo, jhi);
                edge_pair(V, E, first, j, i, jlo, jhi, lim, &found, cap, out_a, out_b, out_d);
            }
        }
    }
done:
    grid_free(&g), free(box), free(P), free(packed), free(longs), free(sweep), free(slot), free(ids), free(pos),
        free(size);
    return found;
}

/* Lower bounds on the distances of given pairs, for meshmei.certify.SeparationCertificate: out[i] is the
 * distance of vertex vt[i] to face ft[i] (the formula above, whose closest point is the true one up to
 * rounding). */
void contact_vertex_face_distances(const double *V, const int64_t *F, int64_t k, const int64_t *vt,
                                   const int64_t *ft, double *out) {
    for (int64_t i = 0; i < k; i++) {
        const int64_t *tri = F + 3 * ft[i];
        out[i] = sqrt(point_triangle(V + 3 * vt[i], V + 3 * tri[0], V + 3 * tri[1], V + 3 * tri[2]));
    }
}

/* ... and of edge ea[i] to edge eb[i]; 0 for two edges within 1e-4 radians of parallel (den <= 1e-8 a e),
 * where the clamped formula's closest points may miss the true ones by the overlap times the angle: a pair
 * the caller must treat as touching. */
void contact_edge_edge_distances(const double *V, const int64_t *E, int64_t k, const int64_t *ea,
                                 const int64_t *eb, double *out) {
    for (int64_t i = 0; i < k; i++) {
        const double *P1 = V + 3 * E[2 * ea[i]], *Q1 = V + 3 * E[2 * ea[i] + 1];
        const double *P2 = V + 3 * E[2 * eb[i]], *Q2 = V + 3 * E[2 * eb[i] + 1];
        double d1[3], d2[3];
        for (int a = 0; a < 3; a++) d1[a] = Q1[a] - P1[a], d2[a] = Q2[a] - P2[a];
        double a = dot3(d1, d1), e = dot3(d2, d2), b = dot3(d1, d2);
        out[i] = a * e - b * b <= 1e-8 * a * e ? 0.0 : sqrt(segment_segment(P1, Q1, P2, Q2));
    }
}

/* The contact energy of k pairs of one mesh, the item-th of a batch (its vertices at V + 3 n item, float64,
 * (n, 3) each): vertex a[i] and face b[i], the corners table[3 b[i] ..] (kind 0), or edge a[i] and edge b[i],
 * the ends table[2 a[i] ..] and table[2 b[i] ..] (kind 1). A pair whose squared distance d2 is below dh^2 adds
 * incremental potential contact's barrier b(d) = -(d - dh)^2 log(d / dh), d = sqrt(max(d2, tiny)) (`tiny`:
 * the smallest positive number of the caller's dtype, as meshmei.contact clamps it), to energy[item] and
 * counts one in count[item]; with `grad` (else NULL), its gradient in the corners is added there (the
 * batch's, (B n, 3); zero for d2 below tiny, as the clamp's): b'(d) (X - Y) / d at the closest points X, Y
 * of the two sides, spread on the corners by the closest points' weights (Danskin's theorem). Coordinates
 * must be finite (the caller checks). */
void contact_energy(int64_t k, const double *V, const int64_t *a, const int64_t *b, const int64_t *table, int kind,
                    int64_t item, int64_t n, double dh, double tiny, double *energy, int64_t *count, double *grad) {
    const int64_t base = n * item;
    const double root_tiny = sqrt(tiny);  /* the clamp of d: the sqrt of the larger is the larger sqrt */
    for (int64_t i = 0; i < k; i++) {
        int64_t r[4];
        if (kind == 0) {
            r[0] = a[i], r[1] = table[3 * b[i]], r[2] = table[3 * b[i] + 1], r[3] = table[3 * b[i] + 2];
        } else {
            r[0] = table[2 * a[i]], r[1] = table[2 * a[i] + 1], r[2] = table[2 * b[i]], r[3] = table[2 * b[i] + 1];
        }
        for (int c = 0; c < 4; c++) r[c] += base;
        const double *X[4] = {V + 3 * r[0], V + 3 * r[1], V + 3 * r[2], V + 3 * r[3]};
        double wgt[4], d2;
        if (kind == 0) {
            d2 = point_triangle_weights(X[0], X[1], X[2], X[3], wgt + 1);
            wgt[0] = -1.0;
        } else {
            double st[2];
            d2 = segment_params(X[0], X[1], X[2], X[3], st);
            wgt[0] = -(1.0 - st[0]), wgt[1] = -st[0], wgt[2] = 1.0 - st[1], wgt[3] = st[1];
        }
        if (!(d2 < dh * dh)) continue;
        double d = sqrt(d2), slope;
        energy[item] += meshmei_barrier(d, dh, root_tiny, &slope);
        count[item] += 1;
        if (grad == NULL || !(d2 > tiny)) continue;
        /* the difference of the two sides' closest points: sum of -wgt * corner (first side's weights -1 or
         * -(1 - s), -s; the other's positive), and the barrier's slope over d */
        double diff[3] = {0.0, 0.0, 0.0};
        for (int c = 0; c < 4; c++)
            for (int a = 0; a < 3; a++) diff[a] -= wgt[c] * X[c][a];
        slope /= d;
        for (int c = 0; c < 4; c++) {
            double *gc = grad + 3 * r[c];
            for (int a = 0; a < 3; a++) gc[a] -= slope * wgt[c] * diff[a];
        }
    }
}

/* atan2(y, x) to within 5e-8 radians (a least-squares odd polynomial of atan on [0, 1], degree 15, and the
 * octant's symmetries; its largest error on [0, 1] is 4.1e-8): several times faster than libm's. Enough where
 * only a whole number of turns is read from a sum of angles. */
static double rough_atan2(double y, double x) {
    static const double c[8] = {0.9999994368431481, -0.333301066776889, 0.19948508985765476, -0.13915802260685678,
                                0.09656256470433223, -0.05606317672867424, 0.02194661103229993, -0.004073309464382779};
    double ax = fabs(x), ay = fabs(y), hi = ax > ay ? ax : ay, lo = ax > ay ? ay : ax;
    if (!(hi > 0.0)) return 0.0;
    double a = lo / hi, s = a * a, p = c[7];
    for (int i = 6; i >= 0; i--) p = p * s + c[i];
    double r = a * p;
    if (ay > ax) r = 1.5707963267948966 - r;
    if (x < 0.0) r = 3.141592653589793 - r;
    return y < 0.0 ? -r : r;
}

/* meshmei.certify.SeparationCertificate's rule 2: ok[v] = 1 where the faces around v, projected onto the
 * plane perpendicular to v's area-weighted normal, all keep their orientation (n . N > 1e-9 |n| |N|) and
 * their corner angles at v sum to one turn (less than one turn at a boundary vertex, by 1e-9). NumPy's twin
 * asks an interior sum to lie within 1e-6 of a turn; here it is asked to lie below three half turns, which
 * for such a fan is the same (see below). A vertex of no face is ok. `work`: room for 4 n doubles. */
void separation_fans(int64_t n, const double *V, int64_t m, const int64_t *F, const uint8_t *boundary,
                     double *work, uint8_t *ok) {
    const double two_pi = 6.283185307179586, tiny = DBL_MIN;
    double *nrm = work, *turn = work + 3 * n;
    for (int64_t i = 0; i < 4 * n; i++) work[i] = 0.0;
    for (int64_t v = 0; v < n; v++) ok[v] = 2; /* 2: no face yet */
    for (int64_t f = 0; f < m; f++) {
        const int64_t *t = F + 3 * f;
        double ab[3], ac[3], N[3];
        for (int a = 0; a < 3; a++) ab[a] = V[3 * t[1] + a] - V[3 * t[0] + a], ac[a] = V[3 * t[2] + a] - V[3 * t[0] + a];
        cross3(ab, ac, N);
        for (int k = 0; k < 3; k++)
            for (int a = 0; a < 3; a++) nrm[3 * t[k] + a] += N[a];
    }
    for (int64_t f = 0; f < m; f++) {
        const int64_t *t = F + 3 * f;
        double ab[3], ac[3], N[3];
        for (int a = 0; a < 3; a++) ab[a] = V[3 * t[1] + a] - V[3 * t[0] + a], ac[a] = V[3 * t[2] + a] - V[3 * t[0] + a];
        cross3(ab, ac, N);
        double NN = sqrt(dot3(N, N));
        for (int k = 0; k < 3; k++) {
            int64_t v = t[k], nx = t[(k + 1) % 3], pv = t[(k + 2) % 3];
            const double *nc = nrm + 3 * v;
            double x1[3], x2[3];
            for (int a = 0; a < 3; a++) x1[a] = V[3 * nx + a] - V[3 * v + a], x2[a] = V[3 * pv + a] - V[3 * v + a];
            double n2 = dot3(nc, nc), nn = sqrt(n2), orient = dot3(nc, N);
            if (ok[v] == 2) ok[v] = 1;
            if (!(orient > 1e-9 * nn * NN) || !(nn > 0.0)) ok[v] = 0;
            double sine = orient / (nn > tiny ? nn : tiny);
            double cosine = dot3(x1, x2) - dot3(nc, x1) * dot3(nc, x2) / (n2 > tiny ? n2 : tiny);
            /* an interior star whose corners all keep their orientation is a closed fan: its angles, each in
             * (0, pi), sum to a whole number of turns up to rounding, so a sum within 1e-6 of one turn is one
             * below three half turns, and rough angles tell them apart (within 5e-8 each); a boundary fan's
             * sum is compared with a turn to 1e-9 and takes libm's */
            turn[v] += boundary[v] ? atan2(sine, cosine) : rough_atan2(sine, cosine);
        }
    }
    for (int64_t v = 0; v < n; v++) {
        if (ok[v] == 2) {
            ok[v] = 1;
            continue;
        }
        if (!ok[v]) continue;
        ok[v] = boundary[v] ? turn[v] < two_pi - 1e-9 : turn[v] < 1.5 * two_pi;
    }
}

/* Whether the 2D segments (x[a0], y[a0])-(x[a1], y[a1]) and (x[b0], ...)-(x[b1], ...) cross or come
 * within tol (squared: tol2): meshmei.certify._segments_closer_than for one pair. */
static double point_segment_sq(double px, double py, double qx, double qy, double rx, double ry) {
    double dx = rx - qx, dy = ry - qy, dd = dx * dx + dy * dy;
    double s = ((px - qx) * dx + (py - qy) * dy) / (dd > DBL_MIN ? dd : DBL_MIN);
    s = s < 0.0 ? 0.0 : (s > 1.0 ? 1.0 : s);
    double ex = qx + dx * s - px, ey = qy + dy * s - py;
    return ex * ex + ey * ey;
}

static double orient2(double px, double py, double qx, double qy, double rx, double ry) {
    return (qx - px) * (ry - py) - (qy - py) * (rx - px);
}

/* meshmei.certify.GraphCertificate.holds: V (n, 3), faces F (m, 3), face normals N (m, 3), direction d (3,),
 * the plane's basis u, w (3,) each; kind[v]: 0 no face, 1 interior, 2 boundary; the boundary segment pairs
 * (a0, a1, b0, b1, np of them); work: room for 3 n doubles. Returns 1 where proven: every face keeps its
 * orientation along d (n . d > margin), every interior vertex's projected corner angles sum to one turn
 * (within 1e-6) and every boundary vertex's to less (by 1e-9), and no two boundary segments that share no
 * vertex cross or come within sep_margin times the projection's extent. As NumPy's twin, except that an
 * interior vertex sums rough angles (within 5e-8 each: its faces keep their orientation, so the sum is a
 * whole number of turns up to rounding, and one turn lies far inside the 1e-6 the rule allows). The
 * certificate is a proof: its answer decides whether libigl's exact test runs, never a verdict. */
int graph_holds(int64_t n, const double *V, int64_t m, const int64_t *F, const double *N, const double *d,
                const double *u, const double *w, const uint8_t *kind, int64_t np, const int64_t *a0,
                const int64_t *a1, const int64_t *b0, const int64_t *b1, double margin, double sep_margin,
                double *work) {
    const double two_pi = 6.283185307179586;
    for (int64_t f = 0; f < m; f++) {
        const double *nf = N + 3 * f;
        if (!(nf[0] * d[0] + nf[1] * d[1] + nf[2] * d[2] > margin)) return 0;
    }
    double *x = work, *y = work + n, *turn = work + 2 * n;
    double xlo = INFINITY, xhi = -INFINITY, ylo = INFINITY, yhi = -INFINITY;
    for (int64_t v = 0; v < n; v++) {
        const double *p = V + 3 * v;
        x[v] = p[0] * u[0] + p[1] * u[1] + p[2] * u[2];
        y[v] = p[0] * w[0] + p[1] * w[1] + p[2] * w[2];
        turn[v] = 0.0;
        xlo = x[v] < xlo ? x[v] : xlo, xhi = x[v] > xhi ? x[v] : xhi;
        ylo = y[v] < ylo ? y[v] : ylo, yhi = y[v] > yhi ? y[v] : yhi;
    }
    for (int64_t f = 0; f < m; f++) {
        const int64_t *t = F + 3 * f;
        for (int k = 0; k < 3; k++) {
            int64_t c = t[k], nx = t[(k + 1) % 3], pv = t[(k + 2) % 3];
            double x1 = x[nx] - x[c], y1 = y[nx] - y[c], x2 = x[pv] - x[c], y2 = y[pv] - y[c];
            double sine = x1 * y2 - y1 * x2, cosine = x1 * x2 + y1 * y2;
            turn[c] += kind[c] == 2 ? atan2(sine, cosine) : rough_atan2(sine, cosine);
        }
    }
    for (int64_t v = 0; v < n; v++) {
        if (kind[v] == 1 && fabs(turn[v] - two_pi) > 1e-6) return 0; /* a fan that wraps twice, or rounding */
        if (kind[v] == 2 && turn[v] >= two_pi - 1e-9) return 0;
    }
    if (np == 0) return 1;
    double tol = sep_margin * hypot(xhi - xlo, yhi - ylo), tol2 = tol * tol;
    for (int64_t i = 0; i < np; i++) {
        double xa0 = x[a0[i]], ya0 = y[a0[i]], xa1 = x[a1[i]], ya1 = y[a1[i]];
        double xb0 = x[b0[i]], yb0 = y[b0[i]], xb1 = x[b1[i]], yb1 = y[b1[i]];
        if (fmin(xa0, xa1) > fmax(xb0, xb1) + tol || fmin(xb0, xb1) > fmax(xa0, xa1) + tol ||
            fmin(ya0, ya1) > fmax(yb0, yb1) + tol || fmin(yb0, yb1) > fmax(ya0, ya1) + tol)
            continue;
        if (orient2(xa0, ya0, xa1, ya1, xb0, yb0) * orient2(xa0, ya0, xa1, ya1, xb1, yb1) < 0.0 &&
            orient2(xb0, yb0, xb1, yb1, xa0, ya0) * orient2(xb0, yb0, xb1, yb1, xa1, ya1) < 0.0)
            return 0; /* a proper crossing */
        if (point_segment_sq(xa0, ya0, xb0, yb0, xb1, yb1) <= tol2 ||
            point_segment_sq(xa1, ya1, xb0, yb0, xb1, yb1) <= tol2 ||
            point_segment_sq(xb0, yb0, xa0, ya0, xa1, ya1) <= tol2 ||
            point_segment_sq(xb1, yb1, xa0, ya0, xa1, ya1) <= tol2)
            return 0;
    }
    return 1;
}

/* meshmei.certify.StarCertificate.holds: V (n, 3), faces F (m, 3) of a closed mesh, face normals N (m, 3);
 * used[v]: 1 where v is a corner of some face; work: room for 4 n doubles. Returns 1 where proven: with c
 * the used vertices' centroid, c lies inside every face's positive side (n . (a - c) > margin |a - c| at
 * the face's first corner a), and the corner angles around each used vertex v, projected onto the plane
 * perpendicular to v - c, sum to one turn (within 1e-6). As NumPy's twin, with rough angles (within 5e-8
 * each: every corner's projected angle lies in (0, pi), so a sum is a whole number of turns up to
 * rounding) and the centroid summed in order. */
int star_holds(int64_t n, const double *V, int64_t m, const int64_t *F, const double *N, const uint8_t *used,
               double margin, double *work) {
    const double two_pi = 6.283185307179586, tiny = DBL_MIN;
    double c[3] = {0.0, 0.0, 0.0}, k = 0.0;
    for (int64_t v = 0; v < n; v++)
        if (used[v]) {
            for (int a = 0; a < 3; a++) c[a] += V[3 * v + a];
            k += 1.0;
        }
    if (k == 0.0) return 1;
    for (int a = 0; a < 3; a++) c[a] /= k;
    double *P = work, *turn = work + 3 * n;
    for (int64_t v = 0; v < n; v++) {
        for (int a = 0; a < 3; a++) P[3 * v + a] = V[3 * v + a] - c[a];
        turn[v] = 0.0;
    }
    for (int64_t f = 0; f < m; f++) {
        const double *a = P + 3 * F[3 * f], *nf = N + 3 * f;
        if (!(dot3(nf, a) > margin * sqrt(dot3(a, a)))) return 0; /* c on or outside the face's plane */
    }
    for (int64_t f = 0; f < m; f++) {
        const int64_t *t = F + 3 * f;
        for (int j = 0; j < 3; j++) {
            const double *r = P + 3 * t[j], *p1 = P + 3 * t[(j + 1) % 3], *p2 = P + 3 * t[(j + 2) % 3];
            double x1[3], x2[3], w[3];
            for (int a = 0; a < 3; a++) x1[a] = p1[a] - r[a], x2[a] = p2[a] - r[a];
            cross3(x1, x2, w);
            double r2 = dot3(r, r);
            r2 = r2 > tiny ? r2 : tiny;
            double sine = dot3(r, w) / sqrt(r2), cosine = dot3(x1, x2) - dot3(r, x1) * dot3(r, x2) / r2;
            turn[t[j]] += rough_atan2(sine, cosine);
        }
    }
    for (int64_t v = 0; v < n; v++)
        if (used[v] && fabs(turn[v] - two_pi) > 1e-6) return 0;
    return 1;
}
