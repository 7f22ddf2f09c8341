/* Fused V-Render forward (full alpha blending, no stored selection): the speed baseline.

   One work-item per (pixel, channel chunk). Pixels are numbered tile-major so that neighbouring
   work-items walk the same tile list. Each work-item re-walks its pixel's depth-sorted list and
   accumulates NV vectors of VW channels: features are rows of cstride floats (a multiple of
   VW * NV), and explicit vector types are what PoCL turns into SIMD code. */
#include "common.h"

#if VW == 1
typedef float vec_t;
#define VLOAD(i, p) ((p)[i])
#define VSTORE(v, i, p) ((p)[i] = (v))
#else
#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)
typedef CAT(float, VW) vec_t;
#define VLOAD(i, p) CAT(vload, VW)(i, p)
#define VSTORE(v, i, p) CAT(vstore, VW)(v, i, p)
#endif

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
    const int c0 = get_global_id(1) * NV * VW;     /* first channel of this chunk */
    const float px = x + 0.5f, py = y + 0.5f;      /* pixel centre */

    vec_t acc[NV];
    for (int v = 0; v < NV; v++) acc[v] = (vec_t)(0.f);
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
        const float w = a * T;                     /* w_i = T_i alpha'_i */
        __global const float *row = features + (size_t)g * cstride + c0;
        for (int v = 0; v < NV; v++) acc[v] += w * VLOAD(v, row);
        depth_sum += w * s.s6;
        T = next_T;
    }
    const int pix = y * width + x;
    __global float *out = image + (size_t)pix * cstride + c0;
    for (int v = 0; v < NV; v++) {
        vec_t bg = use_bg ? VLOAD(v, background + c0) : (vec_t)(0.f);
        VSTORE(acc[v] + T * bg, v, out);
    }
    if (c0 == 0) {
        alpha[pix] = 1.f - T;
        depth[pix] = T < 1.f ? depth_sum / (1.f - T) : 0.f;
    }
}
