/* One-to-one greedy matching of points within a gate: the tracker's inner kernel.
 *
 * The compiled twin of device/pi/vision/matching.py's _match_finite (the numpy
 * version is the specification and the fallback). Compiled by the package's own
 * build (setup.py: pip install, on the leg too: host deploy ships the sdist) with
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

int tf_abi_version(void) { return 8; }

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


/* ------------------------------------------------------------------------------
 * tf_grow: the tracker's per-frame matching and growth into lost pins, the C twin of
 * device/pi/vision/neighbours.py's match_and_grow for its usual case (every reference
 * pin finite, every predicted position within +-1e6 px). The Python function is the
 * specification; each step below names the lines it mirrors. Every float operation
 * is the one numpy does, in the same order, so the results are the same doubles.
 *
 * r (m, 2) reference pins, c (n, 2) current pins (usable rows), pred (m, 2) the
 * prediction, nb (m, k) int64 layout neighbours with valid (m, k) bytes, gate px,
 * grow_rounds, min_support, final_rounds. Writes idx (m,) and disp (m, 2) (disp may
 * be pred) and *n_conf. Returns 0; 1 when a predicted position is not usable (use
 * the numpy path); -1 when memory runs out (nothing written).
 * ------------------------------------------------------------------------------ */

typedef struct {
    int64_t m, n, k;
    const double *r, *c;
    const int64_t *nb;
    const unsigned char *valid;
    double gate;
    double *prior, *ed;             /* ed: per pin err x, err y, dd x, dd y */
    unsigned char *ok, *freec, *supported, *newly;
    int64_t *idx;
    /* scratch */
    double *pa, *pb, *vals;
    int64_t *rows, *rows2, *fc, *sub;
} tf_grow_state;

static int tf_cmp_double(const void *pa, const void *pb) {
    double a = *(const double *)pa, b = *(const double *)pb;
    return (a > b) - (a < b);
}

/* the kth smallest of v[0..n) (0 <= kth < n), every value finite: Hoare's
   selection. v is reordered so that v[0..kth) <= v[kth] <= v(kth..n). */
static double tf_select(double *v, int64_t n, int64_t kth) {
    int64_t lo = 0, hi = n - 1;
    while (lo < hi) {
        const double pivot = v[lo + (hi - lo) / 2];
        int64_t i = lo, j = hi;
        while (i <= j) {
            while (v[i] < pivot) i++;
            while (v[j] > pivot) j--;
            if (i <= j) {
                double t = v[i]; v[i] = v[j]; v[j] = t;
                i++; j--;
            }
        }
        if (kth <= j) hi = j;
        else if (kth >= i) lo = i;
        else break;                                  /* v[kth] == pivot */
    }
    return v[kth];
}

/* np.median of v[0..k) (k >= 1) as column_median / neighbour_median compute it: the
   same order statistics a sort gives, by selection (a NaN, which has no order,
   takes the sort) */
static double tf_median(double *v, int64_t k, int even_as_sum_half) {
    double lo, hi;
    int finite = 1;
    for (int64_t i = 0; i < k; i++) if (v[i] != v[i]) { finite = 0; break; }
    if (k <= 16 || !finite) {
        if (k <= 16) {                               /* insertion sort: few values */
            for (int64_t i = 1; i < k; i++) {
                double x = v[i];
                int64_t j = i - 1;
                while (j >= 0 && v[j] > x) { v[j + 1] = v[j]; j--; }
                v[j + 1] = x;
            }
        } else {
            qsort(v, (size_t)k, sizeof(double), tf_cmp_double);
        }
        lo = v[(k - 1) / 2];
        hi = v[k / 2];
    } else {
        hi = tf_select(v, k, k / 2);
        lo = hi;
        if (k % 2 == 0) {                            /* the largest below the middle */
            lo = v[0];
            for (int64_t i = 1; i < k / 2; i++) if (v[i] > lo) lo = v[i];
        }
    }
    if (even_as_sum_half)                            /* neighbour_median: (lo + hi) * 0.5 */
        return (lo + hi) * 0.5;
    if (k % 2) return hi;                            /* column_median */
    return (lo + hi) / 2.0;
}

