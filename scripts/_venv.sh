# Sourced by scripts/fly.sh and scripts/test.sh: creates (or reuses) the project's own virtual
# environment in .venv/ and puts it first on PATH, so the Quick start works on a stock Debian 12/13,
# Ubuntu 24.04 or Raspberry Pi OS, where pip refuses to install outside a venv
# (externally-managed-environment).  Needs Python >= 3.11; as root it installs python3-venv with apt
# when the interpreter has no venv module (Debian ships it separately).

_companion_python() {
  local py
  for py in "${PYTHON:-}" python3.13 python3.12 python3.11 python3; do
    [ -n "$py" ] || continue
    command -v "$py" >/dev/null 2>&1 || continue
    if "$py" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
      echo "$py"; return 0
    fi
  done
  return 1
}

companion_venv() {
  local venv=".venv" py
  if [ -x "$venv/bin/python" ] && "$venv/bin/python" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
    echo "using the virtual environment in $venv/"
  else
    py="$(_companion_python)" || {
      echo "error: companion needs Python >= 3.11 (found: $(python3 --version 2>&1 || echo none)); set PYTHON=/path/to/python3.11" >&2
      return 1
    }
    echo "creating a virtual environment in $venv/ with $py ($("$py" --version 2>&1))"
    rm -rf "$venv"
    if ! "$py" -m venv "$venv" 2>/dev/null; then
      rm -rf "$venv"
      if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "installing python3-venv with apt (the interpreter has no usable venv module)"
        apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null
        "$py" -m venv "$venv"
      else
        echo "error: '$py -m venv' failed; install the venv module (Debian/Ubuntu/Raspberry Pi OS: sudo apt install python3-venv)" >&2
        return 1
      fi
    fi
  fi
  export VIRTUAL_ENV="$PWD/$venv"
  export PATH="$VIRTUAL_ENV/bin:$PATH"
  hash -r
}

# pip install -e ".[EXTRA]" into the venv, with a word on what and how long
companion_install() {
  echo "installing companion and its Python packages ($1) into .venv/ (first time 1-3 min, then seconds)"
  python -m pip install -q --disable-pip-version-check -e ".[$1]"
  # compile the IMU-rate and LAMBDA kernels once now (numba's disk cache; [kernels], in [test]), not
  # at the first flight; without numba it says so and the pure-Python path runs
  python -m companion.nav.imu_kernel || true
}
