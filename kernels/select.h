/* What the selection kernels of select.cl share, block walk and tile walk: a ray's outputs, its
   walk state between windows, Q-Render's and Stratified-K's boundaries and top-K's heap. */
#ifndef QR_CL_SELECT_H
#define QR_CL_SELECT_H
#include "walk.h"

/* ---- a ray's outputs ---- */

/* Divide the n weights T^Q_j alpha'_j by 1 - T^Q. 1 - T^Q equals their sum exactly (telescoping);
   the sum of positive terms is the better conditioned of the two in float (1 - T^Q cancels when
   alpha is small), and makes the normalized weights sum to 1 to rounding. */
static inline void normalize_weights(__global float *w, int n) {
    float sum = 0.f;
    for (int j = 0; j < n; j++) sum += w[j];
    for (int j = 0; j < n; j++) w[j] /= sum;
}

/* The outputs of the samplers that select at most K Gaussians per ray (rows of K slots). */
#define K_ROWS_ARGS const int K, __global int *out_ids, __global float *out_w, __global int *count, \
    __global float *t_walk, __global float *t_sel, __global float *t_rem

/* Ray p's outputs: its n entries normalized, count, t_walk = T, t_sel = T^Q and t_rem (1 when
   nothing was selected). */
static inline void finish_ray(int p, int n, float T, float TQ, int K, __global float *out_w,
                              __global int *count, __global float *t_walk, __global float *t_sel,
                              __global float *t_rem) {
    normalize_weights(out_w + (size_t)p * K, n);
    count[p] = n; t_walk[p] = T; t_sel[p] = TQ; t_rem[p] = n ? 0.f : 1.f;
}

/* ---- the walk state: a ray's walk between windows ----

   A ray's walk waits between windows (common.h) in its float8 state_f[p] and int4 state_i[p],
   each field in a slot of its own whatever the walk, named by the build (-D, from
   WalkStateLayout in qr_cl/runtime/constants.py): in state_f, WALK_T (T), WALK_TQ (T^Q),
   Stratified-K's boundaries WALK_MU, WALK_SIGMA, WALK_T_END and its first walk's sums WALK_SUM,
   WALK_SUM_SQ, WALK_USED; in state_i, WALK_K (the next boundary), WALK_N (the entries written;
   top-K: its heap's size; V-Render's fill: the next slot) and WALK_DONE (-1 once the ray
   stopped, else 0). Each walk saves and resumes its fields with the pair of macros below, for a
   lane (LANE(T, l), ...) or a ray (T, ...) alike; resuming assigns the arguments. */
#define STATE_ARGS __global float8 *state_f, __global int4 *state_i

/* V-Render's walk (volume, top-K): T; n, done. */
#define SAVE_VOLUME_WALK(p, T, n, done) \
    (state_f[p].WALK_T = (T), state_i[p].WALK_N = (n), state_i[p].WALK_DONE = (done))
#define RESUME_VOLUME_WALK(p, T, n, done) \
    (T = state_f[p].WALK_T, n = state_i[p].WALK_N, done = state_i[p].WALK_DONE)

/* Q-Render's walk (quantile, Stratified-K's second walk): T, T^Q; k, n, done. */
#define SAVE_QUANTILE_WALK(p, T, TQ, k, n, done) \
    (state_f[p].WALK_TQ = (TQ), state_i[p].WALK_K = (k), SAVE_VOLUME_WALK(p, T, n, done))
#define RESUME_QUANTILE_WALK(p, T, TQ, k, n, done) \
    (TQ = state_f[p].WALK_TQ, k = state_i[p].WALK_K, RESUME_VOLUME_WALK(p, T, n, done))

/* Stratified-K's first walk: the sums of T and T^2 and their count, T; done. */
#define SAVE_STATS_WALK(p, sum, sum_sq, used, T, done) \
    (state_f[p].WALK_SUM = (sum), state_f[p].WALK_SUM_SQ = (sum_sq), state_f[p].WALK_USED = (used), \
     state_f[p].WALK_T = (T), state_i[p].WALK_DONE = (done))
#define RESUME_STATS_WALK(p, sum, sum_sq, used, T, done) \
    (sum = state_f[p].WALK_SUM, sum_sq = state_f[p].WALK_SUM_SQ, used = state_f[p].WALK_USED, \
     T = state_f[p].WALK_T, done = state_i[p].WALK_DONE)

