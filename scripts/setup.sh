#!/usr/bin/env bash
# Set up a fresh machine for seathru-nerfstudio: ffmpeg (ns-render needs it), Chromium (the
# viewer's browser test), a virtualenv in .venv (or $VENV) and this package with its test extras.
# Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

apt_packages=()
command -v ffmpeg >/dev/null || apt_packages+=(ffmpeg)
command -v chromium >/dev/null || apt_packages+=(chromium)
# Mitsuba's fast CPU variant (llvm_ad_rgb, seathru-pathtrace) JIT-compiles with libLLVM >= 19; without it
# the renderer falls back to the much slower scalar_rgb.
optional_packages=()
ls /usr/lib/*/libLLVM.so.19* /usr/lib/*/libLLVM-19.so* >/dev/null 2>&1 || optional_packages+=(libllvm19)
if [ $((${#apt_packages[@]} + ${#optional_packages[@]})) -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq
    if [ ${#apt_packages[@]} -gt 0 ]; then
      echo "setup: apt-get install ${apt_packages[*]}"
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${apt_packages[@]}" >/dev/null
    fi
    if [ ${#optional_packages[@]} -gt 0 ]; then  # a speed-up only: never fail the set-up for it
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${optional_packages[@]}" >/dev/null \
        || echo "setup: warning: ${optional_packages[*]} not installed; seathru-pathtrace uses the slower scalar_rgb" >&2
    fi
  else
    echo "setup: warning: please install ${apt_packages[*]} ${optional_packages[*]} (e.g. with sudo apt-get install)" >&2
  fi
fi

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
# torch 2.14.1 / torchvision 0.29.1 are the pair tested here (CPU, and CUDA wheels on PyPI).
"$VENV/bin/python" -m pip install -q torch==2.14.1 torchvision==0.29.1 -e ".[test,pathtrace]"
echo "setup: done ($VENV)"
