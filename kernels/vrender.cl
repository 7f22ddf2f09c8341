/* Fused V-Render forward (full alpha blending, no stored selection): the speed baseline.

   Two walks, one result (as in select.cl). vrender (CPU shapes): a work-item per block of TILE
   pixels (a row of a tile) walks the tile list once for all of them (the block walk of walk.h);
   Gaussians that some pixel blends are buffered BATCH at a time as (id, per-pixel weights) and
   then blended into each pixel's output row chunk by chunk, RV vectors of VW channels per chunk
   held in registers, in depth order (a pixel's zero weights are skipped, so each pixel sums
   exactly its own contributions). tile_vrender (GPU shapes): a work-group per tile walks its
   list (the tile walk of walk.h), a work-item per pixel and group of NV * VW channels (the
   second dimension), which blends each Gaussian its pixel uses into its channels as it goes.
   Feature rows have cstride elements (ROW_T: float, or half with -DHALF_ROWS), a multiple of
   VW * RV. A table larger than one device buffer is rendered a row part at a time (as in
   blend.cl): features hold the rows [row0, row0 + n_rows), other Gaussians are walked but not
   blended, and a later part (accumulate) adds to the image. Both walk the window [walk_from,
   walk_to) of the lists (common.h); a ray's (T, depth sum, done) waits in state_in / state_out
   (two buffers, swapped between windows: a tile_vrender group reads the state all groups of its
   pixels wrote before). The image rows hold the sums between windows. */
#include "walk.h"
#include "rows.h"

#define BATCH 32

/* The arguments of both kernels: the plan (ranges [tiles] of [start, end) into ids, the
   depth-sorted Gaussian ids per tile, splats [N] from project), features [n_rows, cstride] (the
   rows from row0), background [cstride] (used when use_bg), accumulate (add to the image: a later
   part), stream (write the image's rows last with VSTREAM), the outputs image [H*W, cstride],
   alpha [H*W] (1 - T) and depth [H*W] (expected depth), and the window with its state. */
#define VRENDER_ARGS __global const int2 *ranges, __global const int *ids, __global const float8 *splats, \
    __global const ROW_T *features, const int row0, const int n_rows, const int cstride, const int width, \
    const int height, const int tiles_x, __global const float *background, const int use_bg, \
    const int accumulate, const int stream, __global float *image, __global float *alpha, \
    __global float *depth, WINDOW_ARGS, __global const float4 *state_in, __global float4 *state_out

/* For each lane l with row[l] >= 0: out_l[c] = (init ? 0 : out_l[c]) + sum_j w[j]_l features[id[j], c]
   + bg_scale_l * background[c], out_l the lane's row of image; written with VSTREAM when stream
   (the rows' final write, of a large image). */
static inline void blend_batch(__global float *image, __global const ROW_T *features, const int cstride,
                               const int *id, const lanef *w, const int count, const lanei row,
                               const int init, const int stream, const lanef bg_scale,
                               __global const float *background) {
    for (int l = 0; l < TILE; l++) {
        if (LANE_I(row, l) < 0) continue;
        __global float *out = image + (size_t)LANE_I(row, l) * cstride;
        const float bg = LANE(bg_scale, l);
        for (int c0 = 0; c0 < cstride; c0 += RV * VW) {
            vec_t acc[RV];
            #pragma unroll
            for (int v = 0; v < RV; v++) acc[v] = init ? (vec_t)(0.f) : VLOAD(v, out + c0);
            for (int j = 0; j < count; j++) {
                const float wj = LANE(w[j], l);
                if (wj == 0.f) continue;
                __global const ROW_T *f = features + (size_t)id[j] * cstride + c0;
                #pragma unroll
                for (int v = 0; v < RV; v++) acc[v] += wj * RLOAD(v, f);
            }
            if (bg != 0.f) {
                #pragma unroll
                for (int v = 0; v < RV; v++) acc[v] += bg * VLOAD(v, background + c0);
            }
            #pragma unroll
            for (int v = 0; v < RV; v++) {
                if (stream) VSTREAM(acc[v], v, out + c0);
                else VSTORE(acc[v], v, out + c0);
            }
        }
    }
}

/* A ray's walk state between walk windows, its fields in the slots the VSTATE_* names give
   (qr_cl.runtime.VolumeStateLayout); the unused slot is 0. */
static inline float4 volume_state(float T, float depth_sum, int done) {
    float4 st = (float4)(0.f);
    st.VSTATE_T = T;
    st.VSTATE_DEPTH_SUM = depth_sum;
    st.VSTATE_DONE = done ? 1.f : 0.f;
    return st;
}

