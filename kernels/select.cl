/* Selection kernels: which Gaussians a ray blends and with what weight (geometry only).

   One work-item per ray. A ray walks the depth-sorted Gaussian list of its pixel's tile and
   writes (Gaussian id, weight) entries. Per ray it also writes count (entries), t_walk (the
   transmittance T where its walk stopped), t_sel (the transmittance among the selected
   Gaussians before normalization; T for volume) and t_rem (the weight of the background).
   quantile/topk write dense rows of K entries at p * K (-1 / 0 padded, the 1 / (1 - t_sel)
   normalization folded into the weights); volume writes at offsets[p] (CSR, after a counting
   pass and a scan). */
#include "common.h"

#define RAY_ARGS __global const int2 *ranges, __global const int *ids, \
    __global const float8 *splats, __global const int2 *pixels, const int full, \
    const int width, const int height, const int tiles_x

/* Sets x, y, p, range, px, py of ray gid; returns from the kernel for padding rays. */
#define RAY_SETUP \
    int x, y, p; \
    if (!ray_pixel(get_global_id(0), full, pixels, width, height, tiles_x, &x, &y, &p)) return; \
    const int2 range = ranges[pixel_tile(x, y, tiles_x)]; \
    const float px = x + 0.5f, py = y + 0.5f;

/* Divide the n weights T^Q_j alpha'_j by 1 - T^Q. 1 - T^Q equals their sum exactly (telescoping);
   the sum of positive terms is the better conditioned of the two in float (1 - T^Q cancels when
   alpha is small), and makes the normalized weights sum to 1 to rounding. */
inline void normalize(__global float *w, int n) {
    float sum = 0.f;
    for (int j = 0; j < n; j++) sum += w[j];
    for (int j = 0; j < n; j++) w[j] /= sum;
}

/* Q-Render selection, Algorithm 1 of the paper. */
__kernel void select_quantile(RAY_ARGS, const int K, __global int *out_ids, __global float *out_w,
                              __global int *count, __global float *t_walk,
                              __global float *t_sel, __global float *t_rem) {
    RAY_SETUP
    __global int *sid = out_ids + (size_t)p * K;
    __global float *sw = out_w + (size_t)p * K;
    const float stop = 1.f / (float)(K + 1);
    float T = 1.f, TQ = 1.f;
    int k = 0, n = 0;
    for (int i = range.x; i < range.y; i++) {
        const int g = ids[i];
        const float a = splat_alpha(splats[g], px, py);
        if (a == 0.f) continue;
        const float T_test = T * (1.f - a);
        if (T_test < quantile_boundary(k, K)) {     /* crosses the next boundary: a quantile */
            sid[n] = g;
            sw[n] = TQ * a;                          /* w^Q = T^Q alpha' */
            n++;
            TQ *= 1.f - a;
            k++;
            while (T_test < quantile_boundary(k, K)) k++;   /* skip boundaries also crossed */
        }
        T = T_test;
        if (T_test < stop) break;
    }
    normalize(sw, n);
    for (int j = n; j < K; j++) { sid[j] = -1; sw[j] = 0.f; }
    count[p] = n; t_walk[p] = T; t_sel[p] = TQ; t_rem[p] = n ? 0.f : 1.f;
}

/* Min-heap order of (weight, list position): the smaller weight, or on a tie the later
   position (so the K largest weights are kept, earlier depth first on ties). */
inline int heap_less(float wa, int pa, float wb, int pb) { return wa < wb || (wa == wb && pa > pb); }

inline void heap_sift_down(__global float *hw, __global int *hp, int i, int n) {
    for (;;) {
        int m = i;
        const int l = 2 * i + 1, r = l + 1;
        if (l < n && heap_less(hw[l], hp[l], hw[m], hp[m])) m = l;
        if (r < n && heap_less(hw[r], hp[r], hw[m], hp[m])) m = r;
        if (m == i) return;
        const float tw = hw[i]; hw[i] = hw[m]; hw[m] = tw;
        const int tp = hp[i]; hp[i] = hp[m]; hp[m] = tp;
        i = m;
    }
}

