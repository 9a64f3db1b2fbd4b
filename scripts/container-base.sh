#!/usr/bin/env bash
# Makes the base image the Dockerfile builds on where no registry is reachable: a minimal
# Debian bookworm made with debootstrap from the Debian mirror and imported into podman as
# localhost/debian:bookworm. Does nothing when that image exists. On a host that reaches a
# registry, build with the default base (debian:bookworm) instead.
#   scripts/container-base.sh [MIRROR]      (default http://deb.debian.org/debian)
set -euo pipefail

image=localhost/debian:bookworm
mirror=${1:-http://deb.debian.org/debian}
if podman image exists "$image"; then
  echo "container-base: $image exists"
  exit 0
fi
for tool in podman debootstrap; do
  command -v "$tool" >/dev/null || { echo "container-base: $tool is missing (scripts/install-deps.sh --with-containers)" >&2; exit 2; }
done
root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT
echo "container-base: debootstrap bookworm from $mirror"
debootstrap --variant=minbase bookworm "$root" "$mirror" >/dev/null
# Apt inside builds: the same mirror, no recommended packages, no caches left in layers.
echo "deb $mirror bookworm main" >"$root/etc/apt/sources.list"
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
tar -C "$root" -c . | podman import --quiet --change 'CMD ["/bin/bash"]' - "$image" >/dev/null
echo "container-base: $image, $(podman image inspect "$image" --format '{{.Size}}') bytes"
