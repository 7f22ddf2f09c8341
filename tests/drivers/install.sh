#!/usr/bin/env bash
# Install extra OpenCL implementations PRIVATELY (nothing is registered in
# /etc/OpenCL/vendors, so PoCL stays the default), for running qr-cl on them.
#
#   tests/drivers/install.sh            # both
#   tests/drivers/install.sh intel      # Intel oneAPI OpenCL CPU runtime (PyPI)
#   tests/drivers/install.sh rusticl    # Mesa rusticl, llvmpipe CPU device (Debian 12)
#
# Everything goes under ROOT="${QR_CL_DRIVERS:-$HOME/.cache/qr-cl/drivers}".
# After a working install, $ROOT/<name>/env holds KEY=VALUE lines (absolute
# paths) with exactly the environment that makes only that implementation
# visible to a Python process, e.g.  env $(cat "$ROOT/intel/env") python3 ...
# The env file is written last, and only after pyopencl lists exactly one
# platform with it and runs a kernel correctly.
#
# Idempotent: an implementation whose env file exists and passes that check is
# left alone (no network; about a second). A failing implementation is reported
# on one line and skipped. Exit status is 0 unless the arguments are wrong.
# Install logs: $ROOT/<name>.log

set -u

usage() { echo "usage: $0 [intel|rusticl]..." >&2; exit 2; }

TARGETS=()
for arg in "$@"; do
    case "$arg" in
        intel|rusticl) TARGETS+=("$arg") ;;
        -h|--help) echo "usage: $0 [intel|rusticl]..."; exit 0 ;;
        *) usage ;;
    esac
