#!/usr/bin/env bash
# Installs everything s3k needs on a fresh Debian/Ubuntu machine into ./.venv:
# system libraries (OSMesa for MuJoCo's CPU rendering, Chromium for the labelling app's browser test),
# PyTorch, then s3k with its dev, formats, robot, label, stream and cluster extras.
# `setup.sh --demo` installs what `s3k demo` needs only: OSMesa, PyTorch and s3k itself (scripts/demo.sh).
# What is already there is skipped: system packages that are present, and the pip installs when .venv holds
# a stamp of this pyproject.toml from an earlier install of the same extras and s3k imports from here (a
# changed pyproject.toml, a new .venv or a moved checkout installs again).
set -euo pipefail
cd "$(dirname "$0")/.."
demo=0
[ "${1:-}" = "--demo" ] && demo=1

need_apt=()
[ -e /usr/lib/x86_64-linux-gnu/libOSMesa.so.8 ] || [ -e /usr/lib/aarch64-linux-gnu/libOSMesa.so.8 ] \
    || ls /usr/lib/*/libOSMesa.so* >/dev/null 2>&1 || need_apt+=(libosmesa6)
# The browser the labelling app's tests drive (Playwright with this executable; never a downloaded build).
[ $demo = 1 ] || [ -x /usr/bin/chromium ] || need_apt+=(chromium fonts-liberation)
if [ ${#need_apt[@]} -gt 0 ]; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -qq </dev/null
    $SUDO apt-get install -y -qq "${need_apt[@]}" </dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
. .venv/bin/activate
extras="dev,formats,robot,label,stream,cluster"
[ $demo = 1 ] && extras=""
stamp_of() { printf '%s\n' "$(sha256sum pyproject.toml | cut -d' ' -f1)" "$1"; }
installed_here() {  # s3k imports from this checkout
    python -c 'import pathlib, sys, s3k; sys.exit(pathlib.Path(s3k.__file__).resolve().parents[1] != pathlib.Path.cwd().resolve())' 2>/dev/null
}
for have in "$extras" "dev,formats,robot,label,stream,cluster"; do  # a full install serves the demo too
    if [ -f .venv/.s3k-setup-stamp ] && [ "$(cat .venv/.s3k-setup-stamp)" = "$(stamp_of "$have")" ] \
        && installed_here; then
        exit 0
    fi
done
python -m pip install -q --upgrade pip </dev/null
# PyTorch first, so that nothing below pulls a multi-GB CUDA build; a GPU machine may preinstall its own.
python -c "import torch" 2>/dev/null || python -m pip install -q "torch==2.13.0" </dev/null \
    || python -m pip install -q "torch>=2.2,<3" </dev/null
if [ $demo = 1 ]; then
    python -m pip install -q -e . </dev/null
else
    python -m pip install -q -e ".[$extras]" </dev/null
fi
stamp_of "$extras" > .venv/.s3k-setup-stamp
