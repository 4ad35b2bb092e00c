#!/usr/bin/env bash
# Installs everything the test suite needs, then runs it.  Used by the README and by CI.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  # real protocol peers for the service tests (MQTT broker, NTRIP caster from RTKLIB)
  need=""
  command -v mosquitto >/dev/null 2>&1 || need="$need mosquitto"
  command -v str2str >/dev/null 2>&1 || need="$need rtklib"
  if [ -n "$need" ]; then
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need >/dev/null \
      || echo "warning: could not install$need; tests that need them will say so" >&2
  fi
fi
python3 -m pip install -q -e '.[test]'
python3 -m pytest -q "$@"
