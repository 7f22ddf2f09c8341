/* EWA projection, TILE Gaussians per work-item: lane l of the TILE-wide vectors (lanef, lanei
   of lanes.h) is Gaussian i0 + l, so the per-Gaussian math runs as SIMD code (PoCL does not
   vectorize this kernel across work-items).
   3DGS conventions, 0.3 px low-pass. */
#include "spans.h"

/* The largest radius stored in radii (px): a float beyond INT_MAX has no defined int value
   (INT_MIN on x86, saturated on GPUs), so the radii are clamped in float first. Same bound as
   RADIUS_MAX in qr_cl/stages/project_ref.py. */
#define RADIUS_MAX 1073741824.f

/* c = a b for row-major 3x3 matrices of any element types (scalars, lanes or a mix). */
#define MAT3_MUL(a, b, c) \
    for (int i_ = 0; i_ < 3; i_++) \
        for (int j_ = 0; j_ < 3; j_++) \
            (c)[3 * i_ + j_] = (a)[3 * i_] * (b)[j_] + (a)[3 * i_ + 1] * (b)[3 + j_] + (a)[3 * i_ + 2] * (b)[6 + j_]

/* The EWA terms of the Gaussians i0 + l (mean m, unit quaternion q = (w, x, y, z), scales s) seen
   by a camera, lane l each: p = W m + t (camera frame), R (rotation), M = R S, cov = W M M^T W^T
   (camera frame), the Jacobian J = [[j00, 0, j02], [0, j11, j12]] of the perspective projection
   with the view direction clamped to 1.3x the field of view (clamped_x/y set where it was), and
   the 2D covariance (c00, c01, c11) = J cov J^T plus the 0.3 px low-pass. Lanes past n repeat
   Gaussian n - 1. */
typedef struct {
    lanef px, py, pz;
    lanef r[9], ms[9], cov[9];
    lanef j00, j02, j11, j12;
    lanei clamped_x, clamped_y;
    lanef c00, c01, c11;
} ewa_t;

/* A lane of an ewa_t (the backward's scalar view, ewa_lane). */
typedef struct {
    float3 p;
    float r[9], ms[9], cov[9];
    float4 j;
    int2 clamped;
    float3 c;
} ewa1_t;

/* Lane l of the values v[i0 + l] of a float array (repeating v[n - 1] past n). */
static inline lanef load_lanes(__global const float *v, int stride, int i0, int n) {
    lanef out;
    for (int l = 0; l < TILE; l++) LANE(out, l) = v[(size_t)min(i0 + l, n - 1) * stride];
    return out;
}

