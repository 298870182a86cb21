#!/usr/bin/env bash
# A private CA and a server certificate for mosquitto.prod.conf's TLS listener (for a lab; use your own PKI where
# you have one).  deploy/mosquitto/make-certs.sh <broker host name or IP> [DIR]   (default DIR: ./secrets/certs)
# Clients trust ca.crt: FEDRL_BROKER=mqtts://<host>:8883 FEDRL_MQTT_CA_FILE=/path/to/ca.crt
set -euo pipefail
HOST=${1:?usage: make-certs.sh <broker host name or IP> [DIR]}
OUT=${2:-"$(dirname "$0")/secrets/certs"}
DAYS=${DAYS:-825}
mkdir -p "$OUT"
cd "$OUT"

if [[ "$HOST" =~ ^[0-9.]+$ || "$HOST" == *:* ]]; then san="IP:$HOST"; else san="DNS:$HOST"; fi
umask 077
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days "$DAYS" -subj "/CN=fedrl broker CA" \
    -keyout ca.key -out ca.crt 2>/dev/null
openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -subj "/CN=$HOST" -keyout server.key -out server.csr 2>/dev/null
printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth\n' "$san" >server.ext
openssl x509 -req -in server.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days "$DAYS" -extfile server.ext \
    -out server.crt 2>/dev/null
rm -f server.csr server.ext ca.srl
chmod 644 ca.crt server.crt
echo "wrote $(pwd)/ca.crt, server.crt, server.key (keep ca.key offline)"
