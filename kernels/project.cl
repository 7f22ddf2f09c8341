/* EWA projection: one work-item per Gaussian (3DGS conventions, 0.3 px low-pass). */
#include "common.h"

/* The largest radius stored in radii (px): a float beyond INT_MAX has no defined int value
   (INT_MIN on x86, saturated on GPUs), so the radius is clamped in float first. Same bound as
   RADIUS_MAX in qr_cl/stages/project_ref.py. */
#define RADIUS_MAX 1073741824.f

/* The EWA terms of one Gaussian (mean m, unit quaternion q, scales sc) seen by a camera:
   p = W m + t (camera frame), R (rotation), M = R S, cov = W M M^T W^T (camera frame), the
   Jacobian J = [[j.x, 0, j.y], [0, j.z, j.w]] of the perspective projection with the view
   direction clamped to 1.3x the field of view (clamped.x/y set where it was), and the 2D
   covariance c = (c00, c01, c11) = J cov J^T plus the 0.3 px low-pass. */
typedef struct {
    float3 p;
    float r[9], ms[9], cov[9];
    float4 j;
    int2 clamped;
    float3 c;
} ewa_t;

static inline ewa_t ewa(float3 m, float4 q, float3 sc, __global const float *viewmat, float fx, float fy,
                        float cx, float cy, int width, int height) {
    ewa_t e;
    e.p = (float3)(viewmat[0] * m.x + viewmat[1] * m.y + viewmat[2] * m.z + viewmat[3],
                   viewmat[4] * m.x + viewmat[5] * m.y + viewmat[6] * m.z + viewmat[7],
                   viewmat[8] * m.x + viewmat[9] * m.y + viewmat[10] * m.z + viewmat[11]);
    /* Sigma = R S S^T R^T, then its camera-frame version W Sigma W^T. */
    float sigma[9], w[9] = {viewmat[0], viewmat[1], viewmat[2], viewmat[4], viewmat[5], viewmat[6],
                            viewmat[8], viewmat[9], viewmat[10]};
    quat_to_rotmat(q, e.r);
    for (int row = 0; row < 3; row++) {
        e.ms[3 * row] = e.r[3 * row] * sc.x;
        e.ms[3 * row + 1] = e.r[3 * row + 1] * sc.y;
        e.ms[3 * row + 2] = e.r[3 * row + 2] * sc.z;
    }
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            sigma[3 * a + b] = e.ms[3 * a] * e.ms[3 * b] + e.ms[3 * a + 1] * e.ms[3 * b + 1]
                               + e.ms[3 * a + 2] * e.ms[3 * b + 2];
    float ws[9], wt[9] = {w[0], w[3], w[6], w[1], w[4], w[7], w[2], w[5], w[8]};
    mat3_mul(w, sigma, ws);
    mat3_mul(ws, wt, e.cov);

    /* EWA Jacobian with the view-direction clamp at 1.3x the field of view. */
    const float3 p = e.p;
    const float lim_xp = (width - cx) / fx + 0.3f * width / (2.f * fx);
    const float lim_xn = cx / fx + 0.3f * width / (2.f * fx);
    const float lim_yp = (height - cy) / fy + 0.3f * height / (2.f * fy);
    const float lim_yn = cy / fy + 0.3f * height / (2.f * fy);
    const float ux = p.x / p.z, uy = p.y / p.z;
    e.clamped = (int2)(!(ux >= -lim_xn && ux <= lim_xp), !(uy >= -lim_yn && uy <= lim_yp));
    const float tx = p.z * clamp(ux, -lim_xn, lim_xp), ty = p.z * clamp(uy, -lim_yn, lim_yp);
    e.j = (float4)(fx / p.z, -fx * tx / (p.z * p.z), fy / p.z, -fy * ty / (p.z * p.z));
    /* cov2d = J cov J^T, plus the 0.3 px low-pass. */
    const float j00 = e.j.x, j02 = e.j.y, j11 = e.j.z, j12 = e.j.w;
    const float *cov = e.cov;
    e.c = (float3)(j00 * (j00 * cov[0] + j02 * cov[2]) + j02 * (j00 * cov[6] + j02 * cov[8]) + 0.3f,
                   j00 * (j11 * cov[1] + j12 * cov[2]) + j02 * (j11 * cov[7] + j12 * cov[8]),
                   j11 * (j11 * cov[4] + j12 * cov[5]) + j12 * (j11 * cov[7] + j12 * cov[8]) + 0.3f);
    return e;
}

