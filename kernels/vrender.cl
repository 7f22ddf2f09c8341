/* Fused V-Render forward (full alpha blending, no stored selection): the speed baseline.

   One work-item per block of TILE pixels (a row of a tile) walks the tile list once for all of
   them (the block walk of common.h). Gaussians that some pixel blends are buffered BATCH at a time
   as (id, per-pixel weights) and then blended into each pixel's output row chunk by chunk, RV
   vectors of VW channels per chunk held in registers, in depth order (a pixel's zero weights are skipped, so each
   pixel sums exactly its own contributions). Feature rows have cstride elements (ROW_T: float,
   or half with -DHALF_ROWS), a multiple of VW * RV. A table larger than one device buffer is
   rendered a row part at a time (as in blend.cl): features hold the rows [row0, row0 + n_rows),
   other Gaussians are walked but not batched, and a later part (accumulate) adds to the image. */
#include "common.h"

#define BATCH 32

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

__kernel void vrender(__global const int2 *ranges,     /* [tiles] [start, end) in ids */
                      __global const int *ids,         /* depth-sorted Gaussian ids per tile */
                      __global const float8 *splats,   /* [N] from project */
                      __global const ROW_T *features,  /* [n_rows, cstride] */
                      const int row0, const int n_rows, const int cstride,
                      const int width, const int height, const int tiles_x,
                      __global const float *background,  /* [cstride], used when use_bg */
                      const int use_bg, const int accumulate,   /* add to the image (a later part) */
                      const int stream,                /* write the image's rows last with VSTREAM */
                      __global float *image,           /* [H*W, cstride] */
                      __global float *alpha,           /* [H*W] 1 - T */
                      __global float *depth) {         /* [H*W] expected depth */
    lanef px, py;
    lanei row;
    const int2 range = block_rays(get_global_id(0), 1, ranges, 0, 0, 0, width, height, tiles_x,
                                  &px, &py, &row);
    int batch_id[BATCH];
    lanef batch_w[BATCH];
    int count = 0, init = !accumulate;
    lanef depth_sum = (lanef)(0.f);
    VOLUME_WALK(range, px, py, row,
        depth_sum += w * s.s6;
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
    blend_batch(image, features, cstride, batch_id, batch_w, count, row, init, stream,
                use_bg ? T : (lanef)(0.f), background);
    const lanef d = select((lanef)(0.f), depth_sum / (1.f - T), T < 1.f);
    for (int l = 0; l < TILE; l++) {
        const int p = LANE_I(row, l);
        if (p >= 0) { alpha[p] = 1.f - LANE(T, l); depth[p] = LANE(d, l); }
    }
}
