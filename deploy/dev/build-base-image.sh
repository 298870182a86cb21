#!/usr/bin/env bash
# Build a local stand-in for the official python:3.11-slim image from Debian bookworm (whose python3 is 3.11)
# with debootstrap, for machines that reach the Debian mirror but no container registry.
# Usage: sudo deploy/dev/build-base-image.sh [tag]        (default tag fedrl/python:3.11-slim)
#        sudo ARCH=arm64 deploy/dev/build-base-image.sh fedrl/python:3.11-slim-arm64   (needs qemu-user-static with
#        binfmt_misc registered: apt-get install qemu-user-static binfmt-support)
# Then: FEDRL_BASE_IMAGE=fedrl/python:3.11-slim docker compose build   (see .env.example)
# The mirror is the one apt already uses (override with DEBIAN_MIRROR=<url>). Certificate authorities added to this
# host (/usr/local/share/ca-certificates, e.g. a TLS-intercepting proxy's) are trusted in the image too, and pip is
# told to use the system bundle; HOST_CAS=0 turns that off.
set -euo pipefail

TAG=${1:-fedrl/python:3.11-slim}
SUITE=${DEBIAN_SUITE:-bookworm}
ARCH=${ARCH:-$(dpkg --print-architecture)}

mirror_from_apt() {
    # deb822 sources ("URIs: <url>") first, then one-line sources ("deb <url> <suite> ...").
    local uri
    uri=$(grep -hsE '^URIs:' /etc/apt/sources.list.d/*.sources | awk '{print $2}' | grep -v security | head -n1 || true)
    if [ -z "$uri" ]; then
        uri=$(grep -hsE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list \
            | awk '{print $2}' | grep -v security | head -n1 || true)
    fi
    echo "$uri"
}

MIRROR=${DEBIAN_MIRROR:-$(mirror_from_apt)}
[ -n "$MIRROR" ] || { echo "no Debian mirror found in the apt sources; set DEBIAN_MIRROR" >&2; exit 1; }
command -v debootstrap >/dev/null || { echo "debootstrap not found: run deploy/dev/install-docker.sh" >&2; exit 1; }

ROOT=$(mktemp -d /var/tmp/fedrl-rootfs.XXXXXX)
trap 'rm -rf "$ROOT"' EXIT

echo "debootstrap $SUITE ($ARCH) from $MIRROR into $ROOT"
nice debootstrap --arch="$ARCH" --variant=minbase --include=python3,python3-venv,python-is-python3,ca-certificates \
    "$SUITE" "$ROOT" "$MIRROR" >"$ROOT.log" 2>&1 || { tail -n 30 "$ROOT.log" >&2; exit 1; }
rm -f "$ROOT.log"

# Slim it like the official image: no apt lists, docs, man pages or caches (apt-get update restores the lists).
rm -rf "$ROOT"/var/lib/apt/lists/* "$ROOT"/var/cache/apt/*.bin "$ROOT"/var/cache/apt/archives/*.deb \
    "$ROOT"/usr/share/doc/* "$ROOT"/usr/share/man/* "$ROOT"/usr/share/info/* "$ROOT"/usr/share/locale/* \
    "$ROOT"/var/log/*.log
printf 'path-exclude /usr/share/doc/*\npath-exclude /usr/share/man/*\npath-exclude /usr/share/locale/*\n' \
    >"$ROOT/etc/dpkg/dpkg.cfg.d/01-slim"

changes=(--change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin')
if [ "${HOST_CAS:-1}" = 1 ] && compgen -G '/usr/local/share/ca-certificates/*.crt' >/dev/null; then
    cp /usr/local/share/ca-certificates/*.crt "$ROOT/usr/local/share/ca-certificates/"
    chroot "$ROOT" update-ca-certificates >/dev/null
    changes+=(--change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt'
              --change 'ENV REQUESTS_CA_BUNDLE=/etc/ssl/certs/ca-certificates.crt')
    echo "trusting this host's extra CAs: $(ls /usr/local/share/ca-certificates)"
fi

tar --numeric-owner -C "$ROOT" -c . | docker import --platform "linux/$ARCH" "${changes[@]}" \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' \
    - "$TAG" >/dev/null
docker run --rm --network none "$TAG" python3 -c 'import platform, sys, venv; print("python", sys.version.split()[0], platform.machine())'
docker image ls "$TAG"
