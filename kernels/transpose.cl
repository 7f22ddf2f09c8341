/* Transpose of a Selection (group its entries by Gaussian id) for the blend backward: a stable
   counting sort in "CPU style" (a few work-items, each owning a contiguous chunk of rays, private
   histogram slots, no atomics, no barriers), with an exclusive scan between the two passes. */
#include "common.h"

/* Transpose, counting pass: work-item c owns rays [c * rays_per, (c + 1) * rays_per) and counts
   its entries per bin of Gaussian ids b = g >> bin_shift into hist[b * n_chunks + c] (its own
   slots: no atomics). bin_shift 0 counts per Gaussian (the transpose); wider bins give the
   histogram from which blend.py cuts the backward scatter's owner ranges. Ids outside the n
   Gaussians are not counted (nor placed by the passes below). */
__kernel void transpose_count(const int n_rays, const int rays_per, const int n_chunks, const int bin_shift,
                              __global const int *offsets, __global const int *count, const int n_entries,
                              const int n, __global const int *sel_ids, __global int *hist) {
    const int c = get_global_id(0);
    const int p1 = min(n_rays, (c + 1) * rays_per);
    for (int p = c * rays_per; p < p1; p++) {
        const int2 span = ray_span(offsets, count, p, n_entries);
        for (int j = span.x; j < span.y; j++)
            if ((uint)sel_ids[j] < (uint)n) hist[(sel_ids[j] >> bin_shift) * n_chunks + c]++;
    }
}

/* Transpose, fill pass: after an exclusive scan of hist (Gaussian-major, then chunk), cursor
   slot (g, c) is where chunk c's entries of Gaussian g go. Entries of each Gaussian end up
   ordered by ray, then by position in the ray. On return cursor[g * n_chunks + n_chunks - 1]
   is the end of Gaussian g's segment. */
__kernel void transpose_fill(const int n_rays, const int rays_per, const int n_chunks,
                             __global const int *offsets, __global const int *count, const int n_entries,
                             const int n, __global const int *sel_ids, __global const float *sel_w,
                             __global int *cursor, __global int *t_ray, __global float *t_w,
                             __global int *t_entry) {
    const int c = get_global_id(0);
    const int p1 = min(n_rays, (c + 1) * rays_per);
    for (int p = c * rays_per; p < p1; p++) {
        const int2 span = ray_span(offsets, count, p, n_entries);
        for (int j = span.x; j < span.y; j++) {
            if ((uint)sel_ids[j] >= (uint)n) continue;
            const int slot = cursor[sel_ids[j] * n_chunks + c]++;
            t_ray[slot] = p;
            t_w[slot] = sel_w[j];
            t_entry[slot] = j;
        }
    }
}

/* ---- GPU-shaped transpose: one work-item per ray or entry, a device sort in between ----
   The entries are numbered c in CSR order (ray, then position in the ray), sorted by the key
   (Gaussian id << 32 | c): within a Gaussian they keep the order ray, then position, as in the
   counting sort above, so both give identical bytes. */

/* spans[p] = the entries of ray p (count[p] bounded by the buffers, as ray_span). */
__kernel void ray_spans(const int n_rays, __global const int *offsets, __global const int *count,
                        const int n_entries, __global int *spans) {
    const int p = get_global_id(0);
    if (p >= n_rays) return;
    const int2 span = ray_span(offsets, count, p, n_entries);
    spans[p] = span.y - span.x;
}

/* Keys of ray p's entries, numbered from compact[p] (exclusive scan of ray_spans): the sort key,
   the entry's number (the sorted value), its ray, its weight and its index in the selection.
   An id outside the n Gaussians gets the key of Gaussian n (after all of them, in no segment). */
__kernel void transpose_keys(const int n_rays, __global const int *offsets, __global const int *count,
                             const int n_entries, const int n, __global const int *compact,
                             __global const int *sel_ids,
                             __global const float *sel_w, __global ulong *keys, __global int *values,
                             __global int *entry_ray, __global float *entry_w, __global int *entry_index) {
    const int p = get_global_id(0);
    if (p >= n_rays) return;
    const int2 span = ray_span(offsets, count, p, n_entries);
    for (int j = 0; j < span.y - span.x; j++) {
        const int c = compact[p] + j, e = span.x + j;
        const uint g = (uint)sel_ids[e] < (uint)n ? (uint)sel_ids[e] : (uint)n;
        keys[c] = ((ulong)g << 32) | (uint)c;
        values[c] = c;
        entry_ray[c] = p;
        entry_w[c] = sel_w[e];
        entry_index[c] = e;
    }
}

/* After the sort: the transposed ray, weight and selection index of sorted entry i, and ends[g] = i + 1 at the
   last entry of Gaussian g's segment (0 elsewhere; a max-scan then fills the cursor). Entries
   past the n_gaussians (transpose_keys' key n) end no segment. */
__kernel void transpose_gather(const int n, const int n_gaussians, __global const ulong *keys,
                               __global const int *values,
                               __global const int *entry_ray, __global const float *entry_w,
                               __global const int *entry_index, __global int *t_ray, __global float *t_w,
                               __global int *t_entry, __global int *ends) {
    const int i = get_global_id(0);
    if (i >= n) return;
    t_ray[i] = entry_ray[values[i]];
    t_w[i] = entry_w[values[i]];
    t_entry[i] = entry_index[values[i]];
    const uint g = (uint)(keys[i] >> 32);
    if (g < (uint)n_gaussians && (i == n - 1 || (uint)(keys[i + 1] >> 32) != g)) ends[g] = i + 1;
}
