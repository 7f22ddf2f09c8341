/* Shared math of the qr-cl kernels, in the original 3DGS conventions (see docs/design.md).

   The constants TILE (tile side in px), WALK_ALL (a window past every list), ALPHA_MIN (smaller
   alphas are skipped), ALPHA_MAX (alpha clamp), T_MIN (V-Render stops before T would drop to it),
   the SH basis constants SH_C0, SH_C1, SH_C2_0..4, SH_C3_0..6 and the layouts of the splat
   (SPLAT_*) and the footprint (FOOTPRINT_*, SPAN_ROWS) are defined by the build (-D), from
   qr_cl/runtime/constants.py; from the device, by Runtime: ACC_FLOATS (the floats of a row
   kept in registers, see RV), GROUP_RAYS (the rays of a tile walk's work-group) and BLEND_GROUP
   (the work-items of a GPU blend's work-group). */
#ifndef QR_CL_COMMON_H
#define QR_CL_COMMON_H

/* ---- the splat: a Gaussian as project.cl writes it and the walks read it ----
   A float8 whose fields are swizzles named by the build (-D, from SplatLayout in
   qr_cl/runtime/constants.py): s.SPLAT_MEAN (mean2d, px; .._X, .._Y), s.SPLAT_CONIC (conic
   a, b, c, the inverse 2D covariance; .._A, .._B, .._C), s.SPLAT_OPACITY, s.SPLAT_DEPTH (camera
   z) and s.SPLAT_SIGMA_MAX (ln(opacity / ALPHA_MIN)). A splat's gradient d has the same fields,
   with d.SPLAT_ABSGRAD (.._X, .._Y: the sums of |d mean2d x|, |d mean2d y|) in the slots of depth
   and sigma_max. */

/* Gaussian density exponent at offset d = mean2d - pixel: 0.5 (a dx^2 + c dy^2) + b dx dy,
   with conic (a, b, c) the inverse 2D covariance. */
static inline float splat_sigma(float a, float b, float c, float dx, float dy) {
    return 0.5f * (a * dx * dx + c * dy * dy) + b * dx * dy;
}

#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)

/* e^-x in float by the same float operations in scalar and vector code, on every implementation:
   2^n p(r) with n = -x log2 e rounded to nearest (by adding and subtracting 1.5 * 2^23 around an
   fma: exact, where rint on vectors runs lane by lane on PoCL), r = -x - n ln 2 (ln 2 in two
   parts), p Cephes' expf polynomial of e^r on |r| <= ln(2) / 2, every multiply-add an explicit
   fma (within 1.3 ulp of exp). A library exp may round its scalar and vector versions apart
   (PoCL's do, in about 1 % of arguments), and a ray's alphas must be the same bytes whether
   computed alone (tile walk) or in lanes (block walk). x is clamped to [-87, 87], so 2^n is a
   normal float. */
#define DEFINE_EXP_NEG(name, F, CONVERT_INT, AS_FLOAT) \
    static inline F name(F x) { \
        const F y = -clamp(x, (F)(-87.f), (F)(87.f)); \
        const F n = fma(y, (F)(1.44269504088896341f), (F)(12582912.f)) - 12582912.f; \
        F r = fma(n, (F)(-0.693359375f), y); \
        r = fma(n, (F)(2.12194440e-4f), r); \
        F p = (F)(1.9875691500e-4f); \
        p = fma(p, r, (F)(1.3981999507e-3f)); \
        p = fma(p, r, (F)(8.3334519073e-3f)); \
        p = fma(p, r, (F)(4.1665795894e-2f)); \
        p = fma(p, r, (F)(1.6666665459e-1f)); \
        p = fma(p, r, (F)(5.0000001201e-1f)); \
        p = fma(p, r * r, r + 1.f); \
        return p * AS_FLOAT((CONVERT_INT(n) + 127) << 23); \
    }
DEFINE_EXP_NEG(exp_neg, float, convert_int, as_float)

/* ---- rays: blend.cl numbers them one per work-item ---- */

