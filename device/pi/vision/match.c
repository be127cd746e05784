/* One-to-one greedy matching of points within a gate: the tracker's inner kernel.
 *
 * The compiled twin of device/pi/vision/matching.py's _match_finite (the numpy
 * version is the specification and the fallback). Built on the leg by
 * `python -m device.pi.vision.native build` (host deploy runs it) with
 * -ffp-contract=off, so every squared distance is the same double as numpy's
 * (rx - cx)^2 + (ry - cy)^2, summed x first.
 *
 * tf_match(r, m, c, n, max_d2, idx): r (m, 2) and c (n, 2) row-major doubles,
 * every row finite and within +-1e6 px (the caller checks). Writes idx[i] = the row
 * of c matched to r[i], for pairs with squared distance <= max_d2, taken shortest
 * first (ties by r row, then c row); idx must hold -1 on entry. Candidate pairs
 * come from a cell grid over the current points (cells at least a gate wide, about
 * n of them), so the work grows with m + n and the pairs within the gate, not m * n.
 * Returns 0, or -1 when memory runs out (idx untouched: use the numpy path).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

typedef struct {
    double d2;
    int64_t r;
    int64_t c;
} tf_pair;

static int tf_cmp_pair(const void *pa, const void *pb) {
    const tf_pair *a = (const tf_pair *)pa, *b = (const tf_pair *)pb;
    if (a->d2 != b->d2) return a->d2 < b->d2 ? -1 : 1;
    if (a->r != b->r) return a->r < b->r ? -1 : 1;
    return (a->c > b->c) - (a->c < b->c);
}

/* cells are a gate wide plus this margin, so rounding never puts a pair within the
   gate two cells apart */
#define TF_MARGIN (1.0 + 1e-6)
/* at most this many cells along a side of the grid */
#define TF_MAX_SIDE 2048.0

int tf_abi_version(void) { return 1; }

int tf_match(const double *r, int64_t m, const double *c, int64_t n, double max_d2,
             int64_t *idx) {
    if (m <= 0 || n <= 0 || !(max_d2 >= 0.0)) return 0;
    /* the grid covers the current points' bounding box, with about n cells (never
       narrower than the gate, never more than TF_MAX_SIDE a side) */
    double x0 = c[0], x1 = c[0], y0 = c[1], y1 = c[1];
    for (int64_t j = 1; j < n; j++) {
        double x = c[2 * j], y = c[2 * j + 1];
        if (x < x0) x0 = x;
        if (x > x1) x1 = x;
        if (y < y0) y0 = y;
        if (y > y1) y1 = y;
    }
    double bw = x1 - x0, bh = y1 - y0;
    double cell = sqrt(max_d2) * TF_MARGIN;
    double fill = sqrt(bw * bh / (double)n);
    if (fill > cell) cell = fill;
    if (bw / TF_MAX_SIDE > cell) cell = bw / TF_MAX_SIDE;
    if (bh / TF_MAX_SIDE > cell) cell = bh / TF_MAX_SIDE;
    if (!(cell > 0.0)) cell = 1.0;                 /* every point in one place, gate 0 */
    double inv = 1.0 / cell;
    int64_t w = (int64_t)floor(bw * inv) + 1, h = (int64_t)floor(bh * inv) + 1;
    int64_t ncell = w * h;
    /* counting sort of the current points by cell: start[q]..start[q+1] in order */
    int32_t *start = (int32_t *)calloc((size_t)ncell + 1, sizeof(int32_t));
    int32_t *cellof = (int32_t *)malloc((size_t)n * sizeof(int32_t));
    int32_t *order = (int32_t *)malloc((size_t)n * sizeof(int32_t));
    int64_t cap = m + n + 16, k = 0;
    tf_pair *pairs = (tf_pair *)malloc((size_t)cap * sizeof(tf_pair));
    unsigned char *used = (unsigned char *)calloc((size_t)n, 1);
    if (!start || !cellof || !order || !pairs || !used) {
        free(start); free(cellof); free(order); free(pairs); free(used);
        return -1;
    }
    for (int64_t j = 0; j < n; j++) {
        int64_t gx = (int64_t)floor((c[2 * j] - x0) * inv), gy = (int64_t)floor((c[2 * j + 1] - y0) * inv);
        if (gx >= w) gx = w - 1;
        if (gy >= h) gy = h - 1;
        cellof[j] = (int32_t)(gy * w + gx);
        start[cellof[j] + 1]++;
    }
    for (int64_t q = 0; q < ncell; q++) start[q + 1] += start[q];
    for (int64_t j = 0; j < n; j++) order[start[cellof[j]]++] = (int32_t)j;
    for (int64_t q = ncell; q > 0; q--) start[q] = start[q - 1];
    start[0] = 0;
    /* candidate pairs: each reference point against the 3 x 3 cells around it */
    int multi = 0;                                  /* a point with two candidates */
    for (int64_t i = 0; i < m; i++) {
        double rx = r[2 * i], ry = r[2 * i + 1];
        double fx = floor((rx - x0) * inv), fy = floor((ry - y0) * inv);
        if (!(fx >= -1.0 && fy >= -1.0 && fx <= (double)w && fy <= (double)h)) continue;
        int64_t gx = (int64_t)fx, gy = (int64_t)fy, before = k;
        for (int64_t yy = gy - 1; yy <= gy + 1; yy++) {
            if (yy < 0 || yy >= h) continue;
            for (int64_t xx = gx - 1; xx <= gx + 1; xx++) {
                if (xx < 0 || xx >= w) continue;
                int64_t q = yy * w + xx;
                for (int32_t p = start[q]; p < start[q + 1]; p++) {
                    int64_t j = order[p];
                    double ex = rx - c[2 * j], ey = ry - c[2 * j + 1];
                    double d2 = ex * ex + ey * ey;
                    if (!(d2 <= max_d2)) continue;
                    if (k == cap) {
                        cap *= 2;
                        tf_pair *grown = (tf_pair *)realloc(pairs, (size_t)cap * sizeof(tf_pair));
                        if (!grown) {
                            free(start); free(cellof); free(order); free(pairs); free(used);
                            return -1;
                        }
                        pairs = grown;
                    }
                    pairs[k].d2 = d2;
                    pairs[k].r = i;
                    pairs[k].c = j;
                    k++;
                    if (used[j]) multi = 1;
                    used[j] = 1;
                }
            }
        }
        if (k - before > 1) multi = 1;
    }
    if (!multi) {
        /* every point has at most one candidate: that is the greedy answer */
        for (int64_t p = 0; p < k; p++) idx[pairs[p].r] = pairs[p].c;
    } else {
        /* greedy: the shortest pair whose two points are both free, again and again */
        qsort(pairs, (size_t)k, sizeof(tf_pair), tf_cmp_pair);
        for (int64_t j = 0; j < n; j++) used[j] = 0;
        for (int64_t p = 0; p < k; p++) {
            int64_t i = pairs[p].r, j = pairs[p].c;
            if (idx[i] < 0 && !used[j]) {
                idx[i] = j;
                used[j] = 1;
            }
        }
    }
    free(start); free(cellof); free(order); free(pairs); free(used);
    return 0;
}
