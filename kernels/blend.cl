/* Shared blend of a Selection and its backward w.r.t. the features.

   forward:  image[p, :] = sum_j w[p, j] F[id[p, j], :] + t_rem[p] * background
   backward: dF[g, :] = sum over entries (p, j) with id[p, j] = g of w[p, j] dImage[p, :]

   Rows are cstride floats (a multiple of VW * NV); one work-item per (row, channel chunk of NV
   vectors of VW floats), explicit vector types as in vrender.cl. The backward gathers over the
   selection transposed by transpose.cl, so the sum order per Gaussian is fixed: the result is
   bitwise reproducible. */
#include "common.h"

/* Forward. Rays as in select.cl (full image tile-major, or a pixel subset); entries of row p
   are [offsets[p], offsets[p] + count[p]). */
__kernel void blend(__global const int *offsets, __global const int *count,
                    __global const int *sel_ids, __global const float *sel_w,
                    __global const float *features,        /* [N, cstride] */
                    const int cstride, const int full, const int n_rays, const int width, const int height,
                    const int tiles_x, __global const float *background,   /* [cstride] */
                    __global const float *t_rem, const int use_bg,
                    __global float *image) {               /* [P, cstride] */
    int p;
    if (!ray_row(get_global_id(0), full, n_rays, width, height, tiles_x, &p)) return;
    const int c0 = get_global_id(1) * NV * VW;
    vec_t acc[NV];
    for (int v = 0; v < NV; v++) acc[v] = (vec_t)(0.f);
    const int start = offsets[p], n = count[p];
    for (int j = start; j < start + n; j++) {
        const float w = sel_w[j];
        __global const float *row = features + (size_t)sel_ids[j] * cstride + c0;
        for (int v = 0; v < NV; v++) acc[v] += w * VLOAD(v, row);
    }
    __global float *out = image + (size_t)p * cstride + c0;
    const float tb = use_bg ? t_rem[p] : 0.f;
    for (int v = 0; v < NV; v++) {
        const vec_t bg = use_bg ? VLOAD(v, background + c0) : (vec_t)(0.f);
        VSTORE(acc[v] + tb * bg, v, out);
    }
}

/* Backward gather: dF[g, chunk] = sum over Gaussian g's transposed entries of w dImage[p, chunk],
   in the fixed order of the transpose. One work-item per (Gaussian, channel chunk), Gaussians
   taken in the order ``order`` (by their first ray, so neighbours read neighbouring rows). */
__kernel void blend_backward(const int n, __global const int *order,   /* [N] Gaussian of each work-item */
                             const int n_chunks, __global const int *cursor,
                             __global const int *t_ray, __global const float *t_w,
                             __global const float *dimage,   /* [P, cstride] */
                             const int cstride, __global float *dfeatures) {   /* [N, cstride] */
    if (get_global_id(0) >= n) return;
    const int g = order[get_global_id(0)];
    const int c0 = get_global_id(1) * NV * VW;
    const int start = g ? cursor[g * n_chunks - 1] : 0;
    const int end = cursor[(g + 1) * n_chunks - 1];
    vec_t acc[NV];
    for (int v = 0; v < NV; v++) acc[v] = (vec_t)(0.f);
    for (int j = start; j < end; j++) {
        const float w = t_w[j];
        __global const float *row = dimage + (size_t)t_ray[j] * cstride + c0;
        for (int v = 0; v < NV; v++) acc[v] += w * VLOAD(v, row);
    }
    __global float *out = dfeatures + (size_t)g * cstride + c0;
    for (int v = 0; v < NV; v++) VSTORE(acc[v], v, out);
}
