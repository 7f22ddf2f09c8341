/* View-dependent colour from spherical harmonics: one work-item per Gaussian. */
#include "common.h"

/* rgb = max(0, sum_l SH_l(dir) * coeff_l + 0.5) with dir = normalize(mean - camera position).
   sh is [N, (DEGREE+1)^2, 3]; colors is [N, 4] (the 4th channel 0, for 4-wide vector loads). */
__kernel void sh_to_rgb(const int n, __global const float *means, __global const float *sh,
                        const float3 campos, __global float4 *colors) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int K = (DEGREE + 1) * (DEGREE + 1);
    __global const float *c = sh + (size_t)i * K * 3;
    float3 rgb = SH_C0 * vload3(0, c);
#if DEGREE > 0
    float3 d = normalize(vload3(i, means) - campos);
    float x = d.x, y = d.y, z = d.z;
    rgb += -SH_C1 * y * vload3(1, c) + SH_C1 * z * vload3(2, c) - SH_C1 * x * vload3(3, c);
#if DEGREE > 1
    float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    rgb += SH_C2_0 * xy * vload3(4, c) + SH_C2_1 * yz * vload3(5, c)
         + SH_C2_2 * (2.f * zz - xx - yy) * vload3(6, c) + SH_C2_3 * xz * vload3(7, c)
         + SH_C2_4 * (xx - yy) * vload3(8, c);
#if DEGREE > 2
    rgb += SH_C3_0 * y * (3.f * xx - yy) * vload3(9, c) + SH_C3_1 * xy * z * vload3(10, c)
         + SH_C3_2 * y * (4.f * zz - xx - yy) * vload3(11, c)
         + SH_C3_3 * z * (2.f * zz - 3.f * xx - 3.f * yy) * vload3(12, c)
         + SH_C3_4 * x * (4.f * zz - xx - yy) * vload3(13, c)
         + SH_C3_5 * z * (xx - yy) * vload3(14, c) + SH_C3_6 * x * (xx - 3.f * yy) * vload3(15, c);
#endif
#endif
#endif
    rgb = max(rgb + 0.5f, (float3)(0.f));
    colors[i] = (float4)(rgb, 0.f);
}

/* Backward of sh_to_rgb, one work-item per Gaussian: with g = d_colors (zero where the clamp at 0
   was active), d_sh[k] = SH_k(dir) g and d_means = (I - dir dir^T) / |mean - campos| times the
   gradient w.r.t. dir of sum_k SH_k(dir) (coeff_k . g) (the basis polynomials differentiated by
   hand; the torch twin differentiates them by autograd). The camera gets no gradient. */
__kernel void sh_backward(const int n, __global const float *means, __global const float *sh,
                          const float3 campos, __global const float4 *colors,
                          __global const float4 *d_colors, __global float *d_sh, __global float *d_means) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int K = (DEGREE + 1) * (DEGREE + 1);
    __global const float *c = sh + (size_t)i * K * 3;
    __global float *dc = d_sh + (size_t)i * K * 3;
    const float4 col = colors[i], dcol = d_colors[i];
    /* the clamp: rgb = max(pre + 0.5, 0) passes the gradient where rgb > 0 */
    const float3 g = (float3)(col.x > 0.f ? dcol.x : 0.f, col.y > 0.f ? dcol.y : 0.f, col.z > 0.f ? dcol.z : 0.f);
    vstore3(SH_C0 * g, 0, dc);
    float3 dd = (float3)(0.f);                       /* d/d dir of sum_k SH_k(dir) w_k */
#if DEGREE > 0
    const float3 v = vload3(i, means) - campos;
    const float3 d = normalize(v);
    const float x = d.x, y = d.y, z = d.z;
    float w[16];                                     /* w_k = coeff_k . g */
    for (int k = 1; k < K; k++) w[k] = dot(vload3(k, c), g);
    vstore3(-SH_C1 * y * g, 1, dc);
    vstore3(SH_C1 * z * g, 2, dc);
    vstore3(-SH_C1 * x * g, 3, dc);
    dd += SH_C1 * (float3)(-w[3], -w[1], w[2]);
#if DEGREE > 1
    const float xx = x * x, yy = y * y, zz = z * z;
    vstore3(SH_C2_0 * x * y * g, 4, dc);
    vstore3(SH_C2_1 * y * z * g, 5, dc);
    vstore3(SH_C2_2 * (2.f * zz - xx - yy) * g, 6, dc);
    vstore3(SH_C2_3 * x * z * g, 7, dc);
    vstore3(SH_C2_4 * (xx - yy) * g, 8, dc);
    dd += SH_C2_0 * w[4] * (float3)(y, x, 0.f) + SH_C2_1 * w[5] * (float3)(0.f, z, y)
        + SH_C2_2 * w[6] * (float3)(-2.f * x, -2.f * y, 4.f * z) + SH_C2_3 * w[7] * (float3)(z, 0.f, x)
        + SH_C2_4 * w[8] * (float3)(2.f * x, -2.f * y, 0.f);
#if DEGREE > 2
    vstore3(SH_C3_0 * y * (3.f * xx - yy) * g, 9, dc);
    vstore3(SH_C3_1 * x * y * z * g, 10, dc);
    vstore3(SH_C3_2 * y * (4.f * zz - xx - yy) * g, 11, dc);
    vstore3(SH_C3_3 * z * (2.f * zz - 3.f * xx - 3.f * yy) * g, 12, dc);
    vstore3(SH_C3_4 * x * (4.f * zz - xx - yy) * g, 13, dc);
    vstore3(SH_C3_5 * z * (xx - yy) * g, 14, dc);
    vstore3(SH_C3_6 * x * (xx - 3.f * yy) * g, 15, dc);
    dd += SH_C3_0 * w[9] * (float3)(6.f * x * y, 3.f * xx - 3.f * yy, 0.f)
        + SH_C3_1 * w[10] * (float3)(y * z, x * z, x * y)
        + SH_C3_2 * w[11] * (float3)(-2.f * x * y, 4.f * zz - xx - 3.f * yy, 8.f * y * z)
        + SH_C3_3 * w[12] * (float3)(-6.f * x * z, -6.f * y * z, 6.f * zz - 3.f * xx - 3.f * yy)
        + SH_C3_4 * w[13] * (float3)(4.f * zz - 3.f * xx - yy, -2.f * x * y, 8.f * x * z)
        + SH_C3_5 * w[14] * (float3)(2.f * x * z, -2.f * y * z, xx - yy)
        + SH_C3_6 * w[15] * (float3)(3.f * xx - 3.f * yy, -6.f * x * y, 0.f);
#endif
#endif
    vstore3((dd - d * dot(d, dd)) / length(v), i, d_means);
#else
    vstore3((float3)(0.f), i, d_means);
#endif
}
