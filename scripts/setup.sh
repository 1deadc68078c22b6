#!/usr/bin/env bash
# One-command, idempotent setup of the FroDO workspace on a fresh Debian machine:
# apt packages, a Python 3.11+ virtualenv (.venv) with pinned dependencies, and the workspace
# packages installed in editable mode. Re-running only installs what changed.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${FRODO_VENV:-$ROOT/.venv}"
STAMP="$VENV/.frodo-setup-stamp"

die() { echo "setup: ERROR: $*" >&2; exit 1; }
say() { echo "setup: $*"; }

# --- apt packages (only what pip wheels do not bring) ------------------------------------------
APT_PACKAGES=(python3-venv libgl1 libglib2.0-0 libgomp1)
missing=()
if command -v dpkg-query >/dev/null 2>&1; then
    for p in "${APT_PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
    done
fi
if [ "${#missing[@]}" -gt 0 ]; then
    if [ "$(id -u)" -ne 0 ] && ! command -v sudo >/dev/null 2>&1; then
        die "missing apt packages: ${missing[*]} (run as root or install them)"
    fi
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    say "installing apt packages: ${missing[*]}"
    $SUDO apt-get update -qq || die "apt-get update failed (is the Debian mirror reachable?)"
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null \
        || die "apt-get install ${missing[*]} failed"
fi

# --- Python interpreter: the ROS 2 Jazzy wheels are built for CPython 3.11 ---------------------
PY="${FRODO_PYTHON:-}"
if [ -z "$PY" ]; then
    for cand in python3.11 python3; do
        if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
            PY="$(command -v "$cand")"; break
        fi
    done
    if [ -z "$PY" ] && command -v pyenv >/dev/null 2>&1; then
        v="$(pyenv versions --bare 2>/dev/null | grep -E '^3\.11' | tail -1 || true)"
        [ -n "$v" ] && PY="$(pyenv root)/versions/$v/bin/python3"
    fi
fi
[ -n "$PY" ] || die "CPython 3.11 not found (the ros-jazzy-rclpy wheels are cp311); set FRODO_PYTHON=/path/to/python3.11"

# --- virtualenv and pinned dependencies --------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
    say "creating virtualenv $VENV with $PY"
    "$PY" -m venv "$VENV" || die "could not create a virtualenv (apt-get install python3-venv?)"
fi
# shellcheck disable=SC1091
. "$VENV/bin/activate"

want="$(cat "$ROOT/requirements.txt" "$ROOT"/src/*/setup.py | sha256sum | cut -d' ' -f1)"
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    say "environment up to date ($VENV)"
    exit 0
fi
say "installing pinned Python packages (torch pulls CUDA libraries, a few GB; runs on the CPU when there is no GPU)"
python -m pip install -q --upgrade pip wheel "setuptools<80" || die "pip upgrade failed"
python -m pip install -q -r "$ROOT/requirements.txt" || die "pip install -r requirements.txt failed (see above)"
for pkg in "$ROOT"/src/*/; do
    python -m pip install -q --no-deps -e "$pkg" || die "installing workspace package $pkg failed"
done
python - <<'PY' || die "post-install check failed"
import rclpy, torch, trimesh, mcap, rosbags, rerun, cv2  # noqa: F401
import frodo_common, frodo_datasets, frodo_detection, frodo_association, frodo_shape, frodo_optim, frodo_bringup  # noqa: F401
print(f"setup: ok (torch {torch.__version__}, cuda={torch.cuda.is_available()}, trimesh {trimesh.__version__})")
PY
echo "$want" > "$STAMP"
say "done. Activate with: . $VENV/bin/activate"
