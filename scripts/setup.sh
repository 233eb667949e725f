#!/usr/bin/env bash
# Installs whatever is missing on a Debian machine: build tools and libraries from Debian's archive,
# LibTorch (PyPI's torch==2.11.0 wheel) in a virtual environment shared by every checkout
# (${GAPS_CACHE:-~/.cache/gaps}/venv). Idempotent: a second run only checks and returns.
set -euo pipefail

GAPS_CACHE=${GAPS_CACHE:-$HOME/.cache/gaps}
VENV=$GAPS_CACHE/venv
TORCH_VERSION=2.11.0
DEBIAN_PACKAGES=(
  build-essential cmake ninja-build ccache git python3 python3-venv
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler libabsl-dev
  libopencv-dev libeigen3-dev libstb-dev libjpeg62-turbo-dev nlohmann-json3-dev libsqlite3-dev libgtest-dev
  openssl libssl-dev  # TLS key checks; the TLS end-to-end test makes its certificate with openssl
  postgresql libpq-dev  # the shared job store (libpq) and the private servers of its tests
  clang-format  # scripts/check_format.sh (the format check in the test suite)
  clang libclang-rt-14-dev  # scripts/fuzz.sh: libFuzzer and the sanitizers
)
PYTHON_PACKAGES=("torch==$TORCH_VERSION" "torchvision==0.26.0" numpy scipy lpips tqdm matplotlib)

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

missing=()
for p in "${DEBIAN_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

if ! "$VENV/bin/python" -c "import torch, lpips, torchvision, matplotlib; assert torch.__version__.startswith('$TORCH_VERSION')" 2>/dev/null; then
  echo "setup: installing LibTorch (torch==$TORCH_VERSION from PyPI) into $VENV"
  mkdir -p "$GAPS_CACHE"
  [ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip
  "$VENV/bin/pip" install -q "${PYTHON_PACKAGES[@]}"
fi
echo "setup: ready (LibTorch $("$VENV/bin/python" -c 'import torch; print(torch.__version__)') in $VENV)"
