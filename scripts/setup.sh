#!/usr/bin/env bash
# README command 1: install everything the toolkit needs on a fresh Debian 12/13 or Ubuntu
# 22.04+ machine (system packages, a virtual environment with pinned Python dependencies,
# torch's CPU build), then run the main job on built-in defaults.
#
# Idempotent: re-running skips what is already in place. Environment knobs:
#   VENV=.venv          where the virtual environment goes
#   SKIP_SYSTEM=1       do not touch system packages (no root needed)
#   SETUP_ONLY_SYSTEM=1 stop after the system packages (tests/test_setup_script.py uses this)
#   SKIP_MAIN_JOB=1     install only (CI uses this)
#   PYTHON=python3      interpreter the venv is made from (3.10-3.12)
# For tests only (the defaults are the real system's):
#   UWDOCK_OS_RELEASE=/etc/os-release  UWDOCK_APT_ETC=/etc/apt  UWDOCK_APT_LISTS=/var/lib/apt/lists
set -euo pipefail

cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${VENV:-$ROOT/.venv}
PYTHON=${PYTHON:-python3}
OS_RELEASE=${UWDOCK_OS_RELEASE:-/etc/os-release}
APT_ETC=${UWDOCK_APT_ETC:-/etc/apt}
APT_LISTS=${UWDOCK_APT_LISTS:-/var/lib/apt/lists}

# Colours only on a terminal (and not with NO_COLOR), so that logs read "[setup] error: ...".
if [ -t 1 ] && [ -z "${NO_COLOR:-}" ]; then B=$'\033[1m' N=$'\033[0m'; else B="" N=""; fi
if [ -t 2 ] && [ -z "${NO_COLOR:-}" ]; then R=$'\033[31m' RN=$'\033[0m'; else R="" RN=""; fi
say() { printf '%s[setup]%s %s\n' "$B" "$N" "$*"; }
die() { printf '%s[setup] error:%s %s\n' "$R" "$RN" "$*" >&2; exit 1; }

# ---------------------------------------------------------------- system packages
MESA_MIN=24.3
BY_HAND="install Mesa >= $MESA_MIN (lavapipe), libusb-1.0-0 and python3-venv yourself, then rerun with SKIP_SYSTEM=1"
SUDO=""        # "sudo" when not root; set by need_root
APT_UPDATED=0  # apt-get update runs at most once per run

need_root() {  # call before the first change to the system (never inside a pipeline or $(...))
  [ "$(id -u)" = 0 ] && return 0
  command -v sudo >/dev/null \
    || die "need root for system packages: run as root, install sudo, or set SKIP_SYSTEM=1 after installing them yourself (see README)"
  SUDO=sudo
  say "not root: using sudo for system packages"
}

as_root() { if [ -n "$SUDO" ]; then sudo "$@"; else "$@"; fi; }

apt_update() {
  [ "$APT_UPDATED" = 1 ] && return 0
  say "updating the package lists (apt-get update)"
  as_root apt-get update -qq \
    || die "apt-get update failed (apt's messages above say which source): check the network and the sources in $APT_ETC, then rerun; or $BY_HAND"
  APT_UPDATED=1
}

apt_install() {  # apt_install [-t SUITE] PKG...
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" \
    || die "apt-get install $* failed (see apt's messages above): fix the cause (network, disk space, held or broken packages) and rerun, or $BY_HAND"
}

installed() {  # is package $1 installed (not just known, removed or half-installed)?
  local st
  st=$(dpkg-query -W -f='${Status}\n' "$1" 2>/dev/null) || return 1
  case "$st" in *" ok installed"*) return 0 ;; *) return 1 ;; esac
}

mesa_version() {  # installed mesa-vulkan-drivers version (upstream part), empty when absent
  local v
  installed mesa-vulkan-drivers || return 0
  v=$(dpkg-query -W -f='${Version}\n' mesa-vulkan-drivers 2>/dev/null) || v=""
  v=${v%%$'\n'*}  # one line per architecture: the first will do
  printf '%s' "$v" | sed -E 's/^[0-9]+://; s/[^0-9.].*//'
}

version_ge() { [ "$(printf '%s\n%s\n' "$2" "$1" | sort -V | head -n1)" = "$2" ]; }

backports_configured() {  # an enabled (not commented-out) bookworm-backports source
  grep -rqsE --include='*.list' --include='*.sources' '^[^#]*bookworm-backports' \
    "$APT_ETC/sources.list" "$APT_ETC/sources.list.d/"
}

