/* Pin detection in one call: the compiled twin of PinDetector.detect_gray.
 *
 * device/pi/vision/extract.py is the specification and the fallback: OpenCV's
 * GaussianBlur (its bit-exact fixed-point path for 8-bit images), a box-mean
 * threshold (cv2.boxFilter, cv2.subtract, cv2.threshold, the dome mask) and
 * connectedComponentsWithStats (8-connected, Grana's block-based labelling), then
 * the size filter. Every step here is integer arithmetic that gives the same bytes:
 *
 * - blur: the row pass sums k[i] * pixel (kernel in 1/256ths, so at most
 *   256 * 255), the column pass sums k[j] * row, and the pixel is (sum + 2^15) >> 16; borders reflect without repeating the edge (BORDER_DEFAULT);
 * - local mean: the block's sum S (block <= 15, N = block^2 pixels) rounded to the
 *   nearest whole mean, floor((S + (N - 1) / 2) / N) (no sum lies half-way: N is
 *   odd); borders replicate the edge of the region the mean is taken over;
 * - threshold: 255 where pixel - mean (saturated at 0) > f = floor(offset) >= 0,
 *   inside the mask. No mean is divided out: for whole numbers,
 *   p - floor((S + h) / N) > f  <=>  floor((S + h) / N) <= p - f - 1
 *                               <=>  S + h < N * (p - f),
 *   false when p <= f, so the row compares S + h with N * max(p - f, 0) in 16 bits
 *   (both at most 225 * 255 + 112);
 * - blobs: 8-connected components, ordered as OpenCV's block-based labelling orders
 *   them (by the first 2x2 block, in raster order of blocks, that holds a pixel of
 *   the blob), with the area and the centroid (the integer sums of x and y divided
 *   by the area, in double).
 *
 * Python passes one context: an int64 array (TF_D_* slots) that holds the sizes,
 * the parameters and the addresses of preallocated buffers, so a frame is one call
 * with one argument. tf_detect returns the number of pins kept (>= 0), or -1 for a
 * context it refuses (sizes that do not fit the buffers it declares).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

/* On x86-64 the vector loops are also built for AVX2 and picked at load time (as
   OpenCV picks its own); every lane computes the same integers either way. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(TF_NO_CLONES)
#define TF_VECTOR __attribute__((target_clones("avx2", "default")))
#else
#define TF_VECTOR
#endif

/* context slots (device/pi/vision/native.py names them the same) */
enum {
    TF_D_GRAY = 0,      /* const uint8 *: the gray dome box, bh x bw */
    TF_D_GRAY_STRIDE,   /* its row stride, bytes */
    TF_D_BH, TF_D_BW,   /* the box's height and width */
    TF_D_KN,            /* blur taps (odd, 1..15); 0: no blur */
    TF_D_KERNEL,        /* const uint16 *: KN taps in 1/256ths */
    TF_D_ROWS,          /* uint16 *: bh x bw scratch, the row pass */
    TF_D_SMOOTH,        /* uint8 *: bh x bw, the blurred box (written) */
    TF_D_BLOCK,         /* the mean's block side (odd, 3..15) */
    TF_D_FLOOR_OFFSET,  /* floor(offset) >= 0 */
    TF_D_PAD,           /* uint8 *: bw + 14 scratch, a row with its reflected borders */
    TF_D_GY0, TF_D_GX0, TF_D_GY1, TF_D_GX1,   /* the mean's region, box px */
    TF_D_CY0, TF_D_CX0, TF_D_CY1, TF_D_CX1,   /* the thresholded core, box px */
    TF_D_MASK,          /* const uint8 *: (cy1-cy0) x (cx1-cx0), 0 or 255 */
    TF_D_COLSUM,        /* uint16 *: (gx1 - gx0) + (cx1 - cx0) + 15 scratch */
    TF_D_BINARY,        /* uint8 *: the binary buffer (0 outside the core) */
    TF_D_BIN_STRIDE,    /* its row stride (>= cx1) */
    TF_D_LABELS,        /* int32 *: scratch of 6 * ((cx1-cx0) / 2 + 2) */
    TF_D_CAP,           /* provisional labels the next buffers hold (>= 1 + core pixels / 2) */
    TF_D_PARENT,        /* int32 *: CAP */
    TF_D_ACC,           /* int64 *: CAP x 4: area, sum x, sum y, first block */
    TF_D_ORDER,         /* int32 *: CAP */
    TF_D_MIN_AREA, TF_D_MAX_AREA,
    TF_D_OX, TF_D_OY,   /* the box's origin in the frame, px */
    TF_D_XY,            /* float *: OUT_CAP x 2, pins kept (frame px) */
    TF_D_AREAS,         /* int32 *: OUT_CAP, their areas */
    TF_D_OUT_CAP,
    TF_D_N_BLOBS,       /* written: blobs of any size */
    TF_D_STAT_STEP,     /* the plausibility statistics read every STAT_STEP-th row */
    TF_D_STAT_SUM,      /* written: the sum of those rows' smoothed pixels */
    TF_D_STAT_SQSUM,    /* written: the sum of their squares */
    TF_D_STAT_N,        /* written: how many pixels */
    TF_D_CORNERS,       /* const int64 *: N_CORNERS (row, column) pairs in the box */
    TF_D_N_CORNERS,
    TF_D_CORNER_SUM,    /* written: the sum of the smoothed box at those pixels */
    TF_D_N_SLOTS
};

