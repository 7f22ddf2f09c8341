"""``qr-cl devices``: every OpenCL device with its implementation and the self-check's verdict;
``*`` marks the one qr-cl uses (``QR_CL_DEVICE`` chooses another)."""
from __future__ import annotations

import argparse
import warnings

from ...render import check_in_child
from ...runtime import (NoDeviceError, choose_device, implementation, list_devices, loop_limit, self_check_enabled,
                        trial_run)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``qr-cl devices`` takes no options."""


def run(args: argparse.Namespace) -> int:
    """Every device with its implementation and the self-check's verdict (trial kernels and loop
    probe here, the render check in a child process per device); * marks the one qr-cl uses."""
    devices = list_devices()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            chosen = choose_device().int_ptr
        except NoDeviceError:
            chosen = None
    for pi, di, platform, dev in devices:
        status = trial_run(dev)
        if status is None:
            limit = loop_limit(dev)
            status = ("trial kernels ok, " + (f"loops end after {limit} iterations (walks in windows), "
                                              if limit else "")
                      + (check_in_child(pi, di) if self_check_enabled() else "self-check off (QR_CL_SELF_CHECK)"))
        print(f"{'*' if dev.int_ptr == chosen else ' '} [{pi}:{di}] {implementation(dev)}  "
              f"({'GPU' if dev.type & 4 else 'CPU' if dev.type & 2 else 'other'}, "
              f"{dev.max_compute_units} compute units, {dev.global_mem_size >> 20} MiB) - {status}")
    print("* = the device qr-cl uses (QR_CL_DEVICE=cpu|gpu|<platform substring>:<index> chooses another)"
          if chosen is not None else "no device passed the self-check: qr-cl refuses to render here")
    return 0 if chosen is not None else 2
