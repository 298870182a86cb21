#!/usr/bin/env bash
# Everything a machine without registry access needs before `make test-docker` or `docker compose up`:
# the engine (started in the background), the local base and Mosquitto images, the CPU torch wheelhouse.
# Idempotent; run as root from anywhere.  Then:  source <(deploy/dev/prepare.sh --print-env)
set -euo pipefail
cd "$(dirname "$0")/../.."

BASE=fedrl/python:3.11-slim
BROKER=fedrl/mosquitto:2
if [ "${1:-}" = --print-env ]; then
    echo "export FEDRL_BASE_IMAGE=$BASE FEDRL_MOSQUITTO_IMAGE=$BROKER FEDRL_BUILD_NETWORK=host"
    exit 0
fi

command -v dockerd >/dev/null && command -v debootstrap >/dev/null || deploy/dev/install-docker.sh --compose-v2
deploy/dev/start-dockerd.sh
docker image inspect "$BASE" >/dev/null 2>&1 || deploy/dev/build-base-image.sh "$BASE"
docker image inspect "$BROKER" >/dev/null 2>&1 || nice docker build --quiet --network host \
    --build-arg BASE_IMAGE="$BASE" -f deploy/dev/mosquitto.Dockerfile -t "$BROKER" deploy/dev
ls deploy/wheels/torch-* >/dev/null 2>&1 || deploy/dev/fetch-wheels.sh
docker image ls --filter reference='fedrl/*'
echo "ready: export FEDRL_BASE_IMAGE=$BASE FEDRL_MOSQUITTO_IMAGE=$BROKER FEDRL_BUILD_NETWORK=host"
