# A local stand-in for the official eclipse-mosquitto:2 image (same paths, user and command), built from
# Debian's mosquitto package on the local base image, for machines that cannot pull from a registry.
#   docker build --network host -f deploy/dev/mosquitto.Dockerfile -t fedrl/mosquitto:2 deploy/dev
ARG BASE_IMAGE=fedrl/python:3.11-slim
FROM ${BASE_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends mosquitto mosquitto-clients \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /mosquitto/config /mosquitto/data /mosquitto/log \
    && chown -R mosquitto:mosquitto /mosquitto/data /mosquitto/log \
    && printf 'listener 1883\nallow_anonymous true\npersistence true\npersistence_location /mosquitto/data/\n' \
        > /mosquitto/config/mosquitto.conf
VOLUME ["/mosquitto/data", "/mosquitto/log"]
EXPOSE 1883 8883
USER mosquitto
CMD ["/usr/sbin/mosquitto", "-c", "/mosquitto/config/mosquitto.conf"]
