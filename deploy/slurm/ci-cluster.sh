#!/bin/bash
# A real single-node Slurm cluster on this machine, without systemd: munged,
# slurmctld and slurmd started directly with a private configuration under
# a temporary folder (nothing in /etc is changed). Submits the shard array
# twice (--array=0-3 and --array=1-7:2) with the dependent merge, waits, and
# checks the merged chunks equal a single-process bake. The daemons are
# stopped by their process ids at the end, pass or fail.
#
#   deploy/slurm/ci-cluster.sh SHADOWCULL_BINARY SETTINGS
# Needs root (slurmd runs jobs as the submitting user) and the Debian
# packages slurm-wlm and munge (.ci/run installs them).
set -euo pipefail
if [ $# -ne 2 ]; then
  sed -n '2,11p' "$0" >&2
  exit 2
fi
binary=$(realpath "$1")
settings=$(realpath "$2")
here=$(cd "$(dirname "$0")" && pwd)
work=$(mktemp -d /tmp/shadowcull-slurm.XXXXXX)
chmod 755 "$work"
host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 / 2 ))
pids=()

log() { echo "slurm-ci: $*"; }

show_logs() {
  for f in "$work"/log/*.log "$work"/parts*/*.log; do
    [ -f "$f" ] || continue
    echo "----- $f (last 40 lines)"
    tail -n 40 "$f"
  done
}

stop() {
  local status=$?
  trap - EXIT
  if [ $status -ne 0 ]; then
    log "FAILED (exit $status); logs follow"
    show_logs || true
  fi
  # Reverse start order; each by its own pid.
  for (( i=${#pids[@]}-1; i>=0; i-- )); do
    kill "${pids[$i]}" 2>/dev/null || true
  done
  for pid in "${pids[@]}"; do
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
    kill -9 "$pid" 2>/dev/null || true
  done
  rm -rf "$work"
  exit $status
}
trap stop EXIT

mkdir -p "$work"/{munge,state,spool,log}
# munge: a private key and socket (the system's munged, if any, is left alone).
dd if=/dev/urandom of="$work/munge/munge.key" bs=1024 count=1 status=none
chmod 700 "$work/munge"
chmod 400 "$work/munge/munge.key"
munged --foreground --force --key-file="$work/munge/munge.key" \
  --socket="$work/munge/munge.socket" --pid-file="$work/munge/munged.pid" \
  --log-file="$work/log/munged.log" --seed-file="$work/munge/seed" \
  >>"$work/log/munged.log" 2>&1 &
pids+=($!)
for _ in $(seq 50); do [ -S "$work/munge/munge.socket" ] && break; sleep 0.2; done
[ -S "$work/munge/munge.socket" ] || { log "munged did not start"; exit 1; }

export SLURM_CONF="$work/slurm.conf"
cat > "$SLURM_CONF" <<CONF
ClusterName=shadowcullci
SlurmctldHost=$host
SlurmctldPort=16817
SlurmdPort=16818
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$work/munge/munge.socket
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd.pid
SlurmctldLogFile=$work/log/slurmctld.log
SlurmdLogFile=$work/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
MinJobAge=600
MpiDefault=none
NodeName=$host CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=ci Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF

slurmctld -D -c -f "$SLURM_CONF" >"$work/log/slurmctld.out" 2>&1 &
pids+=($!)
slurmd -D -f "$SLURM_CONF" -N "$host" >"$work/log/slurmd.out" 2>&1 &
pids+=($!)

log "waiting for node $host to be idle"
for _ in $(seq 60); do
  state=$(sinfo -h -n "$host" -o %t 2>/dev/null || true)
  [[ $state == idle* ]] && break
  sleep 1
done
[[ ${state:-} == idle* ]] || { log "node state '${state:-none}' after 60 s"; exit 1; }
log "cluster up: $(sinfo -h -o '%P %D %c %m %t')"

log "reference: one bake"
"$binary" bake "$settings" --out "$work/one" >"$work/log/one.log" 2>&1

# Waits for job $1 to end; fails unless it COMPLETED.
wait_job() {
  local id=$1 state=""
  for _ in $(seq 600); do
    state=$(scontrol show job "$id" 2>/dev/null | sed -n 's/.*JobState=\([A-Z_]*\).*/\1/p' | head -n1)
    case "$state" in
      COMPLETED) return 0 ;;
      FAILED|CANCELLED|TIMEOUT|NODE_FAIL|OUT_OF_MEMORY|BOOT_FAIL|DEADLINE|PREEMPTED)
        log "job $id ended $state"; scontrol show job "$id" || true; return 1 ;;
    esac
    sleep 1
  done
  log "job $id still '$state' after 600 s"; scontrol show job "$id" || true
  return 1
}

for array in 0-3 1-7:2; do
  tag=${array//[^0-9]/_}
  parts="$work/parts$tag"
  log "submitting --array=$array"
  ids=$(SHADOWCULL="$binary" "$here/submit.sh" "$settings" "$parts" "$array" "$work/merged$tag")
  read -r array_id merge_id <<<"$ids"
  log "array job $array_id, merge job $merge_id (afterok)"
  wait_job "$merge_id"
  count=$(ls "$parts"/shard-*-of-4.part | wc -l)
  [ "$count" -eq 4 ] || { log "expected 4 partials, found $count"; exit 1; }
  said=$(cat "$parts"/shadowcull-shard-*.log | grep -o 'shard [0-9]/4 from SLURM_ARRAY_TASK_ID=[0-9]*' | sort | tr '\n' ';')
  log "shards said: $said"
  [ "$(grep -o 'from SLURM' <<<"$said" | wc -l)" -eq 4 ] || { log "not every shard took its index from Slurm"; exit 1; }
  diff -r "$work/one" "$work/merged$tag" >/dev/null \
    || { log "--array=$array: merged chunks differ from one bake"; diff -rq "$work/one" "$work/merged$tag"; exit 1; }
  log "--array=$array: 4 shards merged = one bake ($(find "$work/one" -name '*.chunk' | wc -l) chunks)"
done

# A failed task retried as docs/distributed.md says: re-submitted alone
# with the same --export, it bakes its own shard of the original array.
parts="$work/parts1_7_2"
rm -f "$parts"/shard-2-of-4.part
log "re-submitting task 5 of --array=1-7:2 alone"
retry_id=$(sbatch --parsable --array=5 --chdir="$parts" \
  --export=ALL,SHADOWCULL="$binary",SETTINGS="$settings",PARTIALS="$parts" "$here/shard.sbatch")
wait_job "${retry_id%%;*}"
[ -f "$parts"/shard-2-of-4.part ] || { log "the retry did not write shard 2 of 4"; ls "$parts"; exit 1; }
grep -h 'shard 2/4 from SLURM_ARRAY_TASK_ID=5' "$parts"/shadowcull-shard-*.log >/dev/null \
  || { log "the retry did not say it is shard 2/4"; exit 1; }
"$binary" merge "$settings" "$parts"/shard-*-of-4.part --out "$work/retried" >"$work/log/retried.log" 2>&1
diff -r "$work/one" "$work/retried" >/dev/null \
  || { log "merge after the retry differs from one bake"; exit 1; }
log "a task re-submitted alone baked its shard; merged = one bake"
log "PASSED"
