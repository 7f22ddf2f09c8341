"""The OpenCL C sources of qr-cl (the package data ``qr_cl.kernels``): a file's text as it is built,
and which file defines each kernel."""
from __future__ import annotations

import re
from functools import lru_cache
from importlib import resources


#: A line including one of qr-cl's headers (``kernels/*.h``).
_INCLUDE = re.compile(r'^#include "(\w+\.h)"$', re.MULTILINE)


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>`` with the headers it includes inlined, and the headers they
    include, each once where it is first included (so driver caches see header edits)."""
    root = resources.files("qr_cl.kernels")
    inlined = set()

    def header(match: re.Match) -> str:
        if match.group(1) in inlined:
            return ""
        inlined.add(match.group(1))
        return _INCLUDE.sub(header, (root / match.group(1)).read_text())
    return _INCLUDE.sub(header, (root / name).read_text())


@lru_cache(maxsize=None)
def kernel_files() -> dict[str, str]:
    """Kernel name -> the ``kernels/*.cl`` file that defines it."""
    files = {}
    for path in resources.files("qr_cl.kernels").iterdir():
        if path.name.endswith(".cl"):
            for name in re.findall(r"__kernel\s+void\s+(\w+)\s*\(", path.read_text()):
                files[name] = path.name
    return files