int tf_detect_slots(void) { return TF_D_N_SLOTS; }

static inline int64_t reflect101(int64_t p, int64_t len) {
    if (len == 1) return 0;
    while (p < 0 || p >= len) {
        if (p < 0) p = -p;
        else p = 2 * (len - 1) - p;
    }
    return p;
}

static inline int64_t clampi(int64_t p, int64_t lo, int64_t hi) {
    return p < lo ? lo : (p > hi ? hi : p);
}

/* One row of the blur's row pass for a constant tap count: src is the row with r
   reflected pixels before and after it, dst its bw sums (the taps are symmetric:
   k[i] == k[kn-1-i]); 16-bit lanes suffice, the sum is at most 256 * 255. */
static inline void row_taps(const uint8_t *restrict src, uint16_t *restrict dst, int64_t bw,
                            const uint16_t *k, const int kn) {
    const int r = kn / 2;
    for (int64_t x = 0; x < bw; x++) {
        uint16_t t = (uint16_t)(k[r] * src[x + r]);
        for (int i = 0; i < r; i++)
            t = (uint16_t)(t + k[i] * (uint16_t)(src[x + i] + src[x + kn - 1 - i]));
        dst[x] = t;
    }
}

/* One row of the column pass: the pixel is (sum_j k[j] * rows[j] + 2^15) >> 16. Each
   row value (at most 65280) is split into its high and low bytes, so both sums stay
   within 16 bits: (A + (B >> 8) + 128) >> 8 with A = sum k[j] * hi[j] and
   B = sum k[j] * lo[j] (A + B / 256 <= 255 * 256, so no lane overflows). */
static inline void col_taps(const uint16_t *const *s, uint8_t *restrict out, int64_t bw,
                            const uint16_t *k, const int kn) {
    const int r = kn / 2;
    for (int64_t x = 0; x < bw; x++) {
        uint16_t a = (uint16_t)(k[r] * (uint16_t)(s[r][x] >> 8));
        uint16_t b = (uint16_t)(k[r] * (uint16_t)(s[r][x] & 255));
        for (int j = 0; j < r; j++) {
            a = (uint16_t)(a + k[j] * (uint16_t)((s[j][x] >> 8) + (s[kn - 1 - j][x] >> 8)));
            b = (uint16_t)(b + k[j] * (uint16_t)((s[j][x] & 255) + (s[kn - 1 - j][x] & 255)));
        }
        out[x] = (uint8_t)((uint16_t)(a + (b >> 8) + 128) >> 8);
    }
}

#define TF_FOR_ODD_TAPS(X) X(3) X(5) X(7) X(9) X(11) X(13) X(15)

