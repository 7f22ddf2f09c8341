/* Selection kernels: which Gaussians a ray blends and with what weight (geometry only).

   One work-item per block of up to TILE rays sharing a tile list (the block walk of common.h).
   A ray writes (Gaussian id, weight) entries and, per ray, count (entries), t_walk (the
   transmittance T where its walk stopped), t_sel (the transmittance among the selected Gaussians
   before normalization; T for volume) and t_rem (the weight of the background). quantile/topk
   write their count[p] entries into row p of K slots at p * K (nothing past count, the
   1 / (1 - t_sel) normalization folded into the weights); volume writes at offsets[p] (CSR,
   after a counting pass and a scan). */
#include "common.h"

/* Divide the n weights T^Q_j alpha'_j by 1 - T^Q. 1 - T^Q equals their sum exactly (telescoping);
   the sum of positive terms is the better conditioned of the two in float (1 - T^Q cancels when
   alpha is small), and makes the normalized weights sum to 1 to rounding. */
static inline void normalize_weights(__global float *w, int n) {
    float sum = 0.f;
    for (int j = 0; j < n; j++) sum += w[j];
    for (int j = 0; j < n; j++) w[j] /= sum;
}

/* Built with -DBLEND_ROWS (and VW, NV), the K samplers' kernels also blend each ray of a block
   right after selecting it: image row p = blend.cl's blend of the ray's entries (the same
   bytes), read back while they are in cache, so the image is written while the next blocks are
   selected. BLEND_ARGS are their extra arguments (as blend's), BLEND_LANES(row) the blend. The
   features are the table's first n_rows rows: the whole table, or the first of its row parts
   (blend.cl adds the others). */
#ifdef BLEND_ROWS
#define BLEND_ARGS , __global const ROW_T *features, const int n_rows, const int cstride, \
    __global const float *background, const int use_bg, const int stream, __global float *image
#define BLEND_LANES(row) blend_lanes(row, K, out_ids, out_w, count, t_rem, features, n_rows, cstride, \
                                     background, use_bg, stream, image)

static inline void blend_lanes(lanei row, int K, __global const int *ids, __global const float *w,
                               __global const int *count, __global const float *t_rem,
                               __global const ROW_T *features, int n_rows, int cstride,
                               __global const float *background, int use_bg, int stream,
                               __global float *image) {
    for (int l = 0; l < TILE; l++) {
        const int p = LANE_I(row, l);
        if (p < 0) continue;
        const size_t first = (size_t)p * K;
        for (int c0 = 0; c0 < cstride; c0 += NV * VW)
            blend_entries(ids + first, w + first, clamp(count[p], 0, K), features, 0, n_rows, cstride, c0,
                          use_bg ? t_rem[p] : 0.f, background, use_bg, 0, stream, image + (size_t)p * cstride);
    }
}
#else
#define BLEND_ARGS
#define BLEND_LANES(row)
#endif

/* The outputs of the samplers that select at most K Gaussians per ray (rows of K slots). */
#define K_ROWS_ARGS const int K, __global int *out_ids, __global float *out_w, __global int *count, \
    __global float *t_walk, __global float *t_sel, __global float *t_rem BLEND_ARGS

/* The lanes cross of a Stratified-K walk take Gaussian g (alpha' a, transmittance after it
   T_test) as their next quantile Gaussian: entry (g, w^Q = T^Q alpha') in the lane's row, T^Q
   updated, and k advanced past every boundary T_test crossed (bound: the lane's next boundary,
   BOUNDARY(k): its (k+1)-th). Rare: at most K times per ray. */
#define TAKE_QUANTILES(cross, g, a, T_test, BOUNDARY) \
    FOR_LANES(cross, l) { \
        const size_t slot = (size_t)LANE_I(row, l) * K + LANE_I(n, l)++; \
        out_ids[slot] = g; \
        out_w[slot] = LANE(TQ, l) * LANE(a, l); \
        LANE(TQ, l) *= 1.f - LANE(a, l); \
        int kl = LANE_I(k, l) + 1; \
        while (LANE(T_test, l) < BOUNDARY(kl)) kl++; \
        LANE_I(k, l) = kl; \
        LANE(bound, l) = BOUNDARY(kl); \
    }

/* The boundaries of lane l: Stratified-K's, from the lane's statistics. */
#define STRATIFIED(k) stratified_boundary(k, K, LANE(mu, l), LANE(sigma, l), LANE(t_end, l))

