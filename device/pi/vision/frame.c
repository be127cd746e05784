/* The marker pipeline's usual frame in one call: tf_frame.
 *
 * device/pi/vision/pipeline.py's MarkerStream.process is the specification and the
 * fallback: it makes the same steps as separate calls with Python between them. Here
 * they are chained in C, each by the kernel the sequential path calls:
 *
 *   tf_detect (detect.c)  -> the plausibility statistics and check
 *   (plausibility.py's stats_from_sums and FramePlausibility.check: the same doubles,
 *   the same comparisons, its constants passed in the context)
 *   -> tf_track (match.c) -> tf_grid (detect.c) -> tf_shear (detect.c) and the
 *   contact flag (pipeline.py: the grid's flag, or the mean magnitude over the pins
 *   not lost above contact_px).
 *
 * One int64 context (TF_F_* slots) holds the addresses of the kernels' own contexts
 * (set up by device/pi/vision/core.py, tracking.py and features.py, so nothing is
 * set up twice) and of a double array (TF_FD_*: the check's constants, the
 * reference's statistics, and the doubles written). tf_frame returns the first stage
 * Python must take on the existing path (device/pi/vision/frame.py names them):
 *
 *   0  done: pins, plausible, tracked, grid, shear and contact written;
 *   1  tf_detect refused its context: nothing trusted, Python detects (OpenCV);
 *   2  implausible (TF_F_REASON says why): detection and the statistics done;
 *   3  the tracker's numpy path takes the frame (tf_track returned nonzero: a jump,
 *      no pin, a pin beyond +-1e6 px; or more pins than its scratch holds): only
 *      detection done, and the tracker's state is what tf_track leaves on those
 *      returns, which the numpy path overwrites (its prediction and work rows);
 *   4  tf_grid refused its context: detection and tracking done;
 *  -1  a context it refuses (a null address, a scratch too small): nothing run.
 *
 * Every stage it stops before is left exactly as the sequential path would find it.
 */
#include <math.h>
#include <stdint.h>

int64_t tf_detect(int64_t *ctx);
int64_t tf_track(int64_t *ci, const double *cd);
int64_t tf_grid(int64_t *ctx);
int64_t tf_shear(const float *vec, const uint8_t *lost, int64_t m, double clip,
                 double *mags, double *out);

/* the slots of the other kernels' contexts read or written here (each line names the
   enum member it mirrors; tests/device/pi/vision/test_frame.py checks the numbers) */
#define F_D_XY 32            /* detect.c's TF_D_XY */
#define F_D_N_BLOBS 35       /* detect.c's TF_D_N_BLOBS */
#define F_D_STAT_SUM 37      /* detect.c's TF_D_STAT_SUM */
#define F_D_STAT_SQSUM 38    /* detect.c's TF_D_STAT_SQSUM */
#define F_D_STAT_N 39        /* detect.c's TF_D_STAT_N */
#define F_D_N_CORNERS 41     /* detect.c's TF_D_N_CORNERS */
#define F_D_CORNER_SUM 42    /* detect.c's TF_D_CORNER_SUM */
#define F_T_CUR 0            /* match.c's TF_T_CUR */
#define F_T_N 1              /* match.c's TF_T_N */
#define F_T_M 4              /* match.c's TF_T_M */
#define F_T_LOST 17          /* match.c's TF_T_LOST */
#define F_T_VEC 18           /* match.c's TF_T_VEC */

enum {
    TF_F_DETECT = 0,    /* int64 *: tf_detect's context, its gray box set */
    TF_F_TRACK_I,       /* int64 *: tf_track's integers, all but CUR and N set */
    TF_F_TRACK_D,       /* const double *: tf_track's doubles */
    TF_F_TRACK_CAP,     /* pins the tracker's scratch (TF_T_C) holds */
    TF_F_GRID,          /* int64 *: tf_grid's context, the binary buffer set */
    TF_F_MAGS,          /* double *: MAGS_CAP scratch for tf_shear */
    TF_F_MAGS_CAP,      /* >= the reference's pins (TF_T_M) */
    TF_F_DBL,           /* double *: TF_FD_SLOTS */
    TF_F_N_PINS,        /* the profile's pin count (the blob test) */
    TF_F_HAS_REF,       /* 1: the check has the reference's statistics */
    TF_F_REF_BLOBS,     /* the reference's blobs */
    TF_F_PINS,          /* written: pins kept (tf_detect's return) */
    TF_F_REASON,        /* written: 0 plausible, 1 blobs, 2 brightness, 3 contrast, 4 dome */
    TF_F_TRACK_RC,      /* written: tf_track's return (-2: not run) */
    TF_F_GRID_CONTACT,  /* written: tf_grid's return */
    TF_F_N_VALID,       /* written: the pins not lost */
    TF_F_CONTACT,       /* written: the frame's contact flag */
    TF_F_SLOTS
};
enum {
    TF_FD_BLOB_FACTOR = 0, TF_FD_MEAN_SHIFT, TF_FD_STD_LOW, TF_FD_STD_HIGH, TF_FD_DOME_KEEP,
    TF_FD_DOME_MIN,     /* plausibility.py's constants */
    TF_FD_REF_MEAN, TF_FD_REF_STD, TF_FD_REF_CORNER,   /* the reference's statistics */
    TF_FD_CLIP,         /* features.py's MAX_VECTOR_PX */
    TF_FD_CONTACT_PX,   /* the profile's contact_px */
    TF_FD_MEAN, TF_FD_STD, TF_FD_CORNER,   /* written: this frame's statistics */
    TF_FD_SX, TF_FD_SY, TF_FD_MSUM,        /* written: tf_shear's mean vector and sum */
    TF_FD_SLOTS
};

