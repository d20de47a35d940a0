#!/usr/bin/env bash
# Install everything nrbench needs on a fresh machine: the system LLVM that Mitsuba's CPU backend
# (Dr.Jit llvm_ad_rgb) loads at run time, uv, and the locked Python environment in .venv.
set -euo pipefail
cd "$(dirname "$0")/.."

llvm_ok() {
  # Any libLLVM with major version >= 16 on the usual library paths.
  for f in /usr/lib/*/libLLVM*.so* /usr/lib/llvm-*/lib/libLLVM*.so* /usr/lib64/libLLVM*.so* /usr/local/lib/libLLVM*.so*; do
    [ -e "$f" ] || continue
    major=$(basename "$f" | sed -nE 's/^libLLVM[-.]?(so\.)?([0-9]+).*/\2/p')
    [ -n "$major" ] && [ "$major" -ge 16 ] && return 0
  done
  return 1
}

if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] || llvm_ok || command -v nvidia-smi >/dev/null 2>&1; then
  :
elif [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "setup: installing libllvm19 (Mitsuba's CPU backend needs LLVM >= 16)"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
else
  echo "setup: Mitsuba's CPU backend needs an LLVM >= 16 shared library and none was found." >&2
  echo "setup: install it, e.g. 'sudo apt-get install libllvm19' (Debian/Ubuntu) or 'sudo dnf install llvm-libs'," >&2
  echo "setup: or point DRJIT_LIBLLVM_PATH at a libLLVM.so >= 16, then run this again." >&2
  exit 1
fi

if command -v uv >/dev/null 2>&1; then
  UV=(uv)
else
  python3 -m uv --version >/dev/null 2>&1 || { echo "setup: installing uv"; python3 -m pip install --quiet "uv==0.13.8"; }
  UV=(python3 -m uv)
fi
# --compile-bytecode: every `python -m src.run` (each DVC stage, each CLI test) would otherwise recompile
# torch, mlflow and friends from source, ~14 s per process here (PYTHONDONTWRITEBYTECODE is common on CI).
"${UV[@]}" sync --frozen --quiet --compile-bytecode
echo "setup: environment ready in .venv ($(.venv/bin/python --version))"