/* Per lane of a block: normalize its n entries and write count, t_walk = T, t_sel = T^Q and
   t_rem (1 when nothing was selected). */
static inline void finish_rows(lanei row, lanei n, lanef T, lanef TQ, int K, __global float *out_w,
                               __global int *count, __global float *t_walk, __global float *t_sel,
                               __global float *t_rem) {
    for (int l = 0; l < TILE; l++) {
        const int p = LANE_I(row, l), nl = LANE_I(n, l);
        if (p < 0) continue;
        normalize_weights(out_w + (size_t)p * K, nl);
        count[p] = nl; t_walk[p] = LANE(T, l); t_sel[p] = LANE(TQ, l); t_rem[p] = nl ? 0.f : 1.f;
    }
}

/* Q-Render's uniform boundaries of the lanes: the (k+1)-th, 1 - (k+1)/(K+1) (quantile_boundary
   of each lane, the same float operations). */
static inline lanef quantile_bounds(lanei k, int K) {
    return 1.f - CAT(convert_float, TILE)(k + 1) / (float)(K + 1);
}

/* The lanes in cross move from boundary k past every boundary T_test crossed: to the first
   k' > k with T_test >= quantile_bounds(k'), searched from where T_test puts k' in real
   arithmetic, down and then up (the float boundaries decrease with k, so the result is that of
   a one-by-one search), all lanes at once. Other lanes keep k. */
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

/* Q-Render selection, Algorithm 1 of the paper, for each lane: a Gaussian whose T_test crosses
   the lane's next boundary 1 - (k+1)/(K+1) is a quantile Gaussian (w^Q = T^Q alpha', written
   to the lane's row); the walk stops once T_test < 1/(K+1). The crossing lanes' T^Q and k are
   updated as vectors (next_boundary), not lane by lane one boundary at a time. */