/* Stratified-K's boundaries, from its first walk to its second: mu, sigma, T_end. */
#define SAVE_BOUNDARIES(p, mu, sigma, t_end) \
    (state_f[p].WALK_MU = (mu), state_f[p].WALK_SIGMA = (sigma), state_f[p].WALK_T_END = (t_end))
#define RESUME_BOUNDARIES(p, mu, sigma, t_end) \
    (mu = state_f[p].WALK_MU, sigma = state_f[p].WALK_SIGMA, t_end = state_f[p].WALK_T_END)

/* ---- the boundaries of Q-Render and Stratified-K ---- */

/* The (k+1)-th of the K equal transmittance boundaries of Q-Render: 1 - (k+1)/(K+1). */
static inline float quantile_boundary(int k, int K) { return 1.f - (float)(k + 1) / (float)(K + 1); }

/* Q-Render's uniform boundaries: the (k+1)-th, 1 - (k+1)/(K+1), of the lanes (quantile_boundary
   of each lane, the same float operations). */
static inline lanef quantile_bounds(lanei k, int K) {
    return 1.f - CAT(convert_float, TILE)(k + 1) / (float)(K + 1);
}

/* The k after a ray whose transmittance fell to T_test took a quantile Gaussian at boundary k:
   the first k' > k with T_test >= quantile_boundary(k'). */
static inline int next_quantile(int k, float T_test, int K) {
    k++;
    while (T_test < quantile_boundary(k, K)) k++;
    return k;
}

/* The lanes in cross move from boundary k past every boundary T_test crossed (next_quantile of
   each lane), searched from where T_test puts k' in real arithmetic, down and then up (the float
   boundaries decrease with k, so the result is that of a one-by-one search), all lanes at once.
   Other lanes keep k. */
static inline lanei next_boundary(lanei k, lanef T_test, lanei cross, int K) {
    const lanei k1 = k + 1;
    /* saturating: well defined whatever the lanes outside cross hold */
    const lanei guess = CAT(CAT(convert_int, TILE), _sat)((1.f - T_test) * (float)(K + 1)) - 1;
    lanei kl = select(k1, max(k1, min((lanei)(K), guess)), cross);
    for (;;) {
        const lanei down = cross & (kl > k1) & ~(T_test < quantile_bounds(kl - 1, K));
        if (!lanes_any(down)) break;
        kl += down;                                   /* down is -1 where set */
    }
    for (;;) {
        const lanei up = cross & (T_test < quantile_bounds(kl, K));
        if (!lanes_any(up)) break;
        kl -= up;
    }
    return select(k, kl, cross);
}

/* Inverse of the standard normal CDF (Acklam's rational approximation; |Phi(x) - p| < 1e-4 p in
   the tails, < 1e-8 p in [0.02425, 0.97575]), clamped to [-8, 8]. */
static inline float normal_quantile(float p) {
    if (p <= 0.f) return -8.f;
    if (p >= 1.f) return 8.f;
    const float lo = 0.02425f;
    float x;
    if (p < lo || p > 1.f - lo) {
        const float q = sqrt(-2.f * log(p < lo ? p : 1.f - p));
        x = (((((-7.784894002430293e-03f * q - 3.223964580411365e-01f) * q - 2.400758277161838e+00f) * q
               - 2.549671010243101e+00f) * q + 4.374664141464968e+00f) * q + 2.938163982698783e+00f)
            / ((((7.784695709041462e-03f * q + 3.224671290700398e-01f) * q + 2.445134137142996e+00f) * q
                + 3.754408661907416e+00f) * q + 1.f);
        x = p < lo ? x : -x;
    } else {
        const float q = p - 0.5f, r = q * q;
        x = (((((-3.969683028665376e+01f * r + 2.209460984245205e+02f) * r - 2.759285104469687e+02f) * r
               + 1.383577518672690e+02f) * r - 3.066479806614716e+01f) * r + 2.506628277459239e+00f) * q
            / (((((-5.447609879822406e+01f * r + 1.615858368580409e+02f) * r - 1.556989798598866e+02f) * r
                 + 6.680131188771972e+01f) * r - 1.328068155288572e+01f) * r + 1.f);
    }
    return clamp(x, -8.f, 8.f);
}

/* Standard normal CDF. */
static inline float normal_cdf(float x) { return 0.5f * (1.f + erf(x * 0.70710678118654752f)); }

/* The (k+1)-th of Stratified-K's K transmittance boundaries of a ray whose V-Render walk ended at
   T_end with transmittance mean mu and deviation sigma: the quantile (k+1)/(K+1), counted from
   T = 1 down, of the normal N(mu, sigma^2) cut to [T_end, 1] (uniform in [T_end, 1] when sigma is
   0); -1 (never crossed) for k >= K. */