int tf_frame_slots(void) { return TF_F_SLOTS * 100 + TF_FD_SLOTS; }

/* stats_from_sums then FramePlausibility.check: 0, or the reason's code */
static int64_t implausible(const int64_t *d, const int64_t *ctx, double *f) {
    const int64_t total = d[F_D_STAT_SUM], squares = d[F_D_STAT_SQSUM], n = d[F_D_STAT_N];
    const int64_t corner_sum = d[F_D_CORNER_SUM], n_corners = d[F_D_N_CORNERS];
    const int64_t blobs = d[F_D_N_BLOBS];
    double mean = 0.0, std = 0.0, corner = 0.0;
    if (n > 0 && n_corners > 0) {
        const double scale = 1.0 / (double)n;
        mean = (double)total * scale;
        double var = (double)squares * scale - mean * mean;
        std = sqrt(var < 0.0 ? 0.0 : var);        /* max(var, 0.0): -0.0 stays */
        corner = (double)corner_sum / (double)n_corners - mean;
    }
    f[TF_FD_MEAN] = mean;
    f[TF_FD_STD] = std;
    f[TF_FD_CORNER] = corner;
    const int has_ref = ctx[TF_F_HAS_REF] != 0;
    const int64_t ref_blobs = has_ref ? ctx[TF_F_REF_BLOBS] : 0, n_pins = ctx[TF_F_N_PINS];
    const int64_t most = n_pins > ref_blobs ? n_pins : ref_blobs;
    if ((double)blobs > f[TF_FD_BLOB_FACTOR] * (double)most) return 1;
    if (!has_ref) return 0;
    const double ref_std = f[TF_FD_REF_STD], ref_corner = f[TF_FD_REF_CORNER];
    if (fabs(mean - f[TF_FD_REF_MEAN]) > f[TF_FD_MEAN_SHIFT]) return 2;
    const double floor_std = ref_std < 1.0 ? 1.0 : ref_std;   /* max(ref_std, 1.0) */
    if (!(f[TF_FD_STD_LOW] * ref_std <= std && std <= f[TF_FD_STD_HIGH] * floor_std)) return 3;
    if (ref_corner >= f[TF_FD_DOME_MIN] && corner < f[TF_FD_DOME_KEEP] * ref_corner) return 4;
    return 0;
}

int64_t tf_frame(int64_t *ctx) {
    int64_t *d = (int64_t *)(intptr_t)ctx[TF_F_DETECT];
    int64_t *ci = (int64_t *)(intptr_t)ctx[TF_F_TRACK_I];
    const double *cd = (const double *)(intptr_t)ctx[TF_F_TRACK_D];
    int64_t *g = (int64_t *)(intptr_t)ctx[TF_F_GRID];
    double *mags = (double *)(intptr_t)ctx[TF_F_MAGS];
    double *f = (double *)(intptr_t)ctx[TF_F_DBL];
    if (!d || !ci || !cd || !g || !mags || !f || ctx[TF_F_TRACK_CAP] < 0
        || ci[F_T_M] < 0 || ci[F_T_M] > ctx[TF_F_MAGS_CAP])
        return -1;
    ctx[TF_F_TRACK_RC] = -2;
    const int64_t n = tf_detect(d);
    ctx[TF_F_PINS] = n;
    if (n < 0) return 1;
    const int64_t reason = implausible(d, ctx, f);
    ctx[TF_F_REASON] = reason;
    if (reason) return 2;
    if (n > ctx[TF_F_TRACK_CAP]) return 3;
    ci[F_T_CUR] = d[F_D_XY];
    ci[F_T_N] = n;
    const int64_t rc = tf_track(ci, cd);
    ctx[TF_F_TRACK_RC] = rc;
    if (rc != 0) return 3;
    const int64_t hit = tf_grid(g);
    ctx[TF_F_GRID_CONTACT] = hit;
    if (hit < 0) return 4;
    const int64_t m = ci[F_T_M];
    const uint8_t *lost = (const uint8_t *)(intptr_t)ci[F_T_LOST];
    tf_shear((const float *)(intptr_t)ci[F_T_VEC], lost, m, f[TF_FD_CLIP], mags, f + TF_FD_SX);
    int64_t n_valid = m;
    for (int64_t i = 0; i < m; i++) n_valid -= lost[i] != 0;
    ctx[TF_F_N_VALID] = n_valid;
    /* pipeline.py: mean_mag = msum / n_valid if n_valid else 0.0 */
    const double mean_mag = n_valid ? f[TF_FD_MSUM] / (double)n_valid : 0.0;
    ctx[TF_F_CONTACT] = hit != 0 || mean_mag > f[TF_FD_CONTACT_PX];
    return 0;
}