/* the blurred box into smooth (bh x bw, contiguous) */
TF_VECTOR static void blur(const int64_t *ctx) {
    const uint8_t *gray = (const uint8_t *)(intptr_t)ctx[TF_D_GRAY];
    const int64_t gs = ctx[TF_D_GRAY_STRIDE], bh = ctx[TF_D_BH], bw = ctx[TF_D_BW];
    const int64_t kn = ctx[TF_D_KN];
    uint8_t *smooth = (uint8_t *)(intptr_t)ctx[TF_D_SMOOTH];
    if (kn <= 1) {
        for (int64_t y = 0; y < bh; y++) memcpy(smooth + y * bw, gray + y * gs, (size_t)bw);
        return;
    }
    const uint16_t *k = (const uint16_t *)(intptr_t)ctx[TF_D_KERNEL];
    uint16_t *rows = (uint16_t *)(intptr_t)ctx[TF_D_ROWS];
    uint8_t *pad = (uint8_t *)(intptr_t)ctx[TF_D_PAD];
    const int64_t r = kn / 2;
    for (int64_t y = 0; y < bh; y++) {
        const uint8_t *src = gray + y * gs;
        /* the row with r pixels reflected at each end (BORDER_REFLECT_101) */
        memcpy(pad + r, src, (size_t)bw);
        for (int64_t i = 1; i <= r; i++) {
            pad[r - i] = src[reflect101(-i, bw)];
            pad[r + bw - 1 + i] = src[reflect101(bw - 1 + i, bw)];
        }
        uint16_t *dst = rows + y * bw;
        switch (kn) {
#define TF_ROW_CASE(N) case N: row_taps(pad, dst, bw, k, N); break;
            TF_FOR_ODD_TAPS(TF_ROW_CASE)
#undef TF_ROW_CASE
        }
    }
    const uint16_t *s[15];
    for (int64_t y = 0; y < bh; y++) {
        for (int64_t j = 0; j < kn; j++) s[j] = rows + reflect101(y + j - r, bh) * bw;
        switch (kn) {
#define TF_COL_CASE(N) case N: col_taps(s, smooth + y * bw, bw, k, N); break;
            TF_FOR_ODD_TAPS(TF_COL_CASE)
#undef TF_COL_CASE
        }
    }
}

/* One core row's binary from its column sums: the block sums S of the padded sums
   pc (pc[i] is the column cx0 - half + i, replicated at the region's edge), and the
   threshold inside the mask as S + h < N * max(p - f, 0) (see the top of the file). */
static inline void threshold_row(const uint16_t *restrict pc, const uint8_t *restrict srow,
                                 const uint8_t *restrict mrow, uint8_t *restrict brow, int64_t cw, uint16_t h, uint16_t area,
                                 uint16_t f, const int block) {
    for (int64_t x = 0; x < cw; x++) {
        uint16_t sum = h;
        for (int t = 0; t < block; t++) sum = (uint16_t)(sum + pc[x + t]);
        uint16_t p = srow[x];
        uint16_t lim = (uint16_t)(area * (uint16_t)(p > f ? p - f : 0));
        brow[x] = (uint8_t)((sum < lim ? 255 : 0) & mrow[x]);
    }
}

