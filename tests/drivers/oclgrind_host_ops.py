"""pyopencl's scans and radix sorts done on the host in the oclgrind child (oclgrind_child.py):
oclgrind interprets them slowly and they are not qr-cl's kernels (see that module's docstring)."""
from __future__ import annotations

import re


HOST_SCAN_OPS = {"a+b": "add", "max(a,b)": "maximum", "min(a,b)": "minimum"}


def record_scan_and_sort_specs() -> None:
    """Let pyopencl's scan kernels and radix sorts remember their scan expression / sort key, for
    :func:`use_host_scan_sort` (installed first: qr-cl caches the kernels it builds)."""
    from pyopencl.algorithm import RadixSort
    from pyopencl.scan import _LegacyScanKernelBase
    scan_init, radix_init = _LegacyScanKernelBase.__init__, RadixSort.__init__

    def scan_kernel_init(self, ctx, dtype, scan_expr, neutral=None, *args, **kwargs):
        scan_init(self, ctx, dtype, scan_expr, neutral, *args, **kwargs)
        self.host_scan = (HOST_SCAN_OPS.get(scan_expr.replace(" ", "")), neutral)

    def radix_sort_init(self, context, arguments, key_expr, sort_arg_names, *args, **kwargs):
        radix_init(self, context, arguments, key_expr, sort_arg_names, *args, **kwargs)
        key = re.fullmatch(r"\s*(\w+)\s*\[\s*i\s*\]\s*", key_expr)
        self.host_key = key.group(1) if key else None

    _LegacyScanKernelBase.__init__, RadixSort.__init__ = scan_kernel_init, radix_sort_init


def use_host_scan_sort(uninitialized: bool) -> None:
    """Do pyopencl's scans ("a+b", "max(a, b)") and radix sorts (key ``name[i]``) on the host
    (both runs; pyopencl's own kernels are checked once by :func:`exercise_pyopencl`; other scans
    and sorts still run on the device). ``uninitialized``: also fill buffers by host writes and
    keep every device array alive (no buffer is freed and reused), see the module docstring."""
    import numpy as np
    import pyopencl as cl
    import pyopencl.array as cla
    from pyopencl.algorithm import RadixSort
    from pyopencl.scan import ExclusiveScanKernel, _LegacyScanKernelBase
    scan_call, radix_call = _LegacyScanKernelBase.__call__, RadixSort.__call__

    def scan(self, input_ary, output_ary=None, allocator=None, queue=None):
        op, neutral = getattr(self, "host_scan", (None, None))
        exclusive = isinstance(self, ExclusiveScanKernel)
        if op is None or (exclusive and not str(neutral).strip().lstrip("-").isdigit()):
            return scan_call(self, input_ary, output_ary, allocator, queue)
        out = input_ary if output_ary is None else output_ary
        if isinstance(out, str):
            out = cla.empty_like(input_ary)
        x = input_ary.get(queue=queue)
        y = getattr(np, op).accumulate(x, dtype=x.dtype) if x.size else x
        if exclusive and x.size:
            y = np.concatenate([np.array([int(neutral)], x.dtype), y[:-1]])
        out.set(np.ascontiguousarray(y), queue=queue)
        return out

    def radix_sort(self, *args, queue=None, allocator=None, key_bits=None, wait_for=None):
        names = [a.name for a in self.arguments]
        if getattr(self, "host_key", None) not in names:
            return radix_call(self, *args, queue=queue, allocator=allocator, key_bits=key_bits,
                              wait_for=wait_for)
        keys = args[names.index(self.host_key)].get()
        if key_bits is not None and key_bits < 8 * keys.dtype.itemsize:
            keys = keys & keys.dtype.type((1 << key_bits) - 1)
        order = np.argsort(keys, kind="stable")
        queue = queue or args[0].queue
        out = tuple(cla.to_device(queue, np.ascontiguousarray(args[names.index(s)].get()[order]),
                                  allocator=allocator or args[0].allocator)
                    for s in self.sort_arg_names)
        return out, cl.enqueue_marker(queue)

    def fill(queue, mem, pattern, size, offset=0, wait_for=None):
        pat = np.frombuffer(np.ascontiguousarray(pattern).tobytes(), np.uint8)
        return cl.enqueue_copy(queue, mem, np.resize(pat, size), dst_offset=offset,
                               wait_for=wait_for, is_blocking=True)

    kept, array_init = [], cla.Array.__init__

    def keep_array(self, *args, **kwargs):
        array_init(self, *args, **kwargs)
        kept.append(self)

    _LegacyScanKernelBase.__call__, RadixSort.__call__ = scan, radix_sort
    if uninitialized:
        cl.enqueue_fill = fill
        cla.Array.__init__ = keep_array


# ------------------------------------------------------------------- starting a child
