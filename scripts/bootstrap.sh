#!/usr/bin/env bash
# Idempotent set-up on a fresh machine of this kind (Debian 12, Python >= 3.11):
#   1. the Debian packages headless GL rendering needs (pyrender backend, EGL on Mesa llvmpipe);
#   2. Debian's chromium (optional: the HTML report's browser test; skipped where it cannot be installed);
#   3. a virtual environment .venv/ at the repository root with the project installed (editable) and its test extra.
# Re-running it is cheap: packages already present are not reinstalled, and pip runs only when pyproject.toml changed.
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
if [ ! -x .venv/bin/python ]; then
  echo "bootstrap: creating .venv"
  "$py" -m venv .venv
fi
stamp=.venv/.bodyslam-installed
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "bootstrap: installing the project into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$want" > "$stamp"
fi
