"""The launcher's argument lists come from the kernel source (qr_cl.runtime.signatures), so a
program that a driver or pyopencl's cache loads from a binary, without argument info, launches."""
import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

from qr_cl.runtime import runtime
from qr_cl.runtime.sources import kernel_files, kernel_source
from qr_cl.runtime.signatures import SignatureError, kernel_signatures, preprocess

ROWS = [{"VW": 16, "NV": 4}, {"VW": 1, "NV": 1}, {"VW": 4, "NV": 2}, {"VW": 16, "NV": 4, "HALF_ROWS": 1},
        {"VW": 1, "NV": 1, "HALF_ROWS": 1}]
#: Define sets the stages build each kernel file with (the shared constants come on top).
BUILDS = {"blend.cl": ROWS, "vrender.cl": ROWS, "sh.cl": [{"DEGREE": d} for d in range(4)],
          "select.cl": [{}] + [{**r, "BLEND_ROWS": 1} for r in ROWS], "roofline.cl": [{}, {"ITERS": 8}]}


def driver_args(kernel: cl.Kernel) -> list[tuple[str, str, str]]:
    info, space = cl.kernel_arg_info, cl.kernel_arg_address_qualifier
    names = {space.GLOBAL: "global", space.CONSTANT: "constant", space.LOCAL: "local", space.PRIVATE: ""}
    return [(kernel.get_arg_info(i, info.NAME), kernel.get_arg_info(i, info.TYPE_NAME).replace(" ", ""),
             names[kernel.get_arg_info(i, info.ADDRESS_QUALIFIER)]) for i in range(kernel.num_args)]


@pytest.mark.parametrize("file", sorted(set(kernel_files().values())))
def test_source_signatures_equal_the_drivers_argument_info(file):
    rt = runtime()
    source = kernel_source(file)
    for defines in BUILDS.get(file, [{}]):
        constants = {**rt.build_constants, **defines}
        program = cl.Program(rt.context, source).build(
            options=["-cl-kernel-arg-info"] + [f"-D{k}={v}" for k, v in constants.items()])
        parsed = kernel_signatures(source, constants)
        assert sorted(parsed) == sorted(k.function_name for k in program.all_kernels())
        for kernel in program.all_kernels():
            ours = [(a.name, a.type_name, a.space) for a in parsed[kernel.function_name]]
            assert ours == driver_args(kernel), (file, defines, kernel.function_name)


def test_launch_needs_no_argument_info_from_the_driver(monkeypatch):
    """As on a runtime whose cached binaries carry no argument info (Intel's CPU runtime)."""
    def unavailable(self, *args):
        raise cl.RuntimeError("clGetKernelArgInfo failed: KERNEL_ARG_INFO_NOT_AVAILABLE")
    monkeypatch.setattr(cl.Kernel, "get_arg_info", unavailable)
    rt = runtime()
    rt._programs.clear()
    out = cla.zeros(rt.queue, 64, np.float32)
    rt.launch("triad", 4, n=4, a=out, b=cla.to_device(rt.queue, np.ones(64, np.float32)),
              c=cla.to_device(rt.queue, np.full(64, 2, np.float32)), s=3.0)
    assert np.all(out.get() == 7)


def test_conditionals_and_macros():
    source = """
    #define PAIR __global int *a, __global float4 *b
    #if MODE == 2 && defined(EXTRA)
    #define MORE , const uint n
    #elif MODE > 2 || !defined(EXTRA)
    #define MORE , const float3 v
    #else
    #define MORE
    #endif
    /* __kernel void commented(int x) */
    __kernel void k(PAIR MORE) { }
    """
    args = lambda **d: [(a.name, a.type_name, a.space) for a in kernel_signatures(source, d)["k"]]
    base = [("a", "int*", "global"), ("b", "float4*", "global")]
    assert args(MODE=2, EXTRA=1) == base + [("n", "uint", "")]
    assert args(MODE=1) == base + [("v", "float3", "")]
    assert args(MODE=1, EXTRA=1) == base
    assert preprocess("#ifdef X\nint a;\n#endif\nint b;", {})[0].split() == ["int", "b;"]


def test_what_cannot_be_read_is_refused_by_name():
    with pytest.raises(SignatureError, match="kernel k: argument x has the type 'vec_t'"):
        kernel_signatures("typedef float4 vec_t;\n__kernel void k(__global vec_t *x) {}", {})
    with pytest.raises(SignatureError, match="#if without #endif"):
        kernel_signatures("#if 1\n__kernel void k(int x) {}", {})
