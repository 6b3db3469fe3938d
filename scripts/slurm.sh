#!/usr/bin/env bash
# Slurm check (README "Running a sweep on a cluster"): installs slurm-wlm and munge when
# missing, starts a private munged, slurmctld and slurmd (one node: this machine, a generated
# slurm.conf in a temporary folder, free ports), submits scripts/slurm/sweep.toml as a job array
# with `sbatch --wait`, collects it, runs the same sweep locally and compares every task's
# result, render and checkpoint and the merged tables and figures byte for byte. A re-submission
# after deleting one result must list only that task. Stops the daemons on exit.
# Prints one `check passed:` line per check; skips (exit 0) with a message only when the
# daemons cannot start here.
set -euo pipefail
cd "$(dirname "$0")/.."

sudo=$([ "$(id -u)" = 0 ] || echo sudo)
packages=(slurm-wlm munge)
missing=()
for package in "${packages[@]}"; do
    dpkg -s "$package" >/dev/null 2>&1 || missing+=("$package")
done
if [ ${#missing[@]} -gt 0 ]; then
    $sudo apt-get update
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y --no-install-recommends "${missing[@]}"
fi

cargo build --release --bin orbit-nerf
binary=$PWD/target/release/orbit-nerf
description=$PWD/scripts/slurm/sweep.toml

work=$(mktemp -d)
chmod 755 "$work"
pids=()
stop() {
    for pid in "${pids[@]}"; do
        $sudo kill "$pid" 2>/dev/null || true
    done
    for pid in "${pids[@]}"; do
        for _ in $(seq 50); do
            $sudo kill -0 "$pid" 2>/dev/null || break
            sleep 0.1
        done
    done
    $sudo rm -rf "$work"
}
trap stop EXIT
skip() {
    echo "slurm: skipping: $1"
    for log in "$work"/*.log; do
        [ -f "$log" ] && { echo "--- $log"; $sudo tail -n 20 "$log"; }
    done
    exit 0
}

# A private munge: its own key, socket and files in $work.
dd if=/dev/urandom of="$work/munge.key" bs=1024 count=1 status=none
chmod 400 "$work/munge.key"
$sudo chown root: "$work/munge.key"
$sudo munged --force --key-file="$work/munge.key" --socket="$work/munge.sock" \
    --pid-file="$work/munged.pid" --log-file="$work/munged.log" --seed-file="$work/munged.seed" ||
    skip "munged does not start"
pids+=("$($sudo cat "$work/munged.pid")")

# Two free TCP ports for slurmctld and slurmd (other checks may run a Slurm at the same time):
# random ones nothing answers on.
free_port() {
    local port
    while :; do
        port=$((20000 + RANDOM % 20000))
        [ "$port" != "${1:-}" ] || continue
        (exec 3<>"/dev/tcp/127.0.0.1/$port") 2>/dev/null || break
    done
    echo "$port"
}
ctld_port=$(free_port)
slurmd_port=$(free_port "$ctld_port")
host=$(hostname -s)
cpus=$(nproc)
memory=$(awk '/MemTotal/ { print int($2 / 1024 * 0.9) }' /proc/meminfo)
user=$([ "$(id -u)" = 0 ] && echo root || echo "$(id -un)")
export SLURM_CONF=$work/slurm.conf
mkdir -p "$work/state" "$work/spool"
cat >"$SLURM_CONF" <<CONF
ClusterName=orbitnerf
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
SlurmUser=root
AuthType=auth/munge
AuthInfo=socket=$work/munge.sock
CredType=cred/munge
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd.pid
SlurmctldLogFile=$work/slurmctld.log
SlurmdLogFile=$work/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/builtin
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$memory State=UNKNOWN
PartitionName=ci Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
$sudo env SLURM_CONF="$SLURM_CONF" slurmctld -D -i >"$work/slurmctld.out" 2>&1 &
pids+=($!)
$sudo env SLURM_CONF="$SLURM_CONF" slurmd -D -N "$host" >"$work/slurmd.out" 2>&1 &
pids+=($!)
for _ in $(seq 60); do
    state=$(sinfo -h -N -o %t 2>/dev/null || true)
    [ "$state" = idle ] && break
    sleep 0.5
done
[ "$state" = idle ] || skip "slurmctld and slurmd did not bring the node up (state: ${state:-none})"
echo "slurm: node $host ($cpus CPUs, $memory MB) idle in partition ci (user $user)"

# The sweep as a job array, then collected.
"$binary" sweep slurm "$description" --out "$work/cluster" --partition ci --cpus-per-task 1 \
    --time 00:10:00 --no-submit
timeout 600 sbatch --wait "$work/cluster/sweep.sbatch" || {
    echo "slurm: FAILED: the job array did not finish cleanly; its logs:" >&2
    tail -n 20 "$work"/cluster/tasks/*/log.txt "$work"/cluster/slurm/*.out >&2 || true
    exit 1
}
"$binary" sweep collect "$description" --out "$work/cluster" >/dev/null
# The same sweep on this machine.
"$binary" sweep run "$description" --out "$work/local" --jobs 2 --threads 2 >/dev/null

tasks=$("$binary" sweep list "$description" | wc -l)
compared=0
same() {
    cmp "$work/cluster/$1" "$work/local/$1" || {
        echo "slurm: FAILED: $1 differs between the cluster and the local run" >&2
        exit 1
    }
    compared=$((compared + 1))
}
for i in $(seq 0 $((tasks - 1))); do
    for file in result.json render.png checkpoint.onrf; do
        same "tasks/$i/$file"
    done
done
for file in sweep.csv sweep.md renders.png; do
    same "$file"
done
echo "check passed: a $tasks-task sweep as a Slurm job array (1 CPU per task) and locally (2 threads per task) gives the same bytes ($compared files)"

# A re-submission lists only the missing task.
rm "$work/cluster/tasks/1/result.json"
"$binary" sweep slurm "$description" --out "$work/cluster" --partition ci --no-submit >/dev/null
grep -qx '#SBATCH --array=1' "$work/cluster/sweep.sbatch" || {
    echo "slurm: FAILED: the re-submission does not list only task 1:" >&2
    cat "$work/cluster/sweep.sbatch" >&2
    exit 1
}
echo "check passed: a re-submission runs only the task without a result (--array=1)"
