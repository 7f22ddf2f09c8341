"""The OpenCL runtime layer: device choice, context and queue, program cache and kernel launcher,
device memory helpers, and the constants shared with the kernels."""
from .constants import ALPHA_MAX, ALPHA_MIN, MAX_CHANNELS, SAMPLERS, SH_C0, T_MIN, TILE
from .device import NoDeviceError, Runtime, choose_device, device_kind, list_devices, runtime, trial_run
from .memory import (BufferLimitError, channel_layout, check_buffer, check_channels, exclusive_scan, host_output, last_value,
                     padded_rows, padded_vector, to_device)

__all__ = ["ALPHA_MAX", "ALPHA_MIN", "MAX_CHANNELS", "SAMPLERS", "SH_C0", "T_MIN", "TILE",
           "BufferLimitError", "NoDeviceError", "Runtime", "check_buffer", "channel_layout", "check_channels", "choose_device",
           "device_kind", "exclusive_scan", "host_output", "last_value", "list_devices",
           "padded_rows", "padded_vector", "runtime", "to_device", "trial_run"]