/* the core's binary: smooth minus its local mean, thresholded, masked */
TF_VECTOR static void threshold(const int64_t *ctx) {
    const uint8_t *smooth = (const uint8_t *)(intptr_t)ctx[TF_D_SMOOTH];
    const int64_t bw = ctx[TF_D_BW], block = ctx[TF_D_BLOCK];
    const int64_t half = block / 2;
    const int64_t fo64 = ctx[TF_D_FLOOR_OFFSET];
    const uint16_t f = (uint16_t)(fo64 < 255 ? fo64 : 255);   /* p > 255: never */
    const uint16_t area = (uint16_t)(block * block);
    const uint16_t h = (uint16_t)((block * block - 1) / 2);
    const int64_t gy0 = ctx[TF_D_GY0], gx0 = ctx[TF_D_GX0], gy1 = ctx[TF_D_GY1], gx1 = ctx[TF_D_GX1];
    const int64_t cy0 = ctx[TF_D_CY0], cx0 = ctx[TF_D_CX0], cy1 = ctx[TF_D_CY1], cx1 = ctx[TF_D_CX1];
    const uint8_t *mask = (const uint8_t *)(intptr_t)ctx[TF_D_MASK];
    uint8_t *bin = (uint8_t *)(intptr_t)ctx[TF_D_BINARY];
    const int64_t bst = ctx[TF_D_BIN_STRIDE];
    /* the scratch holds the column sums (gx1 - gx0) then the padded row (cw + block) */
    uint16_t *col = (uint16_t *)(intptr_t)ctx[TF_D_COLSUM];
    const int64_t gw = gx1 - gx0, cw = cx1 - cx0;
    uint16_t *pc = col + gw;
    for (int64_t x = 0; x < gw; x++) col[x] = 0;
    for (int64_t dy = -half; dy <= half; dy++) {
        const uint8_t *s = smooth + clampi(cy0 + dy, gy0, gy1 - 1) * bw + gx0;
        for (int64_t x = 0; x < gw; x++) col[x] = (uint16_t)(col[x] + s[x]);
    }
    for (int64_t y = cy0; y < cy1; y++) {
        if (y > cy0) {   /* slide the block's rows down by one */
            const uint8_t *add = smooth + clampi(y + half, gy0, gy1 - 1) * bw + gx0;
            const uint8_t *sub = smooth + clampi(y - half - 1, gy0, gy1 - 1) * bw + gx0;
            for (int64_t x = 0; x < gw; x++) col[x] = (uint16_t)(col[x] + add[x] - sub[x]);
        }
        /* the columns the row's blocks read, the region's edge columns repeated */
        const int64_t i0 = gx0 - (cx0 - half), i1 = gx1 - (cx0 - half);
        const int64_t np_ = cw + 2 * half;
        const int64_t a = i0 > 0 ? i0 : 0, b = i1 < np_ ? i1 : np_;
        for (int64_t i = 0; i < a; i++) pc[i] = col[0];
        memcpy(pc + a, col + (cx0 - half + a - gx0), (size_t)(b - a) * sizeof(uint16_t));
        for (int64_t i = b; i < np_; i++) pc[i] = col[gw - 1];
        const uint8_t *srow = smooth + y * bw + cx0;
        const uint8_t *mrow = mask + (y - cy0) * cw;
        uint8_t *brow = bin + y * bst + cx0;
        switch (block) {
#define TF_THR_CASE(N) case N: threshold_row(pc, srow, mrow, brow, cw, h, area, f, N); break;
            TF_FOR_ODD_TAPS(TF_THR_CASE)
#undef TF_THR_CASE
        }
    }
}

static inline int32_t find_root(int32_t *parent, int32_t a) {
    int32_t r = a;
    while (parent[r] != r) r = parent[r];
    while (parent[a] != r) { int32_t n = parent[a]; parent[a] = r; a = n; }
    return r;
}

static inline int32_t unite(int32_t *parent, int32_t a, int32_t b) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a < b) { parent[b] = a; return a; }
    parent[a] = b;
    return b;
}

/* insertion sort of the roots by their first block (a few hundred at most on a
   dome; a noisy frame's thousands still sort in well under a frame's time) */
static void sort_by_block(int32_t *order, int64_t n, const int64_t *acc) {
    for (int64_t i = 1; i < n; i++) {
        int32_t v = order[i];
        int64_t key = acc[4 * v + 3], j = i - 1;
        while (j >= 0 && acc[4 * order[j] + 3] > key) { order[j + 1] = order[j]; j--; }
        order[j + 1] = v;
    }
}

/* a run of set pixels in a row: [x0, x1), its provisional label */
typedef struct { int32_t x0, x1, lab; } tf_run;

static inline int64_t load8(const uint8_t *p) {
    uint64_t w;
    memcpy(&w, p, 8);
    return (int64_t)w;
}

/* Runs of set pixels, row by row: a run takes the label of the runs of the row
 * above that touch it (8-connected: they overlap or meet at a corner), uniting them;
 * a run that touches none starts a label. Each label keeps its area, sums of x and
 * y, and its first 2x2 block (the run's first pixel is its leftmost); the labels of
 * one blob are then folded into its root, the smallest. */
