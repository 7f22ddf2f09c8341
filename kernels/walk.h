/* The walks of a tile's depth-sorted Gaussian list, by select.cl and vrender.cl: the block walk
   (CPU shapes: a work-item per block of rays in vector lanes) and the tile walk (GPU shapes: a
   work-group per tile, a work-item per ray). Per ray both make the same float operations, so
   they give the same bytes. Both walk the window [walk_from, walk_to) of the lists (common.h). */
#ifndef QR_CL_WALK_H
#define QR_CL_WALK_H
#include "lanes.h"

/* ---- the block walk of select.cl and vrender.cl ----

   A work-item walks one tile's depth-sorted Gaussian list for a block of up to TILE rays at once:
   lane l of the TILE-wide vectors (lanef, lanei) is ray l of the block, and each Gaussian's alpha
   is evaluated for all lanes with explicit vector types (PoCL does not vectorize loops whose trip
   count differs between work-items; explicit vectors become SIMD code). Per lane the 3DGS rules
   are those of one ray walking alone, so the results equal the per-ray walk. Whole image
   (full != 0): block b is row b % TILE of tile b / TILE. Pixel subset (full == 0): the host
   groups the rays by tile; block b holds the rays order[blocks[b].x ..+ blocks[b].y) of tile
   blocks[b].z. */
#define BLOCK_ARGS __global const int2 *ranges, __global const int *ids, \
    __global const float8 *splats, __global const int2 *pixels, __global const int *order, \
    __global const int4 *blocks, const int full, const int width, const int height, const int tiles_x

/* The rays of block b: returns the tile's range [start, end) in ids; px, py get the lanes'
   pixel centres, row their output rows (-1 for lanes without a ray). */
static inline int2 block_rays(int b, int full, __global const int2 *ranges, __global const int2 *pixels,
                              __global const int *order, __global const int4 *blocks, int width,
                              int height, int tiles_x, lanef *px, lanef *py, lanei *row) {
    int tile;
    if (full) {
        tile = b / TILE;
        const int x0 = (tile % tiles_x) * TILE, y = (tile / tiles_x) * TILE + b % TILE;
        for (int l = 0; l < TILE; l++) {
            LANE(*px, l) = x0 + l + 0.5f;
            LANE(*py, l) = y + 0.5f;
            LANE_I(*row, l) = x0 + l < width && y < height ? y * width + x0 + l : -1;
        }
    } else {
        const int4 blk = blocks[b];
        tile = blk.z;
        for (int l = 0; l < TILE; l++) {
            const int ray = l < blk.y ? order[blk.x + l] : -1;
            const int2 xy = ray >= 0 ? pixels[ray] : (int2)(0);
            LANE(*px, l) = xy.x + 0.5f;
            LANE(*py, l) = xy.y + 0.5f;
            LANE_I(*row, l) = ray;
        }
    }
    return ranges[tile];
}

/* The Gaussian exponent sigma of splat s at the lanes' pixel centres (splat_sigma, as vectors). */
static inline lanef block_sigma(float8 s, lanef px, lanef py) {
    const lanef dx = s.SPLAT_MEAN_X - px, dy = s.SPLAT_MEAN_Y - py;
    return 0.5f * (s.SPLAT_CONIC_A * dx * dx + s.SPLAT_CONIC_C * dy * dy) + s.SPLAT_CONIC_B * dx * dy;
}

/* Declares px, py, row and range (the tile list) of the block of this work-item, in a kernel
   declared with BLOCK_ARGS. */
#define BLOCK_SETUP \
    lanef px, py; \
    lanei row; \
    const int2 range = block_rays(get_global_id(0), full, ranges, pixels, order, blocks, width, height, \
                                  tiles_x, &px, &py, &row);

/* splat_alpha of splat s from its exponents sig, as vectors (the same expression). */
static inline lanef block_alpha(float8 s, lanef sig) {
    const lanef a = fmin((lanef)(ALPHA_MAX), s.SPLAT_OPACITY * exp_neg_lanes(sig));
    return select(a, (lanef)(0.f), (sig < 0.f) | (a < ALPHA_MIN));
}

/* Whether splat s may be blended in some lane: an exponent at most sigma_max = ln(opacity /
   ALPHA_MIN) (from project.cl) plus a margin far above float rounding. When no lane is below it,
   every alpha would be skipped and the walk skips the exp. */
#define MAY_BLEND(s, sig) lanes_any((sig) <= (s).SPLAT_SIGMA_MAX + 1e-3f)

/* The V-Render walk of a block over the list positions [from, to): for each Gaussian g (splat s,
   list position i_) that some lane blends, in depth order, runs the statements ... with lanei use
   (-1 in the lanes that blend it), lanef a (alpha'), w (w_i = T_i alpha'_i where used, 0
   elsewhere) and next_T (T (1 - alpha')), then advances T. A lane stops (done) before the
   Gaussian that would bring its T to <= T_MIN. T (lanef) and done (lanei) are the walk's state,
   declared by the caller: (1, row < 0) at the start of a walk, or resumed (walk windows). */
#define VOLUME_WALK(from, to, px, py, row, T, done, ...) \
    for (int i_ = (from); i_ < (to) && !lanes_all(done); i_++) { \
        const int g = ids[i_]; \
        const float8 s = splats[g]; \
        const lanef sig_ = block_sigma(s, px, py); \
        if (!MAY_BLEND(s, sig_)) continue; \
        const lanef a = block_alpha(s, sig_); \
        lanei use = (a > 0.f) & ~done; \
        if (!lanes_any(use)) continue; \
        const lanef next_T = T * (1.f - a); \
        const lanei stop_ = use & (next_T <= T_MIN); \
        done |= stop_; \
        use &= ~stop_; \
        if (!lanes_any(use)) continue; \
        const lanef w = select((lanef)(0.f), a * T, use); \
        __VA_ARGS__; \
        T = select(T, next_T, use); \
    }