/* Ray gid -> output row p. full != 0: the whole image, rays numbered tile-major (neighbouring
   work-items share a tile list), p = y * width + x; returns 0 for padding rays outside the image.
   full == 0: a pixel subset of n_rays rays, p = gid; returns 0 past them. */
static inline int ray_row(int gid, int full, int n_rays, int width, int height, int tiles_x, int *p) {
    if (!full) { *p = gid; return gid < n_rays; }
    const int tile = gid / (TILE * TILE), in_tile = gid % (TILE * TILE);
    const int x = (tile % tiles_x) * TILE + in_tile % TILE, y = (tile / tiles_x) * TILE + in_tile / TILE;
    *p = y * width + x;
    return x < width && y < height;
}

/* Ray p's entries [x, y) in a selection's id and weight buffers of n_entries: count[p] from
   offsets[p], clamped to the buffers, so that a count no kernel wrote (a driver that ended a
   selection early) never sends a walk past them. */
static inline int2 ray_span(__global const int *offsets, __global const int *count, int p, int n_entries) {
    const int start = clamp(offsets[p], 0, n_entries);
    return (int2)(start, start + clamp(count[p], 0, n_entries - start));
}

/* The pixel centre of ray p: of the whole image (full != 0, p = y * width + x) or of pixels[p]. */
static inline float2 ray_pixel(int p, int full, int width, __global const int2 *pixels) {
    const int2 xy = full ? (int2)(p % width, p / width) : pixels[p];
    return (float2)(xy.x + 0.5f, xy.y + 0.5f);
}

/* alpha'_i of a splat at pixel centre (px, py): min(0.99, opacity exp(-sigma)), or 0 when the
   Gaussian is skipped (sigma < 0 or alpha < 1/255). */
static inline float splat_alpha(float8 s, float px, float py) {
    const float sig = splat_sigma(s.SPLAT_CONIC_A, s.SPLAT_CONIC_B, s.SPLAT_CONIC_C, s.SPLAT_MEAN_X - px,
                                  s.SPLAT_MEAN_Y - py);
    if (sig < 0.f) return 0.f;
    const float a = min(ALPHA_MAX, s.SPLAT_OPACITY * exp_neg(sig));
    return a < ALPHA_MIN ? 0.f : a;
}

/* The (k+1)-th of the K equal transmittance boundaries of Q-Render: 1 - (k+1)/(K+1). */
static inline float quantile_boundary(int k, int K) { return 1.f - (float)(k + 1) / (float)(K + 1); }

/* ---- the block walk of select.cl and vrender.cl ----

   A work-item walks one tile's depth-sorted Gaussian list for a block of up to TILE rays at once:
   lane l of the TILE-wide vectors (lanef, lanei) is ray l of the block, and each Gaussian's alpha
   is evaluated for all lanes with explicit vector types (PoCL does not vectorize loops whose trip
   count differs between work-items; explicit vectors become SIMD code). Per lane the 3DGS rules
   are those of one ray walking alone, so the results equal the per-ray walk. Whole image
   (full != 0): block b is row b % TILE of tile b / TILE. Pixel subset (full == 0): the host
   groups the rays by tile; block b holds the rays order[blocks[b].x ..+ blocks[b].y) of tile
   blocks[b].z. */
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

#define BLOCK_ARGS __global const int2 *ranges, __global const int *ids, \
    __global const float8 *splats, __global const int2 *pixels, __global const int *order, \
    __global const int4 *blocks, const int full, const int width, const int height, const int tiles_x

/* The rays of block b: returns the tile's range [start, end) in ids; px, py get the lanes'
   pixel centres, row their output rows (-1 for lanes without a ray). */
