/* The tiles a splat reaches: its tile spans (project.cl computes them, binning.cl reads them)
   and the footprint that stores them. */
#ifndef QR_CL_SPANS_H
#define QR_CL_SPANS_H
#include "lanes.h"

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

#endif
