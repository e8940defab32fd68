#!/usr/bin/env bash
# Idempotent set-up on a fresh machine of this kind (Debian 12, Python >= 3.11):
#   1. the Debian packages headless GL rendering needs (pyrender backend, EGL on Mesa llvmpipe);
#   2. Debian's chromium (optional: the HTML report's browser test; skipped where it cannot be installed);
#   3. a C compiler and Python's headers (optional: SRM's merge loop is compiled where they are, else it runs in
#      Python, ~3x slower classification);
#   4. a virtual environment .venv/ at the repository root with the project installed (editable) and its test extra.
# Re-running it is cheap: packages already present are not reinstalled, and pip runs only when pyproject.toml,
# setup.py or the C source changed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

apt_pkgs=(libegl1 libgl1 libgl1-mesa-dri)
missing=()
for p in "${apt_pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  echo "bootstrap: installing Debian packages: ${missing[*]}"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
# a real browser for the HTML report's test (headless Chromium renders its 3-D view); optional: without it that
# one test is skipped and says so
if ! command -v chromium >/dev/null 2>&1; then
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  echo "bootstrap: installing Debian's chromium (for the report's browser test)"
  { $sudo_cmd apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq \
      --no-install-recommends chromium >/dev/null; } \
    || echo "bootstrap: could not install chromium: the browser test will be skipped"
fi

py="${PYTHON:-python3}"
# a C compiler and the Python headers for bodyslam/vision/_srm_merge.c (optional: setup.py skips it without them)
if ! command -v cc >/dev/null 2>&1; then
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  echo "bootstrap: installing a C compiler (for SRM's compiled merge loop)"
  { $sudo_cmd apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq \
      --no-install-recommends gcc libc6-dev >/dev/null; } \
    || echo "bootstrap: could not install gcc: SRM will run its merge loop in Python (~3x slower classification)"
fi
inc="$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
if [ ! -f "$inc/Python.h" ]; then
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  echo "bootstrap: installing Python's headers (for SRM's compiled merge loop)"
  { $sudo_cmd apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq \
      --no-install-recommends python3-dev >/dev/null; } \
    || echo "bootstrap: could not install python3-dev: SRM will run its merge loop in Python"
fi
if [ ! -x .venv/bin/python ]; then
  echo "bootstrap: creating .venv"
  "$py" -m venv .venv
fi
stamp=.venv/.bodyslam-installed
want="$(cat pyproject.toml setup.py bodyslam/vision/_srm_merge.c | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "bootstrap: installing the project into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$want" > "$stamp"
fi