static inline int2 block_rays(int b, int full, __global const int2 *ranges, __global const int2 *pixels,
                              __global const int *order, __global const int4 *blocks, int width,
                              int height, int tiles_x, lanef *px, lanef *py, lanei *row) {
    int tile;
    if (full) {
        tile = b / TILE;
        const int x0 = (tile % tiles_x) * TILE, y = (tile / tiles_x) * TILE + b % TILE;
        for (int l = 0; l < TILE; l++) {
            LANE(*px, l) = x0 + l + 0.5f;
            LANE(*py, l) = y + 0.5f;
            LANE_I(*row, l) = x0 + l < width && y < height ? y * width + x0 + l : -1;
        }
    } else {
        const int4 blk = blocks[b];
        tile = blk.z;
        for (int l = 0; l < TILE; l++) {
            const int ray = l < blk.y ? order[blk.x + l] : -1;
            const int2 xy = ray >= 0 ? pixels[ray] : (int2)(0);
            LANE(*px, l) = xy.x + 0.5f;
            LANE(*py, l) = xy.y + 0.5f;
            LANE_I(*row, l) = ray;
        }
    }
    return ranges[tile];
}

/* The Gaussian exponent sigma of splat s at the lanes' pixel centres (splat_sigma, as vectors). */
static inline lanef block_sigma(float8 s, lanef px, lanef py) {
    const lanef dx = s.SPLAT_MEAN_X - px, dy = s.SPLAT_MEAN_Y - py;
    return 0.5f * (s.SPLAT_CONIC_A * dx * dx + s.SPLAT_CONIC_C * dy * dy) + s.SPLAT_CONIC_B * dx * dy;
}

/* Declares px, py, row and range (the tile list) of the block of this work-item, in a kernel
   declared with BLOCK_ARGS. */
#define BLOCK_SETUP \
    lanef px, py; \
    lanei row; \
    const int2 range = block_rays(get_global_id(0), full, ranges, pixels, order, blocks, width, height, \
                                  tiles_x, &px, &py, &row);

/* splat_alpha of splat s from its exponents sig, as vectors (the same expression). */
static inline lanef block_alpha(float8 s, lanef sig) {
    const lanef a = fmin((lanef)(ALPHA_MAX), s.SPLAT_OPACITY * exp_neg_lanes(sig));
    return select(a, (lanef)(0.f), (sig < 0.f) | (a < ALPHA_MIN));
}

/* Whether splat s may be blended in some lane: an exponent at most sigma_max = ln(opacity /
   ALPHA_MIN) (from project.cl) plus a margin far above float rounding. When no lane is below it,
   every alpha would be skipped and the walk skips the exp. */
#define MAY_BLEND(s, sig) lanes_any((sig) <= (s).SPLAT_SIGMA_MAX + 1e-3f)

/* The V-Render walk of a block over the list positions [from, to): for each Gaussian g (splat s,
   list position i_) that some lane blends, in depth order, runs the statements ... with lanei use
   (-1 in the lanes that blend it), lanef a (alpha'), w (w_i = T_i alpha'_i where used, 0
   elsewhere) and next_T (T (1 - alpha')), then advances T. A lane stops (done) before the
   Gaussian that would bring its T to <= T_MIN. T (lanef) and done (lanei) are the walk's state,
   declared by the caller: (1, row < 0) at the start of a walk, or resumed (walk windows). */
#define VOLUME_WALK(from, to, px, py, row, T, done, ...) \
    for (int i_ = (from); i_ < (to) && !lanes_all(done); i_++) { \
        const int g = ids[i_]; \
        const float8 s = splats[g]; \
        const lanef sig_ = block_sigma(s, px, py); \
        if (!MAY_BLEND(s, sig_)) continue; \
        const lanef a = block_alpha(s, sig_); \
        lanei use = (a > 0.f) & ~done; \
        if (!lanes_any(use)) continue; \
        const lanef next_T = T * (1.f - a); \
        const lanei stop_ = use & (next_T <= T_MIN); \
        done |= stop_; \
        use &= ~stop_; \
        if (!lanes_any(use)) continue; \
        const lanef w = select((lanef)(0.f), a * T, use); \
        __VA_ARGS__; \
        T = select(T, next_T, use); \
    }