static inline ewa_t ewa(int i0, int n, __global const float *means, __global const float *quats,
                        __global const float *scales, __global const float *viewmat, float fx, float fy,
                        float cx, float cy, int width, int height) {
    ewa_t e;
    const float w[9] = {viewmat[0], viewmat[1], viewmat[2], viewmat[4], viewmat[5], viewmat[6],
                        viewmat[8], viewmat[9], viewmat[10]};
    const float wt[9] = {w[0], w[3], w[6], w[1], w[4], w[7], w[2], w[5], w[8]};
    const lanef mx = load_lanes(means, 3, i0, n), my = load_lanes(means + 1, 3, i0, n),
                mz = load_lanes(means + 2, 3, i0, n);
    e.px = viewmat[0] * mx + viewmat[1] * my + viewmat[2] * mz + viewmat[3];
    e.py = viewmat[4] * mx + viewmat[5] * my + viewmat[6] * mz + viewmat[7];
    e.pz = viewmat[8] * mx + viewmat[9] * my + viewmat[10] * mz + viewmat[11];
    /* R of the unit quaternion, M = R S, Sigma = M M^T, then its camera-frame version W Sigma W^T. */
    const lanef qw = load_lanes(quats, 4, i0, n), qx = load_lanes(quats + 1, 4, i0, n),
                qy = load_lanes(quats + 2, 4, i0, n), qz = load_lanes(quats + 3, 4, i0, n);
    e.r[0] = 1.f - 2.f * (qy * qy + qz * qz); e.r[1] = 2.f * (qx * qy - qw * qz); e.r[2] = 2.f * (qx * qz + qw * qy);
    e.r[3] = 2.f * (qx * qy + qw * qz); e.r[4] = 1.f - 2.f * (qx * qx + qz * qz); e.r[5] = 2.f * (qy * qz - qw * qx);
    e.r[6] = 2.f * (qx * qz - qw * qy); e.r[7] = 2.f * (qy * qz + qw * qx); e.r[8] = 1.f - 2.f * (qx * qx + qy * qy);
    const lanef sc[3] = {load_lanes(scales, 3, i0, n), load_lanes(scales + 1, 3, i0, n),
                         load_lanes(scales + 2, 3, i0, n)};
    for (int k = 0; k < 9; k++) e.ms[k] = e.r[k] * sc[k % 3];
    lanef sigma[9], ws[9];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            sigma[3 * a + b] = e.ms[3 * a] * e.ms[3 * b] + e.ms[3 * a + 1] * e.ms[3 * b + 1]
                               + e.ms[3 * a + 2] * e.ms[3 * b + 2];
    MAT3_MUL(w, sigma, ws);
    MAT3_MUL(ws, wt, e.cov);

    /* EWA Jacobian with the view-direction clamp at 1.3x the field of view. */
    const float lim_xp = (width - cx) / fx + 0.3f * width / (2.f * fx);
    const float lim_xn = cx / fx + 0.3f * width / (2.f * fx);
    const float lim_yp = (height - cy) / fy + 0.3f * height / (2.f * fy);
    const float lim_yn = cy / fy + 0.3f * height / (2.f * fy);
    const lanef ux = e.px / e.pz, uy = e.py / e.pz;
    e.clamped_x = ~((ux >= -lim_xn) & (ux <= lim_xp));
    e.clamped_y = ~((uy >= -lim_yn) & (uy <= lim_yp));
    const lanef tx = e.pz * clamp(ux, -lim_xn, lim_xp), ty = e.pz * clamp(uy, -lim_yn, lim_yp);
    e.j00 = fx / e.pz; e.j02 = -fx * tx / (e.pz * e.pz); e.j11 = fy / e.pz; e.j12 = -fy * ty / (e.pz * e.pz);
    /* cov2d = J cov J^T, plus the 0.3 px low-pass. */
    const lanef *cov = e.cov;
    e.c00 = e.j00 * (e.j00 * cov[0] + e.j02 * cov[2]) + e.j02 * (e.j00 * cov[6] + e.j02 * cov[8]) + 0.3f;
    e.c01 = e.j00 * (e.j11 * cov[1] + e.j12 * cov[2]) + e.j02 * (e.j11 * cov[7] + e.j12 * cov[8]);
    e.c11 = e.j11 * (e.j11 * cov[4] + e.j12 * cov[5]) + e.j12 * (e.j11 * cov[7] + e.j12 * cov[8]) + 0.3f;
    return e;
}

/* Lane l of e into *s (through a pointer: a struct of this size returned by value made LLVM emit
   llvm.experimental.noalias.scope.decl when inlining, which Debian's oclgrind cannot run). */
static inline void ewa_lane(const ewa_t *e, int l, ewa1_t *s) {
    s->p = (float3)(LANE(e->px, l), LANE(e->py, l), LANE(e->pz, l));
    for (int k = 0; k < 9; k++) {
        s->r[k] = LANE(e->r[k], l);
        s->ms[k] = LANE(e->ms[k], l);
        s->cov[k] = LANE(e->cov[k], l);
    }
    s->j = (float4)(LANE(e->j00, l), LANE(e->j02, l), LANE(e->j11, l), LANE(e->j12, l));
    s->clamped = (int2)(LANE_I(e->clamped_x, l) != 0, LANE_I(e->clamped_y, l) != 0);
    s->c = (float3)(LANE(e->c00, l), LANE(e->c01, l), LANE(e->c11, l));
}

/* The tiles touched by splat s in rect: those of each row that the blend ellipse reaches
   (tile_spans in spans.h), written to rows where they fit (spans_stored). A single tile has
   nothing to cull (the twin agrees). */
