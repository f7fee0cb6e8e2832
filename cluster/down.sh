#!/usr/bin/env bash
# Stop the single-node SLURM cluster started by cluster/up.sh: cancel jobs, stop the SLURM daemons (this
# cluster's, by their pid files: another cluster on this host, cluster/nodes.sh, is left alone), slurmdbd, MariaDB
# and munge, and wait until they have exited. State and logs stay in CLUSTER_STATE.
set -euo pipefail
[[ $(id -u) -eq 0 ]] || { echo "cluster: error: must run as root: sudo $0" >&2; exit 1; }
STATE=${CLUSTER_STATE:-/var/lib/nsl-cluster}
alive() { pgrep -x "$1" --runstates D,R,S >/dev/null; }
daemon_pid() {  # this cluster's SLURM daemon $1 by its pid file
  local file=$STATE/$1.pid pid
  [[ -s $file ]] || return 1
  pid=$(cat "$file")
  [[ $(ps -o stat= -p "$pid" 2>/dev/null) != Z* && $(ps -o comm= -p "$pid" 2>/dev/null) == "$1" ]] && echo "$pid"
}
daemon_pid slurmctld >/dev/null && scancel --full --user=root 2>/dev/null || true
for daemon in slurmd slurmctld slurmdbd; do
  if pid=$(daemon_pid "$daemon"); then kill "$pid"; fi
done
service mariadb stop >/dev/null 2>&1 || true
pkill -x munged || true
for daemon in slurmd slurmctld slurmdbd; do
  for _ in $(seq 60); do daemon_pid "$daemon" >/dev/null || break; sleep 0.5; done
  daemon_pid "$daemon" >/dev/null && { echo "cluster: error: $daemon is still running" >&2; exit 1; }
done
for daemon in mariadbd munged; do
  for _ in $(seq 60); do alive "$daemon" || break; sleep 0.5; done
  alive "$daemon" && { echo "cluster: error: $daemon is still running" >&2; exit 1; }
done
echo "cluster: down"
