/* Selection kernels: which Gaussians a ray blends and with what weight (geometry only).

   Two walks, one result: the block walk (CPU shapes: a work-item per block of up to TILE rays
   sharing a tile list, rays in vector lanes, common.h) and the tile walk (GPU shapes: a
   work-group per tile, a work-item per ray, Gaussians staged in local memory; below). Per ray
   both make the same float operations, so they give the same bytes. A ray writes (Gaussian id,
   weight) entries and, per ray, count (entries), t_walk (the transmittance T where its walk
   stopped), t_sel (the transmittance among the selected Gaussians before normalization; T for
   volume) and t_rem (the weight of the background). quantile/topk/stratified write their
   count[p] entries into row p of K slots at p * K (nothing past count, the 1 / (1 - t_sel)
   normalization folded into the weights); volume writes at offsets[p] (CSR, after a counting
   pass and a scan). Every kernel walks the window [walk_from, walk_to) of the lists (common.h),
   each ray's state waiting in state_f / state_i [P] between windows. */
#include "common.h"

/* Divide the n weights T^Q_j alpha'_j by 1 - T^Q. 1 - T^Q equals their sum exactly (telescoping);
   the sum of positive terms is the better conditioned of the two in float (1 - T^Q cancels when
   alpha is small), and makes the normalized weights sum to 1 to rounding. */
static inline void normalize_weights(__global float *w, int n) {
    float sum = 0.f;
    for (int j = 0; j < n; j++) sum += w[j];
    for (int j = 0; j < n; j++) w[j] /= sum;
}

/* Built with -DBLEND_ROWS (and VW, NV), the block walk's K samplers also blend each ray of a block
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

/* The per-ray state of a walk between windows: state_f[p] and state_i[p]. */
#define STATE_ARGS __global float8 *state_f, __global int4 *state_i

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

/* ==== the block walk (CPU shapes) ==== */

/* Declares from, to, first, last of this work-item's window of its block's list (BLOCK_SETUP's
   range); returns when the window has nothing to do. */
#define BLOCK_WINDOW \
    int from, to, first, last; \
    if (!window_span(range, walk_from, walk_to, &from, &to, &first, &last)) return;

/* Lane l's ray, for the loops over a block's lanes that resume or leave state: p (skips lanes
   without a ray). */
#define FOR_RAYS(row, l, p) for (int l = 0, p; l < TILE; l++) if ((p = LANE_I(row, l)) >= 0)

/* The lanes in cross take Gaussian g (alpha' a, transmittance after it T_test) as their next
   quantile Gaussian: entry (g, w^Q = T^Q alpha') in the lane's row, T^Q updated, and k advanced
   past every boundary T_test crossed (bound: the lane's next boundary, BOUNDARY(k): its
   (k+1)-th). Rare: at most K times per ray. */
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

/* Q-Render selection, Algorithm 1 of the paper, for each lane: a Gaussian whose T_test crosses
   the lane's next boundary 1 - (k+1)/(K+1) is a quantile Gaussian (w^Q = T^Q alpha', written
   to the lane's row); the walk stops once T_test < 1/(K+1). The crossing lanes' T^Q and k are
   updated as vectors (next_boundary), not lane by lane one boundary at a time. State: T, T^Q;
   k, n, done. */