/* ---- walk windows: a walk split over launches ----

   A device whose driver ends long loops early (Runtime.loop_limit) walks the tile lists a window
   of positions per launch: a launch walks the positions [walk_from, walk_to) of each tile's list,
   and each ray's walk state waits between launches in the slots of a state buffer, stored and
   loaded exactly, so a walk gives the same bytes in one launch or in many. A single launch walks
   [0, WALK_ALL) (from the build). The window that reaches the end of a list finishes its rays
   (writes their outputs); windows past the end do nothing. */
#define WINDOW_ARGS const int walk_from, const int walk_to

/* The list positions [from, to) of range that the window [walk_from, walk_to) walks. Returns 0
   when the window has nothing to do (it starts past a list that an earlier one finished); *first:
   the window starts the walk; *last: it finishes it. */
static inline int window_span(int2 range, int walk_from, int walk_to, int *from, int *to, int *first,
                              int *last) {
    const int len = range.y - range.x;
    *first = walk_from == 0;
    *last = walk_to >= len;
    *from = range.x + walk_from;
    *to = range.x + min(walk_to, len);
    return *first || walk_from < len;
}

/* ---- the tile walk of select.cl and vrender.cl (GPU shapes) ----

   A work-group of GROUP_RAYS work-items (from the build), one ray each, walks one tile's list:
   its work-items load the next GROUP_RAYS Gaussians (id and splat) into local memory, one each,
   behind a barrier; then every ray walks them from there with the float operations of a lane of
   the block walk (so both walks give the same bytes), and the group stops once all its rays are
   done. Whole image (full != 0): group b holds GROUP_RAYS consecutive pixels (row-major) of tile
   b / TILE_PARTS, part b % TILE_PARTS. Pixel subset: group b holds the rays order[blocks[b].x ..+
   blocks[b].y) of tile blocks[b].z (at most GROUP_RAYS). */
#define TILE_PARTS (TILE * TILE / GROUP_RAYS)

/* The ray of this work-item: *p its output row (-1 for none) and (px, py) its pixel centre;
   returns its tile's range. */
static inline int2 tile_ray(int full, __global const int2 *ranges, __global const int2 *pixels,
                            __global const int *order, __global const int4 *blocks, int width, int height,
                            int tiles_x, float *px, float *py, int *p) {
    const int b = get_group_id(0), lid = get_local_id(0);
    int tile;
    if (full) {
        tile = b / TILE_PARTS;
        const int in_tile = (b % TILE_PARTS) * GROUP_RAYS + lid;
        const int x = (tile % tiles_x) * TILE + in_tile % TILE, y = (tile / tiles_x) * TILE + in_tile / TILE;
        *px = x + 0.5f;
        *py = y + 0.5f;
        *p = x < width && y < height ? y * width + x : -1;
    } else {
        const int4 blk = blocks[b];
        tile = blk.z;
        *p = lid < blk.y ? order[blk.x + lid] : -1;
        const int2 xy = *p >= 0 ? pixels[*p] : (int2)(0);
        *px = xy.x + 0.5f;
        *py = xy.y + 0.5f;
    }
    return ranges[tile];
}

/* Declares the local batch, px, py, p (tile_ray) and the window's from, to, first, last in a
   kernel declared with BLOCK_ARGS and WINDOW_ARGS; returns (the whole group: one tile) when the
   window has nothing to do. */
#define TILE_SETUP \
    __local int batch_ids_[GROUP_RAYS]; \
    __local float8 batch_splats_[GROUP_RAYS]; \
    __local int alive_; \
    float px, py; \
    int p; \
    const int2 range = tile_ray(full, ranges, pixels, order, blocks, width, height, tiles_x, &px, &py, &p); \
    int from, to, first, last; \
    if (!window_span(range, walk_from, walk_to, &from, &to, &first, &last)) return;

/* for (each Gaussian g, splat s, list position i_ in [from, to), in batches staged by the group)
   { ... } of a ray that is not done; the group leaves once every ray is done. Every work-item of
   the group runs the loop (its bounds and exit are the group's), so the barriers are uniform. */
