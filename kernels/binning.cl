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
