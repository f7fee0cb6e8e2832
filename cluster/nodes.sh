#!/usr/bin/env bash
# A second SLURM cluster of NODES (3) nodes on this one host, beside the one of cluster/up.sh (whose munge it
# uses): one slurmd per node (SLURM's multiple-slurmd mode, which Debian's slurm-wlm is built with), each with
# one CPU and 4 GiB, its own port, spool and log; no accounting. For tests of node loss and of jobs moving
# between nodes. Its clients find it through SLURM_CONF:
#
#   cluster/up.sh && cluster/nodes.sh up       # then: SLURM_CONF=/var/lib/nsl-nodes/slurm.conf sinfo
#   cluster/nodes.sh down                      # stop its daemons (state and logs stay)
#
# Settings (environment): NODES (3), NODES_STATE (/var/lib/nsl-nodes), NODES_PORT (6917: the controller's;
# the nodes' are the ports after it).
set -euo pipefail

NODES=${NODES:-3}
STATE=${NODES_STATE:-/var/lib/nsl-nodes}
PORT=${NODES_PORT:-6917}
HERE=$(cd "$(dirname "$0")" && pwd)
CONF=$STATE/slurm.conf

say() { echo "nodes: $*"; }
die() { echo "nodes: error: $*" >&2; exit 1; }
[[ $(id -u) -eq 0 ]] || die "must run as root: sudo $0 ${1:-up}"

stop() {  # stop the daemon whose pid file is $1, and wait until it has exited
  [[ -s $1 ]] || return 0
  local pid; pid=$(cat "$1")
  kill "$pid" 2>/dev/null || true
  for _ in $(seq 60); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
  kill -0 "$pid" 2>/dev/null && die "pid $pid ($1) did not stop"
  rm -f "$1"
}

case ${1:-up} in
  down)
    SLURM_CONF=$CONF scancel --full --user=root 2>/dev/null || true
    for pidfile in "$STATE"/slurmd-*.pid "$STATE"/slurmctld.pid; do stop "$pidfile"; done
    say "down"
    exit 0 ;;
  up) ;;
  *) die "usage: $0 [up|down]" ;;
esac

munge -n >/dev/null 2>&1 || die "munge does not answer: start cluster/up.sh first"
HOST=$(hostname -s)
mkdir -p "$STATE"/{slurmctld,slurmd,log}
chmod 700 "$STATE"
nodes=""
for i in $(seq "$NODES"); do
  nodes+="NodeName=node$i NodeHostname=$HOST NodeAddr=127.0.0.1 Port=$((PORT + i)) CPUs=1 RealMemory=4096 State=UNKNOWN"$'\n'
  mkdir -p "$STATE/slurmd/node$i"
done
rendered=$(sed -e "s|@CLUSTER@|nslnodes|g" -e "s|@HOST@|$HOST|g" -e "s|@CTLD_PORT@|$PORT|g" -e "s|@STATE@|$STATE|g" \
  "$HERE/nodes.conf.template")
printf '%s\n' "${rendered//@NODES@/${nodes%$'\n'}}" > "$CONF"
chmod 644 "$CONF"

# a fresh start each time: no jobs of an earlier run, every node up
for pidfile in "$STATE"/slurmd-*.pid "$STATE"/slurmctld.pid; do stop "$pidfile"; done
/usr/sbin/slurmctld -f "$CONF" -c
for i in $(seq "$NODES"); do /usr/sbin/slurmd -f "$CONF" -N "node$i"; done
for _ in $(seq 60); do
  idle=$(SLURM_CONF=$CONF sinfo -h -N -o "%N %T" 2>/dev/null | grep -c " idle$" || true)
  [[ $idle -eq $NODES ]] && { say "up: cluster nslnodes, $NODES nodes (node1..node$NODES), SLURM_CONF=$CONF"; exit 0; }
  sleep 1
done
die "the nodes did not come up within 60 s; see $STATE/log/"