static int64_t label(int64_t *ctx) {
    const int64_t cy0 = ctx[TF_D_CY0], cx0 = ctx[TF_D_CX0], cy1 = ctx[TF_D_CY1], cx1 = ctx[TF_D_CX1];
    const uint8_t *bin = (const uint8_t *)(intptr_t)ctx[TF_D_BINARY];
    const int64_t bst = ctx[TF_D_BIN_STRIDE];
    int32_t *parent = (int32_t *)(intptr_t)ctx[TF_D_PARENT];
    int64_t *acc = (int64_t *)(intptr_t)ctx[TF_D_ACC];
    int32_t *order = (int32_t *)(intptr_t)ctx[TF_D_ORDER];
    const int64_t cap = ctx[TF_D_CAP], cw = cx1 - cx0, bwb = (ctx[TF_D_BW] + 1) / 2 + 1;
    /* two rows of runs in the labels scratch: at most cw / 2 + 1 runs a row */
    tf_run *prev = (tf_run *)(intptr_t)ctx[TF_D_LABELS];
    tf_run *cur = prev + (cw / 2 + 2);
    int64_t n_prev = 0;
    int32_t next = 1;
    for (int64_t y = cy0; y < cy1; y++) {
        const uint8_t *b = bin + y * bst;
        const int64_t yb = (y >> 1) * bwb;
        int64_t n_cur = 0, j = 0;
        int64_t x = cx0;
        for (;;) {
            while (x + 8 <= cx1 && load8(b + x) == 0) x += 8;
            while (x < cx1 && !b[x]) x++;
            if (x >= cx1) break;
            const int64_t x0 = x;
            while (x + 8 <= cx1 && load8(b + x) == -1) x += 8;
            while (x < cx1 && b[x]) x++;
            const int64_t x1 = x;                  /* the run is [x0, x1) */
            /* the runs above that touch it: they end at or after x0 - 1 and start at
               or before x1 (runs are in order, so j only moves right) */
            while (j < n_prev && prev[j].x1 < x0) j++;
            int32_t lb = 0;
            for (int64_t k = j; k < n_prev && prev[k].x0 <= x1; k++)
                lb = lb ? unite(parent, lb, prev[k].lab) : find_root(parent, prev[k].lab);
            if (!lb) {
                if (next >= cap) return -1;
                lb = next++;
                parent[lb] = lb;
                int64_t *a = acc + 4 * lb;
                a[0] = a[1] = a[2] = 0;
                a[3] = INT64_MAX;
            }
            cur[n_cur].x0 = (int32_t)x0;
            cur[n_cur].x1 = (int32_t)x1;
            cur[n_cur].lab = lb;
            n_cur++;
            const int64_t len = x1 - x0;
            int64_t *a = acc + 4 * lb;
            a[0] += len;
            a[1] += len * x0 + len * (len - 1) / 2;
            a[2] += len * y;
            const int64_t key = yb + (x0 >> 1);
            if (key < a[3]) a[3] = key;
        }
        tf_run *t = prev;
        prev = cur;
        cur = t;
        n_prev = n_cur;
    }
    /* fold each provisional label's sums into its root; the roots are the blobs */
    int64_t n = 0;
    for (int32_t i = 1; i < next; i++) {
        int32_t r = find_root(parent, i);
        if (r == i) { order[n++] = i; continue; }
        int64_t *a = acc + 4 * i, *ar = acc + 4 * r;
        ar[0] += a[0];
        ar[1] += a[1];
        ar[2] += a[2];
        if (a[3] < ar[3]) ar[3] = a[3];
    }
    sort_by_block(order, n, acc);
    return n;
}

/* what device/pi/vision/plausibility.py reads from the smoothed box: the integer sums
   cv2.meanStdDev takes over every STAT_STEP-th row, and the corner pixels' sum */
