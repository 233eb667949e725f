#!/usr/bin/env bash
# Builds the gaps image with podman from this checkout (making the Debian base image first if needed).
#   bash deploy/images/build_image.sh [--cuda] [--tag NAME] [--jobs N]
# Default tag: gaps:cpu (gaps:cuda with --cuda). Prints the image's size at the end. Honours GAPS_BASE_IMAGE,
# GAPS_JOBS, CONTAINERS_CONF and PIP_CERT (a CA bundle for pip, passed into the build).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
export CONTAINERS_CONF=${CONTAINERS_CONF:-$here/containers.conf}
cuda=OFF
tag=
jobs=${GAPS_JOBS:-2}
while [ $# -gt 0 ]; do
  case $1 in
    --cuda) cuda=ON ;;
    --tag) tag=$2; shift ;;
    --jobs) jobs=$2; shift ;;
    *) echo "build_image: unknown argument $1" >&2; exit 2 ;;
  esac
  shift
done
[ -n "$tag" ] || tag=gaps:$([ "$cuda" = ON ] && echo cuda || echo cpu)
command -v podman >/dev/null || { echo "build_image: needs podman (apt-get install podman)" >&2; exit 1; }
base=${GAPS_BASE_IMAGE:-gaps-base:bookworm}
GAPS_BASE_IMAGE=$base bash "$here/make_base_image.sh"
extra=()
if [ -n "${PIP_CERT:-}" ] && [ -f "$PIP_CERT" ]; then
  # pip on this host trusts a CA of its own (a TLS-intercepting proxy, say); the build's pip needs it too.
  extra+=(-v "$(readlink -f "$PIP_CERT"):/etc/gaps-build-ca.pem:ro" --build-arg PIP_CERT=/etc/gaps-build-ca.pem)
fi
# --format docker keeps the HEALTHCHECK (the OCI image format has no field for it).
podman build --format docker --layers -f "$here/Containerfile" --ignorefile "$here/Containerfile.dockerignore" \
  --build-arg BASE_IMAGE="$base" --build-arg GAPS_CUDA="$cuda" --build-arg GAPS_JOBS="$jobs" "${extra[@]}" -t "$tag" "$root"
podman image ls "$tag"
