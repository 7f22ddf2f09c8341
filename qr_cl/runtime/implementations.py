"""Other OpenCL implementations installed privately beside the system's (never registered in
/etc/OpenCL/vendors, so the default device stays the system's): Intel's CPU runtime and Mesa's
rusticl, by ``tests/drivers/install.sh``. Each has a folder ``$QR_CL_DRIVERS/<name>`` (default
``~/.cache/qr-cl/drivers``) whose ``env`` file holds the ``KEY=VALUE`` lines that make a process
see that implementation alone."""
from __future__ import annotations

import os
from pathlib import Path

#: The implementations tests/drivers/install.sh knows, in the order reports list them.
NAMES = ("intel", "rusticl")


def drivers_root() -> Path:
    """``$QR_CL_DRIVERS`` or ``~/.cache/qr-cl/drivers``."""
    return Path(os.environ.get("QR_CL_DRIVERS", Path.home() / ".cache" / "qr-cl" / "drivers"))


def installed() -> dict[str, dict[str, str]]:
    """Name -> the environment variables that select it, for each installed implementation."""
    found = {}
    for name in NAMES:
        env = drivers_root() / name / "env"
        if env.is_file():
            lines = [line.strip() for line in env.read_text().splitlines() if line.strip()]
            found[name] = dict(line.split("=", 1) for line in lines)
    return found


def environment(name: str, **extra: str) -> dict[str, str]:
    """This process's environment with implementation ``name`` selected (``"pocl"`` or any name
    not installed privately: the system's default) and ``extra`` variables on top."""
    env = {k: v for k, v in os.environ.items() if k not in ("QR_CL_DEVICE", "PYOPENCL_CTX")}
    env.update(installed().get(name, {}))
    env.update(extra)
    return env