static void frame_sums(int64_t *ctx) {
    const uint8_t *smooth = (const uint8_t *)(intptr_t)ctx[TF_D_SMOOTH];
    const int64_t bh = ctx[TF_D_BH], bw = ctx[TF_D_BW], step = ctx[TF_D_STAT_STEP];
    uint64_t s = 0, sq = 0;
    int64_t n = 0;
    for (int64_t y = 0; step > 0 && y < bh; y += step) {
        const uint8_t *row = smooth + y * bw;
        uint32_t rs = 0, rq = 0;          /* a row: at most 65535 * 255^2 < 2^32 */
        for (int64_t x = 0; x < bw; x++) {
            rs += row[x];
            rq += (uint32_t)row[x] * row[x];
        }
        s += rs;
        sq += rq;
        n += bw;
    }
    ctx[TF_D_STAT_SUM] = (int64_t)s;
    ctx[TF_D_STAT_SQSUM] = (int64_t)sq;
    ctx[TF_D_STAT_N] = n;
    const int64_t *cr = (const int64_t *)(intptr_t)ctx[TF_D_CORNERS];
    int64_t cs = 0;
    for (int64_t i = 0; i < ctx[TF_D_N_CORNERS]; i++) {
        int64_t r = cr[2 * i], c = cr[2 * i + 1];
        if (r >= 0 && r < bh && c >= 0 && c < bw) cs += smooth[r * bw + c];
    }
    ctx[TF_D_CORNER_SUM] = cs;
}

int64_t tf_detect(int64_t *ctx) {
    const int64_t bh = ctx[TF_D_BH], bw = ctx[TF_D_BW], kn = ctx[TF_D_KN];
    const int64_t block = ctx[TF_D_BLOCK];
    const int64_t cy0 = ctx[TF_D_CY0], cx0 = ctx[TF_D_CX0], cy1 = ctx[TF_D_CY1], cx1 = ctx[TF_D_CX1];
    const int64_t gy0 = ctx[TF_D_GY0], gx0 = ctx[TF_D_GX0], gy1 = ctx[TF_D_GY1], gx1 = ctx[TF_D_GX1];
    if (bh < 1 || bw < 1 || kn < 0 || kn > 15 || (kn > 0 && kn % 2 == 0) || block < 3
        || block > 15 || block % 2 == 0 || ctx[TF_D_FLOOR_OFFSET] < 0
        || ctx[TF_D_GRAY_STRIDE] < bw || ctx[TF_D_BIN_STRIDE] < cx1
        || !(0 <= gy0 && gy0 <= cy0 && cy0 < cy1 && cy1 <= gy1 && gy1 <= bh)
        || !(0 <= gx0 && gx0 <= cx0 && cx0 < cx1 && cx1 <= gx1 && gx1 <= bw)
        || ctx[TF_D_CAP] < 2 || ctx[TF_D_OUT_CAP] < 0)
        return -1;
    if (bw > 65535) return -1;
    blur(ctx);
    frame_sums(ctx);
    threshold(ctx);
    int64_t n = label(ctx);
    if (n < 0) return -1;
    ctx[TF_D_N_BLOBS] = n;
    const int64_t *acc = (const int64_t *)(intptr_t)ctx[TF_D_ACC];
    const int32_t *order = (const int32_t *)(intptr_t)ctx[TF_D_ORDER];
    const int64_t lo = ctx[TF_D_MIN_AREA], hi = ctx[TF_D_MAX_AREA], cap = ctx[TF_D_OUT_CAP];
    const float ox = (float)ctx[TF_D_OX], oy = (float)ctx[TF_D_OY];
    float *xy = (float *)(intptr_t)ctx[TF_D_XY];
    int32_t *areas = (int32_t *)(intptr_t)ctx[TF_D_AREAS];
    int64_t k = 0;
    for (int64_t i = 0; i < n; i++) {
        const int64_t *a = acc + 4 * order[i];
        if (a[0] < lo || a[0] > hi) continue;
        if (k >= cap) return -1;
        double area = (double)a[0];
        xy[2 * k] = (float)((double)a[1] / area) + ox;
        xy[2 * k + 1] = (float)((double)a[2] / area) + oy;
        areas[k] = (int32_t)a[0];
        k++;
    }
    return k;
}

