/* Feature rows: the rows of a feature table that blend.cl, vrender.cl and select.cl's fused
   blend (-DBLEND_ROWS) read in vectors, and their blend. Defined for kernels built with VW (and
   NV for RV and the blend). */
#ifndef QR_CL_ROWS_H
#define QR_CL_ROWS_H
#include "common.h"

/* Feature rows in vectors of VW floats (kernels built with -DVW=1, 2, 4, 8 or 16): vec_t,
   VLOAD(i, p) and VSTORE(v, i, p) load/store the i-th vector of row p. */
#ifdef VW
#if VW == 1
typedef float vec_t;
#define VLOAD(i, p) ((p)[i])
#define VSTORE_ANY(v, i, p) ((p)[i] = (v))
#define VSTORE(v, i, p) VSTORE_ANY(v, i, p)
#else
typedef CAT(float, VW) vec_t;
#define VLOAD(i, p) CAT(vload, VW)(i, p)
#define VSTORE_ANY(v, i, p) CAT(vstore, VW)(v, i, p)   /* any alignment */
/* A store through a vec_t pointer where the address is aligned to vec_t (rows and buffers
   normally are): PoCL's vstoreN of a float16 writes it as four 16-byte pieces. */
#define VSTORE(v, i, p) do { \
        __global vec_t *at_ = (__global vec_t *)((p) + (i) * VW); \
        if (((size_t)at_ & (sizeof(vec_t) - 1)) == 0) *at_ = (v); \
        else VSTORE_ANY(v, i, p); \
    } while (0)
#endif

/* Feature tables (the rows a blend reads, never its outputs) hold ROW_T elements: float, or half
   when built with -DHALF_ROWS (storage only: OpenCL C reads half rows with vload_half, a core
   function that needs no half arithmetic). RLOAD(i, p) loads the i-th vec_t of such a row as
   floats, exactly, so a half table blends as the float table of the same values. */
#ifdef HALF_ROWS
#define ROW_T half
#if VW == 1
#define RLOAD(i, p) vload_half(i, p)
#else
#define RLOAD(i, p) CAT(vload_half, VW)(i, p)
#endif
#else
#define ROW_T float
#define RLOAD(i, p) VLOAD(i, p)
#endif

/* VSTREAM(v, i, p): VSTORE of an output that the kernel does not read again, as a non-temporal
   store where the compiler offers one (clang's builtin) and the address is aligned to vec_t:
   the line is written without being read first (no read-for-ownership) and does not evict
   cached inputs. */
#if defined(__has_builtin)
#if __has_builtin(__builtin_nontemporal_store)
#define HAVE_NONTEMPORAL_STORE
#endif
#endif
#ifdef HAVE_NONTEMPORAL_STORE
#define VSTREAM(v, i, p) do { \
        __global vec_t *at_ = (__global vec_t *)((p) + (i) * VW); \
        if (((size_t)at_ & (sizeof(vec_t) - 1)) == 0) __builtin_nontemporal_store((v), at_); \
        else VSTORE_ANY(v, i, p); \
    } while (0)
#else
#define VSTREAM(v, i, p) VSTORE(v, i, p)
#endif

/* RV: the vectors of a row that a loop over entries accumulates at a time: the largest of 16, 8,
   4, 2, 1 that divides NV with RV * VW <= ACC_FLOATS (the floats the device keeps in registers,
   from the build), in fully unrolled loops so that the accumulators stay in registers. PoCL keeps
   an array of NV accumulators indexed in a loop on the stack: a load and a store of each per
   entry. RV changes no bytes; the budget follows the register file (on AVX2's 16 registers,
   16 float16 accumulators would spill). */
#ifdef NV
#if NV % 16 == 0 && 16 * VW <= ACC_FLOATS
#define RV 16
#elif NV % 8 == 0 && 8 * VW <= ACC_FLOATS
#define RV 8
#elif NV % 4 == 0 && 4 * VW <= ACC_FLOATS
#define RV 4
#elif NV % 2 == 0 && 2 * VW <= ACC_FLOATS
#define RV 2
#else
#define RV 1
#endif
#endif

/* out[c0, c0 + NV * VW) of one image row = (accumulate ? out : 0) + sum over the n entries
   (ids[j], w[j]) of w[j] features[ids[j] - row0, c0 ...] + tb * background[c0 ...] (the
   background only when use_bg), summed in float in entry order RV vectors at a time; written with
   VSTREAM when stream. features hold the rows [row0, row0 + n_rows) of a table (a row part of a
   table larger than one buffer; the whole table is row0 0, n_rows N): ids outside them are
   skipped. accumulate adds the part to what earlier parts wrote. */
static inline void blend_entries(__global const int *ids, __global const float *w, const int n,
                                 __global const ROW_T *features, const int row0, const int n_rows,
                                 const int cstride, const int c0, const float tb,
                                 __global const float *background, const int use_bg, const int accumulate,
                                 const int stream, __global float *out) {
    for (int v0 = 0; v0 < NV; v0 += RV) {
        const int c = c0 + v0 * VW;
        vec_t acc[RV];
        #pragma unroll
        for (int v = 0; v < RV; v++) acc[v] = accumulate ? VLOAD(v, out + c) : (vec_t)(0.f);
        for (int j = 0; j < n; j++) {
            const uint id = (uint)ids[j] - (uint)row0;     /* wraps below row0: skipped too */
            if (id >= (uint)n_rows) continue;
            const float wj = w[j];
            __global const ROW_T *row = features + (size_t)id * cstride + c;
            #pragma unroll
            for (int v = 0; v < RV; v++) acc[v] += wj * RLOAD(v, row);
        }
        #pragma unroll
        for (int v = 0; v < RV; v++) {
            const vec_t bg = use_bg ? VLOAD(v, background + c) : (vec_t)(0.f);
            if (stream) VSTREAM(acc[v] + tb * bg, v, out + c);
            else VSTORE(acc[v] + tb * bg, v, out + c);
        }
    }
}

/* The sum of the VW lanes of v. */
static inline float vec_sum(vec_t v) {
    float s = 0.f;
    for (int i = 0; i < VW; i++) s += ((__private float *)&v)[i];
    return s;
}
#endif

#endif
