#!/usr/bin/env bash
# Start a real single-node SLURM cluster on this Debian machine, as root: munge, MariaDB + slurmdbd (so
# sacct works), slurmctld and slurmd. Idempotent: what runs already is kept; a changed config is applied
# with a restart of the SLURM daemons.
#
#   sudo cluster/up.sh                      # install what is missing, start, wait until the node is idle
#   MAX_ARRAY_SIZE=50 cluster/up.sh         # a cluster with smaller limits (array-splitting tests)
#   cluster/up.sh --optional                # for `make test`: without root, say so and exit 0
#   CLUSTER_INSTANCE=2 cluster/up.sh        # a second such cluster beside the first (make test runs the SLURM
#                                           # tests on both): then SLURM_CONF=/var/lib/nsl-cluster-2/slurm.conf sinfo
#
# Settings (environment): CLUSTER_INSTANCE (1; the second has its own name, state, ports, slurmdbd and accounting
# database, and shares munge and MariaDB), CLUSTER_NAME (nsl, nsl2), MAX_ARRAY_SIZE (1001), MAX_JOB_COUNT (10000),
# CLUSTER_STATE (/var/lib/nsl-cluster, /var/lib/nsl-cluster-2: spool, state and logs).
set -euo pipefail

INSTANCE=${CLUSTER_INSTANCE:-1}
[[ $INSTANCE == 1 || $INSTANCE == 2 ]] || { echo "cluster: error: CLUSTER_INSTANCE=$INSTANCE: 1 or 2" >&2; exit 1; }
if [[ $INSTANCE == 1 ]]; then
  CLUSTER_NAME=${CLUSTER_NAME:-nsl}
  STATE=${CLUSTER_STATE:-/var/lib/nsl-cluster}
  CONF_DIR=/etc/slurm      # SLURM's default: its commands find this cluster without SLURM_CONF
  PORT=6817                # SLURM's default ports: slurmctld, slurmd (+1), slurmdbd (+2)
  DATABASE=slurm_acct_db DB_USER=slurm
  FIRST_JOB_ID=1
else
  CLUSTER_NAME=${CLUSTER_NAME:-nsl2}
  STATE=${CLUSTER_STATE:-/var/lib/nsl-cluster-2}
  CONF_DIR=$STATE
  PORT=6827
  DATABASE=slurm_acct_db_2 DB_USER=slurm2
  FIRST_JOB_ID=500000     # its job ids apart from the first's
fi
MAX_ARRAY_SIZE=${MAX_ARRAY_SIZE:-1001}
MAX_JOB_COUNT=${MAX_JOB_COUNT:-10000}
HERE=$(cd "$(dirname "$0")" && pwd)
PACKAGES=(slurm-wlm slurmdbd munge mariadb-server)

say() { echo "cluster: $*"; }
die() { echo "cluster: error: $*" >&2; exit 1; }

if [[ $(id -u) -ne 0 ]]; then
  if [[ ${1:-} == --optional && ${CI:-} != true ]]; then
    say "not root: no local SLURM cluster, the SLURM tests will be skipped (run 'sudo cluster/up.sh')"
    exit 0
  fi
  die "must run as root (it installs packages and starts daemons): sudo $0"
fi