/* Outputs per Gaussian: splat = (mean2d.x, mean2d.y, conic a, b, c, opacity, depth, sigma_max),
   radius in pixels (0 = culled), footprint (common.h: the tile rectangle [x0, y0, x1, y1) and its
   rows' tile spans) and tiles touched (the tiles of those spans). */
__kernel void project(const int n,
                      __global const float *means,      /* [N,3] world */
                      __global const float4 *quats,     /* [N] unit w,x,y,z */
                      __global const float *scales,     /* [N,3] activated */
                      __global const float *opacities,  /* [N] activated */
                      __global const float *viewmat,    /* [16] world-to-camera, row-major */
                      const float fx, const float fy, const float cx, const float cy,
                      const int width, const int height, const float near, const float far,
                      const int tiles_x, const int tiles_y,
                      __global float8 *splats, __global int *radii,
                      __global int16 *footprints, __global int *tiles_touched) {
    const int i = get_global_id(0);
    if (i >= n) return;
    radii[i] = 0;
    tiles_touched[i] = 0;
    footprints[i] = (int16)(0);
    splats[i] = (float8)(0.f);

    const ewa_t e = ewa(vload3(i, means), quats[i], vload3(i, scales), viewmat, fx, fy, cx, cy, width, height);
    const float3 p = e.p;
    if (p.z < near || p.z > far) return;  /* near/far culling */
    const float c00 = e.c.x, c01 = e.c.y, c11 = e.c.z;
    float det = c00 * c11 - c01 * c01;
    if (!(det > 0.f)) return;
    float inv = 1.f / det;

    /* Radius from the largest eigenvalue, then the [x0, x1) x [y0, y1) tile rectangle. */
    float mid = 0.5f * (c00 + c11);
    /* mid * mid - det (3DGS's discriminant) overflows in float32 for 2D variances above ~1e19 px^2:
       then the same root, ((c00 - c11) / 2)^2 + c01^2, without squaring mid (so the radius stays
       finite, as in the float64 twin). fmax, not max: max is undefined for infinite arguments. */
    float disc = mid * mid - det;
    float lambda1 = mid + (isfinite(disc) ? sqrt(fmax(0.1f, disc)) : hypot(0.5f * (c00 - c11), c01));
    float radius = ceil(3.f * sqrt(lambda1));
    float2 mean2d = (float2)(fx * p.x / p.z + cx, fy * p.y / p.z + cy);
    if (!(isfinite(mean2d.x) && isfinite(mean2d.y))) return;   /* projects beyond FLT_MAX px */
    /* Opacity-aware extent: a pixel is blended only where opacity exp(-sigma) >= ALPHA_MIN, i.e.
       sigma <= sigma_max = ln(opacity / ALPHA_MIN), inside the ellipse d^T Sigma^-1 d <= 2 sigma_max
       whose bounding box has half-sides sqrt(2 sigma_max Sigma_xx) and sqrt(2 sigma_max Sigma_yy).
       Tiles are binned within that box (rounded up, plus a pixel against float rounding) where it
       is smaller than the 3-sigma square: the same pixels are blended, from fewer tile lists. */
    const float opacity = opacities[i];
    if (!(opacity >= ALPHA_MIN)) return;                        /* never blended */
    const float sigma_max = log(opacity / ALPHA_MIN);
    const float2 ext = fmin((float2)(radius), ceil(sqrt(2.f * sigma_max * (float2)(c00, c11))) + 1.f);
    int4 rect = (int4)(tile_index(mean2d.x - ext.x, tiles_x), tile_index(mean2d.y - ext.y, tiles_y),
                       tile_index(mean2d.x + ext.x + TILE - 1, tiles_x),
                       tile_index(mean2d.y + ext.y + TILE - 1, tiles_y));
    const float8 splat = (float8)(mean2d.x, mean2d.y, c11 * inv, -c01 * inv, c00 * inv, opacity, p.z, sigma_max);
    /* Tiles touched: those of each row that the blend ellipse reaches (tile_spans in common.h),
       stored for the binning passes where they fit (spans_stored). A single tile has nothing to
       cull (the twin agrees). */
    ushort rows[SPAN_ROWS] = {0};
    int touched = 1;
    if ((rect.z - rect.x) * (rect.w - rect.y) == 1) {
        rows[0] = 1 << 8;
    } else {
        const span_t span = span_of(splat);
        const int store = spans_stored(rect);
        touched = 0;
        for (int ty0 = rect.y; ty0 < rect.w; ty0 += TILE) {
            lanei x0, x1;
            tile_spans(&span, rect, ty0, tiles_x, &x0, &x1);
            touched += lanes_sum(x1 - x0);
            for (int r = ty0 - rect.y; store && r < min(SPAN_ROWS, ty0 + TILE - rect.y); r++) {
                const int l = r - (ty0 - rect.y);
                rows[r] = (ushort)((LANE_I(x0, l) - rect.x) | (LANE_I(x1, l) - rect.x) << 8);
            }
        }
    }
    if (touched <= 0) return;

    splats[i] = splat;
    radii[i] = (int)fmin(radius, RADIUS_MAX);
    __global int *footprint = (__global int *)(footprints + i);
    vstore4(rect, 0, footprint);
    for (int k = 0; k < SPAN_ROWS / 8; k++) vstore8(vload8(k, rows), k, (__global ushort *)(footprint + 4));
    tiles_touched[i] = touched;
}

