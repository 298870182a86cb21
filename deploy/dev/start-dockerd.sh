#!/usr/bin/env bash
# Start a Docker engine in the background on a machine without systemd or outbound networking (CI VMs, sandboxes):
# no iptables rules and no default docker0 bridge, so containers use host networking on loopback
# (deploy/dev/compose.hostnet.yml). Idempotent: does nothing when an engine already answers.
# Usage: sudo deploy/dev/start-dockerd.sh        (log: $DOCKERD_LOG, default /var/log/fedrl-dockerd.log)
set -euo pipefail

DOCKERD_LOG=${DOCKERD_LOG:-/var/log/fedrl-dockerd.log}
DOCKERD_PIDFILE=${DOCKERD_PIDFILE:-/var/run/fedrl-dockerd.pid}

if docker info >/dev/null 2>&1; then
    echo "a Docker engine is already running"
    exit 0
fi
command -v dockerd >/dev/null || { echo "dockerd not found: run deploy/dev/install-docker.sh first" >&2; exit 1; }

# cgroup v1 hosts without systemd may lack the mounts containerd expects; mount what is missing.
if [ ! -e /sys/fs/cgroup/cgroup.controllers ] && [ ! -d /sys/fs/cgroup/cpu ]; then
    mount -t tmpfs cgroup /sys/fs/cgroup 2>/dev/null || true
    for c in cpu cpuacct cpuset memory devices freezer blkio pids; do
        mkdir -p "/sys/fs/cgroup/$c" && mount -t cgroup -o "$c" cgroup "/sys/fs/cgroup/$c" 2>/dev/null || true
    done
fi

nohup nice -n 5 dockerd --iptables=false --ip-masq=false --bridge=none --pidfile "$DOCKERD_PIDFILE" \
    >>"$DOCKERD_LOG" 2>&1 &
echo "dockerd started (pid $!), log $DOCKERD_LOG"
for _ in $(seq 1 60); do
    if docker info >/dev/null 2>&1; then
        docker version --format 'engine {{.Server.Version}}, API {{.Server.APIVersion}}'
        exit 0
    fi
    sleep 1
done
echo "dockerd did not answer within 60 s; see $DOCKERD_LOG" >&2
exit 1
