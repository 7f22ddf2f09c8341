/* Tile binning: one sort key per (Gaussian, touched tile), then per-tile [start, end) ranges. */
#include "common.h"

/* key = tile id << 32 | float bits of the (positive) depth, so a sort orders by tile then depth. */
__kernel void emit_keys(const int n, __global const int4 *rects, __global const int *offsets,
                        __global const float8 *splats, const int tiles_x,
                        __global ulong *keys, __global int *values) {
    const int i = get_global_id(0);
    if (i >= n) return;
    int4 rect = rects[i];
    int out = offsets[i];
    ulong depth_bits = (ulong)as_uint(splats[i].s6);
    for (int ty = rect.y; ty < rect.w; ty++)
        for (int tx = rect.x; tx < rect.z; tx++) {
            keys[out] = ((ulong)(ty * tiles_x + tx) << 32) | depth_bits;
            values[out] = i;
            out++;
        }
}

/* ranges[tile] = [first, last + 1) of the tile's entries in the sorted keys (0, 0 when empty). */
__kernel void tile_ranges(const int m, __global const ulong *keys, __global int2 *ranges) {
    const int i = get_global_id(0);
    if (i >= m) return;
    uint tile = (uint)(keys[i] >> 32);
    if (i == 0 || (uint)(keys[i - 1] >> 32) != tile) ranges[tile].x = i;
    if (i == m - 1 || (uint)(keys[i + 1] >> 32) != tile) ranges[tile].y = i + 1;
}

/* ---- CPU shapes: a stable counting sort of the (Gaussian, tile) pairs by tile ----
   The Gaussians come in depth order (order: sorted by depth, ties by index, on the host), so each
   tile's list comes out by depth, then index: the order of the key sort above. Work-item c owns
   order[c * per, (c + 1) * per) and uses its own histogram slots (tile * n_chunks + c): no
   atomics, no barriers, an exclusive scan between the two passes. */

/* Counting pass: hist[tile * n_chunks + c] = the pairs of work-item c's Gaussians in the tile. */
__kernel void bin_count(const int n, const int per, const int n_chunks, __global const int *order,
                        __global const int4 *rects, const int tiles_x, __global int *hist) {
    const int c = get_global_id(0);
    const int i1 = min(n, (c + 1) * per);
    for (int i = c * per; i < i1; i++) {
        const int4 rect = rects[order[i]];
        for (int ty = rect.y; ty < rect.w; ty++)
            for (int tx = rect.x; tx < rect.z; tx++) hist[(ty * tiles_x + tx) * n_chunks + c]++;
    }
}

/* Fill pass: cursor (the exclusive scan of hist) slot (tile, c) is where work-item c's next
   Gaussian of the tile goes in ids. */
__kernel void bin_fill(const int n, const int per, const int n_chunks, __global const int *order,
                       __global const int4 *rects, const int tiles_x, __global int *cursor,
                       __global int *ids) {
    const int c = get_global_id(0);
    const int i1 = min(n, (c + 1) * per);
    for (int i = c * per; i < i1; i++) {
        const int g = order[i];
        const int4 rect = rects[g];
        for (int ty = rect.y; ty < rect.w; ty++)
            for (int tx = rect.x; tx < rect.z; tx++) ids[cursor[(ty * tiles_x + tx) * n_chunks + c]++] = g;
    }
}