#define TILE_WALK(from, to, done, ...) \
    for (int b0_ = (from); b0_ < (to); b0_ += GROUP_RAYS) { \
        const int lid_ = get_local_id(0); \
        barrier(CLK_LOCAL_MEM_FENCE); \
        if (lid_ == 0) alive_ = 0; \
        if (b0_ + lid_ < (to)) { \
            const int g_ = ids[b0_ + lid_]; \
            batch_ids_[lid_] = g_; \
            batch_splats_[lid_] = splats[g_]; \
        } \
        barrier(CLK_LOCAL_MEM_FENCE); \
        if (!(done)) alive_ = 1; \
        barrier(CLK_LOCAL_MEM_FENCE); \
        if (!alive_) break; \
        const int n_ = min(GROUP_RAYS, (to) - b0_); \
        for (int j_ = 0; j_ < n_ && !(done); j_++) { \
            const int i_ = b0_ + j_, g = batch_ids_[j_]; \
            const float8 s = batch_splats_[j_]; \
            __VA_ARGS__; \
        } \
    }

/* The alpha'_i of splat s at (px, py), 0 when skipped: a ray's block_alpha, whose Gaussians
   beyond sigma_max (MAY_BLEND) have alphas below ALPHA_MIN, skipped here without the exp. */
static inline float ray_alpha(float8 s, float px, float py) {
    const float sig = splat_sigma(s.SPLAT_CONIC_A, s.SPLAT_CONIC_B, s.SPLAT_CONIC_C, s.SPLAT_MEAN_X - px,
                                  s.SPLAT_MEAN_Y - py);
    return sig <= s.SPLAT_SIGMA_MAX + 1e-3f ? splat_alpha(s, px, py) : 0.f;
}

/* The V-Render walk of one ray over the batches of TILE_WALK: for each Gaussian it blends, runs
   ... with a (alpha'), w = T alpha' and next_T = T (1 - alpha'), then advances T; it is done
   before the Gaussian that would bring T to <= T_MIN (VOLUME_WALK per ray). */
#define RAY_VOLUME_WALK(from, to, T, done, ...) \
    TILE_WALK(from, to, done, \
        const float a = ray_alpha(s, px, py); \
        if (a > 0.f) { \
            const float next_T = T * (1.f - a); \
            if (next_T <= T_MIN) done = 1; \
            else { \
                const float w = a * T; \
                __VA_ARGS__; \
                T = next_T; \
            } \
        })

/* ---- tile spans: the tiles of each tile row that a splat's blend ellipse reaches ----

   A pixel blends splat s only where sigma <= sigma_max: inside the ellipse
   a dx^2 + 2 b dx dy + c dy^2 <= 2 L of its conic (a, b, c), d = pixel - mean.
   Its chord on the line at height dy is (-b dy -/+ sqrt(2 L a - det dy^2)) / a, det = a c - b^2,
   and its x-extremes +/-e_x (e_x = sqrt(2 L c / det)) lie at dy = -/+ b e_x / c. The part of the
   ellipse in a band of rows is convex, so its x-extent is that of the chords on the band's two
   lines and of the extremes that lie inside the band. Against float rounding L is sigma_max +
   SPAN_SLACK, times 1 + SPAN_ROUNDING eps (a c / det) (a float sigma near the ellipse errs by about
   eps a c / det times it), and the x-extent grows by SPAN_MARGIN_PX + SPAN_MARGIN_REL e_x. Conics
   with det <= SPAN_DET_MIN or a c / det > SPAN_COND_MAX keep whole rectangle rows. TILE rows are
   computed at once, row ty0 + l in lane l. Twin: qr_cl/stages/project_ref.py tile_spans. */

/* Tile index of pixel coordinates v clamped to [0, tiles], clamped in float before the
   conversion (out-of-range conversions are undefined); fmax/fmin map NaN to the bound. Truncates
   toward zero like the (int) conversion it replaces. */
static inline int tile_index(float v, int tiles) {
    return (int)fmin(fmax(v / TILE, 0.f), (float)tiles);
}
static inline lanei tile_indices(lanef v, int tiles) {
    return CAT(convert_int, TILE)(fmin(fmax(v / TILE, 0.f), (float)tiles));
}

