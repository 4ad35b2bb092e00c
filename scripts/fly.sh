#!/usr/bin/env bash
# Installs the package and runs the main job: the paper's simulated flight, five navigation modes.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install -q -e .
mkdir -p out
python3 -m sitl paper --runs 20 --json out/paper.json --plot out/paper.png "$@"
