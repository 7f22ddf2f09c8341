/* Tile binning: one sort key per (Gaussian, touched tile), then per-tile [start, end) ranges.
   Every pass visits a Gaussian's tiles as the row spans of its blend ellipse inside its tile
   rectangle, in row-major order (FOR_TILE_SPANS in spans.h). */
#include "spans.h"

/* key = tile id << 32 | float bits of the (positive) depth, so a sort orders by tile then depth. */
__kernel void emit_keys(const int n, __global const int16 *footprints, __global const int *offsets,
                        __global const float8 *splats, const int tiles_x,
                        __global ulong *keys, __global int *values) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const ulong depth_bits = (ulong)as_uint(splats[i].SPLAT_DEPTH);
    int out = offsets[i];
    FOR_TILE_SPANS(i, footprints[i], ty, x,
        for (int tx = x.x; tx < x.y; tx++) {
            keys[out] = ((ulong)(ty * tiles_x + tx) << 32) | depth_bits;
            values[out] = i;
            out++;
        })
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

/* sorted[i] = footprints[order[i]]: the footprints in depth order, so that the two passes below
   read them as one stream (gathered here by many independent loads in flight, instead of one
   dependent miss per Gaussian in each pass). */
__kernel void gather_footprints(const int n, __global const int *order, __global const int16 *footprints,
                                __global int16 *sorted) {
    const int i = get_global_id(0);
    if (i < n) sorted[i] = footprints[order[i]];
}

/* Counting pass: hist[tile * n_chunks + c] = the pairs of work-item c's Gaussians in the tile.
   Each row span adds +1 at its first tile and -1 after its last (a difference along the tile
   row, so the work is per row, not per tile), then the work-item sums its slots along each row. */
__kernel void bin_count(const int n, const int per, const int n_chunks, __global const int *order,
                        __global const int16 *sorted, __global const float8 *splats,
                        const int tiles_x, const int n_tiles, __global int *hist) {
    const int c = get_global_id(0);
    const int i1 = min(n, (c + 1) * per);
    for (int i = c * per; i < i1; i++) {
        const int g = order[i];
        FOR_TILE_SPANS(g, sorted[i], ty, x,
            hist[(ty * tiles_x + x.x) * n_chunks + c]++;
            hist[(ty * tiles_x + min(x.y, tiles_x - 1)) * n_chunks + c] -= x.y < tiles_x;)
    }
    int run = 0;
    for (int t = 0; t < n_tiles; t++) {
        run = (t % tiles_x ? run : 0) + hist[t * n_chunks + c];
        hist[t * n_chunks + c] = run;
    }
}

/* Fill pass: cursor (the exclusive scan of hist) slot (tile, c) is where work-item c's next
   Gaussian of the tile goes in ids. */
__kernel void bin_fill(const int n, const int per, const int n_chunks, __global const int *order,
                       __global const int16 *sorted, __global const float8 *splats,
                       const int tiles_x, __global int *cursor, __global int *ids) {
    const int c = get_global_id(0);
    const int i1 = min(n, (c + 1) * per);
    for (int i = c * per; i < i1; i++) {
        const int g = order[i];
        FOR_TILE_SPANS(g, sorted[i], ty, x,
            for (int tx = x.x; tx < x.y; tx++) ids[cursor[(ty * tiles_x + tx) * n_chunks + c]++] = g;)
    }
}