typedef struct {
    float mx, my, inv_a, slope, det, two_la;  /* mean; 1 / a; chord centre slope -b / a; det; 2 L a */
    float dy_x, e_x, margin;                  /* extremes at dy = -/+ dy_x; x half-width; margin (px) */
    int whole;                                /* keep the rectangle's rows whole */
} span_t;

static inline span_t span_of(float8 s) {
    span_t e;
    const float a = s.SPLAT_CONIC_A, b = s.SPLAT_CONIC_B, c = s.SPLAT_CONIC_C;
    e.mx = s.SPLAT_MEAN_X; e.my = s.SPLAT_MEAN_Y; e.inv_a = 1.f / a; e.slope = -b * e.inv_a;
    e.det = a * c - b * b;
    const float inv_det = 1.f / e.det, cond = a * c * inv_det;
    e.whole = !(e.det > SPAN_DET_MIN && cond <= SPAN_COND_MAX);
    const float L = (s.SPLAT_SIGMA_MAX + SPAN_SLACK) * (1.f + SPAN_ROUNDING * FLT_EPSILON * cond);
    e.e_x = sqrt(2.f * L * c * inv_det);
    e.two_la = 2.f * L * a;
    e.dy_x = b * e.e_x / c;
    e.margin = SPAN_MARGIN_PX + SPAN_MARGIN_REL * e.e_x;
    return e;
}

/* The chords [left, right] of span e on the lines at heights dy (relative to the mean), or
   [+inf, -inf] where a line misses it. */
static inline void span_chords(const span_t *e, lanef dy, lanef *left, lanef *right) {
    const lanef q = e->two_la - e->det * dy * dy;
    const lanef h = sqrt(fmax(q, 0.f)) * e->inv_a, centre = e->slope * dy;
    *left = select(centre - h, (lanef)(INFINITY), q < 0.f);
    *right = select(centre + h, (lanef)(-INFINITY), q < 0.f);
}

/* The tiles [x0, x1) of the rows ty0 + l (lane l) of rect that span e reaches; [rect.x, rect.x)
   where it reaches none or the row is past rect. */
static inline void tile_spans(const span_t *e, int4 rect, int ty0, int tiles_x, lanei *x0, lanei *x1) {
    const lanei ty = ty0 + LANE_IDS;
    const lanei in_rect = ty < rect.w;
    if (e->whole) {
        *x0 = (lanei)(rect.x);
        *x1 = select((lanei)(rect.x), (lanei)(rect.z), in_rect);
        return;
    }
    const lanef top = CAT(convert_float, TILE)(ty * TILE) - e->my, bottom = top + TILE;
    lanef left, right, left_b, right_b;
    span_chords(e, top, &left, &right);
    span_chords(e, bottom, &left_b, &right_b);
    left = select(fmin(left, left_b), (lanef)(-e->e_x), (top <= e->dy_x) & (e->dy_x <= bottom));
    right = select(fmax(right, right_b), (lanef)(e->e_x), (top <= -e->dy_x) & (-e->dy_x <= bottom));
    /* Bounds broadcast to lanei, not max(lanei, int): oclgrind (21.10, and its source up to 26.03)
       reads lanes 1.. of the scalar argument of integer max/min/clamp past its end. */
    const lanei a = max(tile_indices(e->mx + left - e->margin, tiles_x), (lanei)(rect.x));
    const lanei b = min(tile_indices(e->mx + right + e->margin, tiles_x) + 1, (lanei)(rect.z));
    const lanei keep = in_rect & (left <= right) & (a < b);
    *x0 = select((lanei)(rect.x), a, keep);
    *x1 = select((lanei)(rect.x), b, keep);
}

