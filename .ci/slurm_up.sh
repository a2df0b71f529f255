#!/usr/bin/env bash
# A one-node SLURM cluster on this machine from Debian's packages (slurmctld, slurmd, munge), for
# tests/test_sweep.py's real-scheduler test. Run as root. Safe to run again: it starts only the
# daemons of its own cluster that are not running, leaves a cluster it did not set up alone when it
# answers, and never touches a slurm.conf it did not write. State, spool and logs go to
# $SEAR_SLURM_DIR (default /tmp/sear-slurm).
set -euo pipefail
DIR=${SEAR_SLURM_DIR:-/tmp/sear-slurm}
CONF=/etc/slurm/slurm.conf
MARK="# written by sear's .ci/slurm_up.sh"
say() { echo "slurm_up: $*"; }
node_states() { sinfo -h -N -o %T 2>/dev/null || true; }
ours() { [ -e "$CONF" ] && grep -qF "$MARK" "$CONF"; }

if ! ours; then
    if command -v sinfo >/dev/null && node_states | grep -qE '^(idle|mixed|allocated)$'; then
        say "SLURM already answers: $(sinfo -h -o '%P %D nodes %T' | head -1)"
        exit 0
    fi
    if [ -e "$CONF" ]; then
        say "$CONF exists but was not written by this script, and SLURM does not answer; not touching it" >&2
        exit 1
    fi
fi
[ "$(id -u)" = 0 ] || { say "must run as root (it installs packages and starts daemons)" >&2; exit 1; }

installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q 'install ok installed'; }
missing=$(for p in slurmctld slurmd slurm-client munge; do installed "$p" || echo "$p"; done)
if [ -n "$missing" ]; then
    say "installing" $missing
    # No init system in a container: keep the packages' scripts from starting the daemons themselves.
    policy=/usr/sbin/policy-rc.d
    own_policy=0
    if [ ! -e "$policy" ]; then printf '#!/bin/sh\nexit 101\n' > "$policy" && chmod +x "$policy" && own_policy=1; fi
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $missing >/dev/null
    [ "$own_policy" = 1 ] && rm -f "$policy"
fi

mkdir -p "$DIR/state" "$DIR/spool" /etc/slurm
host=$(hostname -s)
# The node as slurmd sees it: this machine's CPUs, sockets, cores and real memory; no GPUs.
node=$(slurmd -C 2>/dev/null | grep '^NodeName=' || true)
[ -n "$node" ] || { say "slurmd -C printed no NodeName line" >&2; exit 1; }
cat > "$CONF" <<EOF
$MARK
ClusterName=sear-ci
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
KillWait=10
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
$node State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF

# munge: one key per machine (the package makes it); a daemon only if none answers.
[ -s /etc/munge/munge.key ] || { mungekey --create && chown munge:munge /etc/munge/munge.key; }
mkdir -p /run/munge && chown munge:munge /run/munge 2>/dev/null || true
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    munged --force
fi

running() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }
running "$DIR/slurmctld.pid" || slurmctld
running "$DIR/slurmd.pid" || slurmd

for _ in $(seq 120); do
    states=$(node_states)
    if echo "$states" | grep -qE '^(idle|mixed|allocated)$'; then
        say "up after ${SECONDS}s: $(sinfo -h -o '%P %D nodes %T, %c CPUs, %m MB, gres %G' | head -1)"
        exit 0
    fi
    if echo "$states" | grep -qE '^(down|drain)'; then  # e.g. the state an earlier start left
        scontrol update nodename="$host" state=resume 2>/dev/null || true
    fi
    sleep 0.5
done
say "no idle node after 60 s; the logs:" >&2
tail -n 20 "$DIR/slurmctld.log" "$DIR/slurmd.log" >&2 || true
exit 1
