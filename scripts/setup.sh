#!/usr/bin/env bash
# Set up mifacerf on a fresh Debian/Ubuntu machine (run as root, or with sudo for the apt steps):
#   - python3 with venv and pip (apt) if missing
#   - a virtual environment in .venv with mifacerf and its dependencies (and the test extras)
#   - an LLVM >= 16 shared library for Mitsuba's llvm_ad_rgb variant (Debian's libllvm19) if none is found
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
die() { printf '\033[1;31m[setup] error:\033[0m %s\n' "$*" >&2; exit 1; }

SUDO=""
if [ "$(id -u)" != "0" ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi
fi
apt_install() {
  command -v apt-get >/dev/null 2>&1 || return 1
  [ "$(id -u)" = "0" ] || [ -n "$SUDO" ] || return 1
  if [ -z "${_APT_UPDATED:-}" ]; then $SUDO apt-get update -qq >/dev/null || return 1; _APT_UPDATED=1; fi
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@" >/dev/null
}

# 1. Python 3.10+ with venv
PY=${PYTHON:-python3}
if ! command -v "$PY" >/dev/null 2>&1 || ! "$PY" -c 'import venv, ensurepip' >/dev/null 2>&1; then
  say "installing python3, python3-venv and python3-pip"
  apt_install python3 python3-venv python3-pip || die "python3 with venv is needed and could not be installed (no apt-get or no root); install Python >= 3.10 with venv and rerun"
fi
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' || die "Python >= 3.10 is needed, found $("$PY" --version)"

# 2. LLVM >= 16 for Dr.Jit's LLVM backend (LLVM 14/15 fail with 'Cannot select: fminimum')
have_llvm() {
  local f v
  for f in /usr/lib/*/libLLVM*.so* /usr/lib/llvm-*/lib/libLLVM*.so* /usr/lib64/libLLVM*.so* /usr/local/lib/libLLVM*.so*; do
    [ -e "$f" ] || continue
    v=$(basename "$f" | sed -nE 's/^libLLVM[-.]?(so\.)?([0-9]+).*/\2/p')
    [ -z "$v" ] && v=$(echo "$f" | sed -nE 's/.*llvm-([0-9]+).*/\1/p')
    [ -n "$v" ] && [ "$v" -ge 16 ] && return 0
  done
  return 1
}
if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && case "${MIFACERF_VARIANT:-llvm_ad_rgb}" in llvm*) true ;; *) false ;; esac && ! have_llvm; then
  say "no LLVM >= 16 shared library found; installing Debian's libllvm19"
  apt_install libllvm19 || die "could not install libllvm19 (needs apt-get and root, Debian 12 or newer). Install an LLVM >= 16 shared library and set DRJIT_LIBLLVM_PATH to it, or choose another Mitsuba variant with MIFACERF_VARIANT (e.g. cuda_ad_rgb)."
  have_llvm || die "libllvm19 installed but no libLLVM >= 16 found; set DRJIT_LIBLLVM_PATH to your libLLVM.so"
fi

# 2b. Debian's chromium and its WebDriver: the studio's browser tests drive them (optional for the rest)
if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
  say "installing Debian's chromium and chromium-driver (for the studio's browser tests)"
  apt_install chromium chromium-driver || say "could not install chromium / chromium-driver: the studio's browser tests will be skipped"
fi

# 3. The virtual environment and the package
if [ ! -x .venv/bin/python ]; then
  say "creating the virtual environment .venv"
  "$PY" -m venv .venv || die "could not create .venv (is python3-venv installed?)"
fi
if ! .venv/bin/python -c 'import mifacerf, mitsuba, drjit, cv2, OpenEXR, distributed, pytest, hypothesis, xdist; assert tuple(map(int, pytest.__version__.split(".")[:2])) < (9, 2)' >/dev/null 2>&1 \
   || [ pyproject.toml -nt .venv/.mifacerf-installed ]; then
  say "installing mifacerf and its dependencies into .venv (first time: a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip >.venv/pip.log 2>&1 || true
  if ! .venv/bin/python -m pip install -e '.[test]' >>.venv/pip.log 2>&1; then
    tail -n 30 .venv/pip.log >&2
    die "pip could not install mifacerf's dependencies (full log: .venv/pip.log)"
  fi
  touch .venv/.mifacerf-installed
fi
.venv/bin/python -c 'from mifacerf.variant import ensure_variant; ensure_variant()' \
  || die "Mitsuba could not start its variant (see the message above)"
say "ready: $(.venv/bin/python -c 'import mitsuba as mi, mifacerf.variant as v; print("mitsuba", mi.__version__, "variant", v.variant_name())')"
