#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, for the sweep tests (tests/test_sweep.py) and for
# running `dvfb sweep --executor slurm` locally (README "Sweeps", docs/sweeps.md).
#
#   scripts/slurm_cluster.sh install   install Debian's munge and slurm-wlm when missing (root)
#   scripts/slurm_cluster.sh start     write the configuration, start munged, slurmctld, slurmd;
#                                      wait until the node is idle; print the daemons' pids
#   scripts/slurm_cluster.sh stop      stop the daemons this script started, by their pid files
#   scripts/slurm_cluster.sh status    sinfo
#
# The configuration is the one verified on a 2-core container: process tracking through /proc
# (no cgroups inside a container), no task binding, cores and memory as consumable resources,
# no accounting database (so no sacct: submitit falls back to its own result files).
# State lives under $DVFB_SLURM_STATE (default /tmp/dvfb-slurm); configuration in /etc/slurm,
# where Debian's slurm binaries look for it.
set -euo pipefail

STATE=${DVFB_SLURM_STATE:-/tmp/dvfb-slurm}
CONF_DIR=/etc/slurm
CONF=$CONF_DIR/slurm.conf

die() { echo "slurm_cluster.sh: $*" >&2; exit 1; }

install_packages() {
    if command -v slurmctld >/dev/null && command -v slurmd >/dev/null \
        && command -v munged >/dev/null && command -v sbatch >/dev/null; then
        return 0
    fi
    [ "$(id -u)" = 0 ] || die "munge and slurm-wlm are missing and installing them needs root: apt-get install -y munge slurm-wlm"
    command -v apt-get >/dev/null || die "munge and slurm-wlm are missing and there is no apt-get to install them"
    echo "installing munge and slurm-wlm (Debian packages)" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -qq munge slurm-wlm >/dev/null 2>&1 \
        || { apt-get update -qq >/dev/null && apt-get install -y -qq munge slurm-wlm >/dev/null; } \
        || die "apt-get install munge slurm-wlm failed"
}

# Node memory: a little under what slurmd measures, so that the node is never drained as
# "Low RealMemory".
real_memory_mb() {
    local measured
    measured=$(slurmd -C 2>/dev/null | tr ' ' '\n' | sed -n 's/^RealMemory=//p' | head -1)
    [ -n "$measured" ] || die "slurmd -C reported no RealMemory"
    echo $(( measured * 9 / 10 ))
}

write_config() {
    local host cpus mem user
    host=$(hostname -s)
    cpus=$(nproc)
    mem=$(real_memory_mb)
    user=$(id -un)
    # Never replace the configuration of a real installation, only one this script wrote.
    if [ -f "$CONF" ] && ! grep -q "Written by dvfb scripts/slurm_cluster.sh" "$CONF"; then
        die "$CONF exists and was not written by this script; not touching a real SLURM installation"
    fi
    mkdir -p "$CONF_DIR" "$STATE"/{ctld,d,log}
    cat >"$CONF" <<EOF
# Written by dvfb scripts/slurm_cluster.sh: a single-node cluster for tests and local sweeps.
ClusterName=dvfb
SlurmctldHost=$host
SlurmUser=$user
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
ReturnToService=2
MaxArraySize=10000
# A requeued job may start again at once (the tests requeue jobs on purpose).
MinJobAge=300
KillWait=30
PreemptType=preempt/none
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
# Without a default, a job that asks for no memory is given all of the node's, and jobs then run
# one at a time.
DefMemPerCPU=$(( mem / cpus ))
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
    # slurm 22 on bookworm wants cgroup.conf only for cgroup plugins; none is used here.
}

