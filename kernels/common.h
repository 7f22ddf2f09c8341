/* Shared math of the qr-cl kernels, in the original 3DGS conventions (see docs/design.md): the
   splat, e^-x, rays and walk windows. The other headers, each for one job, include it: lanes.h
   (rays or Gaussians in vector lanes), walk.h (the walks of a tile's list), spans.h (the tiles a
   splat reaches), rows.h (feature rows) and select.h (what the selection kernels share).

   The constants TILE (tile side in px), WALK_ALL (a window past every list), ALPHA_MIN (smaller
   alphas are skipped), ALPHA_MAX (alpha clamp), T_MIN (V-Render stops before T would drop to it),
   the SH basis constants SH_C0, SH_C1, SH_C2_0..4, SH_C3_0..6 and the layouts of the splat
   (SPLAT_*), the footprint (FOOTPRINT_*, SPAN_ROWS) and a selection's walk state (WALK_*) are
   defined by the build (-D), from qr_cl/runtime/constants.py; from the device, by Runtime:
   ACC_FLOATS (the floats of a row kept in registers, see RV in rows.h), GROUP_RAYS (the rays of
   a tile walk's work-group) and BLEND_GROUP (the work-items of a GPU blend's work-group). */
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

/* ---- walk windows: a walk split over launches ----

   A device whose driver ends long loops early (Runtime.loop_limit) walks the tile lists a window
   of positions per launch: a launch walks the positions [walk_from, walk_to) of each tile's list,
   and each ray's walk state waits between launches in the slots of a state buffer (a
   selection's: select.h), stored and loaded exactly, so a walk gives the same bytes in one launch
   or in many. A single launch walks [0, WALK_ALL) (from the build). The window that reaches the
   end of a list finishes its rays (writes their outputs); windows past the end do nothing. */
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

#endif
