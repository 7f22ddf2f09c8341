/* Fused V-Render forward (full alpha blending, no stored selection): the speed baseline.

   One work-item per pixel, pixels numbered tile-major so that neighbouring work-items walk the
   same tile list. The walk (alpha, transmittance) is done once per pixel; contributing
   Gaussians are buffered BATCH at a time as (id, weight) and then blended into the pixel's
   output row chunk by chunk, NV vectors of VW channels per chunk (explicit vector types are
   what PoCL turns into SIMD code). Feature rows have cstride floats, a multiple of VW * NV. */
#include "common.h"

#define BATCH 32

/* out[c] = (init ? 0 : out[c]) + sum_j w[j] * features[id[j], c] + bg_scale * background[c]. */
inline void blend_batch(__global float *out, __global const float *features, const int cstride,
                        const int *id, const float *w, const int count, const int init,
                        const float bg_scale, __global const float *background) {
    for (int c0 = 0; c0 < cstride; c0 += NV * VW) {
        vec_t acc[NV];
        for (int v = 0; v < NV; v++) acc[v] = init ? (vec_t)(0.f) : VLOAD(v, out + c0);
        for (int j = 0; j < count; j++) {
            __global const float *row = features + (size_t)id[j] * cstride + c0;
            for (int v = 0; v < NV; v++) acc[v] += w[j] * VLOAD(v, row);
        }
        if (bg_scale != 0.f)
            for (int v = 0; v < NV; v++) acc[v] += bg_scale * VLOAD(v, background + c0);
        for (int v = 0; v < NV; v++) VSTORE(acc[v], v, out + c0);
    }
}

__kernel void vrender(__global const int2 *ranges,     /* [tiles] [start, end) in ids */
                      __global const int *ids,         /* depth-sorted Gaussian ids per tile */
                      __global const float8 *splats,   /* [N] from project */
                      __global const float *features,  /* [N, cstride] */
                      const int cstride, const int width, const int height, const int tiles_x,
                      __global const float *background,  /* [cstride], used when use_bg */
                      const int use_bg,
                      __global float *image,           /* [H*W, cstride] */
                      __global float *alpha,           /* [H*W] 1 - T */
                      __global float *depth) {         /* [H*W] expected depth */
    const int gid = get_global_id(0);
    const int tile = gid / (TILE * TILE), in_tile = gid % (TILE * TILE);
    const int x = (tile % tiles_x) * TILE + in_tile % TILE;
    const int y = (tile / tiles_x) * TILE + in_tile / TILE;
    if (x >= width || y >= height) return;
    const float px = x + 0.5f, py = y + 0.5f;      /* pixel centre */
    const int pix = y * width + x;
    __global float *out = image + (size_t)pix * cstride;

    int batch_id[BATCH];
    float batch_w[BATCH];
    int count = 0, init = 1;
    float T = 1.f, depth_sum = 0.f;
    const int2 range = ranges[tile];
    for (int k = range.x; k < range.y; k++) {
        const int g = ids[k];
        const float8 s = splats[g];
        const float sig = splat_sigma(s.s2, s.s3, s.s4, s.s0 - px, s.s1 - py);
        if (sig < 0.f) continue;
        const float a = min(ALPHA_MAX, s.s5 * exp(-sig));
        if (a < ALPHA_MIN) continue;
        const float next_T = T * (1.f - a);
        if (next_T <= T_MIN) break;
        batch_id[count] = g;
        batch_w[count] = a * T;                    /* w_i = T_i alpha'_i */
        depth_sum += a * T * s.s6;
        T = next_T;
        if (++count == BATCH) {
            blend_batch(out, features, cstride, batch_id, batch_w, count, init, 0.f, background);
            count = 0;
            init = 0;
        }
    }
    blend_batch(out, features, cstride, batch_id, batch_w, count, init, use_bg ? T : 0.f, background);
    alpha[pix] = 1.f - T;
    depth[pix] = T < 1.f ? depth_sum / (1.f - T) : 0.f;
}