done
[ ${#TARGETS[@]} -eq 0 ] && TARGETS=(intel rusticl)

ROOT="${QR_CL_DRIVERS:-${HOME:-/tmp}/.cache/qr-cl/drivers}"
if ! mkdir -p "$ROOT" 2>/dev/null || ! ROOT="$(cd "$ROOT" && pwd -P)"; then
    for t in "${TARGETS[@]}"; do echo "$t: skipped: cannot create $ROOT"; done
    exit 0
fi

# One installer at a time (e.g. parallel test workers calling this script).
if command -v flock >/dev/null 2>&1; then
    exec 9>"$ROOT/.lock" && flock -w 1800 9
fi

PYTHON="${QR_CL_PYTHON:-python3}"   # the python that runs the tests (needs pyopencl, numpy)

# Lists the platforms, requires exactly one (only this implementation is
# visible), runs x[i] = 2*x[i] + 1 over 64 floats and checks the result.
# Prints one line: platform | device | device version | driver version.
CHECK_PY='
import sys, warnings
warnings.simplefilter("ignore")
import numpy as np, pyopencl as cl
ps = cl.get_platforms()
if len(ps) != 1:
    sys.exit("expected exactly one OpenCL platform, got %r" % [p.name for p in ps])
p = ps[0]
ds = p.get_devices()
if not ds:
    sys.exit("platform %r has no devices" % p.name)
d = ds[0]
ctx = cl.Context([d])
q = cl.CommandQueue(ctx)
prg = cl.Program(ctx, "__kernel void twice_plus_one(__global float *x)"
                      "{ int i = get_global_id(0); x[i] = 2.0f * x[i] + 1.0f; }").build()
a = np.arange(64, dtype=np.float32)
buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
prg.twice_plus_one(q, a.shape, None, buf)
r = np.empty_like(a)
cl.enqueue_copy(q, r, buf)
q.finish()
if not np.array_equal(r, 2 * a + 1):
    sys.exit("wrong kernel result: %r" % r[:8])
print("%s | %s | %s | driver %s" % (p.name.strip(), d.name.strip(), d.version.strip(),
                                   d.driver_version.strip()))
'

CHECK_OUT=""
# check_env ENVFILE: run the check with the variables of ENVFILE; sets CHECK_OUT.
check_env() {
    local envfile="$1" vars=() line
    [ -s "$envfile" ] || { CHECK_OUT="no env file"; return 1; }
    while IFS= read -r line || [ -n "$line" ]; do
        [ -n "$line" ] && vars+=("$line")
    done < "$envfile"
    CHECK_OUT="$(env "${vars[@]}" timeout 300 "$PYTHON" -c "$CHECK_PY" 2>&1)"
    local rc=$?
    CHECK_OUT="$(printf '%s\n' "$CHECK_OUT" | grep -v '^[[:space:]]*$' | tail -n 1)"
    return $rc
}

# write_env NAME KEY=VALUE...: check the environment, then publish $ROOT/NAME/env.
write_env() {
    local name="$1"; shift
    local tmp="$ROOT/$name/env.tmp"
    printf '%s\n' "$@" > "$tmp" || { CHECK_OUT="cannot write $tmp"; return 1; }
    if check_env "$tmp"; then
        mv -f "$tmp" "$ROOT/$name/env"
    else
        rm -f "$tmp"
        return 1
    fi
}

SKIP=""   # one-line reason set by an installer that fails

# apt-get needs root; without it, use passwordless sudo when there is one.
AS_ROOT=()
[ "$(id -u)" -eq 0 ] || AS_ROOT=(sudo -n)

# ---------------------------------------------------------------- intel --
install_intel() {
    local dir="$ROOT/intel" log="$ROOT/intel.log" lib libdir
    rm -rf "$dir"
    mkdir -p "$dir/icd"
    if ! "$PYTHON" -m venv "$dir/venv" >>"$log" 2>&1; then
        SKIP="'$PYTHON -m venv' failed"; return 1
    fi
    if ! timeout 1800 "$dir/venv/bin/python" -m pip install -q --disable-pip-version-check \
            --retries 1 --timeout 30 \
            "intel-opencl-rt==2026.*" "tbb==2023.*" \
            "intel-cmplr-lib-rt==2026.*" "intel-cmplr-lic-rt==2026.*" >>"$log" 2>&1; then
        SKIP="pip install of intel-opencl-rt failed: $(grep -E '^ERROR' "$log" | tail -n 1)"
        return 1
    fi
    lib="$dir/venv/lib/libintelocl.so"
    [ -e "$lib" ] || lib="$(find "$dir/venv" -name 'libintelocl.so' -print -quit)"
    if [ -z "$lib" ] || [ ! -e "$lib" ]; then
        SKIP="libintelocl.so not found in $dir/venv"; return 1
    fi
    libdir="$(dirname "$lib")"
    echo "$lib" > "$dir/icd/intel.icd"
    # libintelocl.so finds its own libraries through RUNPATH $ORIGIN, but TBB
    # dlopens libtcm/libhwloc by name: LD_LIBRARY_PATH lets it find them.
    if ! write_env intel "OCL_ICD_VENDORS=$dir/icd" "LD_LIBRARY_PATH=$libdir"; then
        SKIP="check failed: $CHECK_OUT"; return 1
    fi
}

# -------------------------------------------------------------- rusticl --
# Libraries that Debian 12's mesa-opencl-icd depends on (installed system-wide;
# libclc-15 must be, since rusticl reads /usr/lib/clc/spirv64-mesa3d-.spv).
RUSTICL_DEPS=(libclc-15 libllvmspirvlib15 libclang-cpp15 libllvm15 libdrm-amdgpu1
              libdrm-nouveau2 libdrm-radeon1 libdrm2 libsensors5 libelf1 libexpat1
              libzstd1 zlib1g)

apt_quiet() {
    DEBIAN_FRONTEND=noninteractive timeout 900 "${AS_ROOT[@]}" apt-get -qq -o=Dpkg::Use-Pty=0 "$@"
}

install_rusticl() {
    local dir="$ROOT/rusticl" log="$ROOT/rusticl.log" missing=() p tmp deb lib missing_libs
    command -v apt-get >/dev/null 2>&1 && command -v dpkg >/dev/null 2>&1 \
        || { SKIP="needs apt-get and dpkg (Debian 12)"; return 1; }
    for p in "${RUSTICL_DEPS[@]}"; do
        dpkg-query -W -f='${Status}\n' "$p" 2>/dev/null | grep -q 'ok installed' || missing+=("$p")
    done
    if [ ${#missing[@]} -gt 0 ]; then
        if ! apt_quiet install -y --no-install-recommends "${missing[@]}" >>"$log" 2>&1; then
            apt_quiet update >>"$log" 2>&1
            if ! apt_quiet install -y --no-install-recommends "${missing[@]}" >>"$log" 2>&1; then
                SKIP="apt-get install ${missing[*]} failed: $(grep -E '^E:' "$log" | tail -n 1)"
                return 1
            fi
        fi
    fi
    tmp="$(mktemp -d)" || { SKIP="mktemp failed"; return 1; }
    chmod 755 "$tmp"
    chown _apt "$tmp" 2>/dev/null   # lets apt download sandboxed, without a warning
    if ! (cd "$tmp" && apt_quiet download mesa-opencl-icd) >>"$log" 2>&1; then
        apt_quiet update >>"$log" 2>&1
        if ! (cd "$tmp" && apt_quiet download mesa-opencl-icd) >>"$log" 2>&1; then
            SKIP="apt-get download mesa-opencl-icd failed: $(grep -E '^E:' "$log" | tail -n 1)"
            rm -rf "$tmp"; return 1
        fi
    fi
    deb="$(ls "$tmp"/mesa-opencl-icd_*.deb 2>/dev/null | head -n 1)"
    rm -rf "$dir"
    mkdir -p "$dir/icd" "$dir/root"
    if [ -z "$deb" ] || ! dpkg -x "$deb" "$dir/root" >>"$log" 2>&1; then
        SKIP="dpkg -x of mesa-opencl-icd failed"; rm -rf "$tmp"; return 1
    fi
    rm -rf "$tmp"
    lib="$(find "$dir/root/usr/lib" -name 'libRusticlOpenCL.so.1' -print -quit)"
    [ -n "$lib" ] || { SKIP="no libRusticlOpenCL.so.1 in mesa-opencl-icd"; return 1; }
    missing_libs="$(ldd "$lib" 2>/dev/null | awk '/not found/ {print $1}' | tr '\n' ' ')"
    [ -z "$missing_libs" ] || { SKIP="libRusticlOpenCL.so.1 lacks: $missing_libs"; return 1; }
    echo "$lib" > "$dir/icd/rusticl.icd"
    # Debian's rusticl 22.3 links its gallium drivers statically (it never reads
    # gallium-pipe/), so GALLIUM_PIPE_SEARCH_DIR is not needed.
    if ! write_env rusticl "OCL_ICD_VENDORS=$dir/icd" "RUSTICL_ENABLE=llvmpipe"; then
        SKIP="check failed: $CHECK_OUT"; return 1
    fi
}

# ----------------------------------------------------------------- main --
if ! "$PYTHON" -c 'import numpy, pyopencl' >/dev/null 2>&1; then
    for t in "${TARGETS[@]}"; do
        echo "$t: skipped: $PYTHON cannot import pyopencl and numpy, needed to check it"
    done
    exit 0
fi

for t in "${TARGETS[@]}"; do
    if check_env "$ROOT/$t/env"; then
        echo "$t: already installed ($CHECK_OUT)"
        continue
    fi
    rm -f "$ROOT/$t/env"
    start=$SECONDS
    SKIP=""
    : > "$ROOT/$t.log"
    if "install_$t"; then
        echo "$t: installed in $((SECONDS - start))s ($CHECK_OUT) -> $ROOT/$t/env"
    else
        rm -f "$ROOT/$t/env"
        case "$SKIP" in check*) ;; *) rm -rf "${ROOT:?}/$t" ;; esac
        echo "$t: skipped: ${SKIP:-install failed} (log: $ROOT/$t.log)"
    fi
done
exit 0