/* Backward of the projection, one work-item per Gaussian: d_splats[i] = (d mean2d x, y, d conic
   A, B, C, d opacity, ...) (from blend.cl's splat_backward) -> d means [N,3], d quats [N,4] (of
   the unit-quaternion formula), d scales [N,3], d opacities [N]. Culled Gaussians (radius 0) get
   zeros. The chain, with c = (a, b, c) the 2D covariance and (A, B, C) its inverse:
     conic:  dc = -(inverse) d(inverse) (inverse), per entry below;
     cov2d = J cov J^T:  d cov = J^T dc J, d J rows = 2 dc J cov (dc symmetric);
     cov = W M M^T W^T, M = R S:  d M = 2 W^T d cov W M, d s_k = sum_i dM_ik R_ik, dR_ik = dM_ik s_k;
     J(p) and mean2d = (fx x / z + cx, fy y / z + cy):  d p, then d means = W^T d p. */
__kernel void project_backward(const int n, __global const float *means, __global const float4 *quats,
                               __global const float *scales, __global const float *viewmat,
                               const float fx, const float fy, const float cx, const float cy,
                               const int width, const int height, __global const int *radii,
                               __global const float8 *d_splats,
                               __global float *d_means, __global float4 *d_quats,
                               __global float *d_scales, __global float *d_opacities) {
    const int i = get_global_id(0);
    if (i >= n) return;
    vstore3((float3)(0.f), i, d_means);
    vstore3((float3)(0.f), i, d_scales);
    d_quats[i] = (float4)(0.f);
    d_opacities[i] = 0.f;
    if (radii[i] == 0) return;
    const float3 sc = vload3(i, scales);
    const float4 q = quats[i];
    const ewa_t e = ewa(vload3(i, means), q, sc, viewmat, fx, fy, cx, cy, width, height);
    const float8 d = d_splats[i];
    d_opacities[i] = d.s5;

    /* conic (A, B, C) = inverse of [[a, b], [b, c]] -> d (a, b, c) */
    const float det = e.c.x * e.c.z - e.c.y * e.c.y;
    const float A = e.c.z / det, B = -e.c.y / det, C = e.c.x / det;
    const float ga = -(d.s2 * A * A + d.s3 * A * B + d.s4 * B * B);
    const float gb = -(2.f * d.s2 * A * B + d.s3 * (A * C + B * B) + 2.f * d.s4 * B * C);
    const float gc = -(d.s2 * B * B + d.s3 * B * C + d.s4 * C * C);

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
    mat3_mul(wt, dcov, tmp);
    mat3_mul(tmp, w, dsigma);
    mat3_mul(dsigma, e.ms, dm);
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
    /* R(q) of quat_to_rotmat, q = (w, x, y, z) */
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
       and mean2d -> d p */
    const float3 p = e.p;
    const float z2 = p.z * p.z, tx = -e.j.y * z2 / fx, ty = -e.j.w * z2 / fy;
    const float dtx = -dJ0.z * fx / z2, dty = -dJ1.z * fy / z2;
    float3 dp = (float3)(d.s0 * fx / p.z, d.s1 * fy / p.z,
                         -dJ0.x * fx / z2 + 2.f * dJ0.z * fx * tx / (z2 * p.z) - dJ1.y * fy / z2
                         + 2.f * dJ1.z * fy * ty / (z2 * p.z) - (d.s0 * fx * p.x + d.s1 * fy * p.y) / z2);
    if (e.clamped.x) dp.z += dtx * tx / p.z; else dp.x += dtx;
    if (e.clamped.y) dp.z += dty * ty / p.z; else dp.y += dty;
    vstore3((float3)(wt[0] * dp.x + wt[1] * dp.y + wt[2] * dp.z, wt[3] * dp.x + wt[4] * dp.y + wt[5] * dp.z,
                     wt[6] * dp.x + wt[7] * dp.y + wt[8] * dp.z), i, d_means);
}