/* A Gaussian's footprint (int16, 64 bytes, from project.cl; layout from the build, -D, as in
   qr_cl/runtime/constants.py): its tile rectangle [x0, y0, x1, y1) from int FOOTPRINT_RECT and,
   when spans_stored, the tiles [x0, x1) of its rows as SPAN_ROWS ushorts (x0 - rect x0) |
   (x1 - rect x0) << 8 from int FOOTPRINT_SPANS on. The binning passes read the footprints in depth
   order, gathered into one stream (gather_footprints). */
static inline int spans_stored(int4 rect) { return rect.w - rect.y <= SPAN_ROWS && rect.z - rect.x <= 255; }
/* The rectangle of footprint fp, and a pointer to its first span. */
#define FOOTPRINT_RECT_OF(fp) vload4(0, (__private const int *)&(fp) + FOOTPRINT_RECT)
#define FOOTPRINT_SPANS_OF(fp) ((__private const ushort *)((__private const int *)&(fp) + FOOTPRINT_SPANS))

/* for (each row ty of the rectangle of footprint fp of Gaussian g) { int2 x = its tiles [x0, x1);
   ... }: from the stored spans, or computed again from splats[g] (the same values). Needs splats
   and tiles_x in scope. */
#define FOR_TILE_SPANS(g, fp, ty, x, ...) \
    const int16 fp_ = (fp); \
    const int4 rect_ = FOOTPRINT_RECT_OF(fp_); \
    if (spans_stored(rect_)) { \
        for (int ty = rect_.y; ty < rect_.w; ty++) { \
            const int row_ = FOOTPRINT_SPANS_OF(fp_)[ty - rect_.y]; \
            const int2 x = rect_.x + (int2)(row_ & 0xff, row_ >> 8); \
            __VA_ARGS__ \
        } \
    } else { \
        const span_t span_ = span_of(splats[g]); \
        for (int ty0_ = rect_.y; ty0_ < rect_.w; ty0_ += TILE) { \
            lanei x0_, x1_; \
            tile_spans(&span_, rect_, ty0_, tiles_x, &x0_, &x1_); \
            for (int ty = ty0_; ty < min(ty0_ + TILE, rect_.w); ty++) { \
                const int2 x = (int2)(LANE_I(x0_, ty - ty0_), LANE_I(x1_, ty - ty0_)); \
                __VA_ARGS__ \
            } \
        } \
    }

/* Feature rows in vectors of VW floats (kernels built with -DVW=1, 2, 4, 8 or 16): vec_t,
   VLOAD(i, p) and VSTORE(v, i, p) load/store the i-th vector of row p. */
#ifdef VW
#if VW == 1
typedef float vec_t;
#define VLOAD(i, p) ((p)[i])
#define VSTORE_ANY(v, i, p) ((p)[i] = (v))
#define VSTORE(v, i, p) VSTORE_ANY(v, i, p)
#else
typedef CAT(float, VW) vec_t;
#define VLOAD(i, p) CAT(vload, VW)(i, p)
#define VSTORE_ANY(v, i, p) CAT(vstore, VW)(v, i, p)   /* any alignment */
/* A store through a vec_t pointer where the address is aligned to vec_t (rows and buffers
   normally are): PoCL's vstoreN of a float16 writes it as four 16-byte pieces. */
#define VSTORE(v, i, p) do { \
        __global vec_t *at_ = (__global vec_t *)((p) + (i) * VW); \
        if (((size_t)at_ & (sizeof(vec_t) - 1)) == 0) *at_ = (v); \
        else VSTORE_ANY(v, i, p); \
    } while (0)
#endif

/* Feature tables (the rows a blend reads, never its outputs) hold ROW_T elements: float, or half
   when built with -DHALF_ROWS (storage only: OpenCL C reads half rows with vload_half, a core
   function that needs no half arithmetic). RLOAD(i, p) loads the i-th vec_t of such a row as
   floats, exactly, so a half table blends as the float table of the same values. */
#ifdef HALF_ROWS
#define ROW_T half
#if VW == 1
#define RLOAD(i, p) vload_half(i, p)
#else
#define RLOAD(i, p) CAT(vload_half, VW)(i, p)
#endif
#else
#define ROW_T float
#define RLOAD(i, p) VLOAD(i, p)
#endif