/* alpha[p] = 1 - T and depth[p] = the expected depth (0 where nothing was hit) of a finished ray. */
static inline void finish_pixel(int p, float T, float depth_sum, __global float *alpha, __global float *depth) {
    alpha[p] = 1.f - T;
    depth[p] = T < 1.f ? depth_sum / (1.f - T) : 0.f;
}

__kernel void vrender(VRENDER_ARGS) {
    lanef px, py;
    lanei row;
    const int2 range = block_rays(get_global_id(0), 1, ranges, 0, 0, 0, width, height, tiles_x,
                                  &px, &py, &row);
    int from, to, first, last;
    if (!window_span(range, walk_from, walk_to, &from, &to, &first, &last)) return;
    int batch_id[BATCH];
    lanef batch_w[BATCH];
    int count = 0, init = first && !accumulate;
    lanef T = (lanef)(1.f), depth_sum = (lanef)(0.f);
    lanei done = row < 0;
    if (!first)
        for (int l = 0; l < TILE; l++)
            if (LANE_I(row, l) >= 0) {
                const float4 st = state_in[LANE_I(row, l)];
                LANE(T, l) = st.VSTATE_T; LANE(depth_sum, l) = st.VSTATE_DEPTH_SUM;
                LANE_I(done, l) = st.VSTATE_DONE != 0.f ? -1 : 0;
            }
    VOLUME_WALK(from, to, px, py, row, T, done,
        depth_sum += w * s.SPLAT_DEPTH;
        if ((uint)g - (uint)row0 < (uint)n_rows) {    /* a Gaussian of this row part */
            batch_id[count] = g - row0;
            batch_w[count] = w;                        /* w_i = T_i alpha'_i */
            if (++count == BATCH) {
                blend_batch(image, features, cstride, batch_id, batch_w, count, row, init, 0, (lanef)(0.f),
                            background);
                count = 0;
                init = 0;
            }
        })
    if (!last) {
        blend_batch(image, features, cstride, batch_id, batch_w, count, row, init, 0, (lanef)(0.f), background);
        for (int l = 0; l < TILE; l++)
            if (LANE_I(row, l) >= 0)
                state_out[LANE_I(row, l)] = volume_state(LANE(T, l), LANE(depth_sum, l), LANE_I(done, l));
        return;
    }
    blend_batch(image, features, cstride, batch_id, batch_w, count, row, init, stream,
                use_bg ? T : (lanef)(0.f), background);
    for (int l = 0; l < TILE; l++)
        if (LANE_I(row, l) >= 0) finish_pixel(LANE_I(row, l), LANE(T, l), LANE(depth_sum, l), alpha, depth);
}

/* The tile walk of vrender: work-item (ray, channel group c) of tile groups (a whole image). */
__kernel void tile_vrender(VRENDER_ARGS) {
    const int full = 1;
    __global const int2 *pixels = 0;
    __global const int *order = 0;
    __global const int4 *blocks = 0;
    TILE_SETUP
    const int c0 = get_global_id(1) * NV * VW, writes_pixel = get_global_id(1) == 0;
    float T = 1.f, depth_sum = 0.f;
    int done = p < 0;
    if (!first && p >= 0) {
        const float4 st = state_in[p];
        T = st.VSTATE_T; depth_sum = st.VSTATE_DEPTH_SUM; done = st.VSTATE_DONE != 0.f;
    }
    __global float *out = image + (size_t)max(p, 0) * cstride + c0;
    vec_t acc[NV];
    #pragma unroll
    for (int v = 0; v < NV; v++) acc[v] = p >= 0 && !(first && !accumulate) ? VLOAD(v, out) : (vec_t)(0.f);
    RAY_VOLUME_WALK(from, to, T, done,
        depth_sum += w * s.SPLAT_DEPTH;
        if ((uint)g - (uint)row0 < (uint)n_rows) {
            __global const ROW_T *f = features + (size_t)(g - row0) * cstride + c0;
            for (int v = 0; v < NV; v++) acc[v] += w * RLOAD(v, f);
        })
    if (p < 0) return;
    if (!last) {
        #pragma unroll
        for (int v = 0; v < NV; v++) VSTORE(acc[v], v, out);
        if (writes_pixel) state_out[p] = volume_state(T, depth_sum, done);
        return;
    }
    const float bg = use_bg ? T : 0.f;
    if (bg != 0.f) {
        #pragma unroll
        for (int v = 0; v < NV; v++) acc[v] += bg * VLOAD(v, background + c0);
    }
    #pragma unroll
    for (int v = 0; v < NV; v++) {
        if (stream) VSTREAM(acc[v], v, out);
        else VSTORE(acc[v], v, out);
    }
    if (writes_pixel) finish_pixel(p, T, depth_sum, alpha, depth);
}
