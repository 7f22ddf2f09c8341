/* Shared blend of a Selection and its backward w.r.t. the features.

   forward:  image[p, :] = sum_j w[p, j] F[id[p, j], :] + t_rem[p] * background
   backward: dF[g, :] = sum over entries (p, j) with id[p, j] = g of w[p, j] dImage[p, :]

   Rows are cstride floats (a multiple of VW * NV), read and written with explicit vector types as
   in vrender.cl; built with -DHALF_ROWS, the kernels that read the feature table read half rows
   (ROW_T) and the feature backward is left out. A table larger than one device buffer is passed
   in row parts: features (and dF) hold the rows [row0, row0 + n_rows) of the table, entries of
   other Gaussians are skipped, and the image is the sum of the parts' blends (it is linear in
   the features), the background added by one part. The forward runs one work-item per (row, channel
   chunk of NV vectors of VW floats). The backward sums each Gaussian's entries in one fixed
   order, by ray then by position in the ray, without atomics, so its result is bitwise
   reproducible; two kernels give the same bytes: a gather over the selection transposed by
   transpose.cl (many short work-items: GPU shapes, and CPU ones for pixel subsets transposed
   ahead) and a scatter by a few work-items that own ranges of Gaussians (CPU shapes otherwise:
   no transpose, every dImage row read whole). GPU shapes run blend_group and
   blend_backward_group: a work-group of rows x the vectors of their rows (neighbouring work-items
   read neighbouring floats of one row), the rows' entries staged in local memory (group_blend).
   The kernels that walk a list that can grow with the scene (a Gaussian's entries, a ray's
   V-Render entries) take a window [walk_from, walk_to) of it (common.h); the sums wait in their
   outputs between windows. */
#include "common.h"
#include "rows.h"

/* Entries of each row a work-group stages in local memory at a time (GPU shapes). */
#define GROUP_ENTRIES 16

/* out's vector c (VW floats) = (accumulate ? out's : 0) + sum over the row's n entries (ids[start
   + j], w[start + j]) of w features[id - row0, vector c] (+ tb * background's vector c when use_bg),
   summed in entry order (the sums of blend_entries); ids outside [row0, row0 + n_rows) skipped.
   Every work-item of the group calls it (it has barriers); the group's rows' entries are staged
   in local memory GROUP_ENTRIES at a time, until the longest row's are done. active: the
   work-item has a row and vector (else it only helps to stage). */
static inline void group_blend(int start, int n, __global const int *ids, __global const float *w,
                               __local int *l_start, __local int *l_n, __local int *l_ids, __local float *l_w,
                               __global const ROW_T *features, int row0, int n_rows, int cstride, int c,
                               int active, float tb, __global const float *background, int use_bg,
                               int accumulate, int stream, __global float *out) {
    const int lc = get_local_id(0), lr = get_local_id(1), nc = get_local_size(0), nr = get_local_size(1);
    if (lc == 0) { l_start[lr] = start; l_n[lr] = n; }
    barrier(CLK_LOCAL_MEM_FENCE);
    int n_max = 0;
    for (int r = 0; r < nr; r++) n_max = max(n_max, l_n[r]);
    vec_t acc = active && accumulate ? VLOAD(c, out) : (vec_t)(0.f);
    for (int j0 = 0; j0 < n_max; j0 += GROUP_ENTRIES) {
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int t = lr * nc + lc; t < nr * GROUP_ENTRIES; t += nr * nc) {
            const int r = t / GROUP_ENTRIES, j = j0 + t % GROUP_ENTRIES;
            if (j < l_n[r]) { l_ids[t] = ids[l_start[r] + j]; l_w[t] = w[l_start[r] + j]; }
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        if (active)
            for (int j = lr * GROUP_ENTRIES; j < lr * GROUP_ENTRIES + min(GROUP_ENTRIES, n - j0); j++) {
                const uint id = (uint)l_ids[j] - (uint)row0;   /* wraps below row0: skipped too */
                if (id >= (uint)n_rows) continue;
                acc += l_w[j] * RLOAD(c, features + (size_t)id * cstride);
            }
    }
    if (!active) return;
    const vec_t bg = use_bg ? VLOAD(c, background) : (vec_t)(0.f);
    if (stream) VSTREAM(acc + tb * bg, c, out);
    else VSTORE(acc + tb * bg, c, out);
}