/* ---------------------------------------------------------------------------
 * The contact grid's update: the compiled twin of
 * device/pi/vision/features.py's ContactGrid.update with a reference set. The cell
 * sums of |binary - reference| are whole numbers; the float steps are numpy's, in
 * float32 and in numpy's order (the mean is numpy's pairwise sum), so the grid and
 * the contact flag are the same bits. Context slots TF_G_*; returns the contact flag
 * (0 or 1), or -1 for a context it refuses.
 */
enum {
    TF_G_BINARY = 0,    /* const uint8 *: h x w, row stride BIN_STRIDE */
    TF_G_BIN_STRIDE,
    TF_G_H, TF_G_W,
    TF_G_REF,           /* const uint8 *: h x w, contiguous */
    TF_G_N,             /* cells a side */
    TF_G_YS, TF_G_XS,   /* const int64 *: n + 1 cell edges each */
    TF_G_INV_AREA,      /* const float *: n x n, 1 / (255 * area) (0 for an empty cell) */
    TF_G_GRID,          /* float *: n x n, the grid (updated) */
    TF_G_CELLS,         /* float *: n x n scratch */
    TF_G_SUMS,          /* int64 *: n x n scratch */
    TF_G_GAMMA,         /* float32 bits of gamma */
    TF_G_THRESHOLD,     /* float32 bits of the contact threshold */
    TF_G_ACC,           /* uint16 *: w scratch */
    TF_G_N_SLOTS
};

int tf_grid_slots(void) { return TF_G_N_SLOTS; }

static float f32_of(int64_t bits) {
    uint32_t u = (uint32_t)bits;
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* numpy's pairwise sum (umath's FLOAT_/DOUBLE_pairwise_sum), in T's arithmetic:
   under 8 values one by one, up to 128 in eight running sums, larger halved (at a
   multiple of 8) */
#define TF_PAIRWISE_SUM(NAME, T)                                                      \
    static T NAME(const T *a, int64_t n) {                                            \
        if (n < 8) {                                                                  \
            T res = 0;                                                                \
            for (int64_t i = 0; i < n; i++) res += a[i];                              \
            return res;                                                               \
        }                                                                             \
        if (n <= 128) {                                                               \
            T r[8];                                                                   \
            int64_t i;                                                                \
            for (int j = 0; j < 8; j++) r[j] = a[j];                                  \
            for (i = 8; i < n - (n % 8); i += 8)                                      \
                for (int j = 0; j < 8; j++) r[j] += a[i + j];                         \
            T res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));\
            for (; i < n; i++) res += a[i];                                           \
            return res;                                                               \
        }                                                                             \
        int64_t n2 = n / 2;                                                           \
        n2 -= n2 % 8;                                                                 \
        return NAME(a, n2) + NAME(a + n2, n - n2);                                    \
    }

TF_PAIRWISE_SUM(pairwise_sum, float)
TF_PAIRWISE_SUM(pairwise_sum_d, double)


/* one row's |b - r| added to the 16-bit column sums acc (w columns) */
TF_VECTOR static void absdiff_add(const uint8_t *b, const uint8_t *r, uint16_t *acc, int64_t w) {
    for (int64_t x = 0; x < w; x++)
        acc[x] = (uint16_t)(acc[x] + (b[x] > r[x] ? b[x] - r[x] : r[x] - b[x]));
}

/* the column sums into the cells of cell row i, then cleared */
static void flush_cells(uint16_t *acc, const int64_t *xs, int64_t n, int64_t *sums, int64_t w) {
    for (int64_t j = 0; j < n; j++) {
        int64_t s = 0;
        for (int64_t x = xs[j]; x < xs[j + 1]; x++) s += acc[x];
        sums[j] += s;
    }
    memset(acc, 0, (size_t)w * sizeof *acc);
}

