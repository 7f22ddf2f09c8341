/* Transpose of a Selection (group its entries by Gaussian id) for the blend backward: a stable
   counting sort in "CPU style" (a few work-items, each owning a contiguous chunk of rays, private
   histogram slots, no atomics, no barriers), with an exclusive scan between the two passes. */

/* Transpose, counting pass: work-item c owns rays [c * rays_per, (c + 1) * rays_per) and counts
   its entries per Gaussian into hist[g * n_chunks + c] (its own slots: no atomics). */
__kernel void transpose_count(const int n_rays, const int rays_per, const int n_chunks,
                              __global const int *offsets, __global const int *count,
                              __global const int *sel_ids, __global int *hist) {
    const int c = get_global_id(0);
    const int p1 = min(n_rays, (c + 1) * rays_per);
    for (int p = c * rays_per; p < p1; p++)
        for (int j = offsets[p]; j < offsets[p] + count[p]; j++)
            hist[sel_ids[j] * n_chunks + c]++;
}

/* Transpose, fill pass: after an exclusive scan of hist (Gaussian-major, then chunk), cursor
   slot (g, c) is where chunk c's entries of Gaussian g go. Entries of each Gaussian end up
   ordered by ray, then by position in the ray. On return cursor[g * n_chunks + n_chunks - 1]
   is the end of Gaussian g's segment. */
__kernel void transpose_fill(const int n_rays, const int rays_per, const int n_chunks,
                             __global const int *offsets, __global const int *count,
                             __global const int *sel_ids, __global const float *sel_w,
                             __global int *cursor, __global int *t_ray, __global float *t_w) {
    const int c = get_global_id(0);
    const int p1 = min(n_rays, (c + 1) * rays_per);
    for (int p = c * rays_per; p < p1; p++)
        for (int j = offsets[p]; j < offsets[p] + count[p]; j++) {
            const int slot = cursor[sel_ids[j] * n_chunks + c]++;
            t_ray[slot] = p;
            t_w[slot] = sel_w[j];
        }
}
