#!/usr/bin/env bash
# Build a local stand-in for python:3.11-slim where no container registry is reachable:
# Debian bookworm (minbase) from Debian's own mirror with debootstrap, plus Python 3.11, venv and
# the CA certificates, imported into podman as $BASE_IMAGE. Needs root, debootstrap and podman.
#
#   docker/make-base.sh            # builds it unless an image from this same script exists
#   docker/make-base.sh --force    # builds it again (e.g. for Debian's security updates)
#
# The host's CA bundle replaces the image's, and PIP_CERT points pip at it, so that builds on a
# machine whose TLS goes through an intercepting proxy reach PyPI the way the host's pip does.
# The image is labelled with the hash of this script and that bundle: a change to either means a new base.
set -euo pipefail

BASE_IMAGE="${BASE_IMAGE:-localhost/ogmapping-base:bookworm}"
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
PACKAGES="python3,python3-venv,ca-certificates"
HOST_CA_BUNDLE="${HOST_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}"

recipe=$(cat "$0" "$HOST_CA_BUNDLE" 2>/dev/null | sha256sum | cut -c1-16)
if [[ "${1:-}" != "--force" ]] &&
   [[ "$(podman image inspect --format '{{index .Labels "ogmapping.base.recipe"}}' "$BASE_IMAGE" 2>/dev/null)" == "$recipe" ]]; then
    echo "make-base: $BASE_IMAGE is up to date (recipe $recipe)"
    exit 0
fi

previous=$(podman image inspect --format '{{.Id}}' "$BASE_IMAGE" 2>/dev/null || true)
rootfs=$(mktemp -d /tmp/ogmapping-base.XXXXXX)
trap 'rm -rf "$rootfs" "$rootfs.log"' EXIT
echo "make-base: debootstrap bookworm ($PACKAGES) from $MIRROR"
debootstrap --variant=minbase --include="$PACKAGES" bookworm "$rootfs" "$MIRROR" > "$rootfs.log" 2>&1 ||
    { tail -20 "$rootfs.log"; exit 1; }
# What python:3.11-slim (debian:bookworm-slim) leaves out: downloaded packages, package lists, and
# manuals, documentation but copyrights, and translations, now and from packages installed later.
rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/cache/apt/*.bin "$rootfs"/var/lib/apt/lists/*
cat > "$rootfs/etc/dpkg/dpkg.cfg.d/slim" <<'SLIM'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
SLIM
rm -rf "$rootfs"/usr/share/{man,info,locale}/*
find "$rootfs/usr/share/doc" -mindepth 2 ! -name copyright ! -type d -delete
if [[ -f "$HOST_CA_BUNDLE" ]]; then
    install -m 644 "$HOST_CA_BUNDLE" "$rootfs/etc/ssl/certs/ca-certificates.crt"
fi
tar -C "$rootfs" -c . | podman import --quiet \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
    --change "LABEL ogmapping.base.recipe=$recipe" \
    --change 'CMD ["python3"]' \
    --message "debootstrap bookworm minbase + $PACKAGES (docker/make-base.sh)" \
    - "$BASE_IMAGE" > /dev/null
if [[ -n "$previous" ]]; then
    podman rmi "$previous" > /dev/null 2>&1 || true  # kept while images built on it remain
fi
echo "make-base: $BASE_IMAGE built ($(podman image inspect --format '{{.Size}}' "$BASE_IMAGE") bytes)"
