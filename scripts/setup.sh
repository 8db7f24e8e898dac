#!/usr/bin/env bash
# Install gscan on Debian / Ubuntu into a virtual environment, then run it (the README's two commands):
#
#   bash scripts/setup.sh [DEMO ARGS]          system packages, a venv, gscan; then `gscan demo [DEMO ARGS]`
#   bash scripts/setup.sh --test [PYTEST ARGS] the same with the test extra and Chromium; then `ruff check` and
#                                              `mypy` (configured in pyproject.toml; either failing fails the
#                                              run), beside them `gscan demo --no-view` (compiles the numeric
#                                              kernels once), then `python -m pytest -q -n auto --dist loadfile
#                                              [PYTEST ARGS]` (every core) in the repository
#   bash scripts/setup.sh --system [--test]    only the system packages (a container's build step, say)
#
# Works as root (apt-get directly) or as a user (apt-get through sudo, only when a package is missing);
# Debian's own Python refuses a global pip install (PEP 668), hence the venv. Environment:
#   GSCAN_VENV    the venv to create or reuse (default: .venv in the repository)
#   PYTHON        the interpreter that creates it (default: python3, >= 3.10)
#   GSCAN_NO_APT  set to 1 to skip the system packages (other distributions: install their equivalents)
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
test_mode=0
system_only=0
if [ "${1:-}" = "--system" ]; then system_only=1; shift; fi
if [ "${1:-}" = "--test" ]; then test_mode=1; shift; fi
venv="${GSCAN_VENV:-$root/.venv}"
python="${PYTHON:-python3}"

say() { echo "setup: $*" >&2; }
die() { echo "setup: error: $*" >&2; exit 2; }

# --- system packages: open3d needs libGL/EGL/gomp/usb to import; the viewer's browser test drives Chromium
pkgs="libusb-1.0-0 libgl1 libegl1 libx11-6 libgomp1"
if [ "$test_mode" = 1 ]; then pkgs="$pkgs chromium fonts-dejavu-core"; fi
# Debian's Python makes venvs only with python3-venv (its ensurepip is split off)
if ! command -v "$python" >/dev/null 2>&1; then pkgs="python3 python3-venv $pkgs"; python=python3
else case "$(command -v "$python")" in /usr/bin/*) pkgs="python3-venv $pkgs" ;; esac; fi
if [ "${GSCAN_NO_APT:-0}" != 1 ]; then
  if ! command -v dpkg-query >/dev/null 2>&1; then
    say "not a Debian/Ubuntu system: install the equivalents of: $pkgs (then set GSCAN_NO_APT=1)"
  else
    missing=""
    for p in $pkgs; do
      status="$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)"
      [ "$status" = "install ok installed" ] || missing="$missing $p"
    done
    if [ -n "$missing" ]; then
      if [ "$(id -u)" -eq 0 ]; then sudo=""
      elif command -v sudo >/dev/null 2>&1; then sudo="sudo"
      else die "missing system packages:$missing; install them as root (apt-get install$missing) and run again"; fi
      say "installing system packages:$missing"
      # env, not export: sudo would drop the variable
      $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq
      $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $missing
    fi
  fi
fi
if [ "$system_only" = 1 ]; then exit 0; fi
"$python" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
  || die "$("$python" --version 2>&1) is too old: gscan needs Python >= 3.10 (set PYTHON)"

# --- the venv and gscan in it (editable: the venv runs this checkout's code)
if [ ! -x "$venv/bin/python" ]; then
  say "creating the virtual environment $venv"
  "$python" -m venv "$venv"
fi
extra=""
if [ "$test_mode" = 1 ]; then extra="[test]"; fi
say "installing gscan$extra into $venv (first time: about 2 GB of wheels)"
# --no-compile: Python compiles a module's bytecode on its first import instead (of the wheels' 150 MB of sources,
# only what gscan imports), not all of it up front
"$venv/bin/python" -m pip install -q --disable-pip-version-check --no-compile -e "$root$extra"

if [ "$test_mode" = 1 ]; then
  # the RealSense recording tests record with the SDK's own recorder of each recording layout: the venv's
  # pyrealsense2 (2.59: .db3, PNG images), and 2.57 (.bag) and 2.58 (.db3, zstd messages) each in a folder of its
  # own (GSCAN_TEST_PYREALSENSE2), where gscan never imports them
  sdks=""
  for v in 2.57.7.10387 2.58.4.10922; do
    d="$venv/realsense-sdks/$v"
    if [ ! -d "$d/pyrealsense2" ]; then
      say "installing pyrealsense2 $v into $d (the recording tests)"
      "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps --target "$d" "pyrealsense2==$v" \
        || die "could not install pyrealsense2 $v (the recording tests)"
    fi
    sdks="${sdks:+$sdks:}$d"
  done
  export GSCAN_TEST_PYREALSENSE2="${GSCAN_TEST_PYREALSENSE2:-$sdks}"
  cd "$root"
  # numba compiles the kernels on their first use into its on-disk cache (beside the modules): the demo compiles
  # them once, on a core of its own while ruff and mypy run, and every test worker then loads them from the cache
  # instead of each compiling its own
  warm="$(mktemp -d)"
  say "compiling the numeric kernels (gscan demo --no-view, beside the checks)"
  "$venv/bin/python" -m gscan.cli demo --no-view --output "$warm/demo-output" >"$warm/demo.log" 2>&1 &
  warm_pid=$!
  trap 'kill "$warm_pid" 2>/dev/null || true; rm -rf "$warm"' EXIT
  say "ruff check (lint)"
  "$venv/bin/python" -m ruff check --no-cache || { echo "setup: error: ruff check failed" >&2; exit 1; }
  say "mypy (types: gscan)"
  "$venv/bin/python" -m mypy --cache-dir /dev/null || { echo "setup: error: mypy failed" >&2; exit 1; }
  if ! wait "$warm_pid"; then
    tail -n 20 "$warm/demo.log" >&2
    echo "setup: error: gscan demo --no-view (the kernels' compilation) failed" >&2; exit 1
  fi
  rm -rf "$warm"
  trap - EXIT
  # the suite on every core (pytest-xdist), each test file on one worker: a file's module fixtures are made once
  exec "$venv/bin/python" -m pytest -q -n auto --dist loadfile "$@"
fi
exec "$venv/bin/gscan" demo "$@"
