#!/usr/bin/env bash
# Makes the base image every gaps image starts from, without a registry: a minimal Debian bookworm tree
# from debootstrap (--variant=minbase), imported into podman as gaps-base:bookworm. Run as root (debootstrap
# needs it). Idempotent: an existing image is kept unless --force is given.
#   bash deploy/images/make_base_image.sh [--force] [--mirror URL]
# Environment: GAPS_BASE_IMAGE (default gaps-base:bookworm), CONTAINERS_CONF (default: containers.conf here).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
export CONTAINERS_CONF=${CONTAINERS_CONF:-$here/containers.conf}
image=${GAPS_BASE_IMAGE:-gaps-base:bookworm}
mirror=http://deb.debian.org/debian
force=0
while [ $# -gt 0 ]; do
  case $1 in
    --force) force=1 ;;
    --mirror) mirror=$2; shift ;;
    *) echo "make_base_image: unknown argument $1" >&2; exit 2 ;;
  esac
  shift
done
for tool in debootstrap podman; do
  command -v "$tool" >/dev/null || { echo "make_base_image: needs $tool (apt-get install $tool)" >&2; exit 1; }
done
if [ "$force" = 0 ] && podman image exists "$image"; then
  echo "make_base_image: $image exists (--force rebuilds it)"
  exit 0
fi
root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT
debootstrap --variant=minbase bookworm "$root" "$mirror"
# Security and point-release updates too, so that images built later get the fixes.
cat >"$root/etc/apt/sources.list" <<SOURCES
deb $mirror bookworm main
deb $mirror bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main
SOURCES
# Package lists and caches are fetched again by every build; the image does not carry them.
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/var/cache/apt/archives/*.deb
tar -C "$root" -c . | podman import --change 'CMD ["/bin/bash"]' - "$image"
podman image ls "$image"
