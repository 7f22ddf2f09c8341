#!/usr/bin/env bash
# The GPU report in one command, from the repository root, on a bare machine:
#
#   bench/gpu_report.sh OUT                          # the machine's OpenCL GPU driver
#   bench/gpu_report.sh OUT --implementation pocl    # here: PoCL (or intel, rusticl) in a fresh venv
#   bench/gpu_report.sh OUT --tiny ...               # tiny scenes and sizes (the test's run)
#   bench/gpu_report.sh --prepare [--python-version 3.12] [--tiny]   # here, with a network
# Options of both: --carry DIR (default .gpu-report), --budget SECONDS (default 540).
#
# It installs nothing from the network and never pip-installs torch on the GPU machine: it uses the
# machine's own python3 and torch plus what --prepare put in the carry folder (carried beside the
# tree, ignored by git): wheels of pyopencl and what it needs, gsplat 1.5.3's sdist, the real scenes
# and PoCL's parity results made here (--tiny: the wheels and the small scene's results). It finds
# the vendor's OpenCL library (NVIDIA's libnvidia-opencl.so.1, ROCm's libamdocl64.so, Intel's
# compute runtime libigdrcl.so), writes a private ICD folder naming it and runs, in order,
# bench/gpu_report.py's phases: devices, parity, sweep, gsplat (built in the background from the
# start where nvcc and a CUDA torch are there), twins, each within what is left of the budget,
# then the report. OUT gets at most 8 files: report.md, report.json and the logs.
# --implementation NAME runs the same in a fresh venv holding only the carried wheels and torch
# 2.13.0 (this machine's disk file), on PoCL or on an implementation tests/drivers/install.sh
# installed.
set -uo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
CARRY="$REPO/.gpu-report"

usage() { sed -n '2,7p' "$0" >&2; exit 2; }

prepare() {   # the wheels for --python-version, gsplat's sdist, the scenes and PoCL's results
    local pyver="3.12" tiny="" data="${QR_CL_DATA:-$REPO/../shared/data}" py="${QR_CL_PYTHON:-python3}"
    while [ $# -gt 0 ]; do
        case "$1" in
            --python-version) pyver="$2"; shift 2 ;;
            --tiny) tiny="--tiny"; shift ;;
            *) usage ;;
        esac
    done
    local tag="${pyver/./}"
    mkdir -p "$CARRY/wheels/cp$tag" || exit 1
    if [ "$CARRY" = "$REPO/.gpu-report" ]; then
        grep -qx '/.gpu-report/' "$REPO/.git/info/exclude" 2>/dev/null || echo '/.gpu-report/' >> "$REPO/.git/info/exclude"
    fi
    # the versions installed here, so that the carried set is the one the tests pass with: what the
    # GPU machine lacks, and for this Python's own version (a fresh venv here) what a venv lacks too
    local pins
    pins=$("$py" - "$pyver" <<'PY'
import sys
from importlib.metadata import version
names = ["pyopencl", "pytools", "platformdirs", "siphash24", "mako"]
if sys.argv[1] == f"{sys.version_info[0]}.{sys.version_info[1]}":
    names += ["typing_extensions", "markupsafe", "numpy", "tqdm", "setuptools", "pytest", "pluggy", "iniconfig",
              "packaging", "pygments", "matplotlib", "contourpy", "cycler", "fonttools", "kiwisolver", "pillow",
              "pyparsing", "python-dateutil", "six"]
print(" ".join(f"{n}=={version(n)}" for n in names), "wheel==0.45.1" if len(names) > 5 else "")
PY
) || { echo "prepare: a package pinned from this environment is missing" >&2; exit 1; }
    "$py" -m pip download -q --no-deps --only-binary=:all: --python-version "$pyver" --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        -d "$CARRY/wheels/cp$tag" $pins || exit 1
    if [ -z "$tiny" ]; then
        # its setup.py wants CUDA to say its metadata: BUILD_NO_CUDA (the build on the GPU machine compiles it)
        BUILD_NO_CUDA=1 "$py" -m pip download -q --no-deps --no-binary=:all: --no-build-isolation -d "$CARRY" \
            gsplat==1.5.3 || exit 1
        mkdir -p "$CARRY/data"
        for scene in wakufactory-fox v3dg-donut; do
            [ -d "$data/$scene" ] && cp -r "$data/$scene" "$CARRY/data/"
        done
    fi
    local scenes=(--tiny)
    [ -z "$tiny" ] && scenes=(--data "$CARRY/data")
    "$py" "$REPO/bench/gpu_report.py" make-reference "$CARRY" "$CARRY/work" "${scenes[@]}" \
        --reference "$CARRY/reference.npz" || exit 1
    rm -rf "$CARRY/work"
    du -sh "$CARRY"
}

