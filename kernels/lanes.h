/* Lanes: TILE-wide vectors whose lane l holds item l of a work-item's block (the rays of the
   block walk in walk.h, project.cl's Gaussians, the tile rows of spans.h), and their tests. */
#ifndef QR_CL_LANES_H
#define QR_CL_LANES_H
#include "common.h"

typedef CAT(float, TILE) lanef;
typedef CAT(int, TILE) lanei;
#define LANE(v, l) (((__private float *)&(v))[l])      /* lane l of a lanef */
#define LANE_I(v, l) (((__private int *)&(v))[l])      /* lane l of a lanei */
DEFINE_EXP_NEG(exp_neg_lanes, lanef, CAT(convert_int, TILE), CAT(as_float, TILE))

/* any() and all() of a lane mask (each lane -1 or 0, as vector comparisons give them): the lanes
   narrowed to bytes and tested as whole 64-bit words. PoCL's built-ins test the lanes one at a
   time, a branch each, which costs the walk more than its arithmetic. */
static inline int lanes_any(lanei m) {
#if TILE == 16
    const ulong2 b = as_ulong2(convert_char16(m));
    return (b.x | b.y) != 0;
#elif TILE == 8
    return as_ulong(convert_char8(m)) != 0;
#else
#error "lanes_any: TILE must be 8 or 16"
#endif
}
static inline int lanes_all(lanei m) { return !lanes_any(~m); }

/* The sum of the lanes of v (a plain loop: a tree of .lo + .hi swizzles was flagged by oclgrind,
   like the reduction in lane_bits). */
static inline int lanes_sum(lanei v) {
    int s = 0;
    for (int l = 0; l < TILE; l++) s += LANE_I(v, l);
    return s;
}

/* (0, 1, ..., TILE - 1): the lane numbers. */
#if TILE == 16
#define LANE_IDS ((lanei)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#else
#define LANE_IDS ((lanei)(0, 1, 2, 3, 4, 5, 6, 7))
#endif

/* The lanes set in mask m as the bits of an integer (bit l: lane l), without branches (a vector
   reduction by swizzles was flagged by oclgrind: their shuffles have undefined operands). */
static inline uint lane_bits(lanei m) {
    uint bits = 0;
    for (int l = 0; l < TILE; l++) bits |= (uint)(LANE_I(m, l) & 1) << l;
    return bits;
}

/* for (each lane l set in mask m, in increasing order): visits only those lanes. For masks with
   few lanes set, such as the lanes that cross a Q-Render boundary at a Gaussian, this beats a
   loop over all TILE lanes with a test each; for masks with most lanes set (the V-Render and
   top-K writes) the plain loop is faster. */
#define FOR_LANES(m, l) \
    for (uint bits_##l = lane_bits(m), l = 0; bits_##l && (l = 31 - clz(bits_##l & (0u - bits_##l)), 1); \
         bits_##l &= bits_##l - 1)

#endif