/* The local memory of group_blend, for work-groups of at most BLEND_GROUP work-items (the build). */
#define GROUP_BLEND_LOCALS \
    __local int l_start[BLEND_GROUP], l_n[BLEND_GROUP], l_ids[BLEND_GROUP * GROUP_ENTRIES]; \
    __local float l_w[BLEND_GROUP * GROUP_ENTRIES];

/* Forward. Rays as in select.cl (full image tile-major, or a pixel subset); entries of row p
   are [offsets[p], offsets[p] + count[p]). accumulate: add to the image (a later row part). */
__kernel void blend(__global const int *offsets, __global const int *count,
                    __global const int *sel_ids, __global const float *sel_w,
                    const int n_entries, __global const ROW_T *features,   /* [n_rows, cstride] */
                    const int row0, const int n_rows, const int cstride, const int full, const int n_rays,
                    const int width, const int height,
                    const int tiles_x, __global const float *background,   /* [cstride] */
                    __global const float *t_rem, const int use_bg, const int accumulate,
                    const int stream,                      /* write the image with VSTREAM */
                    __global float *image) {               /* [P, cstride] */
    int p;
    if (!ray_row(get_global_id(0), full, n_rays, width, height, tiles_x, &p)) return;
    const int2 span = ray_span(offsets, count, p, n_entries);
    blend_entries(sel_ids + span.x, sel_w + span.x, span.y - span.x, features, row0, n_rows, cstride,
                  get_global_id(1) * NV * VW, use_bg ? t_rem[p] : 0.f, background, use_bg, accumulate, stream,
                  image + (size_t)p * cstride);
}

/* Forward, GPU shapes: work-item (vector c of a row, ray) in work-groups of rays x vectors; rays
   as blend's (the whole image tile-major: a group's rays share a tile). */
__kernel void blend_group(__global const int *offsets, __global const int *count,
                          __global const int *sel_ids, __global const float *sel_w,
                          const int n_entries, __global const ROW_T *features,
                          const int row0, const int n_rows, const int cstride, const int full, const int n_rays,
                          const int width, const int height,
                          const int tiles_x, __global const float *background,
                          __global const float *t_rem, const int use_bg, const int accumulate,
                          const int stream, __global float *image) {
    GROUP_BLEND_LOCALS
    int p;
    const int has_ray = ray_row(get_global_id(1), full, n_rays, width, height, tiles_x, &p);
    const int2 span = has_ray ? ray_span(offsets, count, p, n_entries) : (int2)(0);
    const int c = get_global_id(0);
    group_blend(span.x, span.y - span.x, sel_ids, sel_w, l_start, l_n, l_ids, l_w, features, row0, n_rows,
                cstride, c, has_ray && c < cstride / VW, has_ray && use_bg ? t_rem[p] : 0.f, background, use_bg,
                accumulate, stream, image + (size_t)(has_ray ? p : 0) * cstride);
}

/* The transposed entries [x, y) of Gaussian g in the window [walk_from, walk_to) of its list; x = y
   past its end. *first: the window starts the list. */
static inline int2 gaussian_window(__global const int *cursor, int n_chunks, int g, int walk_from, int walk_to,
                                   int *first) {
    const int start = g ? cursor[g * n_chunks - 1] : 0, end = cursor[(g + 1) * n_chunks - 1];
    int from, to, last;
    if (!window_span((int2)(start, end), walk_from, walk_to, &from, &to, first, &last)) return (int2)(end);
    return (int2)(from, to);
}

