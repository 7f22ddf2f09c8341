"""The OpenCL runtime layer, one job a module: device choice and probes (device), the Runtime:
context, queue, program cache and kernel launcher (context), the kernels' sources (sources),
feature-row layout (rows), device memory and sharing host arrays with the kernels (memory), large
host arrays (host_memory), and the constants and layouts shared with the kernels (constants)."""
from .constants import (ALPHA_MAX, ALPHA_MIN, DEFAULTS, FOOTPRINT_INTS, FOOTPRINT_RECT, FOOTPRINT_SPANS, MAX_CHANNELS,
                        SAMPLERS, SH_C0, SPAN_ROWS, SPLAT, SPLAT_FLOATS, T_MIN, TILE, VOLUME_STATE, VOLUME_STATE_FLOATS, WALK_ALL,
                        WALK_STATE, WALK_STATE_FLOATS, WALK_STATE_INTS, Defaults, SplatLayout, VolumeStateLayout,
                        WalkStateLayout)
from .context import BLOCK_GROUP, Runtime, runtime
from .device import (DeviceLimitError, NoDeviceError, choose_device, device_kind, list_devices, loop_limit, trial_run,
                     walk_windows)
from .host_memory import HostMemoryError, HostPool, host_empty, host_pool
from .memory import (BufferLimitError, check_buffer, device_empty, device_rows, device_scan_works, device_zeros,
                     exclusive_scan, last_value, row_parts, shared_array, streamed, table_parts, to_device, trim_device_pool)
from .rows import channel_layout, check_channels, padded_rows, padded_vector
from .constants import (KERNEL_CONSTANTS, SH_C1, SH_C2, SH_C3, SPAN_COND_MAX, SPAN_DET_MIN, SPAN_MARGIN_PX,
                        SPAN_MARGIN_REL, SPAN_ROUNDING, SPAN_SLACK)
from .device import implementation, self_check_enabled
from .implementations import environment, installed
from .sources import kernel_files, kernel_source

__all__ = ["ALPHA_MAX", "BLOCK_GROUP", "ALPHA_MIN", "MAX_CHANNELS", "SAMPLERS", "SH_C0", "T_MIN", "TILE",
           "FOOTPRINT_INTS", "FOOTPRINT_RECT", "FOOTPRINT_SPANS", "SPAN_ROWS", "SPLAT", "SPLAT_FLOATS", "SplatLayout",
           "BufferLimitError", "DeviceLimitError", "HostMemoryError", "HostPool", "NoDeviceError", "Runtime", "check_buffer", "channel_layout",
           "check_channels", "choose_device", "device_empty", "device_kind", "device_rows", "device_scan_works", "device_zeros",
           "exclusive_scan", "host_empty", "host_pool", "last_value", "list_devices", "loop_limit",
           "padded_rows", "padded_vector", "row_parts", "runtime", "shared_array", "streamed", "table_parts", "to_device", "trim_device_pool",
           "trial_run", "WALK_ALL", "walk_windows",
           "WALK_STATE", "WALK_STATE_FLOATS", "WALK_STATE_INTS", "WalkStateLayout", "VOLUME_STATE",
           "VOLUME_STATE_FLOATS", "VolumeStateLayout", "DEFAULTS", "Defaults",
           "KERNEL_CONSTANTS", "SH_C1", "SH_C2", "SH_C3", "SPAN_COND_MAX", "SPAN_DET_MIN", "SPAN_MARGIN_PX",
           "SPAN_MARGIN_REL", "SPAN_ROUNDING", "SPAN_SLACK", "environment", "implementation", "installed",
           "kernel_files", "kernel_source", "self_check_enabled"]