/* match points p (cnt, 2) against the current pins listed in cols (nc of them, or all
   when cols is NULL), gate g; out[i] = row of c or -1 */
static int tf_match_sub(tf_grow_state *S, const double *p, int64_t cnt, const int64_t *cols,
                        int64_t nc, double g, int64_t *out) {
    for (int64_t i = 0; i < cnt; i++) out[i] = -1;
    if (cnt == 0 || nc == 0) return 0;
    const double *cc = S->c;
    if (cols) {
        for (int64_t j = 0; j < nc; j++) {
            S->pb[2 * j] = S->c[2 * cols[j]];
            S->pb[2 * j + 1] = S->c[2 * cols[j] + 1];
        }
        cc = S->pb;
    }
    if (tf_match(p, cnt, cc, nc, g * g, out) != 0) return -1;
    if (cols)
        for (int64_t i = 0; i < cnt; i++)
            if (out[i] >= 0) out[i] = cols[out[i]];
    return 0;
}

/* neighbour_median over ed for rows[0..nr), then the prediction of predict():
   writes dd and supported; sup[i] = 1 where row i has min_support neighbours */
static void tf_predict(tf_grow_state *S, const int64_t *rows, int64_t nr, int64_t min_support,
                       unsigned char *sup) {
    int64_t k = S->k;
    double g2 = S->gate * S->gate;
    for (int64_t t = 0; t < nr; t++) {
        int64_t i = rows[t], count = 0;
        const int64_t *nbi = S->nb + i * k;
        const unsigned char *vi = S->valid + i * k;
        double med[4] = {0.0, 0.0, 0.0, 0.0};
        for (int64_t j = 0; j < k; j++)
            if (vi[j] && S->ok[nbi[j]]) count++;
        if (count > 0) {
            for (int d = 0; d < 4; d++) {
                int64_t q = 0;
                for (int64_t j = 0; j < k; j++)
                    if (vi[j] && S->ok[nbi[j]]) S->vals[q++] = S->ed[4 * nbi[j] + d];
                med[d] = tf_median(S->vals, count, 1);
            }
        }
        int s = count >= min_support;
        S->supported[i] = (unsigned char)s;
        sup[t] = (unsigned char)s;
        if (s) {
            double ownx = S->prior[2 * i] + med[0], owny = S->prior[2 * i + 1] + med[1];
            double devx = ownx - med[2], devy = owny - med[3];
            int agree = devx * devx + devy * devy <= g2;
            S->ed[4 * i + 2] = agree ? ownx : med[2];
            S->ed[4 * i + 3] = agree ? owny : med[3];
        }
    }
}

/* take(): match rows at r + dd against the free current pins with gate g; the pins
   caught become tracked. Returns how many were caught; their rows go to got. */
static int64_t tf_take(tf_grow_state *S, const int64_t *rows, int64_t nr, double g, int64_t *got) {
    int64_t nc = 0;
    for (int64_t j = 0; j < S->n; j++)
        if (S->freec[j]) S->fc[nc++] = j;
    for (int64_t t = 0; t < nr; t++) {
        int64_t i = rows[t];
        S->pa[2 * t] = S->r[2 * i] + S->ed[4 * i + 2];
        S->pa[2 * t + 1] = S->r[2 * i + 1] + S->ed[4 * i + 3];
    }
    if (tf_match_sub(S, S->pa, nr, S->fc, nc, g, S->sub) != 0) return -1;
    int64_t ng = 0;
    for (int64_t t = 0; t < nr; t++) {
        if (S->sub[t] < 0) continue;
        int64_t i = rows[t], j = S->sub[t];
        S->idx[i] = j;
        S->ok[i] = 1;
        S->freec[j] = 0;
        double ddx = S->c[2 * j] - S->r[2 * i], ddy = S->c[2 * j + 1] - S->r[2 * i + 1];
        S->ed[4 * i + 2] = ddx;
        S->ed[4 * i + 3] = ddy;
        S->ed[4 * i] = ddx - S->prior[2 * i];
        S->ed[4 * i + 1] = ddy - S->prior[2 * i + 1];
        got[ng++] = i;
    }
    return ng;
}

