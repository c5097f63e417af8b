#!/usr/bin/env bash
# Create or update the project's virtual environment (.venv) with the toolkit installed.
# Safe to run again: it only reinstalls when pyproject.toml changed. Used by demo.sh and test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# open3d's import fails without the system library libusb-1.0.
if ! { ldconfig -p 2>/dev/null || true; } | grep -q 'libusb-1.0.so.0'; then
  if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "setup: installing libusb-1.0-0 (needed by open3d)" >&2
    $SUDO apt-get update -qq >/dev/null && $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "setup: warning: install libusb-1.0 with your system's package manager (open3d needs it)" >&2
  fi
fi

# The viewer's browser tests drive Debian's Chromium with playwright (never a browser download).
if [ ! -x /usr/bin/chromium ]; then
  if command -v apt-get >/dev/null 2>&1 && { [ "$(id -u)" -eq 0 ] || command -v sudo >/dev/null 2>&1; }; then
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "setup: installing chromium (the viewer's browser tests)" >&2
    { $SUDO apt-get update -qq >/dev/null && $SUDO apt-get install -y -qq chromium >/dev/null; } \
      || echo "setup: warning: chromium could not be installed; the viewer's browser tests will be skipped" >&2
  else
    echo "setup: note: no /usr/bin/chromium; the viewer's browser tests will be skipped" >&2
  fi
fi

# pip, quietly: some machines' pip configuration warns about every missing local index.
pipq() {
  local rc
  set +o pipefail
  .venv/bin/python -m pip "$@" 2>&1 | { grep -v "^WARNING: Location '" || true; }
  rc=${PIPESTATUS[0]}
  set -o pipefail
  return "$rc"
}

[ -x .venv/bin/python ] || { echo "setup: creating .venv" >&2; "$PY" -m venv .venv; }
stamp=.venv/.dbb-setup-stamp
want=$(sha256sum pyproject.toml | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || ! .venv/bin/python -c "import dbb_capture" 2>/dev/null; then
  echo "setup: installing the toolkit and its dependencies into .venv (first time: a few minutes)" >&2
  pipq install -q --upgrade pip
  # Bring your own torch (e.g. a CUDA build) by installing it into .venv first. Otherwise
  # machines without an NVIDIA driver get the CPU build 2.13.0 rather than a multi-GB CUDA one.
  if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    if command -v nvidia-smi >/dev/null 2>&1; then
      pipq install -q torch
    else
      pipq install -q "torch==2.13.0" || pipq install -q torch
    fi
  fi
  pipq install -q -e ".[test,ray]"
  # svox (PlenOctrees' own library) for the interoperability tests; its CUDA extension is optional,
  # and without build isolation pip builds the pure-Python package against the torch above.
  pipq install -q --no-build-isolation "svox==0.2.32"
  echo "$want" > "$stamp"
fi

# JavaScript packages, from package-lock.json: the viewer's three.js and cannon-es (dbb-serve
# serves node_modules at /vendor/), and tools the tests use (the Khronos glTF validator, iwer).
if command -v npm >/dev/null 2>&1; then
  if [ ! -f node_modules/.package-lock.json ] || [ package-lock.json -nt node_modules/.package-lock.json ]; then
    echo "setup: installing the JavaScript tools (npm ci)" >&2
    npm ci --no-audit --no-fund --loglevel=error >/dev/null
  fi
else
  echo "setup: note: npm not found; the viewer has no three.js and the glTF validator and viewer tests will be skipped" >&2
fi
