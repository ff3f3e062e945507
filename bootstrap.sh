#!/usr/bin/env bash
# Create (or refresh) the project's environment on a fresh Debian machine.
# Idempotent: a second run only checks. Used by both Quick start commands and by .ci/run.
set -euo pipefail
cd "$(dirname "$0")"

# System libraries: open3d needs libEGL/libGL (offscreen rendering) and libusb at import time.
need_apt=()
for lib in libEGL.so.1 libGL.so.1 libusb-1.0.so.0; do
    ldconfig -p 2>/dev/null | grep -q "$lib" || need_apt+=("$lib")
done
if [ ${#need_apt[@]} -gt 0 ]; then
    echo "bootstrap: installing system libraries for: ${need_apt[*]}"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
        libegl1 libgl1 libusb-1.0-0 >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv with $($PY --version)"
    $PY -m venv .venv
fi
# Reinstall only when pyproject.toml changed since the last successful install.
stamp=.venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)
if [ ! -f "$stamp" ]; then
    echo "bootstrap: installing Python packages (about 2 minutes the first time)"
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".[dev]"
    rm -f .venv/.installed-*
    touch "$stamp"
fi
