#!/bin/sh
# Prepare a Raspberry Pi (Raspberry Pi OS, Debian or Ubuntu) to run the QUBE-Servo 2 bridge as the non-root user
# `fedrl`: the `spi` group (created where the distribution has none, with a udev rule that gives it /dev/spidev*),
# the user, /etc/fedrl readable by that user only, and the state folder /var/lib/fedrl.
#
#   sudo deploy/rpi/setup-host.sh [--ca ca.crt] [--env bridge.env] [--root DIR] [--user NAME]
#
# --ca and --env copy the broker's CA and the bridge's settings into /etc/fedrl (root:fedrl, 0640); without --env the
# example file is installed for you to edit. --root installs under DIR instead of / (tests), --user names another
# user. Safe to run again: it changes only what is missing or wrong.
set -eu

ROOT=""
USER_NAME=fedrl
CA=""
ENV_FILE=""
HERE=$(cd "$(dirname "$0")" && pwd)

die() { echo "setup-host.sh: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case "$1" in
        --root) [ $# -ge 2 ] || die "--root needs a folder"; ROOT=$2; shift 2 ;;
        --user) [ $# -ge 2 ] || die "--user needs a name"; USER_NAME=$2; shift 2 ;;
        --ca) [ $# -ge 2 ] || die "--ca needs a file"; CA=$2; shift 2 ;;
        --env) [ $# -ge 2 ] || die "--env needs a file"; ENV_FILE=$2; shift 2 ;;
        -h|--help) sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) die "unknown argument: $1 (see --help)" ;;
    esac
done

[ "$(id -u)" -eq 0 ] || die "run it as root (sudo)"
case "$USER_NAME" in
    *[!a-z0-9_-]*|"") die "user name $USER_NAME: lower-case letters, digits, - and _ only" ;;
esac
for f in "$CA" "$ENV_FILE"; do
    if [ -n "$f" ] && [ ! -r "$f" ]; then die "cannot read $f"; fi
done

# The spi group: Raspberry Pi OS has it and its udev rule; plain Debian and Ubuntu have neither.
if ! getent group spi >/dev/null; then
    groupadd --system spi
    echo "created the group spi"
fi
RULE="$ROOT/etc/udev/rules.d/90-fedrl-spi.rules"
if [ ! -e "$ROOT/lib/udev/rules.d/99-com.rules" ] && [ ! -e "$RULE" ]; then
    mkdir -p "$(dirname "$RULE")"
    echo 'SUBSYSTEM=="spidev", GROUP="spi", MODE="0660"' > "$RULE"
    echo "wrote $RULE (run 'sudo udevadm trigger' or reboot to apply it)"
fi

# The user that runs the bridge: no login, no home of its own beyond the state folder.
if ! id "$USER_NAME" >/dev/null 2>&1; then
    useradd --system --user-group --home-dir /var/lib/fedrl --no-create-home --shell /usr/sbin/nologin "$USER_NAME"
    echo "created the user $USER_NAME"
fi
usermod --append --groups spi "$USER_NAME"

# /etc/fedrl: root owns it, the bridge's group reads it, nobody else sees it (the env file holds a password).
install -d -o root -g "$USER_NAME" -m 750 "$ROOT/etc/fedrl"
if [ -n "$CA" ]; then
    install -o root -g "$USER_NAME" -m 640 "$CA" "$ROOT/etc/fedrl/ca.crt"
fi
if [ -n "$ENV_FILE" ]; then
    install -o root -g "$USER_NAME" -m 640 "$ENV_FILE" "$ROOT/etc/fedrl/bridge.env"
elif [ ! -e "$ROOT/etc/fedrl/bridge.env" ]; then
    install -o root -g "$USER_NAME" -m 640 "$HERE/bridge.env.example" "$ROOT/etc/fedrl/bridge.env"
    echo "installed $ROOT/etc/fedrl/bridge.env from the example: edit it (sudoedit)"
fi
for f in "$ROOT/etc/fedrl/ca.crt" "$ROOT/etc/fedrl/bridge.env"; do
    if [ -e "$f" ]; then chown "root:$USER_NAME" "$f"; chmod 640 "$f"; fi
done

# The state folder (calibration files): systemd's StateDirectory makes it too, but a manual start needs it as well.
install -d -o "$USER_NAME" -g "$USER_NAME" -m 750 "$ROOT/var/lib/fedrl"
echo "ready: $USER_NAME can read $ROOT/etc/fedrl and write $ROOT/var/lib/fedrl"
