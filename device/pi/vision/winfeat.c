/* Window features: the compiled twin of device/pi/models/winfeat.py (window_stats,
 * the specification). One call per frame computes the features of every model that
 * reads them, from the rolling window's quantised rows into the models' input buffers.
 *
 * The context is an int64 array: ctx[0] = number of models, then TF_W_SLOTS slots per
 * model (winfeat.py's CTX_SLOTS):
 *   T, M (pins), n_imu (6 or 0), K (neighbours per pin, 0: no roughness),
 *   vec (float32 T*M*2: the window's vectors, frame by frame),
 *   imu (float32 T*6, or 0), mask (float32 M of 0/1, or 0), nb (int32 M*K, or 0),
 *   use (float32 M, or 0 without K), out (float32 n_features), scratch (float32 T*M*2),
 *   floor (the roughness floor's float32 bits).
 * Every sum runs in float32 in index order, as the numpy specification's running
 * sums; the library is built with -ffp-contract=off, so a*a + b*b is not fused and
 * the numbers are numpy's to the bit. A value that is NaN reads as 0, one beyond
 * +-TF_W_BOUND (inf too) as the bound. Returns 0, or -1 for a context it refuses
 * (nothing written for that model and the ones after it).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define TF_W_SLOTS 12
#define TF_W_BOUND 2000.0f

int tf_winfeat_slots(void) { return TF_W_SLOTS; }

static inline float bounded(float a) {
    if (a != a) return 0.0f;
    if (a > TF_W_BOUND) return TF_W_BOUND;
    if (a < -TF_W_BOUND) return -TF_W_BOUND;
    return a;
}

static inline float norm2(float a, float b) { return sqrtf(a * a + b * b); }

static int one_model(const int64_t *s) {
    const int64_t T = s[0], M = s[1], n_imu = s[2], K = s[3];
    const float *vec = (const float *)(intptr_t)s[4];
    const float *imu = (const float *)(intptr_t)s[5];
    const float *mask = (const float *)(intptr_t)s[6];
    const int32_t *nb = (const int32_t *)(intptr_t)s[7];
    const float *use = (const float *)(intptr_t)s[8];
    float *out = (float *)(intptr_t)s[9];
    float *r = (float *)(intptr_t)s[10];
    float floor_px;
    uint32_t bits = (uint32_t)s[11];
    memcpy(&floor_px, &bits, sizeof floor_px);
    if (T < 1 || M < 1 || T > 100000 || M > 100000 || (n_imu != 0 && n_imu != 6) ||
        K < 0 || !vec || !out || (n_imu && !imu) || (K && (!nb || !use || !r)))
        return -1;
    const int64_t W = M * 2, TW = T * W;
    const float fM = (float)M, fK = (float)K;
    /* the window: v (masked), then the IMU rows */
    float *v = out;
    for (int64_t t = 0; t < T; t++)
        for (int64_t m = 0; m < M; m++)
            for (int64_t c = 0; c < 2; c++) {
                float a = bounded(vec[t * W + m * 2 + c]);
                v[t * W + m * 2 + c] = mask ? a * mask[m] : a;
            }
    float *o = out + TW;
    for (int64_t i = 0; i < n_imu * T; i++) *o++ = bounded(imu[i]);
    /* dv */
    for (int64_t i = 0; i < (T - 1) * W; i++) *o++ = v[i + W] - v[i];
    /* avg */
    float *avg = o;
    for (int64_t t = 0; t < T; t++) {
        float s0 = 0.0f, s1 = 0.0f;
        for (int64_t m = 0; m < M; m++) {
            s0 += v[t * W + m * 2];
            s1 += v[t * W + m * 2 + 1];
        }
        *o++ = s0 / fM;
        *o++ = s1 / fM;
    }
    /* davg, then its length */
    float *davg = o;
    for (int64_t i = 0; i < (T - 1) * 2; i++) *o++ = avg[i + 2] - avg[i];
    for (int64_t t = 0; t < T - 1; t++) *o++ = norm2(davg[t * 2], davg[t * 2 + 1]);
    /* mean |dv| */
    for (int64_t t = 0; t < T - 1; t++) {
        float s = 0.0f;
        for (int64_t m = 0; m < M; m++) {
            const float *a = v + t * W + m * 2;
            s += norm2(a[W] - a[0], a[W + 1] - a[1]);
        }
        *o++ = s / fM;
    }
    /* mag */
    float *mag = o;
    for (int64_t t = 0; t < T; t++) {
        float s = 0.0f;
        for (int64_t m = 0; m < M; m++) s += norm2(v[t * W + m * 2], v[t * W + m * 2 + 1]);
        *o++ = s / fM;
    }
    if (K == 0) return 0;
    /* roughness: r = v - mean of the K neighbours */
    for (int64_t m = 0; m < M; m++)
        for (int64_t k = 0; k < K; k++)
            if (nb[m * K + k] < 0 || nb[m * K + k] >= M) return -1;
    for (int64_t t = 0; t < T; t++)
        for (int64_t m = 0; m < M; m++)
            for (int64_t c = 0; c < 2; c++) {
                float s = 0.0f;
                for (int64_t k = 0; k < K; k++) s += v[t * W + (int64_t)nb[m * K + k] * 2 + c];
                r[t * W + m * 2 + c] = v[t * W + m * 2 + c] - s / fK;
            }
    float *rm = o, *rmd = o + T, *drm = o + 2 * T, *drmd = o + 3 * T - 1;
    for (int64_t t = 0; t < T; t++) {
        float s = 0.0f;
        for (int64_t m = 0; m < M; m++)
            s += norm2(r[t * W + m * 2], r[t * W + m * 2 + 1]) * use[m];
        rm[t] = s;
        rmd[t] = s / (mag[t] + floor_px);
    }
    for (int64_t t = 0; t < T - 1; t++) {
        float s = 0.0f;
        for (int64_t m = 0; m < M; m++) {
            const float *a = r + t * W + m * 2;
            s += norm2(a[W] - a[0], a[W + 1] - a[1]) * use[m];
        }
        drm[t] = s;
        drmd[t] = s / (mag[t + 1] + floor_px);
    }
    return 0;
}

int tf_winfeat(const int64_t *ctx) {
    if (!ctx || ctx[0] < 0 || ctx[0] > 64) return -1;
    for (int64_t i = 0; i < ctx[0]; i++)
        if (one_model(ctx + 1 + i * TF_W_SLOTS) != 0) return -1;
    return 0;
}