static inline int touched_tiles(float8 s, int4 rect, int tiles_x, ushort *rows) {
    if ((rect.z - rect.x) * (rect.w - rect.y) == 1) {
        rows[0] = 1 << 8;
        return 1;
    }
    const span_t span = span_of(s);
    const int store = spans_stored(rect);
    int touched = 0;
    for (int ty0 = rect.y; ty0 < rect.w; ty0 += TILE) {
        lanei x0, x1;
        tile_spans(&span, rect, ty0, tiles_x, &x0, &x1);
        touched += lanes_sum(x1 - x0);
        for (int r = ty0 - rect.y; store && r < min(SPAN_ROWS, ty0 + TILE - rect.y); r++) {
            const int l = r - (ty0 - rect.y);
            rows[r] = (ushort)((LANE_I(x0, l) - rect.x) | (LANE_I(x1, l) - rect.x) << 8);
        }
    }
    return touched;
}

/* Outputs per Gaussian: splat (mean2d, conic, opacity, depth and sigma_max; common.h),
   radii (x, y) in pixels (the half-sides of the opacity-aware box it is binned within, at most
   the 3-sigma radius; (0, 0) = culled), footprint (spans.h: the tile rectangle [x0, y0, x1, y1)
   and its rows' tile spans), tiles touched (the tiles of those spans) and its depth key (the bits
   of its positive float depth, which order as the depths do; INT_MAX, past all of them, when
   culled).
   Work-item g projects the Gaussians [g TILE, (g + 1) TILE). */
__kernel void project(const int n,
                      __global const float *means,      /* [N,3] world */
                      __global const float *quats,      /* [N,4] unit w,x,y,z */
                      __global const float *scales,     /* [N,3] activated */
                      __global const float *opacities,  /* [N] activated */
                      __global const float *viewmat,    /* [16] world-to-camera, row-major */
                      const float fx, const float fy, const float cx, const float cy,
                      const int width, const int height, const float near, const float far,
                      const int tiles_x, const int tiles_y,
                      __global float8 *splats, __global int2 *radii,
                      __global int16 *footprints, __global int *tiles_touched,
                      __global int *depth_keys) {
    const int i0 = get_global_id(0) * TILE;
    if (i0 >= n) return;
    const ewa_t e = ewa(i0, n, means, quats, scales, viewmat, fx, fy, cx, cy, width, height);
    const lanef c00 = e.c00, c01 = e.c01, c11 = e.c11;
    const lanef det = c00 * c11 - c01 * c01, inv = 1.f / det;

    /* Radius from the largest eigenvalue, then the [x0, x1) x [y0, y1) tile rectangle. */
    const lanef mid = 0.5f * (c00 + c11);
    /* mid * mid - det (3DGS's discriminant) overflows in float32 for 2D variances above ~1e19 px^2:
       then the same root, ((c00 - c11) / 2)^2 + c01^2, without squaring mid (so the radius stays
       finite, as in the float64 twin). fmax, not max: max is undefined for infinite arguments. */
    const lanef disc = mid * mid - det;
    const lanef lambda1 = mid + select(hypot(0.5f * (c00 - c11), c01), sqrt(fmax(disc, 0.1f)), isfinite(disc));
    const lanef radius = ceil(3.f * sqrt(lambda1));
    const lanef mean_x = fx * e.px / e.pz + cx, mean_y = fy * e.py / e.pz + cy;
    /* Opacity-aware extent: a pixel is blended only where opacity exp(-sigma) >= ALPHA_MIN, i.e.
       sigma <= sigma_max = ln(opacity / ALPHA_MIN), inside the ellipse d^T Sigma^-1 d <= 2 sigma_max
       whose bounding box has half-sides sqrt(2 sigma_max Sigma_xx) and sqrt(2 sigma_max Sigma_yy).
       Tiles are binned within that box (rounded up, plus a pixel against float rounding) where it
       is smaller than the 3-sigma square: the same pixels are blended, from fewer tile lists. */
    const lanef opacity = load_lanes(opacities, 1, i0, n);
    const lanef sigma_max = log(opacity / ALPHA_MIN);
    const lanef ext_x = fmin(radius, ceil(sqrt(2.f * sigma_max * c00)) + 1.f);
    const lanef ext_y = fmin(radius, ceil(sqrt(2.f * sigma_max * c11)) + 1.f);
    const lanei x0 = tile_indices(mean_x - ext_x, tiles_x), y0 = tile_indices(mean_y - ext_y, tiles_y);
    const lanei x1 = tile_indices(mean_x + ext_x + TILE - 1, tiles_x);
    const lanei y1 = tile_indices(mean_y + ext_y + TILE - 1, tiles_y);
    /* Culled: outside [near, far], a 2D covariance that is not positive definite, a mean projected
       beyond FLT_MAX px, or an opacity below ALPHA_MIN (never blended); or no tile touched below. */
    const lanei visible = ~((e.pz < near) | (e.pz > far)) & (det > 0.f) & isfinite(mean_x) & isfinite(mean_y)
                          & (opacity >= ALPHA_MIN);

    for (int l = 0; l < TILE && i0 + l < n; l++) {
        const int i = i0 + l;
        const int4 rect = (int4)(LANE_I(x0, l), LANE_I(y0, l), LANE_I(x1, l), LANE_I(y1, l));
        float8 splat = (float8)(0.f);
        splat.SPLAT_MEAN = (float2)(LANE(mean_x, l), LANE(mean_y, l));
        splat.SPLAT_CONIC = (float3)(LANE(c11, l) * LANE(inv, l), -LANE(c01, l) * LANE(inv, l),
                                     LANE(c00, l) * LANE(inv, l));
        splat.SPLAT_OPACITY = LANE(opacity, l);
        splat.SPLAT_DEPTH = LANE(e.pz, l);
        splat.SPLAT_SIGMA_MAX = LANE(sigma_max, l);
        ushort rows[SPAN_ROWS] = {0};
        const int touched = LANE_I(visible, l) ? touched_tiles(splat, rect, tiles_x, rows) : 0;
        if (touched <= 0) {
            splats[i] = (float8)(0.f);
            radii[i] = (int2)(0);
            footprints[i] = (int16)(0);
            tiles_touched[i] = 0;
            depth_keys[i] = INT_MAX;
            continue;
        }
        splats[i] = splat;
        radii[i] = (int2)((int)fmin(LANE(ext_x, l), RADIUS_MAX), (int)fmin(LANE(ext_y, l), RADIUS_MAX));
        __global int *footprint = (__global int *)(footprints + i);
        vstore4(rect, 0, footprint + FOOTPRINT_RECT);
        for (int k = 0; k < SPAN_ROWS / 8; k++)
            vstore8(vload8(k, rows), k, (__global ushort *)(footprint + FOOTPRINT_SPANS));
        tiles_touched[i] = touched;
        depth_keys[i] = as_int(LANE(e.pz, l));
    }
}

