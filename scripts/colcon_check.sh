#!/usr/bin/env bash
# Build the workspace with colcon (as a stock ROS 2 install would) into a scratch dir, then start every
# installed node executable once: it must come up, publish /diagnostics and exit cleanly on SIGINT.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
. "$ROOT/.venv/bin/activate"
WS="${COLCON_WS:-$ROOT/build_colcon}"
rm -rf "$WS" && mkdir -p "$WS"
cd "$WS"
cp "$ROOT/colcon.meta" .
colcon build --base-paths "$ROOT/src" --event-handlers console_cohesion- summary+ 2>&1 | grep -v "byte-compiling is disabled" | tail -5
set +u
# shellcheck disable=SC1091
. install/setup.bash
set -u
python "$ROOT/scripts/check_nodes.py" install