/* ---- the tile walk of select.cl and vrender.cl (GPU shapes) ----

   A work-group of GROUP_RAYS work-items (from the build), one ray each, walks one tile's list:
   its work-items load the next GROUP_RAYS Gaussians (id and splat) into local memory, one each,
   behind a barrier; then every ray walks them from there with the float operations of a lane of
   the block walk (so both walks give the same bytes), and the group stops once all its rays are
   done. Whole image (full != 0): group b holds GROUP_RAYS consecutive pixels (row-major) of tile
   b / TILE_PARTS, part b % TILE_PARTS. Pixel subset: group b holds the rays order[blocks[b].x ..+
   blocks[b].y) of tile blocks[b].z (at most GROUP_RAYS). */
#define TILE_PARTS (TILE * TILE / GROUP_RAYS)

/* The ray of this work-item: *p its output row (-1 for none) and (px, py) its pixel centre;
   returns its tile's range. */
static inline int2 tile_ray(int full, __global const int2 *ranges, __global const int2 *pixels,
                            __global const int *order, __global const int4 *blocks, int width, int height,
                            int tiles_x, float *px, float *py, int *p) {
    const int b = get_group_id(0), lid = get_local_id(0);
    int tile;
    if (full) {
        tile = b / TILE_PARTS;
        const int in_tile = (b % TILE_PARTS) * GROUP_RAYS + lid;
        const int x = (tile % tiles_x) * TILE + in_tile % TILE, y = (tile / tiles_x) * TILE + in_tile / TILE;
        *px = x + 0.5f;
        *py = y + 0.5f;
        *p = x < width && y < height ? y * width + x : -1;
    } else {
        const int4 blk = blocks[b];
        tile = blk.z;
        *p = lid < blk.y ? order[blk.x + lid] : -1;
        const int2 xy = *p >= 0 ? pixels[*p] : (int2)(0);
        *px = xy.x + 0.5f;
        *py = xy.y + 0.5f;
    }
    return ranges[tile];
}

/* Declares the local batch, px, py, p (tile_ray) and the window's from, to, first, last in a
   kernel declared with BLOCK_ARGS and WINDOW_ARGS; returns (the whole group: one tile) when the
   window has nothing to do. */
#define TILE_SETUP \
    __local int batch_ids_[GROUP_RAYS]; \
    __local float8 batch_splats_[GROUP_RAYS]; \
    __local int alive_; \
    float px, py; \
    int p; \
    const int2 range = tile_ray(full, ranges, pixels, order, blocks, width, height, tiles_x, &px, &py, &p); \
    int from, to, first, last; \
    if (!window_span(range, walk_from, walk_to, &from, &to, &first, &last)) return;

/* for (each Gaussian g, splat s, list position i_ in [from, to), in batches staged by the group)
   { ... } of a ray that is not done; the group leaves once every ray is done. Every work-item of
   the group runs the loop (its bounds and exit are the group's), so the barriers are uniform. */
#define TILE_WALK(from, to, done, ...) \
    for (int b0_ = (from); b0_ < (to); b0_ += GROUP_RAYS) { \
        const int lid_ = get_local_id(0); \
        barrier(CLK_LOCAL_MEM_FENCE); \
        if (lid_ == 0) alive_ = 0; \
        if (b0_ + lid_ < (to)) { \
            const int g_ = ids[b0_ + lid_]; \
            batch_ids_[lid_] = g_; \
            batch_splats_[lid_] = splats[g_]; \
        } \
        barrier(CLK_LOCAL_MEM_FENCE); \
        if (!(done)) alive_ = 1; \
        barrier(CLK_LOCAL_MEM_FENCE); \
        if (!alive_) break; \
        const int n_ = min(GROUP_RAYS, (to) - b0_); \
        for (int j_ = 0; j_ < n_ && !(done); j_++) { \
            const int i_ = b0_ + j_, g = batch_ids_[j_]; \
            const float8 s = batch_splats_[j_]; \
            __VA_ARGS__; \
        } \
    }

/* The alpha'_i of splat s at (px, py), 0 when skipped: a ray's block_alpha, whose Gaussians
   beyond sigma_max (MAY_BLEND) have alphas below ALPHA_MIN, skipped here without the exp. */
static inline float ray_alpha(float8 s, float px, float py) {
    const float sig = splat_sigma(s.SPLAT_CONIC_A, s.SPLAT_CONIC_B, s.SPLAT_CONIC_C, s.SPLAT_MEAN_X - px,
                                  s.SPLAT_MEAN_Y - py);
    return sig <= s.SPLAT_SIGMA_MAX + 1e-3f ? splat_alpha(s, px, py) : 0.f;
}

/* The V-Render walk of one ray over the batches of TILE_WALK: for each Gaussian it blends, runs
   ... with a (alpha'), w = T alpha' and next_T = T (1 - alpha'), then advances T; it is done
   before the Gaussian that would bring T to <= T_MIN (VOLUME_WALK per ray). */
#define RAY_VOLUME_WALK(from, to, T, done, ...) \
    TILE_WALK(from, to, done, \
        const float a = ray_alpha(s, px, py); \
        if (a > 0.f) { \
            const float next_T = T * (1.f - a); \
            if (next_T <= T_MIN) done = 1; \
            else { \
                const float w = a * T; \
                __VA_ARGS__; \
                T = next_T; \
            } \
        })

#endif
