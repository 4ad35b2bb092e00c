#!/usr/bin/env bash
# Installs the package and runs the main job: the end-to-end simulated flight.  An emulated
# autopilot (MAVLink over UDP on 127.0.0.1), a simulated base station behind an NTRIP caster and
# `companion run` as its own process; the estimates the autopilot receives are scored against truth.
# Everything goes into the project's own virtual environment (.venv/, reused when present).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_venv.sh
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1 && ! command -v str2str >/dev/null 2>&1; then
  # RTKLIB's str2str is the NTRIP caster; without it the flight uses a small built-in caster
  echo "installing rtklib with apt (its str2str is the NTRIP caster)"
  (apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq rtklib >/dev/null) \
    || echo "note: rtklib not installed; using the built-in NTRIP caster" >&2
fi
companion_venv
companion_install sitl
mkdir -p out
python -m sitl fly --duration 120 --out out/fly --json out/fly.json "$@"
echo "replaying the field log of that flight (must reproduce every solution bit for bit):"
python -m companion replay out/fly/fieldlog --json out/replay.json
