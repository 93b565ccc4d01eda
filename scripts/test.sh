#!/usr/bin/env bash
# The test command of README.md: installs what the tests need on a fresh machine
# (Debian's Chromium, Node.js and the browser test's npm packages, a Python venv for the
# contract test and the format checks), then runs every test: `cargo test --release --workspace` (unit, engine, service
# over real HTTP, crash test, the dashboard in headless Chromium) and the HTTP contract
# test (schemathesis against the live server) and the export format checks (PyYAML,
# OpenCV, pycolmap in a venv). .ci/run calls this same script.
#
# Safe to run again: every install step is skipped when its result is already there.
# RIGCAL_TEST_NO_INSTALL=1 skips the installs (for a machine set up by hand).
set -euo pipefail
cd "$(dirname "$0")/.."

if ! command -v cargo >/dev/null; then
  echo "cargo is required (the machine's rustup toolchain)" >&2
  exit 1
fi

apt_updated=0
apt_install() {
  # Debian packages, as root (CI) or through sudo.
  local sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  if [ "$apt_updated" -eq 0 ]; then
    $sudo apt-get update -qq >/dev/null
    apt_updated=1
  fi
  echo "installing $*" >&2
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@" >/dev/null
}

if [ "${RIGCAL_TEST_NO_INSTALL:-0}" != 1 ]; then
  python3 -c 'import venv, ensurepip' 2>/dev/null || apt_install python3-venv
  # The dashboard's browser test: Debian's Chromium driven by playwright-core (no browser
  # download; tests/dashboard.rs finds /usr/bin/chromium).
  [ -x "${RIGCAL_CHROMIUM:-/usr/bin/chromium}" ] || apt_install chromium
  command -v node >/dev/null || apt_install nodejs npm
  if [ ! -d tests/browser/node_modules/playwright-core ] ||
    [ tests/browser/package-lock.json -nt tests/browser/node_modules ]; then
    npm ci --prefix tests/browser --no-audit --no-fund --loglevel=error
  fi
fi

cargo test --release --workspace "$@"
# The HTTP contract: openapi.yaml against the running server (built by the line above).
bash scripts/contract.sh
# The exports read back by the tools that consume them (Kalibr's rules, OpenCV, COLMAP).
bash scripts/format_checks.sh