__kernel void select_quantile(BLOCK_ARGS, K_ROWS_ARGS) {
    BLOCK_SETUP
    const float stop = 1.f / (float)(K + 1);
    lanef T = (lanef)(1.f), TQ = (lanef)(1.f), bound = (lanef)(quantile_boundary(0, K));
    lanei k = (lanei)(0), n = (lanei)(0), done = row < 0;
    for (int i = range.x; i < range.y && !lanes_all(done); i++) {
        const int g = ids[i];
        const float8 s = splats[g];
        const lanef sig = block_sigma(s, px, py);
        if (!MAY_BLEND(s, sig)) continue;
        const lanef a = block_alpha(s, sig);
        const lanei use = (a > 0.f) & ~done;
        if (!lanes_any(use)) continue;
        const lanef T_test = T * (1.f - a);
        const lanei cross = use & (T_test < bound);
        if (lanes_any(cross)) {
            const lanef w = TQ * a;
            FOR_LANES(cross, l) {
                const size_t slot = (size_t)LANE_I(row, l) * K + LANE_I(n, l);
                out_ids[slot] = g;
                out_w[slot] = LANE(w, l);
            }
            n -= cross;                                   /* cross is -1 where set */
            TQ = select(TQ, TQ * (1.f - a), cross);
            k = next_boundary(k, T_test, cross, K);
            bound = quantile_bounds(k, K);
        }
        T = select(T, T_test, use);
        done |= use & (T_test < stop);
    }
    finish_rows(row, n, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
    BLEND_LANES(row);
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

/* Stratified-K selection (the paper's App. E): a first V-Render walk measures the mean and
   standard deviation of the transmittance along the ray (the T after each blended Gaussian); a
   second walk is Algorithm 1 with the K boundaries placed uniformly in probability under the
   normal fitted to them (denser where the transmittance values cluster) instead of uniformly in
   T. Weights and normalization as Q-Render. */
__kernel void select_stratified(BLOCK_ARGS, K_ROWS_ARGS) {
    BLOCK_SETUP
    lanef sum = (lanef)(0.f), sum_sq = (lanef)(0.f), used = (lanef)(0.f), t_end;
    {                                                 /* pass 1: the transmittance statistics */
        VOLUME_WALK(range, px, py, row,
            sum += select((lanef)(0.f), next_T, use);
            sum_sq += select((lanef)(0.f), next_T * next_T, use);
            used += select((lanef)(0.f), (lanef)(1.f), use))
        t_end = T;
    }
    const lanef mu = sum / fmax(used, 1.f);
    const lanef sigma = sqrt(fmax(sum_sq / fmax(used, 1.f) - mu * mu, 0.f));
    lanef TQ = (lanef)(1.f), bound;
    lanei k = (lanei)(0), n = (lanei)(0);
    for (int l = 0; l < TILE; l++)
        LANE(bound, l) = stratified_boundary(0, K, LANE(mu, l), LANE(sigma, l), LANE(t_end, l));
    VOLUME_WALK(range, px, py, row,                  /* pass 2: Algorithm 1, stratified boundaries */
        const lanei cross = use & (next_T < bound);
        if (lanes_any(cross)) TAKE_QUANTILES(cross, g, a, next_T, STRATIFIED))
    finish_rows(row, n, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
    BLEND_LANES(row);
}

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

/* top-K selection: the K largest V-Render weights w_i = T_i alpha'_i of each lane (bounded
   min-heap kept in the ray's output row, O(N log K)), then re-composited in depth order among
   the selected. */
__kernel void select_topk(BLOCK_ARGS, K_ROWS_ARGS) {
    BLOCK_SETUP
    int n[TILE];
    for (int l = 0; l < TILE; l++) n[l] = 0;
    VOLUME_WALK(range, px, py, row,
        for (int l = 0; l < TILE; l++)
            if (LANE_I(use, l)) {
                const size_t r = (size_t)LANE_I(row, l) * K;
                heap_offer(out_w + r, out_ids + r, &n[l], K, LANE(w, l), i_);
            })
    for (int l = 0; l < TILE; l++) {
        const int p = LANE_I(row, l), nl = n[l];
        if (p < 0) continue;
        __global int *hp = out_ids + (size_t)p * K;   /* heap: list positions ... */
        __global float *hw = out_w + (size_t)p * K;   /* ... and their V-Render weights */
        for (int j = nl / 2 - 1; j >= 0; j--) pos_sift_down(hp, j, nl);    /* heapsort positions */
        for (int end = nl - 1; end > 0; end--) {
            const int t = hp[0]; hp[0] = hp[end]; hp[end] = t;
            pos_sift_down(hp, 0, end);
        }
        float TQ = 1.f;                               /* re-composite in depth order */
        for (int j = 0; j < nl; j++) {
            const int g = ids[hp[j]];
            const float a = splat_alpha(splats[g], LANE(px, l), LANE(py, l));
            hp[j] = g;
            hw[j] = TQ * a;
            TQ *= 1.f - a;
        }
        normalize_weights(hw, nl);
        count[p] = nl; t_walk[p] = LANE(T, l); t_sel[p] = TQ; t_rem[p] = nl ? 0.f : 1.f;
    }
    BLEND_LANES(row);
}

/* V-Render selection, counting pass: entries per ray and the final T. */
__kernel void volume_count(BLOCK_ARGS, __global int *count, __global float *t_walk) {
    BLOCK_SETUP
    lanei n = (lanei)(0);
    VOLUME_WALK(range, px, py, row, n -= use)         /* use is -1 where a lane blends */
    for (int l = 0; l < TILE; l++) {
        const int p = LANE_I(row, l);
        if (p >= 0) { count[p] = LANE_I(n, l); t_walk[p] = LANE(T, l); }
    }
}

/* V-Render selection, fill pass: every Gaussian V-Render blends, w_i = T_i alpha'_i, at offsets[p]
   (exclusive scan of count). The background weight is the final T. */
__kernel void volume_fill(BLOCK_ARGS, __global const int *offsets, __global int *out_ids,
                          __global float *out_w, __global float *t_sel, __global float *t_rem) {
    BLOCK_SETUP
    int slot[TILE];
    for (int l = 0; l < TILE; l++) slot[l] = LANE_I(row, l) >= 0 ? offsets[LANE_I(row, l)] : 0;
    VOLUME_WALK(range, px, py, row,
        for (int l = 0; l < TILE; l++)
            if (LANE_I(use, l)) {
                out_ids[slot[l]] = g;
                out_w[slot[l]++] = LANE(w, l);
            })
    for (int l = 0; l < TILE; l++) {
        const int p = LANE_I(row, l);
        if (p >= 0) { t_sel[p] = LANE(T, l); t_rem[p] = LANE(T, l); }
    }
}
