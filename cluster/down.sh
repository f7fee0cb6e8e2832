#!/usr/bin/env bash
# Stop the single-node SLURM clusters started by cluster/up.sh (the first and, if it ran, the second): cancel their
# jobs, stop their SLURM daemons (by their pid files: another cluster on this host, cluster/nodes.sh, is left
# alone) and slurmdbds, then MariaDB and munge, and wait until they have exited. State and logs stay in
# CLUSTER_STATE (both by default: /var/lib/nsl-cluster and /var/lib/nsl-cluster-2).
set -euo pipefail
[[ $(id -u) -eq 0 ]] || { echo "cluster: error: must run as root: sudo $0" >&2; exit 1; }
read -r -a STATES <<< "${CLUSTER_STATE:-/var/lib/nsl-cluster /var/lib/nsl-cluster-2}"
alive() { pgrep -x "$1" --runstates D,R,S >/dev/null; }
daemon_pid() {  # the SLURM daemon $2 of the cluster whose state is in $1, by its pid file
  local file=$1/$2.pid pid
  [[ -s $file ]] || return 1
  pid=$(cat "$file")
  [[ $(ps -o stat= -p "$pid" 2>/dev/null) != Z* && $(ps -o comm= -p "$pid" 2>/dev/null) == "$2" ]] && echo "$pid"
}
for state in "${STATES[@]}"; do
  conf=/etc/slurm/slurm.conf
  [[ -f $state/slurm.conf ]] && conf=$state/slurm.conf  # the second cluster's lies in its state
  daemon_pid "$state" slurmctld >/dev/null && SLURM_CONF=$conf scancel --full --user=root 2>/dev/null || true
  for daemon in slurmd slurmctld slurmdbd; do
    if pid=$(daemon_pid "$state" "$daemon"); then kill "$pid"; fi
  done
done
for state in "${STATES[@]}"; do
  for daemon in slurmd slurmctld slurmdbd; do
    for _ in $(seq 60); do daemon_pid "$state" "$daemon" >/dev/null || break; sleep 0.5; done
    daemon_pid "$state" "$daemon" >/dev/null && { echo "cluster: error: $daemon ($state) is still running" >&2; exit 1; }
  done
done
service mariadb stop >/dev/null 2>&1 || true
pkill -x munged || true
for daemon in mariadbd munged; do
  for _ in $(seq 60); do alive "$daemon" || break; sleep 0.5; done
  alive "$daemon" && { echo "cluster: error: $daemon is still running" >&2; exit 1; }
done
echo "cluster: down"
