/* Shared math of the qr-cl kernels: 3DGS conventions (see NOTES.md / the original 3DGS).

   The constants TILE (tile side in px), ALPHA_MIN (smaller alphas are skipped), ALPHA_MAX (alpha
   clamp), T_MIN (V-Render stops before T would drop to it) and the SH basis constants SH_C0,
   SH_C1, SH_C2_0..4, SH_C3_0..6 are defined by the build (-D), from qr_cl/runtime/constants.py. */
#ifndef QR_CL_COMMON_H
#define QR_CL_COMMON_H

/* Rotation matrix (row-major, 9 floats) of a unit quaternion q = (w, x, y, z). */
inline void quat_to_rotmat(float4 q, float *r) {
    float w = q.x, x = q.y, y = q.z, z = q.w;
    r[0] = 1.f - 2.f * (y * y + z * z); r[1] = 2.f * (x * y - w * z); r[2] = 2.f * (x * z + w * y);
    r[3] = 2.f * (x * y + w * z); r[4] = 1.f - 2.f * (x * x + z * z); r[5] = 2.f * (y * z - w * x);
    r[6] = 2.f * (x * z - w * y); r[7] = 2.f * (y * z + w * x); r[8] = 1.f - 2.f * (x * x + y * y);
}

/* c = a * b for row-major 3x3 matrices. */
inline void mat3_mul(const float *a, const float *b, float *c) {
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            c[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
}

/* Gaussian density exponent at offset d = mean2d - pixel: 0.5 (a dx^2 + c dy^2) + b dx dy,
   with conic (a, b, c) the inverse 2D covariance. */
inline float splat_sigma(float a, float b, float c, float dx, float dy) {
    return 0.5f * (a * dx * dx + c * dy * dy) + b * dx * dy;
}

/* ---- helpers of the selection and blend kernels (select.cl, blend.cl) ---- */

/* Ray gid -> pixel (x, y) and output row p. full != 0: the whole image, rays numbered tile-major
   (neighbouring work-items share a tile list), p = y * width + x; returns 0 for padding rays
   outside the image. full == 0: a pixel subset, (x, y) = pixels[gid], p = gid. */
inline int ray_pixel(int gid, int full, __global const int2 *pixels, int width, int height,
                     int tiles_x, int *x, int *y, int *p) {
    if (full) {
        const int tile = gid / (TILE * TILE), in_tile = gid % (TILE * TILE);
        *x = (tile % tiles_x) * TILE + in_tile % TILE;
        *y = (tile / tiles_x) * TILE + in_tile / TILE;
        *p = *y * width + *x;
        return *x < width && *y < height;
    }
    const int2 xy = pixels[gid];
    *x = xy.x; *y = xy.y; *p = gid;
    return 1;
}

/* The tile of pixel (x, y). */
inline int pixel_tile(int x, int y, int tiles_x) { return (y / TILE) * tiles_x + x / TILE; }

/* alpha'_i of a splat at pixel centre (px, py): min(0.99, opacity exp(-sigma)), or 0 when the
   Gaussian is skipped (sigma < 0 or alpha < 1/255). Same expression as vrender.cl. */
inline float splat_alpha(float8 s, float px, float py) {
    const float sig = splat_sigma(s.s2, s.s3, s.s4, s.s0 - px, s.s1 - py);
    if (sig < 0.f) return 0.f;
    const float a = min(ALPHA_MAX, s.s5 * exp(-sig));
    return a < ALPHA_MIN ? 0.f : a;
}

/* The (k+1)-th of the K equal transmittance boundaries of Q-Render: 1 - (k+1)/(K+1). */
inline float quantile_boundary(int k, int K) { return 1.f - (float)(k + 1) / (float)(K + 1); }

/* Feature rows in vectors of VW floats (kernels built with -DVW=1, 2, 4, 8 or 16): vec_t,
   VLOAD(i, p) and VSTORE(v, i, p) load/store the i-th vector of row p. */
#ifdef VW
#if VW == 1
typedef float vec_t;
#define VLOAD(i, p) ((p)[i])
#define VSTORE(v, i, p) ((p)[i] = (v))
#else
#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)
typedef CAT(float, VW) vec_t;
#define VLOAD(i, p) CAT(vload, VW)(i, p)
#define VSTORE(v, i, p) CAT(vstore, VW)(v, i, p)
#endif
#endif

#endif
