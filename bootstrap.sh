#!/usr/bin/env bash
# Create (or refresh) the project's environment on a fresh Debian machine.
# Idempotent: a second run only checks. Used by both Quick start commands and by .ci/run.
set -euo pipefail
cd "$(dirname "$0")"

# Options (environment):
#   GS_NO_RERUN=1    skip the `rerun` extra (rerun-sdk + pyarrow, ~650 MB in .venv): no
#                    `--viewer rerun`, its tests skip with a message.
#   GS_NO_BROWSER=1  skip Debian's chromium (~350 MB): the browser checks of report.html and of
#                    the Rerun web viewer skip with a message.

# System libraries: open3d needs libEGL/libGL (offscreen rendering) and libusb at import time;
# the browser tests need Debian's chromium (Playwright drives it; no browser is downloaded).
need_apt=()
pkgs=()
for pair in libEGL.so.1:libegl1 libGL.so.1:libgl1 libusb-1.0.so.0:libusb-1.0-0; do
    lib=${pair%%:*}
    if ! ldconfig -p 2>/dev/null | grep -q "$lib"; then
        need_apt+=("$lib"); pkgs+=("${pair#*:}")
    fi
done
if [ "${GS_NO_BROWSER:-0}" != "1" ] && ! command -v chromium >/dev/null 2>&1; then
    need_apt+=("chromium"); pkgs+=("chromium")
fi
if [ ${#need_apt[@]} -gt 0 ]; then
    echo "bootstrap: installing system packages for: ${need_apt[*]}"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
        "${pkgs[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv with $($PY --version)"
    $PY -m venv .venv
fi
extras="dev,rerun"
[ "${GS_NO_RERUN:-0}" = "1" ] && extras="dev"
# Reinstall only when pyproject.toml (or the extras chosen) changed since the last install.
stamp=.venv/.installed-$( (cat pyproject.toml; echo "$extras") | sha1sum | cut -c1-12)
if [ ! -f "$stamp" ]; then
    echo "bootstrap: installing Python packages [$extras] (about 2 minutes the first time)"
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".[$extras]"
    rm -f .venv/.installed-*
    touch "$stamp"
fi
