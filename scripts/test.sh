#!/usr/bin/env bash
# Installs everything the test suite needs, then runs it.  Used by the README and by CI.
# Python packages go into the project's own virtual environment (.venv/, reused when present); run
# as root it also installs the real protocol peers with apt: mosquitto (MQTT broker) and rtklib
# (str2str, the NTRIP caster) and chromium (renders the status page in a test).  About 10 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_venv.sh
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  need=""
  command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || need="$need mosquitto"
  command -v str2str >/dev/null 2>&1 || need="$need rtklib"
  command -v chromium >/dev/null 2>&1 || need="$need chromium"
  if [ -n "$need" ]; then
    echo "installing$need with apt (real MQTT broker and NTRIP caster for the service tests)"
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need >/dev/null \
      || echo "warning: could not install$need; tests that need them will say so" >&2
  fi
fi
companion_venv
companion_install test
# two workers (pytest-xdist): much of the suite waits on real-time flights and SITL peers, so two
# processes keep both cores busy (about 18 -> 9 min here); COMPANION_TEST_WORKERS=0 runs in one process
python -m pytest -q -n "${COMPANION_TEST_WORKERS:-2}" "$@"
