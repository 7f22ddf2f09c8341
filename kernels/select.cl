/* Selection kernels: which Gaussians a ray blends and with what weight (geometry only).

   Two walks, one result: the block walk (CPU shapes: a work-item per block of up to TILE rays
   sharing a tile list, rays in vector lanes, walk.h) and the tile walk (GPU shapes: a
   work-group per tile, a work-item per ray, Gaussians staged in local memory; below). Per ray
   both make the same float operations, so they give the same bytes. A ray writes (Gaussian id,
   weight) entries and, per ray, count (entries), t_walk (the transmittance T where its walk
   stopped), t_sel (the transmittance among the selected Gaussians before normalization; T for
   volume) and t_rem (the weight of the background). quantile/topk/stratified write their
   count[p] entries into row p of K slots at p * K (nothing past count, the 1 / (1 - t_sel)
   normalization folded into the weights); volume writes at offsets[p] (CSR, after a counting
   pass and a scan). Every kernel walks the window [walk_from, walk_to) of the lists (common.h),
   each ray's walk state waiting in state_f / state_i [P] between windows (select.h). */
#include "select.h"
#include "rows.h"

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
        FOR_RAYS(row, l, p)
            RESUME_QUANTILE_WALK(p, LANE(T, l), LANE(TQ, l), LANE_I(k, l), LANE_I(n, l), LANE_I(done, l));
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
        FOR_RAYS(row, l, p) SAVE_QUANTILE_WALK(p, LANE(T, l), LANE(TQ, l), LANE_I(k, l), LANE_I(n, l), LANE_I(done, l));
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
            FOR_RAYS(row, l, p)
                RESUME_STATS_WALK(p, LANE(sum, l), LANE(sum_sq, l), LANE(used, l), LANE(T, l), LANE_I(done, l));
        VOLUME_WALK(from, to, px, py, row, T, done,
            sum += select((lanef)(0.f), next_T, use);
            sum_sq += select((lanef)(0.f), next_T * next_T, use);
            used += select((lanef)(0.f), (lanef)(1.f), use))
        if (pass == 1 && !last) {
            FOR_RAYS(row, l, p)
                SAVE_STATS_WALK(p, LANE(sum, l), LANE(sum_sq, l), LANE(used, l), LANE(T, l), LANE_I(done, l));
            return;
        }
        for (int l = 0; l < TILE; l++) {
            const float2 stats = transmittance_stats(LANE(sum, l), LANE(sum_sq, l), LANE(used, l));
            LANE(mu, l) = stats.x; LANE(sigma, l) = stats.y;
        }
        t_end = T;
        if (pass == 1) {                              /* pass 2 starts from these */
            FOR_RAYS(row, l, p) SAVE_BOUNDARIES(p, LANE(mu, l), LANE(sigma, l), LANE(t_end, l));
            return;
        }
        from = range.x;                               /* pass 0: the second walk follows */
    }
    lanef T = (lanef)(1.f), TQ = (lanef)(1.f), bound;
    lanei k = (lanei)(0), n = (lanei)(0), done = row < 0;
    if (pass == 2)
        FOR_RAYS(row, l, p) {
            RESUME_BOUNDARIES(p, LANE(mu, l), LANE(sigma, l), LANE(t_end, l));
            if (!first) RESUME_QUANTILE_WALK(p, LANE(T, l), LANE(TQ, l), LANE_I(k, l), LANE_I(n, l), LANE_I(done, l));
        }
    for (int l = 0; l < TILE; l++) LANE(bound, l) = STRATIFIED(LANE_I(k, l));
    VOLUME_WALK(from, to, px, py, row, T, done,       /* pass 2: Algorithm 1, stratified boundaries */
        const lanei cross = use & (next_T < bound);
        if (lanes_any(cross)) TAKE_QUANTILES(cross, g, a, next_T, STRATIFIED))
    if (!last) {
        FOR_RAYS(row, l, p) SAVE_QUANTILE_WALK(p, LANE(T, l), LANE(TQ, l), LANE_I(k, l), LANE_I(n, l), LANE_I(done, l));
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
        FOR_RAYS(row, l, p) RESUME_VOLUME_WALK(p, LANE(T, l), n[l], LANE_I(done, l));
    VOLUME_WALK(from, to, px, py, row, T, done,
        for (int l = 0; l < TILE; l++)
            if (LANE_I(use, l)) {
                const size_t r = (size_t)LANE_I(row, l) * K;
                heap_offer(out_w + r, out_ids + r, &n[l], K, LANE(w, l), i_);
            })
    if (!last) {
        FOR_RAYS(row, l, p) SAVE_VOLUME_WALK(p, LANE(T, l), n[l], LANE_I(done, l));
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
        FOR_RAYS(row, l, p) RESUME_VOLUME_WALK(p, LANE(T, l), LANE_I(n, l), LANE_I(done, l));
    VOLUME_WALK(from, to, px, py, row, T, done, n -= use)   /* use is -1 where a lane blends */
    FOR_RAYS(row, l, p) {
        if (last) { count[p] = LANE_I(n, l); t_walk[p] = LANE(T, l); }
        else SAVE_VOLUME_WALK(p, LANE(T, l), LANE_I(n, l), LANE_I(done, l));
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
        FOR_RAYS(row, l, p) RESUME_VOLUME_WALK(p, LANE(T, l), slot[l], LANE_I(done, l));
    VOLUME_WALK(from, to, px, py, row, T, done,
        for (int l = 0; l < TILE; l++)
            if (LANE_I(use, l)) {
                out_ids[slot[l]] = g;
                out_w[slot[l]++] = LANE(w, l);
            })
    FOR_RAYS(row, l, p) {
        if (last) { t_sel[p] = LANE(T, l); t_rem[p] = LANE(T, l); }
        else SAVE_VOLUME_WALK(p, LANE(T, l), slot[l], LANE_I(done, l));
    }
}

/* ==== the tile walk (GPU shapes: walk.h) ==== */

/* Q-Render's tile walk (select_quantile per ray). */
__kernel void tile_quantile(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS) {
    TILE_SETUP
    float T = 1.f, TQ = 1.f;
    int k = 0, n = 0, done = p < 0;
    if (!first && p >= 0) RESUME_QUANTILE_WALK(p, T, TQ, k, n, done);
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
    if (!last) { SAVE_QUANTILE_WALK(p, T, TQ, k, n, done ? -1 : 0); return; }
    finish_ray(p, n, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
}

/* Stratified-K's tile walk (select_stratified per ray; the same passes and state). */
__kernel void tile_stratified(BLOCK_ARGS, const int pass, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS) {
    TILE_SETUP
    float mu = 0.f, sigma = 0.f, t_end = 1.f;
    if (pass != 2) {
        float sum = 0.f, sum_sq = 0.f, used = 0.f, T = 1.f;
        int done = p < 0;
        if (!first && p >= 0) RESUME_STATS_WALK(p, sum, sum_sq, used, T, done);
        RAY_VOLUME_WALK(from, to, T, done,
            sum += next_T;
            const float sq = next_T * next_T;     /* not fused into the sum, as in the lanes */
            sum_sq += sq;
            used += 1.f)
        const float2 stats = transmittance_stats(sum, sum_sq, used);
        mu = stats.x; sigma = stats.y; t_end = T;
        if (pass == 1) {                              /* the whole group returns: pass is uniform */
            if (p >= 0 && !last) SAVE_STATS_WALK(p, sum, sum_sq, used, T, done ? -1 : 0);
            else if (p >= 0) SAVE_BOUNDARIES(p, mu, sigma, t_end);
            return;
        }
        from = range.x;                               /* pass 0: every work-item walks again */
    }
    float T = 1.f, TQ = 1.f;
    int k = 0, n = 0, done = p < 0;
    if (pass == 2 && p >= 0) {
        RESUME_BOUNDARIES(p, mu, sigma, t_end);
        if (!first) RESUME_QUANTILE_WALK(p, T, TQ, k, n, done);
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
    if (!last) { SAVE_QUANTILE_WALK(p, T, TQ, k, n, done ? -1 : 0); return; }
    finish_ray(p, n, T, TQ, K, out_w, count, t_walk, t_sel, t_rem);
}

/* top-K's tile walk (select_topk per ray; the same state). */
__kernel void tile_topk(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, K_ROWS_ARGS) {
    TILE_SETUP
    float T = 1.f;
    int n = 0, done = p < 0;
    if (!first && p >= 0) RESUME_VOLUME_WALK(p, T, n, done);
    RAY_VOLUME_WALK(from, to, T, done,
        heap_offer(out_w + (size_t)p * K, out_ids + (size_t)p * K, &n, K, w, i_))
    if (p < 0) return;
    if (!last) { SAVE_VOLUME_WALK(p, T, n, done ? -1 : 0); return; }
    topk_finish(p, n, T, px, py, K, ids, splats, out_ids, out_w, count, t_walk, t_sel, t_rem);
}

/* V-Render's counting pass as a tile walk (volume_count per ray). */
__kernel void tile_volume_count(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, __global int *count, __global float *t_walk) {
    TILE_SETUP
    float T = 1.f;
    int n = 0, done = p < 0;
    if (!first && p >= 0) RESUME_VOLUME_WALK(p, T, n, done);
    RAY_VOLUME_WALK(from, to, T, done, n++)
    if (p < 0) return;
    if (last) { count[p] = n; t_walk[p] = T; }
    else SAVE_VOLUME_WALK(p, T, n, done ? -1 : 0);
}

/* V-Render's fill pass as a tile walk (volume_fill per ray). */
__kernel void tile_volume_fill(BLOCK_ARGS, WINDOW_ARGS, STATE_ARGS, __global const int *offsets,
                               __global int *out_ids, __global float *out_w, __global float *t_sel,
                               __global float *t_rem) {
    TILE_SETUP
    float T = 1.f;
    int slot = p >= 0 ? offsets[p] : 0, done = p < 0;
    if (!first && p >= 0) RESUME_VOLUME_WALK(p, T, slot, done);
    RAY_VOLUME_WALK(from, to, T, done,
        out_ids[slot] = g;
        out_w[slot++] = w)
    if (p < 0) return;
    if (last) { t_sel[p] = T; t_rem[p] = T; }
    else SAVE_VOLUME_WALK(p, T, slot, done ? -1 : 0);
}