start_munge() {
    if [ -f "$STATE/munged.pid" ] && kill -0 "$(cat "$STATE/munged.pid")" 2>/dev/null; then return 0; fi
    mkdir -p /etc/munge /var/lib/munge /var/log/munge /run/munge
    if [ ! -s /etc/munge/munge.key ]; then
        dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key status=none
    fi
    chown -R munge:munge /etc/munge /var/lib/munge /var/log/munge /run/munge 2>/dev/null || true
    chmod 0400 /etc/munge/munge.key
    chmod 0700 /etc/munge
    chmod 0755 /run/munge
    # munged runs as the munge user, which owns the key; its pid file goes to munge's own run
    # directory and is copied next to the other daemons' pid files.
    rm -f /run/munge/munged.pid
    runuser -u munge -- munged --pid-file=/run/munge/munged.pid --force 2>>"$STATE/log/start.err" \
        || die "munged did not start: $(tail -3 "$STATE/log/start.err")"
    wait_for 10 test -s /run/munge/munged.pid || die "munged wrote no pid file"
    cp /run/munge/munged.pid "$STATE/munged.pid"
}

wait_for() {  # wait_for SECONDS COMMAND...
    local limit=$1; shift
    local t=0
    until "$@" >/dev/null 2>&1; do
        t=$((t + 1))
        [ $t -le "$limit" ] || return 1
        sleep 1
    done
}

node_idle() { sinfo -h -N -o '%T' | grep -Eq '^(idle|mixed|allocated)'; }

start() {
    [ "$(id -u)" = 0 ] || die "starting slurmd needs root"
    install_packages
    write_config
    start_munge
    if ! { [ -f "$STATE/slurmctld.pid" ] && kill -0 "$(cat "$STATE/slurmctld.pid")" 2>/dev/null; }; then
        # -c: start with no jobs; jobs of an earlier start of this throw-away cluster are gone with
        # their slurmd (a sweep re-run resubmits what did not finish).
        slurmctld -c -i 2>>"$STATE/log/start.err" || die "slurmctld did not start: $(tail -3 "$STATE/log/start.err")"
    fi
    wait_for 30 scontrol ping || die "slurmctld does not answer (log: $STATE/log/slurmctld.log)"
    if ! { [ -f "$STATE/slurmd.pid" ] && kill -0 "$(cat "$STATE/slurmd.pid")" 2>/dev/null; }; then
        slurmd 2>>"$STATE/log/start.err" || die "slurmd did not start: $(tail -3 "$STATE/log/start.err")"
    fi
    if ! wait_for 60 node_idle; then
        scontrol update NodeName="$(hostname -s)" State=RESUME >/dev/null 2>&1 || true
        wait_for 30 node_idle || die "the node did not become idle: $(sinfo -h -N -o '%T %E') (log: $STATE/log/slurmd.log)"
    fi
    # The daemons write their pid files after they fork: wait for all three, so that the caller
    # gets every pid (it stops exactly these processes).
    for daemon in munged slurmctld slurmd; do
        wait_for 30 test -s "$STATE/$daemon.pid" || die "$daemon wrote no pid file ($STATE/$daemon.pid)"
    done
    echo "munged=$(cat "$STATE/munged.pid") slurmctld=$(cat "$STATE/slurmctld.pid") slurmd=$(cat "$STATE/slurmd.pid")"
}

stop_pidfile() {  # stop_pidfile FILE: TERM the process named in FILE, wait for it to end
    local file=$1 pid
    [ -f "$file" ] || return 0
    pid=$(cat "$file")
    if kill -0 "$pid" 2>/dev/null; then
        kill -TERM "$pid"
        for _ in $(seq 30); do kill -0 "$pid" 2>/dev/null || break; sleep 1; done
        kill -0 "$pid" 2>/dev/null && kill -KILL "$pid"
    fi
    rm -f "$file"
}

stop() {
    stop_pidfile "$STATE/slurmd.pid"
    stop_pidfile "$STATE/slurmctld.pid"
    stop_pidfile "$STATE/munged.pid"
}

case "${1:-}" in
    install) install_packages ;;
    start) start ;;
    stop) stop ;;
    status) sinfo ;;
    *) echo "usage: $0 install|start|stop|status" >&2; exit 2 ;;
esac