__kernel void select_quantile(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS BLEND_ARGS) {
    BLOCK_SETUP
    BLOCK_WINDOW
    const float stop = 1.f / (float)(K + 1);
    lanef T = (lanef)(1.f), TQ = (lanef)(1.f);
    lanei k = (lanei)(0), n = (lanei)(0), done = row < 0;
    if (!first)
        FOR_RAYS(row, l, p) {
            LANE(T, l) = state_f[p].s0; LANE(TQ, l) = state_f[p].s1;
            LANE_I(k, l) = state_i[p].x; LANE_I(n, l) = state_i[p].y; LANE_I(done, l) = state_i[p].z;
        }
    lanef bound = quantile_bounds(k, K);
    for (int i = from; i < to && !lanes_all(done); i++) {
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
    if (!last) {
        FOR_RAYS(row, l, p) {
            state_f[p].s01 = (float2)(LANE(T, l), LANE(TQ, l));
            state_i[p] = (int4)(LANE_I(k, l), LANE_I(n, l), LANE_I(done, l), 0);
        }
        return;
    }
    FOR_RAYS(row, l, p) finish_ray(p, LANE_I(n, l), LANE(T, l), LANE(TQ, l), K, out_w, count, t_walk, t_sel, t_rem);
    BLEND_LANES(row);
}

/* Stratified-K selection (the paper's App. E): a first V-Render walk measures the mean and standard
   deviation of the transmittance along the ray (the T after each blended Gaussian); a second walk
   is Algorithm 1 with the K boundaries placed uniformly in probability under the normal fitted to
   them (denser where the transmittance values cluster) instead of uniformly in T. Weights and
   normalization as Q-Render. pass 0 makes both walks; windows make pass 1 (state: the sums and
   T; done), whose last window leaves (mu, sigma, T_end) for pass 2 (state: those, T, T^Q; k, n,
   done). */
__kernel void select_stratified(BLOCK_ARGS, const int pass, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS BLEND_ARGS) {
    BLOCK_SETUP
    BLOCK_WINDOW
    lanef mu = (lanef)(0.f), sigma = (lanef)(0.f), t_end = (lanef)(1.f);   /* lanes without a ray keep these */
    if (pass != 2) {                                  /* pass 1: the transmittance statistics */
        lanef sum = (lanef)(0.f), sum_sq = (lanef)(0.f), used = (lanef)(0.f), T = (lanef)(1.f);
        lanei done = row < 0;
        if (!first)
            FOR_RAYS(row, l, p) {
                const float8 f = state_f[p];
                LANE(sum, l) = f.s0; LANE(sum_sq, l) = f.s1; LANE(used, l) = f.s2; LANE(T, l) = f.s3;
                LANE_I(done, l) = state_i[p].z;
            }
        VOLUME_WALK(from, to, px, py, row, T, done,
            sum += select((lanef)(0.f), next_T, use);
            sum_sq += select((lanef)(0.f), next_T * next_T, use);
            used += select((lanef)(0.f), (lanef)(1.f), use))
        if (pass == 1 && !last) {
            FOR_RAYS(row, l, p) {
                state_f[p].s0123 = (float4)(LANE(sum, l), LANE(sum_sq, l), LANE(used, l), LANE(T, l));
                state_i[p].z = LANE_I(done, l);
            }
            return;
        }
        for (int l = 0; l < TILE; l++) {
            const float2 stats = transmittance_stats(LANE(sum, l), LANE(sum_sq, l), LANE(used, l));
            LANE(mu, l) = stats.x; LANE(sigma, l) = stats.y;
        }
        t_end = T;
        if (pass == 1) {                              /* pass 2 starts from these */
            FOR_RAYS(row, l, p) state_f[p].s012 = (float3)(LANE(mu, l), LANE(sigma, l), LANE(t_end, l));
            return;
        }
        from = range.x;                               /* pass 0: the second walk follows */
    }
    lanef T = (lanef)(1.f), TQ = (lanef)(1.f), bound;
    lanei k = (lanei)(0), n = (lanei)(0), done = row < 0;
    if (pass == 2)
        FOR_RAYS(row, l, p) {
            const float8 f = state_f[p];
            LANE(mu, l) = f.s0; LANE(sigma, l) = f.s1; LANE(t_end, l) = f.s2;
            if (!first) {
                LANE(T, l) = f.s3; LANE(TQ, l) = f.s4;
                LANE_I(k, l) = state_i[p].x; LANE_I(n, l) = state_i[p].y; LANE_I(done, l) = state_i[p].z;
            }
        }
    for (int l = 0; l < TILE; l++) LANE(bound, l) = STRATIFIED(LANE_I(k, l));
    VOLUME_WALK(from, to, px, py, row, T, done,       /* pass 2: Algorithm 1, stratified boundaries */
        const lanei cross = use & (next_T < bound);
        if (lanes_any(cross)) TAKE_QUANTILES(cross, g, a, next_T, STRATIFIED))
    if (!last) {
        FOR_RAYS(row, l, p) {
            state_f[p].s34 = (float2)(LANE(T, l), LANE(TQ, l));
            state_i[p] = (int4)(LANE_I(k, l), LANE_I(n, l), LANE_I(done, l), 0);
        }
        return;
    }
    FOR_RAYS(row, l, p) finish_ray(p, LANE_I(n, l), LANE(T, l), LANE(TQ, l), K, out_w, count, t_walk, t_sel, t_rem);
    BLEND_LANES(row);
}

/* top-K selection: the K largest V-Render weights w_i = T_i alpha'_i of each lane (bounded
   min-heap kept in the ray's output row, O(N log K)), then re-composited in depth order among
   the selected. State: T; n (the heap's size), done. */
__kernel void select_topk(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS BLEND_ARGS) {
    BLOCK_SETUP
    BLOCK_WINDOW
    int n[TILE];
    lanef T = (lanef)(1.f);
    lanei done = row < 0;
    for (int l = 0; l < TILE; l++) n[l] = 0;
    if (!first)
        FOR_RAYS(row, l, p) { LANE(T, l) = state_f[p].s0; n[l] = state_i[p].y; LANE_I(done, l) = state_i[p].z; }
    VOLUME_WALK(from, to, px, py, row, T, done,
        for (int l = 0; l < TILE; l++)
            if (LANE_I(use, l)) {
                const size_t r = (size_t)LANE_I(row, l) * K;
                heap_offer(out_w + r, out_ids + r, &n[l], K, LANE(w, l), i_);
            })
    if (!last) {
        FOR_RAYS(row, l, p) { state_f[p].s0 = LANE(T, l); state_i[p] = (int4)(0, n[l], LANE_I(done, l), 0); }
        return;
    }
    FOR_RAYS(row, l, p)
        topk_finish(p, n[l], LANE(T, l), LANE(px, l), LANE(py, l), K, ids, splats, out_ids, out_w, count, t_walk,
                    t_sel, t_rem);
    BLEND_LANES(row);
}

/* V-Render selection, counting pass: entries per ray and the final T. State: T; n, done. */
__kernel void volume_count(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, __global int *count, __global float *t_walk) {
    BLOCK_SETUP
    BLOCK_WINDOW
    lanef T = (lanef)(1.f);
    lanei n = (lanei)(0), done = row < 0;
    if (!first)
        FOR_RAYS(row, l, p) { LANE(T, l) = state_f[p].s0; LANE_I(n, l) = state_i[p].y; LANE_I(done, l) = state_i[p].z; }
    VOLUME_WALK(from, to, px, py, row, T, done, n -= use)   /* use is -1 where a lane blends */
    FOR_RAYS(row, l, p) {
        if (last) { count[p] = LANE_I(n, l); t_walk[p] = LANE(T, l); }
        else { state_f[p].s0 = LANE(T, l); state_i[p] = (int4)(0, LANE_I(n, l), LANE_I(done, l), 0); }
    }
}

/* V-Render selection, fill pass: every Gaussian V-Render blends, w_i = T_i alpha'_i, at offsets[p]
   (exclusive scan of count). The background weight is the final T. State: T; the next slot,
   done. */
__kernel void volume_fill(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, __global const int *offsets, __global int *out_ids,
                          __global float *out_w, __global float *t_sel, __global float *t_rem) {
    BLOCK_SETUP
    BLOCK_WINDOW
    int slot[TILE];
    lanef T = (lanef)(1.f);
    lanei done = row < 0;
    for (int l = 0; l < TILE; l++) slot[l] = LANE_I(row, l) >= 0 ? offsets[LANE_I(row, l)] : 0;
    if (!first)
        FOR_RAYS(row, l, p) { LANE(T, l) = state_f[p].s0; slot[l] = state_i[p].y; LANE_I(done, l) = state_i[p].z; }
    VOLUME_WALK(from, to, px, py, row, T, done,
        for (int l = 0; l < TILE; l++)
            if (LANE_I(use, l)) {
                out_ids[slot[l]] = g;
                out_w[slot[l]++] = LANE(w, l);
            })
    FOR_RAYS(row, l, p) {
        if (last) { t_sel[p] = LANE(T, l); t_rem[p] = LANE(T, l); }
        else { state_f[p].s0 = LANE(T, l); state_i[p] = (int4)(0, slot[l], LANE_I(done, l), 0); }
    }
}

/* ==== the tile walk (GPU shapes: common.h) ==== */

/* Q-Render's tile walk (select_quantile per ray). */
__kernel void tile_quantile(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS) {
    TILE_SETUP
    float T = 1.f, TQ = 1.f;
    int k = 0, n = 0, done = p < 0;
    if (!first && p >= 0) { T = state_f[p].s0; TQ = state_f[p].s1; k = state_i[p].x; n = state_i[p].y; done = state_i[p].z; }
    float bound = quantile_boundary(k, K);
    const float stop = 1.f / (float)(K + 1);
    TILE_WALK(from, to, done,
        const float a = ray_alpha(s, px, py);
        if (a > 0.f) {
            const float T_test = T * (1.f - a);
            if (T_test < bound) {
                const size_t slot = (size_t)p * K + n++;
                out_ids[slot] = g;
                out_w[slot] = TQ * a;
                TQ = TQ * (1.f - a);
                k = next_quantile(k, T_test, K);
                bound = quantile_boundary(k, K);
            }
            T = T_test;
            done = T_test < stop;
        })
    if (p < 0) return;
    if (!last) { state_f[p].s01 = (float2)(T, TQ); state_i[p] = (int4)(k, n, done ? -1 : 0, 0); return; }
    finish_ray(p, n, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
}

/* Stratified-K's tile walk (select_stratified per ray; the same passes and state). */
__kernel void tile_stratified(BLOCK_ARGS, const int pass, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS) {
    TILE_SETUP
    float mu = 0.f, sigma = 0.f, t_end = 1.f;
    if (pass != 2) {
        float sum = 0.f, sum_sq = 0.f, used = 0.f, T = 1.f;
        int done = p < 0;
        if (!first && p >= 0) {
            const float8 f = state_f[p];
            sum = f.s0; sum_sq = f.s1; used = f.s2; T = f.s3; done = state_i[p].z;
        }
        RAY_VOLUME_WALK(from, to, T, done,
            sum += next_T;
            const float sq = next_T * next_T;     /* not fused into the sum, as in the lanes */
            sum_sq += sq;
            used += 1.f)
        const float2 stats = transmittance_stats(sum, sum_sq, used);
        mu = stats.x; sigma = stats.y; t_end = T;
        if (pass == 1) {                              /* the whole group returns: pass is uniform */
            if (p >= 0 && !last) {
                state_f[p].s0123 = (float4)(sum, sum_sq, used, T);
                state_i[p].z = done ? -1 : 0;
            } else if (p >= 0) {
                state_f[p].s012 = (float3)(mu, sigma, t_end);
            }
            return;
        }
        from = range.x;                               /* pass 0: every work-item walks again */
    }
    float T = 1.f, TQ = 1.f;
    int k = 0, n = 0, done = p < 0;
    if (pass == 2 && p >= 0) {
        const float8 f = state_f[p];
        mu = f.s0; sigma = f.s1; t_end = f.s2;
        if (!first) { T = f.s3; TQ = f.s4; k = state_i[p].x; n = state_i[p].y; done = state_i[p].z; }
    }
    float bound = stratified_boundary(k, K, mu, sigma, t_end);
    RAY_VOLUME_WALK(from, to, T, done,
        if (next_T < bound) {
            const size_t slot = (size_t)p * K + n++;
            out_ids[slot] = g;
            out_w[slot] = TQ * a;
            TQ *= 1.f - a;
            k++;
            while (next_T < stratified_boundary(k, K, mu, sigma, t_end)) k++;
            bound = stratified_boundary(k, K, mu, sigma, t_end);
        })
    if (p < 0) return;
    if (!last) { state_f[p].s34 = (float2)(T, TQ); state_i[p] = (int4)(k, n, done ? -1 : 0, 0); return; }
    finish_ray(p, n, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
}

/* top-K's tile walk (select_topk per ray; the same state). */
__kernel void tile_topk(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS) {
    TILE_SETUP
    float T = 1.f;
    int n = 0, done = p < 0;
    if (!first && p >= 0) { T = state_f[p].s0; n = state_i[p].y; done = state_i[p].z; }
    RAY_VOLUME_WALK(from, to, T, done,
        heap_offer(out_w + (size_t)p * K, out_ids + (size_t)p * K, &n, K, w, i_))
    if (p < 0) return;
    if (!last) { state_f[p].s0 = T; state_i[p] = (int4)(0, n, done ? -1 : 0, 0); return; }
    topk_finish(p, n, T, px, py, K, ids, splats, out_ids, out_w, count, t_walk, t_sel, t_rem);
}

/* V-Render's counting pass as a tile walk (volume_count per ray). */
__kernel void tile_volume_count(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, __global int *count, __global float *t_walk) {
    TILE_SETUP
    float T = 1.f;
    int n = 0, done = p < 0;
    if (!first && p >= 0) { T = state_f[p].s0; n = state_i[p].y; done = state_i[p].z; }
    RAY_VOLUME_WALK(from, to, T, done, n++)
    if (p < 0) return;
    if (last) { count[p] = n; t_walk[p] = T; }
    else { state_f[p].s0 = T; state_i[p] = (int4)(0, n, done ? -1 : 0, 0); }
}

/* V-Render's fill pass as a tile walk (volume_fill per ray). */
__kernel void tile_volume_fill(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, __global const int *offsets,
                               __global int *out_ids, __global float *out_w, __global float *t_sel,
                               __global float *t_rem) {
    TILE_SETUP
    float T = 1.f;
    int slot = p >= 0 ? offsets[p] : 0, done = p < 0;
    if (!first && p >= 0) { T = state_f[p].s0; slot = state_i[p].y; done = state_i[p].z; }
    RAY_VOLUME_WALK(from, to, T, done,
        out_ids[slot] = g;
        out_w[slot++] = w)
    if (p < 0) return;
    if (last) { t_sel[p] = T; t_rem[p] = T; }
    else { state_f[p].s0 = T; state_i[p] = (int4)(0, slot, done ? -1 : 0, 0); }
}