static int64_t tf_count_ok(const tf_grow_state *S) {
    int64_t q = 0;
    for (int64_t i = 0; i < S->m; i++) q += S->ok[i];
    return q;
}

static int tf_any_free(const tf_grow_state *S) {
    for (int64_t j = 0; j < S->n; j++)
        if (S->freec[j]) return 1;
    return 0;
}

int tf_grow(const double *r, int64_t m, const double *c, int64_t n, const double *pred,
            const int64_t *nb, const unsigned char *valid, int64_t k, double gate,
            int64_t grow_rounds, int64_t min_support, int64_t final_rounds,
            int64_t *idx_out, double *disp, int64_t *n_conf) {
    if (m <= 0 || n <= 0) return 1;
    tf_grow_state S;
    S.m = m; S.n = n; S.k = k; S.r = r; S.c = c; S.nb = nb; S.valid = valid; S.gate = gate;
    int64_t big = m > n ? m : n;
    S.prior = (double *)malloc((size_t)m * 2 * sizeof(double));
    S.ed = (double *)malloc((size_t)m * 4 * sizeof(double));
    S.ok = (unsigned char *)calloc((size_t)m, 1);
    S.freec = (unsigned char *)malloc((size_t)n);
    S.supported = (unsigned char *)calloc((size_t)m, 1);
    S.newly = (unsigned char *)calloc((size_t)m, 1);
    S.idx = (int64_t *)malloc((size_t)m * sizeof(int64_t));
    S.pa = (double *)malloc((size_t)big * 2 * sizeof(double));
    S.pb = (double *)malloc((size_t)big * 2 * sizeof(double));
    S.vals = (double *)malloc((size_t)(k > big ? k : big) * sizeof(double));
    S.rows = (int64_t *)malloc((size_t)m * sizeof(int64_t));
    S.rows2 = (int64_t *)malloc((size_t)m * sizeof(int64_t));
    S.fc = (int64_t *)malloc((size_t)n * sizeof(int64_t));
    S.sub = (int64_t *)malloc((size_t)big * sizeof(int64_t));
    unsigned char *sup = (unsigned char *)malloc((size_t)m);
    int64_t *wide = (int64_t *)malloc((size_t)m * sizeof(int64_t));
    int64_t *got = (int64_t *)malloc((size_t)m * sizeof(int64_t));
    int rc = -1;
    if (!S.prior || !S.ed || !S.ok || !S.freec || !S.supported || !S.newly || !S.idx || !S.pa ||
        !S.pb || !S.vals || !S.rows || !S.rows2 || !S.fc || !S.sub || !sup || !wide || !got)
        goto done;
    /* prior = pred; pos = r + prior; every position usable, else the numpy path */
    for (int64_t i = 0; i < 2 * m; i++) {
        S.prior[i] = pred[i];
        double p = r[i] + pred[i];
        if (!(p <= 1e6 && p >= -1e6)) { rc = 1; goto done; }
        S.pa[i] = p;
    }
    /* 1. confident matches with half the gate */
    if (tf_match_sub(&S, S.pa, m, NULL, n, 0.5 * gate, S.idx) != 0) goto done;
    int64_t n_ok = 0;
    for (int64_t i = 0; i < m; i++) { S.ok[i] = S.idx[i] >= 0; n_ok += S.ok[i]; }
    if (n_ok < 0.5 * m) {
        /* a common jump: shift every prediction by the median offset of wide matches */
        if (tf_match_sub(&S, S.pa, m, NULL, n, 1.25 * gate, wide) != 0) goto done;
        int64_t nh = 0;
        for (int64_t i = 0; i < m; i++) nh += wide[i] >= 0;
        if (nh > 0) {
            double shift[2];
            for (int d = 0; d < 2; d++) {
                int64_t q = 0;
                for (int64_t i = 0; i < m; i++)
                    if (wide[i] >= 0) S.vals[q++] = c[2 * wide[i] + d] - S.pa[2 * i + d];
                shift[d] = tf_median(S.vals, q, 0);
            }
            for (int64_t i = 0; i < m; i++) {
                S.pb[2 * i] = S.pa[2 * i] + shift[0];
                S.pb[2 * i + 1] = S.pa[2 * i + 1] + shift[1];
            }
            /* idx2 = match(pos + shift, c, 0.5 gate); pb is tf_match_sub's scratch
               only when it is given cols, so it may hold pos + shift here */
            if (tf_match_sub(&S, S.pb, m, NULL, n, 0.5 * gate, S.sub) != 0) goto done;
            int64_t n2 = 0, kept = 0;
            for (int64_t i = 0; i < m; i++) {
                n2 += S.sub[i] >= 0;
                if (S.ok[i] && S.sub[i] == S.idx[i]) kept++;
            }
            if (n2 > n_ok && 2 * kept >= n_ok) {
                for (int64_t i = 0; i < m; i++) {
                    S.prior[2 * i] += shift[0];
                    S.prior[2 * i + 1] += shift[1];
                    S.pa[2 * i] += shift[0];
                    S.pa[2 * i + 1] += shift[1];
                    S.idx[i] = S.sub[i];
                    S.ok[i] = S.sub[i] >= 0;
                }
                n_ok = n2;
            }
        }
    }
    *n_conf = n_ok;
    /* ed: dd = prior, measured for tracked pins; err = dd - prior */
    for (int64_t j = 0; j < n; j++) S.freec[j] = 1;
    for (int64_t i = 0; i < m; i++) {
        double ddx = S.prior[2 * i], ddy = S.prior[2 * i + 1];
        if (S.ok[i]) {
            int64_t j = S.idx[i];
            ddx = c[2 * j] - r[2 * i];
            ddy = c[2 * j + 1] - r[2 * i + 1];
            S.freec[j] = 0;
        }
        S.ed[4 * i + 2] = ddx;
        S.ed[4 * i + 3] = ddy;
        S.ed[4 * i] = ddx - S.prior[2 * i];
        S.ed[4 * i + 1] = ddy - S.prior[2 * i + 1];
    }
    /* 2. grow from tracked neighbours, half the gate */
    int64_t n_pred = -1, nr = 0;
    for (int64_t i = 0; i < m; i++)
        if (!S.ok[i]) S.rows[nr++] = i;
    for (int64_t round = 0; round < grow_rounds; round++) {
        if (nr == 0 || tf_count_ok(&S) == 0) break;
        tf_predict(&S, S.rows, nr, min_support, sup);
        n_pred = tf_count_ok(&S);
        int64_t ns = 0;
        for (int64_t t = 0; t < nr; t++)
            if (sup[t]) S.rows2[ns++] = S.rows[t];
        if (ns == 0 || !tf_any_free(&S)) break;
        int64_t ng = tf_take(&S, S.rows2, ns, 0.5 * gate, got);
        if (ng < 0) goto done;
        if (ng == 0) break;
        for (int64_t i = 0; i < m; i++) S.newly[i] = 0;
        for (int64_t t = 0; t < ng; t++) S.newly[got[t]] = 1;
        nr = 0;
        for (int64_t i = 0; i < m; i++) {
            if (S.ok[i]) continue;
            for (int64_t j = 0; j < k; j++)
                if (valid[i * k + j] && S.newly[nb[i * k + j]]) { S.rows[nr++] = i; break; }
        }
        if (nr == 0) n_pred = tf_count_ok(&S);
    }
    /* 3. every pin still lost, with the full gate */
    for (int64_t round = 0; round < final_rounds; round++) {
        int64_t nl = 0;
        for (int64_t i = 0; i < m; i++)
            if (!S.ok[i]) S.rows[nl++] = i;
        int64_t n_now = m - nl;
        if (nl == 0 || n_now == 0) break;
        if (n_now != n_pred) {
            tf_predict(&S, S.rows, nl, min_support, sup);
            n_pred = n_now;
        }
        int64_t nf = 0;
        for (int64_t t = 0; t < nl; t++)
            if (!S.supported[S.rows[t]]) S.rows2[nf++] = S.rows[t];
        if (n_now >= 3 && nf > 0) {
            double cm[2];
            for (int d = 0; d < 2; d++) {
                int64_t q = 0;
                for (int64_t i = 0; i < m; i++)
                    if (S.ok[i]) S.vals[q++] = S.ed[4 * i + d];
                cm[d] = tf_median(S.vals, q, 0);
            }
            for (int64_t t = 0; t < nf; t++) {
                int64_t i = S.rows2[t];
                S.ed[4 * i + 2] = S.prior[2 * i] + cm[0];
                S.ed[4 * i + 3] = S.prior[2 * i + 1] + cm[1];
            }
        }
        if (!tf_any_free(&S)) break;
        int64_t ng = tf_take(&S, S.rows, nl, gate, got);
        if (ng < 0) goto done;
        if (ng == 0) break;
    }
    for (int64_t i = 0; i < m; i++) {
        idx_out[i] = S.idx[i];
        disp[2 * i] = S.ed[4 * i + 2];
        disp[2 * i + 1] = S.ed[4 * i + 3];
    }
    rc = 0;
done:
    free(S.prior); free(S.ed); free(S.ok); free(S.freec); free(S.supported); free(S.newly);
    free(S.idx); free(S.pa); free(S.pb); free(S.vals); free(S.rows); free(S.rows2); free(S.fc);
    free(S.sub); free(sup); free(wide); free(got);
    return rc;
}

