/* Micro-kernels that measure this device's limits: streaming bandwidth and FMA rate. */

/* a = b + s * c over float16 vectors: 3 x 64 bytes of traffic per work-item. */
__kernel void triad(const int n, __global float16 *a, __global const float16 *b,
                    __global const float16 *c, const float s) {
    const int i = get_global_id(0);
    if (i >= n) return;
    a[i] = b[i] + s * c[i];
}

#ifndef ITERS
#define ITERS 4096
#endif

/* 8 independent float16 FMA chains, ITERS steps each: 8 * 16 * 2 * ITERS flops per work-item.
   The result is stored so that the compiler cannot drop the loop. */
__kernel void fma_peak(const int n, __global float *out, const float x) {
    if (get_global_id(0) >= n) return;
    float16 a0 = (float16)(x), a1 = a0 + 1.f, a2 = a0 + 2.f, a3 = a0 + 3.f,
            a4 = a0 + 4.f, a5 = a0 + 5.f, a6 = a0 + 6.f, a7 = a0 + 7.f;
    const float16 m = (float16)(0.999f), c = (float16)(0.001f);
    for (int i = 0; i < ITERS; i++) {
        a0 = fma(a0, m, c); a1 = fma(a1, m, c); a2 = fma(a2, m, c); a3 = fma(a3, m, c);
        a4 = fma(a4, m, c); a5 = fma(a5, m, c); a6 = fma(a6, m, c); a7 = fma(a7, m, c);
    }
    const float16 s = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7;
    float sum = 0.f;                                  /* its 16 lanes, in order */
    for (int k = 0; k < 16; k++) sum += ((__private const float *)&s)[k];
    out[get_global_id(0)] = sum;
}