#ifndef HALF_ROWS   /* the feature backward reads and writes float rows only */
/* Backward gather: dF[g, chunk] = sum over Gaussian g's transposed entries of w dImage[p, chunk],
   in the fixed order of the transpose. One work-item per (Gaussian, channel chunk), Gaussians
   taken in the order ``order`` (by their first ray, so neighbours read neighbouring rows): the n
   Gaussians of the row part [row0, ...) that dF holds. A window after the first adds to dF. */
__kernel void blend_backward(const int n, __global const int *order,   /* [n] Gaussian of each work-item */
                             const int n_chunks, __global const int *cursor,
                             __global const int *t_ray, __global const float *t_w,
                             __global const float *dimage, const int n_rays,   /* [P, cstride] */
                             const int cstride, const int row0,
                             __global float *dfeatures, WINDOW_ARGS) {  /* [n, cstride] */
    if (get_global_id(0) >= n) return;
    const int g = order[get_global_id(0)];
    int first;
    const int2 span = gaussian_window(cursor, n_chunks, g, walk_from, walk_to, &first);
    if (span.x == span.y && !first) return;
    blend_entries(t_ray + span.x, t_w + span.x, span.y - span.x, dimage, 0, n_rays, cstride,
                  get_global_id(1) * NV * VW, 0.f, dimage, 0, !first, 0,
                  dfeatures + (size_t)(g - row0) * cstride);   /* no background */
}

/* Backward gather, GPU shapes: work-item (vector c of a row, Gaussian) in work-groups of Gaussians
   x vectors (group_blend over each Gaussian's transposed entries). */
__kernel void blend_backward_group(const int n, __global const int *order, const int n_chunks,
                                   __global const int *cursor, __global const int *t_ray,
                                   __global const float *t_w, __global const float *dimage, const int n_rays,
                                   const int cstride, const int row0, __global float *dfeatures, WINDOW_ARGS) {
    GROUP_BLEND_LOCALS
    const int i = get_global_id(1), c = get_global_id(0);
    const int g = i < n ? order[i] : row0;
    int first = 1;
    const int2 span = i < n ? gaussian_window(cursor, n_chunks, g, walk_from, walk_to, &first) : (int2)(0);
    const int active = i < n && c < cstride / VW && (first || span.x < span.y);
    group_blend(span.x, span.y - span.x, t_ray, t_w, l_start, l_n, l_ids, l_w, dimage, 0, n_rays, cstride, c,
                active, 0.f, dimage, 0, !first, 0, dfeatures + (size_t)(g - row0) * cstride);
}

/* Backward scatter: work-item m owns the Gaussians [bounds[m], bounds[m + 1]), within the row part
   [row0, ...) that dF and touched hold. It walks every ray in order and adds w dImage[p, :] to
   the rows of dF of the Gaussians it owns (the first entry of a Gaussian writes 0 + w dImage[p, :],
   marking it in touched, zeroed by the host), then zeroes the rows of its Gaussians without
   entries. Each owner reads all the entries' ids but only its own entries' rows. */
__kernel void blend_backward_scatter(const int n_owners, __global const int *bounds, const int n_rays,
                                     __global const int *offsets, __global const int *count,
                                     const int n_entries, __global const int *sel_ids,
                                     __global const float *sel_w,
                                     __global const float *dimage,   /* [P, cstride] */
                                     const int cstride, const int row0,
                                     __global uchar *touched,        /* [part rows] */
                                     __global float *dfeatures) {    /* [part rows, cstride] */
    const int m = get_global_id(0);
    if (m >= n_owners) return;
    const int g0 = bounds[m], g1 = bounds[m + 1], n_vec = cstride / VW;
    for (int p = 0; p < n_rays; p++) {
        __global const float *d = dimage + (size_t)p * cstride;
        const int2 span = ray_span(offsets, count, p, n_entries);
        for (int j = span.x; j < span.y; j++) {
            const int g = sel_ids[j];
            if (g < g0 || g >= g1) continue;
            const float w = sel_w[j];
            __global float *out = dfeatures + (size_t)(g - row0) * cstride;
            if (touched[g - row0])
                for (int v = 0; v < n_vec; v++) VSTORE(VLOAD(v, out) + w * VLOAD(v, d), v, out);
            else
                for (int v = 0; v < n_vec; v++) VSTORE(0.f + w * VLOAD(v, d), v, out);
            touched[g - row0] = 1;
        }
    }
    for (int g = g0; g < g1; g++)
        if (!touched[g - row0])
            for (int v = 0; v < n_vec; v++) VSTREAM((vec_t)(0.f), v, dfeatures + (size_t)(g - row0) * cstride);
}
#endif

