#!/usr/bin/env bash
# Export round-trips through the real parsers (PyYAML with Kalibr's type rules,
# cv2.FileStorage + cv2.stereoRectify, xml.etree, pycolmap.read_rig_config), in a venv of
# their own: tests/formats/check_exports.py. Format checks, not peers. Called by
# scripts/test.sh after the release build.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${RIGCAL_BIN:-${CARGO_TARGET_DIR:-target}/release/rigcal}
VENV=${RIGCAL_FMT_VENV:-target/fmt-venv}
if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import yaml, cv2, pycolmap' 2>/dev/null; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install -q 'PyYAML>=6,<7' 'numpy<3' 'opencv-python-headless>=4.8' 'pycolmap>=3.12'
fi
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
"$VENV/bin/python" tests/formats/check_exports.py "$BIN" "$WORK"