/* The backward of Gaussian i (project_backward) from its EWA terms e; d_views[i] its share of the
   viewmat's gradient when view_grads. */
static inline void gaussian_backward(int i, const ewa1_t *e_, __global const float *means,
                                     __global const float *scales, __global const float *quats,
                                     __global const float *viewmat, float fx, float fy,
                                     __global const int2 *radii, __global const float8 *d_splats,
                                     __global float *d_means, __global float4 *d_quats,
                                     __global float *d_scales, const int view_grads, __global float *d_views) {
    vstore3((float3)(0.f), i, d_means);
    vstore3((float3)(0.f), i, d_scales);
    d_quats[i] = (float4)(0.f);
    if (view_grads)
        for (int k = 0; k < 12; k++) d_views[12 * i + k] = 0.f;
    if (radii[i].x == 0) return;
    const float3 sc = vload3(i, scales);
    const float4 q = vload4(i, quats);
    const ewa1_t e = *e_;
    const float8 d = d_splats[i];

    /* conic (A, B, C) = inverse of [[a, b], [b, c]] -> d (a, b, c) */
    const float det = e.c.x * e.c.z - e.c.y * e.c.y;
    const float A = e.c.z / det, B = -e.c.y / det, C = e.c.x / det;
    const float dA = d.SPLAT_CONIC_A, dB = d.SPLAT_CONIC_B, dC = d.SPLAT_CONIC_C;
    const float ga = -(dA * A * A + dB * A * B + dC * B * B);
    const float gb = -(2.f * dA * A * B + dB * (A * C + B * B) + 2.f * dC * B * C);
    const float gc = -(dA * B * B + dB * B * C + dC * C * C);

    /* cov2d = J cov J^T with rows J0 = (j00, 0, j02), J1 = (0, j11, j12) */
    const float3 J0 = (float3)(e.j.x, 0.f, e.j.y), J1 = (float3)(0.f, e.j.z, e.j.w);
    const float *cov = e.cov;
    const float3 v0 = (float3)(dot(vload3(0, cov), J0), dot(vload3(1, cov), J0), dot(vload3(2, cov), J0));
    const float3 v1 = (float3)(dot(vload3(0, cov), J1), dot(vload3(1, cov), J1), dot(vload3(2, cov), J1));
    const float3 dJ0 = 2.f * ga * v0 + gb * v1, dJ1 = 2.f * gc * v1 + gb * v0;
    float dcov[9];                      /* ga J0 J0^T + gb (J0 J1^T + J1 J0^T) / 2 + gc J1 J1^T */
    const float j0[3] = {J0.x, J0.y, J0.z}, j1[3] = {J1.x, J1.y, J1.z};
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            dcov[3 * a + b] = ga * j0[a] * j0[b] + 0.5f * gb * (j0[a] * j1[b] + j1[a] * j0[b]) + gc * j1[a] * j1[b];

    /* cov = W Sigma W^T, Sigma = M M^T, M = R S */
    float w[9] = {viewmat[0], viewmat[1], viewmat[2], viewmat[4], viewmat[5], viewmat[6],
                  viewmat[8], viewmat[9], viewmat[10]};
    float wt[9] = {w[0], w[3], w[6], w[1], w[4], w[7], w[2], w[5], w[8]}, tmp[9], dsigma[9], dm[9];
    MAT3_MUL(wt, dcov, tmp);
    MAT3_MUL(tmp, w, dsigma);
    MAT3_MUL(dsigma, e.ms, dm);
    float dr[9];
    float3 ds = (float3)(0.f);
    for (int row = 0; row < 3; row++) {
        ds += 2.f * (float3)(dm[3 * row] * e.r[3 * row], dm[3 * row + 1] * e.r[3 * row + 1],
                             dm[3 * row + 2] * e.r[3 * row + 2]);
        dr[3 * row] = 2.f * dm[3 * row] * sc.x;
        dr[3 * row + 1] = 2.f * dm[3 * row + 1] * sc.y;
        dr[3 * row + 2] = 2.f * dm[3 * row + 2] * sc.z;
    }
    vstore3(ds, i, d_scales);
    /* R(q) of ewa, q = (w, x, y, z) */
    const float qw = q.x, qx = q.y, qy = q.z, qz = q.w;
    d_quats[i] = 2.f * (float4)(
        -qz * dr[1] + qy * dr[2] + qz * dr[3] - qx * dr[5] - qy * dr[6] + qx * dr[7],
        qy * dr[1] + qz * dr[2] + qy * dr[3] - 2.f * qx * dr[4] - qw * dr[5] + qz * dr[6] + qw * dr[7]
            - 2.f * qx * dr[8],
        -2.f * qy * dr[0] + qx * dr[1] + qw * dr[2] + qx * dr[3] + qz * dr[5] - qw * dr[6] + qz * dr[7]
            - 2.f * qy * dr[8],
        -2.f * qz * dr[0] - qw * dr[1] + qx * dr[2] + qw * dr[3] - 2.f * qz * dr[4] + qy * dr[5]
            + qx * dr[6] + qy * dr[7]);

    /* J = [[fx / z, 0, -fx tx / z^2], [0, fy / z, -fy ty / z^2]], t = z clamp(x / z) (= x unclamped),
       mean2d and the depth z -> d p */
    const float3 p = e.p;
    const float z2 = p.z * p.z, tx = -e.j.y * z2 / fx, ty = -e.j.w * z2 / fy;
    const float dtx = -dJ0.z * fx / z2, dty = -dJ1.z * fy / z2;
    const float dmx = d.SPLAT_MEAN_X, dmy = d.SPLAT_MEAN_Y;
    float3 dp = (float3)(dmx * fx / p.z, dmy * fy / p.z,
                         d.SPLAT_DEPTH - dJ0.x * fx / z2 + 2.f * dJ0.z * fx * tx / (z2 * p.z) - dJ1.y * fy / z2
                         + 2.f * dJ1.z * fy * ty / (z2 * p.z) - (dmx * fx * p.x + dmy * fy * p.y) / z2);
    if (e.clamped.x) dp.z += dtx * tx / p.z; else dp.x += dtx;
    if (e.clamped.y) dp.z += dty * ty / p.z; else dp.y += dty;
    vstore3((float3)(wt[0] * dp.x + wt[1] * dp.y + wt[2] * dp.z, wt[3] * dp.x + wt[4] * dp.y + wt[5] * dp.z,
                     wt[6] * dp.x + wt[7] * dp.y + wt[8] * dp.z), i, d_means);
    if (!view_grads) return;
    /* p = W m + t and cov = W Sigma W^T (Sigma = M M^T): d W = d p m^T + 2 d cov W Sigma (d cov and
       Sigma symmetric), d t = d p; row-major [d W | d t] per Gaussian, summed by the host. */
    float sigma[9], w_sigma[9], dw[9];
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            sigma[3 * a + b] = e.ms[3 * a] * e.ms[3 * b] + e.ms[3 * a + 1] * e.ms[3 * b + 1]
                               + e.ms[3 * a + 2] * e.ms[3 * b + 2];
    MAT3_MUL(w, sigma, w_sigma);
    MAT3_MUL(dcov, w_sigma, dw);
    const float3 m = vload3(i, means);
    const float dpa[3] = {dp.x, dp.y, dp.z}, ma[3] = {m.x, m.y, m.z};
    for (int a = 0; a < 3; a++) {
        for (int b = 0; b < 3; b++) d_views[12 * i + 3 * a + b] = dpa[a] * ma[b] + 2.f * dw[3 * a + b];
        d_views[12 * i + 9 + a] = dpa[a];
    }
}