int64_t tf_grid(int64_t *ctx) {
    const int64_t h = ctx[TF_G_H], w = ctx[TF_G_W], n = ctx[TF_G_N], bst = ctx[TF_G_BIN_STRIDE];
    const int64_t *ys = (const int64_t *)(intptr_t)ctx[TF_G_YS];
    const int64_t *xs = (const int64_t *)(intptr_t)ctx[TF_G_XS];
    if (h < 0 || w < 0 || n < 1 || bst < w || ys[0] != 0 || xs[0] != 0 || ys[n] != h || xs[n] != w)
        return -1;
    for (int64_t i = 0; i < n; i++)
        if (ys[i + 1] < ys[i] || xs[i + 1] < xs[i]) return -1;
    const uint8_t *bin = (const uint8_t *)(intptr_t)ctx[TF_G_BINARY];
    const uint8_t *ref = (const uint8_t *)(intptr_t)ctx[TF_G_REF];
    const float *inv = (const float *)(intptr_t)ctx[TF_G_INV_AREA];
    float *grid = (float *)(intptr_t)ctx[TF_G_GRID];
    float *cells = (float *)(intptr_t)ctx[TF_G_CELLS];
    int64_t *sums = (int64_t *)(intptr_t)ctx[TF_G_SUMS];
    const float gamma = f32_of(ctx[TF_G_GAMMA]), thr = f32_of(ctx[TF_G_THRESHOLD]);
    const int64_t nn = n * n;
    uint16_t *acc = (uint16_t *)(intptr_t)ctx[TF_G_ACC];
    for (int64_t k = 0; k < nn; k++) sums[k] = 0;
    memset(acc, 0, (size_t)w * sizeof *acc);
    for (int64_t i = 0; i < n; i++) {
        /* a row's |b - r| summed down the cell row's columns (16 bits hold 257 rows
           of 255), then into its cells */
        int64_t rows = 0;
        for (int64_t y = ys[i]; y < ys[i + 1]; y++) {
            absdiff_add(bin + y * bst, ref + y * w, acc, w);
            if (++rows == 257) {
                flush_cells(acc, xs, n, sums + i * n, w);
                rows = 0;
            }
        }
        flush_cells(acc, xs, n, sums + i * n, w);
    }
    /* cells: the sum (a float64) times 1 / (255 area) (float32 widened), to float32 */
    for (int64_t k = 0; k < nn; k++) cells[k] = (float)((double)sums[k] * (double)inv[k]);
    const float glob = pairwise_sum(cells, nn) / (float)nn;
    float mx = -INFINITY;
    for (int64_t k = 0; k < nn; k++) {
        cells[k] -= glob;
        if (cells[k] > mx) mx = cells[k];
    }
    const int contact = (float)(mx - gamma) > thr;
    for (int64_t k = 0; k < nn; k++) {
        /* np.maximum's choice (the first when >=), so a -0.0 stays what numpy keeps */
        float g = cells[k] >= grid[k] ? cells[k] : grid[k];
        g -= gamma;
        grid[k] = g >= 0.f ? g : 0.f;
    }
    return contact;
}

/* The mean pin vector and the sum of magnitudes (features.py's shear_and_sum) over
 * the rows of vectors (m, 2 float32, taken as doubles) not lost and finite, each clipped to
 * +-clip: out[0..1] the mean (numpy's order: summed row by row, then divided),
 * out[2] the sum of hypot(x, y) (numpy's pairwise sum); mags (m,) double scratch.
 * Returns how many rows counted. */
int64_t tf_shear(const float *vec, const uint8_t *lost, int64_t m, double clip,
                 double *mags, double *out) {
    double sx = 0.0, sy = 0.0;
    int64_t k = 0;
    for (int64_t i = 0; i < m; i++) {
        double x = vec[2 * i], y = vec[2 * i + 1];
        if (lost[i]) continue;
        if (!isfinite(x) || !isfinite(y)) continue;
        x = x < -clip ? -clip : (x > clip ? clip : x);
        y = y < -clip ? -clip : (y > clip ? clip : y);
        sx += x;
        sy += y;
        mags[k++] = hypot(x, y);
    }
    if (k == 0) {
        out[0] = out[1] = out[2] = 0.0;
        return 0;
    }
    out[0] = sx / (double)k;
    out[1] = sy / (double)k;
    out[2] = pairwise_sum_d(mags, k);
    return k;
}