[ $# -ge 1 ] || usage
OUT=""; IMPL=""; TINY=""; BUDGET=540; PREPARE=""; PREPARE_ARGS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --prepare) PREPARE=1; shift ;;
        --python-version) PREPARE_ARGS+=("$1" "$2"); shift 2 ;;
        --carry) CARRY="$(mkdir -p "$2" && cd "$2" && pwd)"; shift 2 ;;
        --implementation) IMPL="$2"; shift 2 ;;
        --tiny) TINY="--tiny"; shift ;;
        --budget) BUDGET="$2"; shift 2 ;;
        -*) usage ;;
        *) [ -z "$OUT" ] || usage; OUT="$1"; shift ;;
    esac
done
if [ -n "$PREPARE" ]; then prepare "${PREPARE_ARGS[@]}" $TINY; exit; fi
[ -n "$OUT" ] || usage
START=$(date +%s)
mkdir -p "$OUT"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/qr-cl-gpu-report.XXXXXX")"
SETUP_LOG="$OUT/setup.log"
exec 3>&1
log() { echo "[$(( $(date +%s) - START ))s] $*" | tee -a "$SETUP_LOG" >&3; }
left() { echo $(( BUDGET - ($(date +%s) - START) )); }
: > "$SETUP_LOG"

# ---- python: the machine's own, or a fresh venv with torch 2.13.0 (here) ----
PY="${QR_CL_PYTHON:-python3}"
if [ -n "$IMPL" ]; then
    log "fresh venv for --implementation $IMPL"
    "$PY" -m venv "$WORK/venv" >> "$SETUP_LOG" 2>&1 || { log "venv failed"; exit 1; }
    PY="$WORK/venv/bin/python"
    "$PY" -m pip install -q torch==2.13.0 >> "$SETUP_LOG" 2>&1 || { log "torch 2.13.0 failed to install"; exit 1; }
