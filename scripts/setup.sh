#!/usr/bin/env bash
# One-time (idempotent) set-up: system libraries, a virtual environment in .venv,
# and the project with the extras named in $BCSDF_EXTRAS (default: test).
set -euo pipefail
cd "$(dirname "$0")/.."

# Dr.Jit's LLVM backend needs LLVM >= 16 (the system's LLVM 15 aborts with
# "Cannot select ... fmaximum"); Debian ships libllvm19.
if ! ls /usr/lib/*/libLLVM-19.so* >/dev/null 2>&1 && ! ls /usr/lib/libLLVM-19.so* >/dev/null 2>&1; then
    echo "[setup] installing libllvm19 (Dr.Jit LLVM backend)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get install -y -q libllvm19 >/dev/null 2>&1 || {
        $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q libllvm19 >/dev/null; }
fi

extras="${BCSDF_EXTRAS:-train,onnx,render,stability,test}"
# The tests open the HTML report in headless Chromium
if [[ "$extras" == *test* ]] && ! command -v chromium >/dev/null 2>&1; then
    echo "[setup] installing chromium (report test)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get install -y -q chromium >/dev/null 2>&1 || {
        $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q chromium >/dev/null; }
fi
stamp=".venv/.installed-${extras//,/-}"
if [ ! -x .venv/bin/python ]; then
    echo "[setup] creating .venv"
    python3 -m venv .venv
fi
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "[setup] installing the project with extras [$extras]"
    # uv resolves and installs in seconds what pip takes a minute for (docs/BENCHMARKS.md,
    # "The whole default pipeline"); pip stays the fallback where uv cannot be had. Both
    # compile the bytecode at install (uv only when asked): with PYTHONDONTWRITEBYTECODE
    # set, as on some machines, every process would otherwise compile torch's sources
    # again (~10 s).
    [ -x .venv/bin/uv ] || .venv/bin/pip install -q uv >/dev/null 2>&1 || echo "[setup] no uv: installing with pip"
    install() {
        if [ -x .venv/bin/uv ]; then
            .venv/bin/uv pip install -q --compile-bytecode --python .venv/bin/python "$@" && return
            echo "[setup] uv could not install $*; trying pip"
        fi
        .venv/bin/pip install -q "$@"
    }
    # torch==2.13.0 is a CPU build on this machine's disk (pip's find-links, /opt/wheels);
    # install that file first so that the range in pyproject resolves to it instead of
    # downloading a CUDA build (uv does not read pip's find-links, so it is given the file).
    if [[ "$extras" == *train* || "$extras" == *test* ]]; then
        wheel=""
        for dir in ${PIP_FIND_LINKS:-} /opt/wheels; do
            for f in "$dir"/torch-2.13.0+cpu-*.whl; do [ -f "$f" ] && wheel="$f" && break 2; done
        done
        if [ -n "$wheel" ]; then install --no-deps "$wheel"; else .venv/bin/pip install -q "torch==2.13.0"; fi
    fi
    install -e ".[${extras}]"
    touch "$stamp"
fi
