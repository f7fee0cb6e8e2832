#!/usr/bin/env bash
# Stop the single-node SLURM cluster started by cluster/up.sh: cancel jobs, stop the SLURM daemons,
# slurmdbd, MariaDB and munge, and wait until they have exited. State and logs stay in CLUSTER_STATE.
set -euo pipefail
[[ $(id -u) -eq 0 ]] || { echo "cluster: error: must run as root: sudo $0" >&2; exit 1; }
alive() { pgrep -x "$1" --runstates D,R,S >/dev/null; }
alive slurmctld && scancel --full --user=root 2>/dev/null || true
for daemon in slurmd slurmctld slurmdbd; do pkill -x "$daemon" || true; done
service mariadb stop >/dev/null 2>&1 || true
pkill -x munged || true
for daemon in slurmd slurmctld slurmdbd mariadbd munged; do
  for _ in $(seq 60); do alive "$daemon" || break; sleep 0.5; done
  alive "$daemon" && { echo "cluster: error: $daemon is still running" >&2; exit 1; }
done
echo "cluster: down"