fi
TAG=$("$PY" -c 'import sys; print(f"cp{sys.version_info[0]}{sys.version_info[1]}")')
WHEELS="$CARRY/wheels/$TAG"
[ -d "$WHEELS" ] || { log "no carried wheels for $TAG in $WHEELS (bench/gpu_report.sh --prepare --python-version X.Y)"; exit 1; }
SITE="$WORK/site"
log "installing the carried wheels ($TAG) and qr-cl into $SITE"
"$PY" -m pip install -q --no-index --no-deps --no-compile --target "$SITE" "$WHEELS"/*.whl >> "$SETUP_LOG" 2>&1 \
    || { log "the carried wheels failed to install"; exit 1; }
export PYTHONPATH="$SITE"
"$PY" -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --target "$WORK/qr-cl" "$REPO" \
    >> "$SETUP_LOG" 2>&1 || { log "qr-cl failed to install"; exit 1; }
export PYTHONPATH="$WORK/qr-cl:$SITE"
"$PY" -c 'import torch, numpy, pyopencl; print("torch", torch.__version__, "numpy", numpy.__version__, "pyopencl", pyopencl.VERSION_TEXT)' \
    >> "$SETUP_LOG" 2>&1 || { log "torch, numpy or pyopencl does not import"; exit 1; }

# ---- the OpenCL driver: a private ICD folder naming the vendor's library ----
VENDORS="$WORK/vendors"; mkdir -p "$VENDORS"
if [ -n "$IMPL" ] && [ "$IMPL" != "pocl" ]; then
    ENV_FILE="${QR_CL_DRIVERS:-$HOME/.cache/qr-cl/drivers}/$IMPL/env"
    [ -f "$ENV_FILE" ] || { log "$IMPL is not installed (bash tests/drivers/install.sh $IMPL)"; exit 1; }
    while IFS= read -r line; do [ -n "$line" ] && export "$line"; done < "$ENV_FILE"
    log "OpenCL: $IMPL ($ENV_FILE)"
elif [ "$IMPL" = "pocl" ]; then
    lib=$(ls /etc/OpenCL/vendors/pocl.icd >/dev/null 2>&1 && cat /etc/OpenCL/vendors/pocl.icd)
    [ -n "$lib" ] || { log "PoCL's ICD file /etc/OpenCL/vendors/pocl.icd is missing"; exit 1; }
    echo "$lib" > "$VENDORS/pocl.icd"; export OCL_ICD_VENDORS="$VENDORS"
    log "OpenCL: PoCL ($lib)"
else
    found=""
    for name in libnvidia-opencl.so.1 libamdocl64.so libigdrcl.so; do
        path=$( (ldconfig -p 2>/dev/null | awk -v n="$name" '$1 == n {print $NF; exit}') )
        for dir in /usr/local/nvidia/lib64 /usr/lib/x86_64-linux-gnu /usr/lib64 /opt/rocm/lib /opt/rocm/opencl/lib; do
            [ -z "$path" ] && [ -e "$dir/$name" ] && path="$dir/$name"
        done
        if [ -n "$path" ]; then echo "$path" > "$VENDORS/${name%%.so*}.icd"; found="$found $path"; fi
    done
    [ -n "$found" ] || { log "no vendor OpenCL library found (libnvidia-opencl.so.1, libamdocl64.so, libigdrcl.so)"; exit 1; }
    export OCL_ICD_VENDORS="$VENDORS"
    log "OpenCL:$found"
fi
# PYTHONSAFEPATH: no process puts the source tree (the working folder) before the installed qr-cl
export QR_CL_CACHE="$WORK/cache" XDG_CACHE_HOME="$WORK/xdg" PYTHONUNBUFFERED=1 PYTHONWARNINGS=ignore PYTHONSAFEPATH=1

# ---- gsplat: built in the background from the start (nvcc and a CUDA torch) ----
GSPLAT_LOG="$OUT/gsplat.log"; : > "$GSPLAT_LOG"
SDIST=$(ls "$CARRY"/gsplat-1.5.3.tar.gz 2>/dev/null)
CUDA_ARCH=$("$PY" -c 'import torch; c = torch.cuda.get_device_capability() if torch.cuda.is_available() else None; print(f"{c[0]}.{c[1]}" if c else "")' 2>/dev/null)
GSPLAT_PID=""
if [ -n "$SDIST" ] && [ -n "$CUDA_ARCH" ] && command -v nvcc >/dev/null; then
    log "building gsplat 1.5.3 for sm_${CUDA_ARCH/./} in the background"
    ( TORCH_CUDA_ARCH_LIST="$CUDA_ARCH" MAX_JOBS=$(nproc) "$PY" -m pip install --no-index --no-deps \
        --no-build-isolation --no-compile --target "$WORK/gsplat" "$SDIST" >> "$GSPLAT_LOG" 2>&1 ) &
    GSPLAT_PID=$!
else
    echo "gsplat not built: ${SDIST:-no sdist carried}${CUDA_ARCH:+}${CUDA_ARCH:- / no CUDA device} / nvcc $(command -v nvcc || echo missing)" >> "$GSPLAT_LOG"
fi

ARGS=("$OUT" "$WORK/results" $TINY --reference "$CARRY/reference.npz")
[ -d "$CARRY/data" ] && ARGS+=(--data "$CARRY/data")
[ -n "${QR_CL_DATA:-}" ] && ARGS+=(--data "$QR_CL_DATA")
phase() {   # phase NAME LOG: bench/gpu_report.py NAME within what is left of the budget
    local name="$1" out="$2" t
    t=$(left)
    if [ "$t" -lt 20 ]; then log "$name: skipped, the budget is spent"; return; fi
    log "$name (up to ${t}s)"
    timeout "$t" "$PY" "$REPO/bench/gpu_report.py" "$name" "${ARGS[@]}" >> "$out" 2>&1
    log "$name: exit $?"
}
phase devices "$OUT/devices.log"
phase parity "$OUT/parity.log"
phase sweep "$OUT/sweep.log"
if [ -n "$GSPLAT_PID" ]; then
    log "waiting for gsplat's build"
    wait "$GSPLAT_PID" && export PYTHONPATH="$WORK/gsplat:$PYTHONPATH"
fi
phase gsplat "$GSPLAT_LOG"
phase twins "$OUT/twins.log"
"$PY" "$REPO/bench/gpu_report.py" report "${ARGS[@]}" --seconds $(( $(date +%s) - START )) \
    --command "bench/gpu_report.sh $(basename "$OUT")${IMPL:+ --implementation $IMPL}${TINY:+ --tiny}" >> "$SETUP_LOG" 2>&1
rm -rf "$WORK"
[ -f "$OUT/report.md" ] || { log "the report failed (see the end of this log)"; exit 1; }
log "report: $OUT/report.md"
