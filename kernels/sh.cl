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