/* dst[i] = src[i] rounded to half, to nearest even (as a float -> half cast): the float32 sums of
   a float16 table's gradient in the table's dtype. One work-item per element. */
__kernel void rows_to_half(const long n, __global const float *src, __global half *dst) {
    const long i = get_global_id(0);
    if (i < n) vstore_half_rte(src[i], 0, dst + i);
}

/* ---- gradients w.r.t. the geometry: dL/dalpha per entry, then per Gaussian splat ---- */

/* dL/dw_j = g_j = dImage[p] . F[id_j] of ray p's entries whose Gaussian is in the row part
   [row0, row0 + n_rows) that features hold, into d_w (the layout of sel_ids); other entries are
   left to the other parts. One work-item per ray, over the window of its entries. The input of
   blend_backward_alpha. */
__kernel void weight_grads(const int n_rays, __global const int *offsets, __global const int *count,
                           const int n_entries, __global const int *sel_ids,
                           __global const ROW_T *features,   /* [n_rows, cstride] */
                           const int row0, const int n_rows,
                           __global const float *dimage,     /* [P, cstride] */
                           const int cstride, __global float *d_w, WINDOW_ARGS) {
    const int p = get_global_id(0);
    if (p >= n_rays) return;
    int from, to, first, last;
    window_span(ray_span(offsets, count, p, n_entries), walk_from, walk_to, &from, &to, &first, &last);
    __global const float *di = dimage + (size_t)p * cstride;
    for (int j = from; j < to; j++) {
        const uint id = (uint)sel_ids[j] - (uint)row0;   /* wraps below row0: skipped too */
        if (id >= (uint)n_rows) continue;
        __global const ROW_T *f = features + (size_t)id * cstride;
        vec_t acc = (vec_t)(0.f);
        for (int v = 0; v < cstride / VW; v++) acc += RLOAD(v, f) * VLOAD(v, di);
        d_w[j] = vec_sum(acc);
    }
}

/* Backward of the blend w.r.t. the alphas a_j of ray p's entries (depth order; recomputed from
   the splats at the pixel centre), from g_j = dL/dw_j (weight_grads of every row part, in
   d_alpha on entry):
   volume (normalized == 0): w_j = T_j a_j, T_j = prod_{i<j} (1 - a_i), the background weight is
       the final T, whose gradient is d_trem[p]:
       dL/da_j = T_j g_j - (sum_{i>j} g_i w_i + d_trem T) / (1 - a_j)
   K samplers (normalized != 0): w_j = u_j / U with u_j = T_j a_j among the selected and
       U = sum_j u_j (= 1 - T^Q), so dL/du_j = h_j = (g_j - sum_i g_i w_i) / U and
       dL/da_j = T_j h_j - (sum_{i>j} h_i u_i) / (1 - a_j)
   One work-item per ray; d_alpha has the layout of sel_ids. Entries whose id is outside the n
   Gaussians count as alpha 0 (d_alpha 0). */