install_packages() {
  local missing=()
  for package in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "ok installed" || missing+=("$package")
  done
  [[ ${#missing[@]} -eq 0 ]] && return
  say "installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
}

# Zombies of daemons stopped by down.sh do not count.
running() { pgrep -x "$1" --runstates D,R,S >/dev/null; }
# This cluster's SLURM daemon $1 (slurmctld, slurmd, slurmdbd) by its pid file: the slurmctld and slurmds of another
# cluster on this host (cluster/nodes.sh) are not this one's, and a restart leaves them alone.
daemon_pid() {
  local file=$STATE/$1.pid pid
  [[ -s $file ]] || return 1
  pid=$(cat "$file")
  [[ $(ps -o stat= -p "$pid" 2>/dev/null) != Z* && $(ps -o comm= -p "$pid" 2>/dev/null) == "$1" ]] && echo "$pid"
}

wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...
  local seconds=$1 what=$2; shift 2
  for _ in $(seq "$seconds"); do "$@" >/dev/null 2>&1 && return 0; sleep 1; done
  die "$what did not come up within ${seconds} s; see $STATE/log/"
}

start_munge() {
  if [[ ! -s /etc/munge/munge.key ]]; then
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
  fi
  chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
  mkdir -p /run/munge && chown munge:munge /run/munge
  running munged || su -s /bin/sh munge -c "/usr/sbin/munged --force"
  wait_for 20 munge munge -n
}

start_database() {
  running mariadbd || running mysqld || service mariadb start >/dev/null
  wait_for 60 MariaDB mysqladmin ping
  mysql -e "CREATE USER IF NOT EXISTS '$DB_USER'@'localhost' IDENTIFIED BY '$DB_PASSWORD';
            ALTER USER '$DB_USER'@'localhost' IDENTIFIED BY '$DB_PASSWORD';
            GRANT ALL ON $DATABASE.* TO '$DB_USER'@'localhost';"
}

render() {  # render TEMPLATE DESTINATION MODE: returns 0 when the destination changed
  local rendered
  rendered=$(sed -e "s|@CLUSTER@|$CLUSTER_NAME|g" -e "s|@HOST@|$HOST|g" -e "s|@CPUS@|$CPUS|g" \
    -e "s|@MEMORY_MB@|$MEMORY_MB|g" -e "s|@STATE@|$STATE|g" -e "s|@MAX_ARRAY_SIZE@|$MAX_ARRAY_SIZE|g" \
    -e "s|@MAX_JOB_COUNT@|$MAX_JOB_COUNT|g" -e "s|@FIRST_JOB_ID@|$FIRST_JOB_ID|g" \
    -e "s|@DATABASE@|$DATABASE|g" -e "s|@DB_USER@|$DB_USER|g" -e "s|@DB_PASSWORD@|$DB_PASSWORD|g" \
    -e "s|@CTLD_PORT@|$PORT|g" -e "s|@SLURMD_PORT@|$((PORT + 1))|g" -e "s|@DBD_PORT@|$((PORT + 2))|g" "$1")
  if [[ -f $2 && "$(cat "$2")" == "$rendered" ]]; then return 1; fi
  install -m "$3" /dev/null "$2"
  printf '%s\n' "$rendered" > "$2"
}

restart() {  # restart DAEMON: stop it if running (a busy controller saves its state first), start it
  local pid
  if pid=$(daemon_pid "$1"); then
    kill "$pid"
    for _ in $(seq 120); do daemon_pid "$1" >/dev/null || break; sleep 0.5; done
    daemon_pid "$1" >/dev/null && die "$1 did not stop within 60 s; see $STATE/log/"
  fi
  "/usr/sbin/$1"
}

install_packages
HOST=$(hostname -s)
# GNU nproc honours OMP_NUM_THREADS (exported for single-threaded training): the node's CPUs are those without it
CPUS=$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc)
# Leave 512 MB to the system; slurmd refuses a node that claims more memory than it has.
MEMORY_MB=$(( $(awk '/MemTotal/ {print int($2 / 1024)}' /proc/meminfo) - 512 ))
mkdir -p "$STATE"/{slurmctld,slurmd,log} "$CONF_DIR"
chmod 700 "$STATE"
[[ -s $STATE/db_password ]] || head -c 18 /dev/urandom | base64 | tr -d '/+=' > "$STATE/db_password"
DB_PASSWORD=$(cat "$STATE/db_password")

start_munge
start_database
dbd_changed=0; ctl_changed=0
render "$HERE/slurmdbd.conf.template" "$CONF_DIR/slurmdbd.conf" 600 && dbd_changed=1
render "$HERE/slurm.conf.template" "$CONF_DIR/slurm.conf" 644 && ctl_changed=1
export SLURM_CONF=$CONF_DIR/slurm.conf  # this cluster's, for the SLURM commands below

if [[ $dbd_changed == 1 ]] || ! daemon_pid slurmdbd >/dev/null; then restart slurmdbd; fi
wait_for 60 slurmdbd sacctmgr -n show cluster
if ! sacctmgr -n -P show cluster format=cluster | grep -qx "$CLUSTER_NAME"; then
  sacctmgr -i add cluster "$CLUSTER_NAME" >/dev/null
fi
if [[ $ctl_changed == 1 ]] || ! daemon_pid slurmctld >/dev/null; then restart slurmctld; fi
if [[ $ctl_changed == 1 ]] || ! daemon_pid slurmd >/dev/null; then restart slurmd; fi
wait_for 60 "the node $HOST" bash -c "sinfo -h -N -o %T | grep -Eq '^(idle|mixed|allocated)'"
wait_for 60 "MaxArraySize=$MAX_ARRAY_SIZE in the controller" bash -c \
  "scontrol show config | grep -Eq '^MaxArraySize +=  *$MAX_ARRAY_SIZE\$'"
say "up: cluster $CLUSTER_NAME, node $HOST, $CPUS CPUs, MaxArraySize=$MAX_ARRAY_SIZE, logs in $STATE/log, SLURM_CONF=$SLURM_CONF"
