#!/usr/bin/env bash
# The test command of README.md: installs what the tests need on a fresh machine
# (Debian's Chromium, Node.js and the browser test's npm packages, Debian's PostgreSQL,
# moto's S3 server and Python venvs for the contract test and the format checks), then
# runs every test: `cargo test --release --workspace` (unit, engine, service over real
# HTTP, crash test, the dashboard in headless Chromium) on the embedded default (SQLite,
# local blobs); the service, queue, crash, fleet, client, dashboard-API, vehicle-model and webhook tests again on a
# throwaway PostgreSQL cluster and S3-compatible server; the HTTP contract test
# (schemathesis against the live server) and the export format checks (PyYAML, OpenCV,
# pycolmap in a venv). .ci/run calls this same script.
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

export RIGCAL_MOTO_VENV="${RIGCAL_MOTO_VENV:-$PWD/target/moto-venv}"
if [ "${RIGCAL_TEST_NO_INSTALL:-0}" != 1 ]; then
  python3 -c 'import venv, ensurepip' 2>/dev/null || apt_install python3-venv
  # The dashboard's browser test: Debian's Chromium driven by playwright-core (no browser
  # download; tests/dashboard.rs finds /usr/bin/chromium).
  [ -x "${RIGCAL_CHROMIUM:-/usr/bin/chromium}" ] || apt_install chromium
  command -v node >/dev/null || apt_install nodejs npm
  # The remote-backend run: PostgreSQL (initdb, pg_ctl, psql) and curl for moto.
  ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || apt_install postgresql
  command -v curl >/dev/null || apt_install curl
  if [ ! -x "$RIGCAL_MOTO_VENV/bin/moto_server" ]; then
    python3 -m venv "$RIGCAL_MOTO_VENV"
    "$RIGCAL_MOTO_VENV/bin/pip" install -q --disable-pip-version-check 'moto[server]==5.*'
  fi
  if [ ! -d tests/browser/node_modules/playwright-core ] ||
    [ tests/browser/package-lock.json -nt tests/browser/node_modules ]; then
    npm ci --prefix tests/browser --no-audit --no-fund --loglevel=error
  fi
fi

cargo test --release --workspace "$@"
# The same service tests on PostgreSQL + S3 (tests/common reads the variables that
# start_backends exports).
source scripts/backends.sh
trap stop_backends EXIT
start_backends
cargo test --release --test service --test queue --test crash --test fleet --test client \
  --test dashboard_api --test idempotency --test bundle --test blobs --test vehicle_models --test webhooks --test capture_feedback "$@"
stop_backends
trap - EXIT
# The HTTP contract: openapi.yaml against the running server (built by the line above).
bash scripts/contract.sh
# The exports read back by the tools that consume them (Kalibr's rules, OpenCV, COLMAP).
bash scripts/format_checks.sh
