#!/usr/bin/env bash
# One entry point that sets up a fresh Debian machine (as root, or with sudo) and then runs
#   bash run.sh demo   -- the main job on the embedded default data
#   bash run.sh test   -- lint, type check and the test suite (what CI runs)
# Set-up is idempotent: system libraries, then a virtual environment in .venv.
set -euo pipefail
cd "$(dirname "$0")"

need_apt=()
# chromium: the browser tests of the explorer page (headless, WebGL on SwiftShader).
for pkg in libusb-1.0-0 libgomp1 libgl1 libvulkan1 mesa-vulkan-drivers chromium; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
PY=${PYTHON:-python3}
if [ ${#need_apt[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.o3dreg-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[test]"
  touch "$stamp"
fi

cmd=${1:-demo}
shift || true
case "$cmd" in
  demo)
    exec .venv/bin/o3dreg demo "$@"
    ;;
  test)
    .venv/bin/ruff check o3dreg tests examples benchmarks
    .venv/bin/ruff format --check o3dreg tests examples benchmarks
    .venv/bin/mypy
    .venv/bin/mkdocs build --strict --quiet --site-dir "$(mktemp -d)"
    exec .venv/bin/python -m pytest -q "$@"
    ;;
  *)
    echo "usage: bash run.sh {demo|test} [args...]" >&2
    exit 2
    ;;
esac
