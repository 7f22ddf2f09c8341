"""Every public kernel path under oclgrind, the OpenCL device simulator (issue 12: "Prove any
OpenCL driver"): a report of oclgrind about one of qr-cl's own kernels fails the test.

Two checking runs of the child (tests/drivers/oclgrind_child.py: ``races`` and
``uninitialized``), started at once (oclgrind simulates on one core). Reports about pyopencl's
kernels (scan_lev1, scan_lev2, scan_final_update, the radix sort's) and about pyopencl's probing
of vendor-specific device queries (clGetDeviceInfo -> CL_INVALID_VALUE) are printed, not failed
on. Skipped when oclgrind's ICD library is not installed (Debian/Ubuntu: ``apt-get install
oclgrind``).
"""
from __future__ import annotations

import re
from collections import Counter
from typing import Callable, Iterator

import pytest

from tests.drivers.oclgrind_child import MODES, REPO, Child, finish_child, oclgrind_icd, start_child


# ------------------------------------------------------------------------ oclgrind's reports

def qr_cl_kernel_names() -> set[str]:
    names = set()
    for path in (REPO / "kernels").glob("*.cl"):
        names.update(re.findall(r"__kernel\s+void\s+(\w+)\s*\(", path.read_text()))
    return names


#: First lines of oclgrind's messages ("Invalid read of size 4 at global memory address ...",
#: "Read-write data race at ...", "Uninitialized value written to ...", "Controlflow depends on
#: uninitialized value", "OCLGRIND FATAL ERROR (...)", "Oclgrind - OpenCL runtime error detected").
OCLGRIND_HEADER = re.compile(r"(Invalid |Uninitiali[sz]ed |Controlflow depends|\S+(-\S+)? data race|"
                             r"OCLGRIND|Oclgrind|Unsupported |Undefined external|Work-group divergence)")


def reports(stderr: str) -> list[str]:
    """oclgrind's messages on ``stderr`` (where it prints them, between the child's own output):
    a first line at column 0 matching :data:`OCLGRIND_HEADER`, then tab-indented lines ("Kernel:
    name", "Entity: ...", "First entity: ...", "Function: clXxx", "Error: CL_...", instructions,
    source lines; blank lines inside a message hold a tab). A lone "OCLGRIND FATAL ERROR" line
    heads the message after it; "Oclgrind: N errors generated" notes are left out."""
    out, cur = [], None
    for line in stderr.splitlines():
        if line.startswith(("\t", " ")):
            if cur is not None:
                cur.append(line.rstrip())
            continue
        if cur is not None:
            out.append(cur)
        cur = [line.rstrip()] if OCLGRIND_HEADER.match(line) else None
    if cur is not None:
        out.append(cur)
    merged = []
    for lines in out:
        if merged and len(merged[-1]) == 1 and merged[-1][0].startswith("OCLGRIND FATAL ERROR"):
            merged[-1] += lines
        else:
            merged.append(lines)
    return ["\n".join(lines) for lines in merged
            if not (lines[0].startswith("Oclgrind: ") and "errors generated" in lines[0])]


def is_api_report(report: str) -> bool:
    return report.startswith("Oclgrind - OpenCL runtime error detected")


def kernel_of(report: str) -> str | None:
    m = re.search(r"^\s*Kernel:\s*(\w+)", report, re.M)
    return m.group(1) if m else None


def is_pyopencl_probe(report: str) -> bool:
    """pyopencl's probing of vendor-specific device queries (e.g. the NVIDIA compute capability
    when it checks for a build cache), answered CL_INVALID_VALUE and caught by pyopencl."""
    return ("Function: clGetDeviceInfo" in report and "CL_INVALID_VALUE" in report
            and "'param_name'" in report)


def summary(reports: list[str]) -> str:
    """One line per kind of report (address and entity left out) with its count."""
    def kind(r):
        lines = r.splitlines()
        head = re.sub(r"0x[0-9a-f]+", "ADDR", lines[0])
        where = " | ".join(line.strip() for line in lines[1:] if re.match(
            r"\s*(Kernel:|Function:|Error:|At line|store|load|tail call|call|%)", line))
        return f"{head} | {where}"
    return "\n".join(f"{n:5d} x {k}" for k, n in Counter(map(kind, reports)).most_common())


@pytest.fixture(scope="module")
def clean_runs(tmp_path_factory) -> Iterator[Callable[[str, str], Child]]:
    """The checking run of (mode, scope): both modes' runs of a scope (:data:`MODES`) start at once
    on first use: oclgrind simulates on one core, so on two cores the second costs little wall time."""
    if oclgrind_icd() is None:
        pytest.skip("oclgrind is not installed (apt-get install oclgrind)")
    runs: dict[tuple[str, str], Child] = {}

    def run(mode: str, scope: str) -> Child:
        if (mode, scope) not in runs:
            runs.update({(m, scope): start_child(m, tmp_path_factory.mktemp(f"oclgrind-{m}-{scope}"), args=(scope,))
                         for m in MODES})
        return runs[mode, scope]
    yield run
    for child in runs.values():
        if child.proc.poll() is None:
            child.proc.kill()
            child.proc.wait()


# ---------------------------------------------------------------------------------------- the test

@pytest.mark.parametrize("scope", ["quick", pytest.param("full", marks=pytest.mark.slow)])
@pytest.mark.parametrize("mode", list(MODES))
def test_qr_cl_kernels_are_clean_under_oclgrind(mode, scope, clean_runs):
    """``quick`` (the default suite): every kernel file on one path each; ``full`` (slow): every
    public path, both walks in one launch and in windows, and pyopencl's kernels once."""
    proc, seconds = finish_child(clean_runs(mode, scope))
    print(f"[{mode}] child ran {seconds:.0f} s:\n{proc.stdout}")
    assert proc.returncode == 0, f"child failed (rc {proc.returncode}):\n{proc.stdout}\n{proc.stderr[-8000:]}"
    assert "device: Oclgrind" in proc.stdout, proc.stdout
    ours = qr_cl_kernel_names()
    mine, theirs = [], []
    for r in reports(proc.stderr):
        if is_api_report(r):
            (theirs if is_pyopencl_probe(r) else mine).append(r)
        else:
            (mine if kernel_of(r) is None or kernel_of(r) in ours else theirs).append(r)
    if theirs:
        print(f"[{mode}] oclgrind's reports about pyopencl's own kernels and queries "
              f"({len(theirs)}, not failed on):\n{summary(theirs)}")
        examples = {}
        for r in theirs:
            examples.setdefault((kernel_of(r), r.splitlines()[0][:30]), r)
        print("\n\n".join(examples.values()))
    assert not mine, (f"oclgrind reports about qr-cl's kernels ({len(mine)}):\n{summary(mine)}\n\n"
                      + "\n\n".join(mine[:5]))