install_system() {
  [ -r "$OS_RELEASE" ] || die "no $OS_RELEASE: unsupported system; $BY_HAND"
  local ID="" VERSION_CODENAME="" PRETTY_NAME=""
  # shellcheck source=/dev/null
  . "$OS_RELEASE" || die "cannot read $OS_RELEASE: $BY_HAND"
  case "${ID:-}" in
    debian|ubuntu) ;;
    *) die "unsupported system '${PRETTY_NAME:-unknown}': $BY_HAND" ;;
  esac
  if ! command -v dpkg-query >/dev/null || ! command -v apt-get >/dev/null; then
    die "'${PRETTY_NAME:-$ID}' without dpkg-query/apt-get: $BY_HAND"
  fi

  local pkgs=(python3-venv python3-dev libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1 libgomp1 ca-certificates)
  local backports=0 have p
  # Debian 12's Mesa 22.3 lavapipe lacks VK_KHR_external_semaphore_fd, which SAPIEN needs.
  if [ "$ID" = debian ] && [ "${VERSION_CODENAME:-}" = bookworm ]; then
    have=$(mesa_version)
    if [ -z "$have" ] || ! version_ge "$have" "$MESA_MIN"; then backports=1; fi
  fi
  local missing=()
  for p in "${pkgs[@]}"; do
    # on Debian 12 Mesa comes from backports (below), not with the others from bookworm
    if [ "$backports" = 1 ] && [ "$p" = mesa-vulkan-drivers ]; then continue; fi
    installed "$p" || missing+=("$p")
  done

  if [ "$backports" = 0 ] && [ "${#missing[@]}" = 0 ]; then
    say "system packages already installed"
  else
    need_root
    if [ "$backports" = 1 ]; then
      if ! backports_configured; then
        say "adding Debian bookworm-backports (Mesa >= $MESA_MIN for SAPIEN's CPU renderer)"
        printf 'Types: deb\nURIs: http://deb.debian.org/debian\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
          | as_root tee "$APT_ETC/sources.list.d/bookworm-backports.sources" >/dev/null \
          || die "cannot write $APT_ETC/sources.list.d/bookworm-backports.sources: add bookworm-backports to the APT sources yourself and rerun"
      fi
      apt_update
      [ -n "$(find "$APT_LISTS" -name '*bookworm-backports*Packages*' 2>/dev/null | head -n1)" ] \
        || die "apt-get update fetched no bookworm-backports package lists into $APT_LISTS: check the bookworm-backports source in $APT_ETC (or your mirror), then rerun"
      say "installing mesa-vulkan-drivers from bookworm-backports"
      apt_install -t bookworm-backports mesa-vulkan-drivers
    fi
    if [ "${#missing[@]}" != 0 ]; then
      say "installing system packages: ${missing[*]}"
      apt_update
      apt_install "${missing[@]}"
    fi
  fi

  have=$(mesa_version)
  if [ -z "$have" ] || ! version_ge "$have" "$MESA_MIN"; then
    say "WARNING: Mesa ${have:-none} < $MESA_MIN: SAPIEN cannot render on the CPU. On Ubuntu 22.04/24.04 use the"
    say "         kisak-mesa PPA or a newer release; with an NVIDIA GPU and driver SAPIEN uses the GPU instead."
  else
    say "Mesa $have (lavapipe) is new enough for SAPIEN on the CPU"
  fi
}

if [ "${SKIP_SYSTEM:-0}" != 1 ]; then install_system; else say "SKIP_SYSTEM=1: leaving system packages alone"; fi
if [ "${SETUP_ONLY_SYSTEM:-0}" = 1 ]; then say "SETUP_ONLY_SYSTEM=1: done"; exit 0; fi

# ---------------------------------------------------------------- python environment
command -v "$PYTHON" >/dev/null || die "$PYTHON not found: install python3 (3.10-3.12)"
"$PYTHON" -c 'import sys; sys.exit(not ((3,10) <= sys.version_info[:2] <= (3,12)))' \
  || die "$("$PYTHON" -V 2>&1) is not supported: need Python 3.10-3.12 (set PYTHON=python3.11)"
if [ ! -x "$VENV/bin/python" ]; then
  say "creating virtual environment $VENV"
  "$PYTHON" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip)
STAMP="$VENV/.requirements.sha256"
WANT=$(cat requirements.lock pyproject.toml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ]; then
  say "installing pinned Python dependencies (requirements.lock)"
  "${PIP[@]}" install -q --upgrade pip
  TORCH_INDEX=()
  # torch's CPU build: PyPI's Linux wheel pulls several GB of CUDA libraries.
  # (probed with Python, not curl, which a minimal image lacks)
  if "$VENV/bin/python" -c 'import urllib.request as u; u.urlopen("https://download.pytorch.org/whl/cpu/torch/", timeout=5)' 2>/dev/null; then
    TORCH_INDEX=(--extra-index-url https://download.pytorch.org/whl/cpu)
  fi
  "${PIP[@]}" install -q "${TORCH_INDEX[@]}" -r requirements.lock
  # sapien depends on opencv-python (GUI build); both install the cv2 module. Keep the headless one.
  if "${PIP[@]}" show -q opencv-python 2>/dev/null; then
    "${PIP[@]}" uninstall -q -y opencv-python
    "${PIP[@]}" install -q --force-reinstall --no-deps "$(grep -i '^opencv-python-headless==' requirements.lock)"
  fi
  "${PIP[@]}" install -q --no-deps -e .
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
POLICY=$ROOT/rl/policies/realistic_ppo
say "main job 2/2: one docking episode with the camera in the loop (shipped policy: PPO from scratch, the vehicle's own navigation) into $OUT/demo"
say "  (render -> underwater model -> 3DBM detector -> board PnP -> policy, at 5 Hz; well under a minute on a CPU)"
"$VENV/bin/rl" eval --policy "$POLICY" --obs camera --episodes 1 --seed 7 --videos 0 \
  --out "$OUT/demo" \
  || die "the camera-in-the-loop episode failed (see above); SAPIEN needs Mesa >= 24.3 or a GPU"
say "wrote $OUT/demo/camera_ep0.mp4 (camera view), camera_ep0_frames.jpg, summary.json, trajectories_top.png, traces_ep0.png"
say "done. Activate the environment with: source $VENV/bin/activate"
