/* EWA projection: one work-item per Gaussian (3DGS conventions, 0.3 px low-pass). */
#include "common.h"

/* The largest radius stored in radii (px): a float beyond INT_MAX has no defined int value
   (INT_MIN on x86, saturated on GPUs), so the radius is clamped in float first. Same bound as
   RADIUS_MAX in qr_cl/stages/project_ref.py. */
#define RADIUS_MAX 1073741824.f

/* Tile index of pixel coordinate v clamped to [0, tiles], clamped in float before the
   conversion (out-of-range conversions are undefined); fmax/fmin map NaN to the bound. Truncates
   toward zero like the (int) conversion it replaces. */
static inline int tile_index(float v, int tiles) {
    return (int)fmin(fmax(v / TILE, 0.f), (float)tiles);
}

/* Outputs per Gaussian: splat = (mean2d.x, mean2d.y, conic a, b, c, opacity, depth, sigma_max),
   radius in pixels (0 = culled), tile rectangle [x0, y0, x1, y1) and tiles touched. */
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
                      __global int4 *rects, __global int *tiles_touched) {
    const int i = get_global_id(0);
    if (i >= n) return;
    radii[i] = 0;
    tiles_touched[i] = 0;
    rects[i] = (int4)(0);
    splats[i] = (float8)(0.f);

    float3 m = vload3(i, means);
    float3 p = (float3)(viewmat[0] * m.x + viewmat[1] * m.y + viewmat[2] * m.z + viewmat[3],
                        viewmat[4] * m.x + viewmat[5] * m.y + viewmat[6] * m.z + viewmat[7],
                        viewmat[8] * m.x + viewmat[9] * m.y + viewmat[10] * m.z + viewmat[11]);
    if (p.z < near || p.z > far) return;  /* near/far culling */

    /* Sigma = R S S^T R^T, then its camera-frame version W Sigma W^T. */
    float r[9], ms[9], sigma[9], w[9] = {viewmat[0], viewmat[1], viewmat[2], viewmat[4], viewmat[5],
                                          viewmat[6], viewmat[8], viewmat[9], viewmat[10]};
    quat_to_rotmat(quats[i], r);
    float3 s = vload3(i, scales);
    for (int row = 0; row < 3; row++) {
        ms[3 * row] = r[3 * row] * s.x;
        ms[3 * row + 1] = r[3 * row + 1] * s.y;
        ms[3 * row + 2] = r[3 * row + 2] * s.z;
    }
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++)
            sigma[3 * a + b] = ms[3 * a] * ms[3 * b] + ms[3 * a + 1] * ms[3 * b + 1] + ms[3 * a + 2] * ms[3 * b + 2];
    float ws[9], cov[9], wt[9] = {w[0], w[3], w[6], w[1], w[4], w[7], w[2], w[5], w[8]};
    mat3_mul(w, sigma, ws);
    mat3_mul(ws, wt, cov);

    /* EWA Jacobian with the view-direction clamp at 1.3x the field of view. */
    float lim_xp = (width - cx) / fx + 0.3f * width / (2.f * fx);
    float lim_xn = cx / fx + 0.3f * width / (2.f * fx);
    float lim_yp = (height - cy) / fy + 0.3f * height / (2.f * fy);
    float lim_yn = cy / fy + 0.3f * height / (2.f * fy);
    float tx = p.z * clamp(p.x / p.z, -lim_xn, lim_xp);
    float ty = p.z * clamp(p.y / p.z, -lim_yn, lim_yp);
    float j00 = fx / p.z, j02 = -fx * tx / (p.z * p.z);
    float j11 = fy / p.z, j12 = -fy * ty / (p.z * p.z);
    /* cov2d = J cov J^T for J = [[j00, 0, j02], [0, j11, j12]], plus the 0.3 px low-pass. */
    float c00 = j00 * (j00 * cov[0] + j02 * cov[2]) + j02 * (j00 * cov[6] + j02 * cov[8]) + 0.3f;
    float c01 = j00 * (j11 * cov[1] + j12 * cov[2]) + j02 * (j11 * cov[7] + j12 * cov[8]);
    float c11 = j11 * (j11 * cov[4] + j12 * cov[5]) + j12 * (j11 * cov[7] + j12 * cov[8]) + 0.3f;
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
    int touched = (rect.z - rect.x) * (rect.w - rect.y);
    if (touched <= 0) return;

    splats[i] = (float8)(mean2d.x, mean2d.y, c11 * inv, -c01 * inv, c00 * inv, opacity, p.z, sigma_max);
    radii[i] = (int)fmin(radius, RADIUS_MAX);
    rects[i] = rect;
    tiles_touched[i] = touched;
}