/* VSTREAM(v, i, p): VSTORE of an output that the kernel does not read again, as a non-temporal
   store where the compiler offers one (clang's builtin) and the address is aligned to vec_t:
   the line is written without being read first (no read-for-ownership) and does not evict
   cached inputs. */
#if defined(__has_builtin)
#if __has_builtin(__builtin_nontemporal_store)
#define HAVE_NONTEMPORAL_STORE
#endif
#endif
#ifdef HAVE_NONTEMPORAL_STORE
#define VSTREAM(v, i, p) do { \
        __global vec_t *at_ = (__global vec_t *)((p) + (i) * VW); \
        if (((size_t)at_ & (sizeof(vec_t) - 1)) == 0) __builtin_nontemporal_store((v), at_); \
        else VSTORE_ANY(v, i, p); \
    } while (0)
#else
#define VSTREAM(v, i, p) VSTORE(v, i, p)
#endif

/* RV: the vectors of a row that a loop over entries accumulates at a time: the largest of 16, 8,
   4, 2, 1 that divides NV with RV * VW <= ACC_FLOATS (the floats the device keeps in registers,
   from the build), in fully unrolled loops so that the accumulators stay in registers. PoCL keeps
   an array of NV accumulators indexed in a loop on the stack: a load and a store of each per
   entry. RV changes no bytes; the budget follows the register file (on AVX2's 16 registers,
   16 float16 accumulators would spill). */
#ifdef NV
#if NV % 16 == 0 && 16 * VW <= ACC_FLOATS
#define RV 16
#elif NV % 8 == 0 && 8 * VW <= ACC_FLOATS
#define RV 8
#elif NV % 4 == 0 && 4 * VW <= ACC_FLOATS
#define RV 4
#elif NV % 2 == 0 && 2 * VW <= ACC_FLOATS
#define RV 2
#else
#define RV 1
#endif
#endif

/* out[c0, c0 + NV * VW) of one image row = (accumulate ? out : 0) + sum over the n entries
   (ids[j], w[j]) of w[j] features[ids[j] - row0, c0 ...] + tb * background[c0 ...] (the
   background only when use_bg), summed in float in entry order RV vectors at a time; written with
   VSTREAM when stream. features hold the rows [row0, row0 + n_rows) of a table (a row part of a
   table larger than one buffer; the whole table is row0 0, n_rows N): ids outside them are
   skipped. accumulate adds the part to what earlier parts wrote. */
static inline void blend_entries(__global const int *ids, __global const float *w, const int n,
                                 __global const ROW_T *features, const int row0, const int n_rows,
                                 const int cstride, const int c0, const float tb,
                                 __global const float *background, const int use_bg, const int accumulate,
                                 const int stream, __global float *out) {
    for (int v0 = 0; v0 < NV; v0 += RV) {
        const int c = c0 + v0 * VW;
        vec_t acc[RV];
        #pragma unroll
        for (int v = 0; v < RV; v++) acc[v] = accumulate ? VLOAD(v, out + c) : (vec_t)(0.f);
        for (int j = 0; j < n; j++) {
            const uint id = (uint)ids[j] - (uint)row0;     /* wraps below row0: skipped too */
            if (id >= (uint)n_rows) continue;
            const float wj = w[j];
            __global const ROW_T *row = features + (size_t)id * cstride + c;
            #pragma unroll
            for (int v = 0; v < RV; v++) acc[v] += wj * RLOAD(v, row);
        }
        #pragma unroll
        for (int v = 0; v < RV; v++) {
            const vec_t bg = use_bg ? VLOAD(v, background + c) : (vec_t)(0.f);
            if (stream) VSTREAM(acc[v] + tb * bg, v, out + c);
            else VSTORE(acc[v] + tb * bg, v, out + c);
        }
    }
}

/* The sum of the VW lanes of v. */
static inline float vec_sum(vec_t v) {
    float s = 0.f;
    for (int i = 0; i < VW; i++) s += ((__private float *)&v)[i];
    return s;
}
#endif

#endif
