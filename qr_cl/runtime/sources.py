"""The OpenCL C sources of qr-cl (the package data ``qr_cl.kernels``): a file's text as it is built,
and which file defines each kernel."""
from __future__ import annotations

import re
from functools import lru_cache
from importlib import resources


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>`` with ``common.h`` inlined (so driver caches see header edits)."""
    root = resources.files("qr_cl.kernels")
    text = (root / name).read_text()
    header = (root / "common.h").read_text()
    return text.replace('#include "common.h"', header)


@lru_cache(maxsize=None)
def kernel_files() -> dict[str, str]:
    """Kernel name -> the ``kernels/*.cl`` file that defines it."""
    files = {}
    for path in resources.files("qr_cl.kernels").iterdir():
        if path.name.endswith(".cl"):
            for name in re.findall(r"__kernel\s+void\s+(\w+)\s*\(", path.read_text()):
                files[name] = path.name
    return files
