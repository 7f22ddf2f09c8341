"""The OpenCL runtime layer: device choice, context and queue, program cache and kernel launcher,
device memory helpers (pooled device arrays, zero-copy host sharing, the host pool of large
outputs), and the constants shared with the kernels."""
from .constants import (ALPHA_MAX, ALPHA_MIN, FOOTPRINT_INTS, FOOTPRINT_RECT, FOOTPRINT_SPANS, MAX_CHANNELS, SAMPLERS,
                        SH_C0, SPAN_ROWS, SPLAT, SPLAT_FLOATS, T_MIN, TILE, WALK_ALL, SplatLayout)
from .device import (BLOCK_GROUP, DeviceLimitError, NoDeviceError, Runtime, choose_device, device_kind, list_devices,
                     loop_limit, runtime, trial_run, walk_windows)
from .memory import (BufferLimitError, HostMemoryError, HostPool, channel_layout, check_buffer, check_channels, device_empty,
                     device_rows, device_scan_works, device_zeros, exclusive_scan, host_empty, host_pool, last_value,
                     padded_rows, padded_vector, row_parts, shared_array, streamed, table_parts, to_device,
                     trim_device_pool)

__all__ = ["ALPHA_MAX", "BLOCK_GROUP", "ALPHA_MIN", "MAX_CHANNELS", "SAMPLERS", "SH_C0", "T_MIN", "TILE",
           "FOOTPRINT_INTS", "FOOTPRINT_RECT", "FOOTPRINT_SPANS", "SPAN_ROWS", "SPLAT", "SPLAT_FLOATS", "SplatLayout",
           "BufferLimitError", "DeviceLimitError", "HostMemoryError", "HostPool", "NoDeviceError", "Runtime", "check_buffer", "channel_layout",
           "check_channels", "choose_device", "device_empty", "device_kind", "device_rows", "device_scan_works", "device_zeros",
           "exclusive_scan", "host_empty", "host_pool", "last_value", "list_devices", "loop_limit",
           "padded_rows", "padded_vector", "row_parts", "runtime", "shared_array", "streamed", "table_parts", "to_device", "trim_device_pool",
           "trial_run", "WALK_ALL", "walk_windows"]