static inline float stratified_boundary(int k, int K, float mu, float sigma, float T_end) {
    if (k >= K) return -1.f;
    const float f = (float)(k + 1) / (float)(K + 1);
    if (!(sigma > 0.f)) return 1.f - f * (1.f - T_end);
    const float p_hi = normal_cdf((1.f - mu) / sigma), p_lo = normal_cdf((T_end - mu) / sigma);
    return mu + sigma * normal_quantile(p_hi - f * (p_hi - p_lo));
}

/* The statistics of a ray's first Stratified-K walk: the mean and deviation of the
   transmittance after each Gaussian it blended (sum, sum of squares, count). */
static inline float2 transmittance_stats(float sum, float sum_sq, float used) {
    const float mu = sum / fmax(used, 1.f);
    return (float2)(mu, sqrt(fmax(sum_sq / fmax(used, 1.f) - mu * mu, 0.f)));
}

/* ---- top-K's heap ---- */

/* Min-heap order of (weight, list position): the smaller weight, or on a tie the later
   position (so the K largest weights are kept, earlier depth first on ties). */
static inline int heap_less(float wa, int pa, float wb, int pb) { return wa < wb || (wa == wb && pa > pb); }

static inline void heap_sift_down(__global float *hw, __global int *hp, int i, int n) {
    for (;;) {
        int m = i;
        const int l = 2 * i + 1, r = l + 1;
        if (l < n && heap_less(hw[l], hp[l], hw[m], hp[m])) m = l;
        if (r < n && heap_less(hw[r], hp[r], hw[m], hp[m])) m = r;
        if (m == i) return;
        const float tw = hw[i]; hw[i] = hw[m]; hw[m] = tw;
        const int tp = hp[i]; hp[i] = hp[m]; hp[m] = tp;
        i = m;
    }
}

/* Keep (w, position i) among the K largest of the n entries of the min-heap (hw, hp). */
static inline void heap_offer(__global float *hw, __global int *hp, int *n, int K, float w, int i) {
    if (*n < K) {                                     /* push, sift up */
        int j = (*n)++;
        while (j > 0 && heap_less(w, i, hw[(j - 1) / 2], hp[(j - 1) / 2])) {
            hw[j] = hw[(j - 1) / 2]; hp[j] = hp[(j - 1) / 2];
            j = (j - 1) / 2;
        }
        hw[j] = w; hp[j] = i;
    } else if (w > hw[0]) {                           /* replace the smallest kept weight */
        hw[0] = w; hp[0] = i;
        heap_sift_down(hw, hp, 0, K);
    }
}

/* Max-heap sift on positions alone (heapsort of the kept positions into depth order). */
static inline void pos_sift_down(__global int *hp, int i, int n) {
    for (;;) {
        int m = i;
        const int l = 2 * i + 1, r = l + 1;
        if (l < n && hp[l] > hp[m]) m = l;
        if (r < n && hp[r] > hp[m]) m = r;
        if (m == i) return;
        const int t = hp[i]; hp[i] = hp[m]; hp[m] = t;
        i = m;
    }
}

/* top-K's outputs of ray p (pixel centre px, py) from its heap of nl kept (V-Render weight, list
   position) pairs in its row: the positions heap-sorted into depth order, then re-composited
   among the selected (alphas recomputed) and normalized as Q-Render. */
static inline void topk_finish(int p, int nl, float T, float px, float py, int K, __global const int *ids,
                               __global const float8 *splats, __global int *out_ids, __global float *out_w,
                               __global int *count, __global float *t_walk, __global float *t_sel,
                               __global float *t_rem) {
    __global int *hp = out_ids + (size_t)p * K;       /* heap: list positions ... */
    __global float *hw = out_w + (size_t)p * K;       /* ... and their V-Render weights */
    for (int j = nl / 2 - 1; j >= 0; j--) pos_sift_down(hp, j, nl);    /* heapsort positions */
    for (int end = nl - 1; end > 0; end--) {
        const int t = hp[0]; hp[0] = hp[end]; hp[end] = t;
        pos_sift_down(hp, 0, end);
    }
    float TQ = 1.f;
    for (int j = 0; j < nl; j++) {
        const int g = ids[hp[j]];
        const float a = splat_alpha(splats[g], px, py);
        hp[j] = g;
        hw[j] = TQ * a;
        TQ *= 1.f - a;
    }
    finish_ray(p, nl, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
}

#endif
