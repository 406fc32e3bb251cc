#!/usr/bin/env bash
# README command 1: install everything the toolkit needs on a fresh Debian 12/13 or Ubuntu
# 22.04+ machine (system packages, a virtual environment with pinned Python dependencies,
# torch's CPU build), then run the main job on built-in defaults.
#
# Idempotent: re-running skips what is already in place. Environment knobs:
#   VENV=.venv          where the virtual environment goes
#   SKIP_SYSTEM=1       do not touch system packages (no root needed)
#   SKIP_MAIN_JOB=1     install only (CI uses this)
#   PYTHON=python3      interpreter the venv is made from (3.10-3.12)
set -euo pipefail

cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${VENV:-$ROOT/.venv}
PYTHON=${PYTHON:-python3}

say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
die() { printf '\033[31m[setup] error:\033[0m %s\n' "$*" >&2; exit 1; }

# ---------------------------------------------------------------- system packages
as_root() {
  if [ "$(id -u)" = 0 ]; then "$@"
  elif command -v sudo >/dev/null; then sudo "$@"
  else die "need root for system packages: run as root, install sudo, or set SKIP_SYSTEM=1 after installing them yourself (see README)"
  fi
}

mesa_version() {  # installed mesa-vulkan-drivers version (upstream part), empty when absent
  local v
  v=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null) || v=""
  printf '%s' "$v" | sed -E 's/^[0-9]+://; s/[^0-9.].*//'
}

version_ge() { [ "$(printf '%s\n%s\n' "$2" "$1" | sort -V | head -n1)" = "$2" ]; }

install_system() {
  [ -r /etc/os-release ] || die "no /etc/os-release: unsupported system; install Mesa >= 24.3 (lavapipe), libusb-1.0-0 and python3-venv yourself, then rerun with SKIP_SYSTEM=1"
  . /etc/os-release
  local pkgs="python3-venv python3-dev libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1 libgomp1 ca-certificates"
  case "${ID:-}" in
    debian)
      if [ "${VERSION_CODENAME:-}" = bookworm ]; then
        # Debian 12's Mesa 22.3 lavapipe lacks VK_KHR_external_semaphore_fd, which SAPIEN needs.
        if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
          say "adding Debian bookworm-backports (Mesa >= 24.3 for SAPIEN's CPU renderer)"
          printf 'Types: deb\nURIs: http://deb.debian.org/debian\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
            | as_root tee /etc/apt/sources.list.d/bookworm-backports.sources >/dev/null
          as_root apt-get update -qq
        fi
        local have; have=$(mesa_version)
        if [ -z "$have" ] || ! version_ge "$have" 24.3; then
          say "installing mesa-vulkan-drivers from bookworm-backports"
          [ -n "$(find /var/lib/apt/lists -name '*bookworm-backports*Packages*' 2>/dev/null | head -n1)" ] || as_root apt-get update -qq
          as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers
        fi
      fi
      ;;
    ubuntu) ;;
    *) die "unsupported system '${PRETTY_NAME:-unknown}': install Mesa >= 24.3 (lavapipe), libusb-1.0-0 and python3-venv yourself, then rerun with SKIP_SYSTEM=1" ;;
  esac
  local missing=""
  for p in $pkgs; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed' || missing="$missing $p"; done
  if [ -n "$missing" ]; then
    say "installing system packages:$missing"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing
  else
    say "system packages already installed"
  fi
  local have; have=$(mesa_version)
  if [ -z "$have" ] || ! version_ge "$have" 24.3; then
    say "WARNING: Mesa ${have:-none} < 24.3: SAPIEN cannot render on the CPU. On Ubuntu 22.04/24.04 use the"
    say "         kisak-mesa PPA or a newer release; with an NVIDIA GPU and driver SAPIEN uses the GPU instead."
  else
    say "Mesa $have (lavapipe) is new enough for SAPIEN on the CPU"
  fi
}

if [ "${SKIP_SYSTEM:-0}" != 1 ]; then install_system; else say "SKIP_SYSTEM=1: leaving system packages alone"; fi

# ---------------------------------------------------------------- python environment
command -v "$PYTHON" >/dev/null || die "$PYTHON not found: install python3 (3.10-3.12)"
"$PYTHON" -c 'import sys; sys.exit(not ((3,10) <= sys.version_info[:2] <= (3,12)))' \
  || die "$("$PYTHON" -V 2>&1) is not supported: need Python 3.10-3.12 (set PYTHON=python3.11)"
if [ ! -x "$VENV/bin/python" ]; then
  say "creating virtual environment $VENV"
  "$PYTHON" -m venv "$VENV"
fi
PIP="$VENV/bin/python -m pip"
STAMP="$VENV/.requirements.sha256"
WANT=$(cat requirements.lock pyproject.toml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ]; then
  say "installing pinned Python dependencies (requirements.lock)"
  $PIP install -q --upgrade pip
  TORCH_INDEX=()
  # torch's CPU build: PyPI's Linux wheel pulls several GB of CUDA libraries.
  if curl -sf --max-time 5 -o /dev/null https://download.pytorch.org/whl/cpu/torch/ 2>/dev/null; then
    TORCH_INDEX=(--extra-index-url https://download.pytorch.org/whl/cpu)
  fi
  $PIP install -q "${TORCH_INDEX[@]}" -r requirements.lock
  # sapien depends on opencv-python (GUI build); both install the cv2 module. Keep the headless one.
  if $PIP show -q opencv-python 2>/dev/null; then
    $PIP uninstall -q -y opencv-python
    $PIP install -q --force-reinstall --no-deps "$(grep -i '^opencv-python-headless==' requirements.lock)"
  fi
  $PIP install -q --no-deps -e .
  echo "$WANT" > "$STAMP"
else
  say "Python dependencies up to date"
fi
"$VENV/bin/python" -c 'import cv2, numpy, trimesh, manifold3d; print("[setup] cv2", cv2.__version__, "numpy", numpy.__version__)'

# ---------------------------------------------------------------- main job
if [ "${SKIP_MAIN_JOB:-0}" = 1 ]; then say "SKIP_MAIN_JOB=1: done"; exit 0; fi
OUT=${OUT_DIR:-$ROOT/out}
say "main job 1/2: generating the docking-station marker set into $OUT/markers"
"$VENV/bin/markers" generate --quiet --out "$OUT/markers"
POLICY=$ROOT/rl/policies/error_model_ppo
say "main job 2/2: one docking episode with the camera in the loop (shipped policy) into $OUT/demo"
say "  (render -> underwater model -> 3DBM detector -> board PnP -> policy, at 5 Hz; well under a minute on a CPU)"
"$VENV/bin/rl" eval --policy "$POLICY" --obs camera --episodes 1 --seed 7 --videos 0 \
  --out "$OUT/demo" \
  || die "the camera-in-the-loop episode failed (see above); SAPIEN needs Mesa >= 24.3 or a GPU"
say "wrote $OUT/demo/camera_ep0.mp4 (camera view), camera_ep0_frames.jpg, summary.json, trajectories_top.png, traces_ep0.png"
say "done. Activate the environment with: source $VENV/bin/activate"