/* Max-heap sift on positions alone (heapsort of the kept positions into depth order). */
inline void pos_sift_down(__global int *hp, int i, int n) {
    for (;;) {
        int m = i;
        const int l = 2 * i + 1, r = l + 1;
        if (l < n && hp[l] > hp[m]) m = l;
        if (r < n && hp[r] > hp[m]) m = r;
        if (m == i) return;
        const int t = hp[i]; hp[i] = hp[m]; hp[m] = t;
        i = m;
    }
}

/* top-K selection: the K largest V-Render weights w_i = T_i alpha'_i (bounded min-heap kept in
   the ray's output row, O(N log K)), then re-composited in depth order among the selected. */
__kernel void select_topk(RAY_ARGS, const int K, __global int *out_ids, __global float *out_w,
                          __global int *count, __global float *t_walk,
                          __global float *t_sel, __global float *t_rem) {
    RAY_SETUP
    __global int *hp = out_ids + (size_t)p * K;      /* heap: list positions ... */
    __global float *hw = out_w + (size_t)p * K;      /* ... and their V-Render weights */
    float T = 1.f;
    int n = 0;
    for (int i = range.x; i < range.y; i++) {
        const float a = splat_alpha(splats[ids[i]], px, py);
        if (a == 0.f) continue;
        const float next_T = T * (1.f - a);
        if (next_T <= T_MIN) break;                  /* the V-Render walk */
        const float w = a * T;
        if (n < K) {                                 /* push, sift up */
            int j = n++;
            while (j > 0 && heap_less(w, i, hw[(j - 1) / 2], hp[(j - 1) / 2])) {
                hw[j] = hw[(j - 1) / 2]; hp[j] = hp[(j - 1) / 2];
                j = (j - 1) / 2;
            }
            hw[j] = w; hp[j] = i;
        } else if (w > hw[0]) {                      /* replace the smallest kept weight */
            hw[0] = w; hp[0] = i;
            heap_sift_down(hw, hp, 0, K);
        }
        T = next_T;
    }
    for (int j = n / 2 - 1; j >= 0; j--) pos_sift_down(hp, j, n);   /* heapsort positions */
    for (int end = n - 1; end > 0; end--) {
        const int t = hp[0]; hp[0] = hp[end]; hp[end] = t;
        pos_sift_down(hp, 0, end);
    }
    float TQ = 1.f;                                  /* re-composite in depth order */
    for (int j = 0; j < n; j++) {
        const int g = ids[hp[j]];
        const float a = splat_alpha(splats[g], px, py);
        hp[j] = g;
        hw[j] = TQ * a;
        TQ *= 1.f - a;
    }
    normalize(hw, n);
    for (int j = n; j < K; j++) { hp[j] = -1; hw[j] = 0.f; }
    count[p] = n; t_walk[p] = T; t_sel[p] = TQ; t_rem[p] = n ? 0.f : 1.f;
}

/* V-Render selection, counting pass: entries per ray and the final T. */
__kernel void volume_count(RAY_ARGS, __global int *count, __global float *t_walk) {
    RAY_SETUP
    float T = 1.f;
    int n = 0;
    for (int i = range.x; i < range.y; i++) {
        const float a = splat_alpha(splats[ids[i]], px, py);
        if (a == 0.f) continue;
        const float next_T = T * (1.f - a);
        if (next_T <= T_MIN) break;
        n++;
        T = next_T;
    }
    count[p] = n; t_walk[p] = T;
}

/* V-Render selection, fill pass: every Gaussian V-Render blends, w_i = T_i alpha'_i, at offsets[p]
   (exclusive scan of count). The background weight is the final T. */
__kernel void volume_fill(RAY_ARGS, __global const int *offsets, __global int *out_ids,
                          __global float *out_w, __global float *t_sel, __global float *t_rem) {
    RAY_SETUP
    __global int *sid = out_ids + offsets[p];
    __global float *sw = out_w + offsets[p];
    float T = 1.f;
    int n = 0;
    for (int i = range.x; i < range.y; i++) {
        const int g = ids[i];
        const float a = splat_alpha(splats[g], px, py);
        if (a == 0.f) continue;
        const float next_T = T * (1.f - a);
        if (next_T <= T_MIN) break;
        sid[n] = g;
        sw[n] = a * T;
        n++;
        T = next_T;
    }
    t_sel[p] = T; t_rem[p] = T;
}