__kernel void blend_backward_alpha(const int n_rays, const int full, const int width,
                                   __global const int2 *pixels,
                                   __global const int *offsets, __global const int *count,
                                   const int n_entries, const int n,
                                   __global const int *sel_ids, __global const float *sel_w,
                                   __global const float8 *splats, const int normalized,
                                   __global const float *d_trem, __global float *d_alpha) {
    const int p = get_global_id(0);
    if (p >= n_rays) return;
    const float2 pix = ray_pixel(p, full, width, pixels);
    const int2 span = ray_span(offsets, count, p, n_entries);
    const int start = span.x, end = span.y;
    float gw = 0.f, T = 1.f, U = 0.f;                 /* pass 1: sum g w, the final T and U */
    for (int j = start; j < end; j++) {
        if ((uint)sel_ids[j] >= (uint)n) { d_alpha[j] = 0.f; continue; }
        gw += d_alpha[j] * sel_w[j];
        const float a = splat_alpha(splats[sel_ids[j]], pix.x, pix.y);
        U += T * a;
        T *= 1.f - a;
    }
    float S = normalized ? 0.f : d_trem[p] * T;      /* pass 2, back to front: S = sum_{i>j} ... */
    for (int j = end - 1; j >= start; j--) {
        if ((uint)sel_ids[j] >= (uint)n) continue;
        const float a = splat_alpha(splats[sel_ids[j]], pix.x, pix.y);
        T /= 1.f - a;                                 /* T_j */
        const float h = normalized ? (d_alpha[j] - gw) / U : d_alpha[j];
        d_alpha[j] = T * h - S / (1.f - a);
        S += h * T * a;
    }
}

/* Per Gaussian g, the gradient of its splat from dL/dalpha of its entries, summed in the fixed
   order of the transpose: alpha = opacity exp(-sigma) (entries clamped to ALPHA_MAX have none),
   sigma = 0.5 (A dx^2 + C dy^2) + B dx dy with (dx, dy) = mean2d - pixel centre, so
   dL/dsigma = -alpha dL/dalpha, dsigma/dmean2d = (A dx + B dy, B dx + C dy) and
   dsigma/d(A, B, C) = (dx^2 / 2, dx dy, dy^2 / 2). d_splats[g] = the gradient of mean2d, conic
   and opacity, and absgrad (common.h): the sums of the absolute value of each entry's (each
   pixel's) d mean2d term, gsplat's "absgrad". One work-item per Gaussian, over the window of its
   entries (a window after the first adds to d_splats). */
__kernel void splat_backward(const int n, const int n_chunks, __global const int *cursor,
                             __global const int *t_ray, __global const int *t_entry,
                             __global const float *d_alpha, __global const float8 *splats,
                             const int full, const int width, __global const int2 *pixels,
                             __global float8 *d_splats, WINDOW_ARGS) {
    const int g = get_global_id(0);
    if (g >= n) return;
    int first;
    const int2 span = gaussian_window(cursor, n_chunks, g, walk_from, walk_to, &first);
    if (span.x == span.y && !first) return;
    const float8 s = splats[g];
    float8 d = first ? (float8)(0.f) : d_splats[g];
    for (int j = span.x; j < span.y; j++) {
        const float2 pix = ray_pixel(t_ray[j], full, width, pixels);
        const float dx = s.SPLAT_MEAN_X - pix.x, dy = s.SPLAT_MEAN_Y - pix.y;
        const float e = exp_neg(splat_sigma(s.SPLAT_CONIC_A, s.SPLAT_CONIC_B, s.SPLAT_CONIC_C, dx, dy));
        const float raw = s.SPLAT_OPACITY * e;
        if (!(raw <= ALPHA_MAX)) continue;           /* clamped: alpha does not move */
        const float da = d_alpha[t_entry[j]], dsig = -da * raw;
        const float2 dm = dsig * (float2)(s.SPLAT_CONIC_A * dx + s.SPLAT_CONIC_B * dy,
                                          s.SPLAT_CONIC_B * dx + s.SPLAT_CONIC_C * dy);
        d.SPLAT_MEAN += dm;
        d.SPLAT_ABSGRAD += fabs(dm);
        d.SPLAT_CONIC_A += dsig * 0.5f * dx * dx;
        d.SPLAT_CONIC_B += dsig * dx * dy;
        d.SPLAT_CONIC_C += dsig * 0.5f * dy * dy;
        d.SPLAT_OPACITY += da * e;
    }
    d_splats[g] = d;
}