/* The tracker's prediction state moved to this frame (Tracker._advance, numpy's
 * elementwise float64 steps in the same order): vel = vel * (1 - alpha) + (work -
 * disp) * (alpha / steps); a lost pin's vel times 0.8 (when not every pin was
 * tracked); clipped to +-cap with np.minimum/np.maximum's NaN rule; disp = work.
 * work, disp, vel (m, 2) doubles; lost (m,) bytes. */
void tf_advance(const double *work, double *disp, double *vel, const uint8_t *lost,
                int64_t m, double keep, double gain, int64_t damp_lost, double cap) {
    for (int64_t i = 0; i < m; i++) {
        for (int64_t j = 0; j < 2; j++) {
            int64_t e = 2 * i + j;
            double v = vel[e] * keep;
            double d = (work[e] - disp[e]) * gain;
            v += d;
            if (damp_lost && lost[i]) v *= 0.8;
            v = (v <= cap || v != v) ? v : cap;
            v = (v >= -cap || v != v) ? v : -cap;
            vel[e] = v;
            disp[e] = work[e];
        }
    }
}

/* One tracker update's usual path (Tracker.update, the compiled twin): the
 * constant-velocity prediction, tf_grow, the jump test, tf_advance and the fill, in
 * numpy's order with the same doubles. Integer slots TF_T_* in ci, doubles TF_TD_* in
 * cd. Returns 0 when done (idx, lost, vec, the state and the counts written), 1 when
 * the frame is a jump (nothing but pred and work written: the Python path takes the
 * frame from the start), 2 when it is not the usual case (a current pin beyond
 * +-1e6 px or not finite, no pin, no memory: nothing trusted), -1 for a bad context. */