/* Backward of the projection, TILE Gaussians per work-item (as project): d_splats[i] = the gradient
   of the splat's mean2d, conic and depth (its opacity and sigma_max are not read: the opacity
   passes the projection unchanged) ->
   d means [N,3], d quats [N,4] (of the unit-quaternion formula), d scales [N,3] and, when
   view_grads, each Gaussian's share of d viewmat, d_views [N,12] (rows 0..2 of the 3x4 [W | t]).
   Culled Gaussians (radii 0) get zeros. The chain, with c = (a, b, c) the 2D covariance and
   (A, B, C) its inverse:
     conic:  dc = -(inverse) d(inverse) (inverse), per entry below;
     cov2d = J cov J^T:  d cov = J^T dc J, d J rows = 2 dc J cov (dc symmetric);
     cov = W M M^T W^T, M = R S:  d M = 2 W^T d cov W M, d s_k = sum_i dM_ik R_ik, dR_ik = dM_ik s_k;
     J(p), mean2d = (fx x / z + cx, fy y / z + cy) and depth = z:  d p, then d means = W^T d p;
     p = W m + t:  d W += d p m^T, d t = d p; cov:  d W += 2 d cov W M M^T. */
__kernel void project_backward(const int n, __global const float *means, __global const float *quats,
                               __global const float *scales, __global const float *viewmat,
                               const float fx, const float fy, const float cx, const float cy,
                               const int width, const int height, __global const int2 *radii,
                               __global const float8 *d_splats,
                               __global float *d_means, __global float4 *d_quats,
                               __global float *d_scales, const int view_grads,
                               __global float *d_views) {   /* [N,12] when view_grads */
    const int i0 = get_global_id(0) * TILE;
    if (i0 >= n) return;
    const ewa_t lanes = ewa(i0, n, means, quats, scales, viewmat, fx, fy, cx, cy, width, height);
    for (int l = 0; l < TILE && i0 + l < n; l++) {
        ewa1_t e;
        ewa_lane(&lanes, l, &e);
        gaussian_backward(i0 + l, &e, means, scales, quats, viewmat, fx, fy, radii, d_splats,
                          d_means, d_quats, d_scales, view_grads, d_views);
    }
}
