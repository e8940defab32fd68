#!/usr/bin/env bash
# Idempotent set-up on a fresh machine of this kind (Debian 12, Python >= 3.11):
#   1. the Debian packages headless GL rendering needs (pyrender backend, EGL on Mesa llvmpipe);
#   2. Debian's chromium (optional: the HTML report's browser test; skipped where it cannot be installed);
#   3. a C compiler and Python's headers (optional: four inner loops are compiled where they are, else they run in
#      Python/numpy: fast-mode whole exams ~1.5x as long, the fusion of a whole exam with RF ~2x);
#   4. a virtual environment .venv/ at the repository root with the project installed (editable) and its test extra.
# Re-running it is cheap: packages already present are not reinstalled, and pip runs only when pyproject.toml,
# setup.py or a C source changed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

sudo_cmd=""
[ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
# apt_optional WHAT PACKAGE...: install packages the project can do without; on failure say what WHAT loses
apt_optional() {
  local what="$1"
  shift
  echo "bootstrap: installing $* (for $what)"
  { $sudo_cmd apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq \
      --no-install-recommends "$@" >/dev/null; } \
    || echo "bootstrap: could not install $*: $what goes without"
}

apt_pkgs=(libegl1 libgl1 libgl1-mesa-dri)
missing=()
for p in "${apt_pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "bootstrap: installing Debian packages: ${missing[*]}"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
# a real browser for the HTML report's test (headless Chromium renders its 3-D view); without it that one test is
# skipped and says so
command -v chromium >/dev/null 2>&1 || apt_optional "the report's browser test (it will be skipped)" chromium

py="${PYTHON:-python3}"
# a C compiler and the Python headers for the compiled loops (setup.py: bodyslam/*/*.c); without them the
# install skips those and the same computations run in Python/numpy (fast-mode whole exams ~1.5x as long)
command -v cc >/dev/null 2>&1 || apt_optional "the compiled loops (Python/numpy is used instead)" gcc libc6-dev
inc="$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
[ -f "$inc/Python.h" ] || apt_optional "the compiled loops (Python/numpy is used instead)" python3-dev
if [ ! -x .venv/bin/python ]; then
  echo "bootstrap: creating .venv"
  "$py" -m venv .venv
fi
stamp=.venv/.bodyslam-installed
want="$(cat pyproject.toml setup.py bodyslam/*.h bodyslam/vision/*.c bodyslam/fusion/*.c | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "bootstrap: installing the project into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$want" > "$stamp"
fi