enum {
    TF_T_CUR = 0,      /* const float *: n x 2 current pins */
    TF_T_N,
    TF_T_C,            /* double *: n x 2 scratch (the pins as doubles) */
    TF_T_R, TF_T_M,    /* const double *: m x 2 reference pins (all finite) */
    TF_T_PRED, TF_T_VEL, TF_T_DISP, TF_T_WORK,   /* double *: m x 2 each */
    TF_T_NB, TF_T_VALID, TF_T_K,                 /* neighbours (m x k) and their flags */
    TF_T_GROW_ROUNDS, TF_T_FINAL_ROUNDS,
    TF_T_STEPS,
    TF_T_FILL,         /* 0 predict, 1 hold, 2 zero */
    TF_T_IDX,          /* int64 *: m, written */
    TF_T_LOST,         /* uint8 *: m, written */
    TF_T_VEC,          /* float *: m x 2, written */
    TF_T_N_OK, TF_T_N_CONF,   /* written */
    TF_T_SCRATCH,      /* double *: m scratch (the jump test's distances) */
    TF_T_SLOTS
};
enum { TF_TD_GATE = 0, TF_TD_GAIN_STEPS, TF_TD_REACQ_FRAC, TF_TD_MIN_TRACKED, TF_TD_PITCH,
       TF_TD_VEL_KEEP, TF_TD_VEL_GAIN, TF_TD_SLOTS };

