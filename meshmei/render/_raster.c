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

int meshmei_raster_abi(void) { return 1; }