int tf_track_slots(void) { return TF_T_SLOTS * 100 + TF_TD_SLOTS; }

int64_t tf_track(int64_t *ci, const double *cd) {
    const int64_t n = ci[TF_T_N], m = ci[TF_T_M], steps = ci[TF_T_STEPS];
    if (m <= 0 || n < 0 || steps < 1) return -1;
    if (n == 0) return 2;
    const float *cur = (const float *)(intptr_t)ci[TF_T_CUR];
    double *c = (double *)(intptr_t)ci[TF_T_C];
    for (int64_t i = 0; i < 2 * n; i++) {
        double v = (double)cur[i];
        if (!(v <= 1.0e6 && v >= -1.0e6)) return 2;      /* NaN fails too */
        c[i] = v;
    }
    const double *r = (const double *)(intptr_t)ci[TF_T_R];
    double *pred = (double *)(intptr_t)ci[TF_T_PRED], *vel = (double *)(intptr_t)ci[TF_T_VEL];
    double *disp = (double *)(intptr_t)ci[TF_T_DISP], *work = (double *)(intptr_t)ci[TF_T_WORK];
    int64_t *idx = (int64_t *)(intptr_t)ci[TF_T_IDX];
    unsigned char *lost = (unsigned char *)(intptr_t)ci[TF_T_LOST];
    float *vec = (float *)(intptr_t)ci[TF_T_VEC];
    const double gate = cd[TF_TD_GATE], rf = cd[TF_TD_REACQ_FRAC];
    /* np.multiply(vel, gain * steps, out=pred); pred += disp */
    for (int64_t e = 0; e < 2 * m; e++) {
        double p = vel[e] * cd[TF_TD_GAIN_STEPS];
        pred[e] = p + disp[e];
    }
    int64_t n_conf = 0;
    int rc = tf_grow(r, m, c, n, pred, (const int64_t *)(intptr_t)ci[TF_T_NB],
                     (const unsigned char *)(intptr_t)ci[TF_T_VALID], ci[TF_T_K], gate,
                     ci[TF_T_GROW_ROUNDS], 2, ci[TF_T_FINAL_ROUNDS], idx, work, &n_conf);
    if (rc != 0) return 2;
    int64_t n_ok = 0;
    for (int64_t i = 0; i < m; i++) n_ok += idx[i] >= 0;
    const double fm = (double)m;
    if ((double)n_conf < rf * fm && (double)n >= rf * fm) {
        int jump = steps > 1 || (double)n_ok < rf * fm;
        if (!jump) {                 /* the median distance of tracked pins to their prediction */
            double *d = (double *)(intptr_t)ci[TF_T_SCRATCH];
            int64_t q = 0;
            for (int64_t i = 0; i < m; i++)
                if (idx[i] >= 0)
                    d[q++] = hypot(work[2 * i] - pred[2 * i], work[2 * i + 1] - pred[2 * i + 1]);
            double moved = q ? tf_median(d, q, 0) : 0.0;
            jump = moved > 0.8 * gate;
        }
        if (jump) return 1;
    }
    for (int64_t i = 0; i < m; i++) lost[i] = idx[i] < 0;
    if ((double)n_ok >= cd[TF_TD_MIN_TRACKED] * fm)
        tf_advance(work, disp, vel, lost, m, cd[TF_TD_VEL_KEEP], cd[TF_TD_VEL_GAIN], n_ok < m,
                   0.5 * cd[TF_TD_PITCH]);
    const int64_t fill = ci[TF_T_FILL];
    for (int64_t i = 0; i < m; i++) {
        if (fill == 1 && lost[i]) continue;
        if (fill == 2 && lost[i]) { vec[2 * i] = 0.f; vec[2 * i + 1] = 0.f; continue; }
        vec[2 * i] = (float)work[2 * i];
        vec[2 * i + 1] = (float)work[2 * i + 1];
    }
    ci[TF_T_N_OK] = n_ok;
    ci[TF_T_N_CONF] = n_conf;
    return 0;
}
