#!/usr/bin/env bash
# Tests deploy/slurm/xfactor.sbatch on a real one-node Slurm cluster on this machine.
#
#   scripts/test-slurm.sh            # builds the binaries, then runs every case
#   scripts/test-slurm.sh --no-build # uses the binaries already in $CARGO_TARGET_DIR/release
#   XFACTOR_SLURM_CASES="finish suspend" scripts/test-slurm.sh   # a subset
#
# Needs root (slurmd runs jobs as root here). Installs Debian's slurm-wlm (22.05 on bookworm)
# and jq if missing, writes a slurm.conf for a cluster of this machine alone, starts slurmctld
# and slurmd in the foreground mode under a temporary folder, and stops them (and every job
# process) on exit. Each case submits the sbatch script with two worker tasks on the one node:
#   finish     the job runs to its end: COMPLETED, report outcome finished, both workers
#              registered under their Slurm names with the coordinator found from the node list
#   suspend    `scancel --batch --signal=USR1` once a checkpoint is committed: the script passes
#              USR1 on, the coordinator exits 75, the job requeues itself, runs again with
#              SLURM_RESTART_COUNT=1 and resumes from the committed step, then finishes
#   timelimit  the same through --time=3 and the script's own --signal=B:USR1@90; the resumed
#              run is then cancelled with a plain scancel (SIGTERM): it stops, is not requeued
#   noworkers  every worker fails at once: the script stops the coordinator instead of
#              letting the allocation wait for registrations that will never come
# and prints its figures as key=value lines.
#
# slurm.conf settings that matter here (the rest is the smallest cluster that runs as root):
# - AuthInfo=cred_expire=5: a requeued job gets BeginTime = now + cred_expire + 1, 120 s by
#   default; 5 is the smallest value slurmctld accepts (lower ones are refused, back to 120).
# - SchedulerParameters=sched_interval=1: once that BeginTime passes no event wakes the
#   scheduler, so the job waits for the periodic pass (every 60 s by default). Together the
#   defaults make the 2.5 minutes between a requeue and the next start; these make 6 s.
# - KillWait=10: SIGTERM to SIGKILL when a job is cancelled (30 s by default).
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$PWD"

build=1
for arg in "$@"; do
    case "$arg" in
        --no-build) build=0 ;;
        *) echo "usage: $0 [--no-build]" >&2; exit 2 ;;
    esac
done
cases="${XFACTOR_SLURM_CASES:-finish suspend timelimit noworkers}"
port="${XFACTOR_SLURM_TEST_PORT:-50051}"          # the coordinator's (the workers' default)
slurm_port="${XFACTOR_SLURM_DAEMON_PORT:-6817}"   # slurmctld's; slurmd takes the next one

say() { echo "test-slurm: $*" >&2; }
# Seconds from epoch $1 to epoch $2, one decimal.
elapsed() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }'; }
fail() { say "FAILED: $*"; exit 1; }

if [ "$(id -u)" != 0 ]; then
    fail "run as root (the one-node cluster's slurmd runs the jobs as root)"
fi

# --- packages ---------------------------------------------------------------------------------
packages=()
command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v sbatch >/dev/null \
    || packages+=(slurm-wlm)
command -v jq >/dev/null || packages+=(jq)
if [ "${#packages[@]}" -gt 0 ]; then
    say "installing ${packages[*]}"
    apt-get update -qq
    # slurm-wlm pulls in munge, which auth/none below does not use (its service is not started).
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        "${packages[@]}" >/dev/null
fi

# --- binaries ---------------------------------------------------------------------------------
tmp="$(mktemp -d /tmp/xfactor-slurm.XXXXXX)"
chmod 755 "$tmp"
export SLURM_CONF="$tmp/slurm.conf"
source scripts/env.sh
if [ "$build" = 1 ]; then
    bash scripts/setup.sh
    # The package set of scripts/run.sh, so that both share one build.
    cargo build --release -p coordinator -p worker -p evaluation --bins
fi
bin="$CARGO_TARGET_DIR/release"
for program in xfactor-coordinator xfactor-worker xfactor-local; do
    [ -x "$bin/$program" ] || fail "$bin/$program is missing (build it, or drop --no-build)"
done

# --- cleanup ----------------------------------------------------------------------------------
daemon_pids=()
# Processes of this test's cluster left behind by its daemons (job steps, their tasks): they
# carry its SLURM_CONF (slurmd has it, jobs inherit it from sbatch) and run in sessions of their
# own, unlike this script and its subshells, so nothing else on the machine is touched.
session_of() { awk '{ sub(/^.*\) /, ""); print $4 }' "/proc/$1/stat" 2>/dev/null; }
cluster_pids() {
    local environ pid own
    own="$(session_of $$)"
    for environ in /proc/[0-9]*/environ; do
        pid="${environ#/proc/}"
        pid="${pid%/environ}"
        [ "$(session_of "$pid")" != "$own" ] || continue
        if { tr '\0' '\n' <"$environ"; } 2>/dev/null | grep -qxF "SLURM_CONF=$SLURM_CONF"; then
            echo "$pid"
        fi
    done
}
cleanup() {
    local status=$? pid i
    trap - EXIT INT TERM
    if [ "${#daemon_pids[@]}" -gt 0 ]; then
        scancel --quiet --user=root 2>/dev/null || true
        for ((i = 0; i < 20; i++)); do
            [ -z "$(squeue -h -o %i 2>/dev/null)" ] && break
            sleep 0.5
        done
        for pid in "${daemon_pids[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
        for pid in "${daemon_pids[@]}"; do
            for ((i = 0; i < 20; i++)); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
            kill -KILL "$pid" 2>/dev/null || true
        done
        for pid in $(cluster_pids); do
            say "killing leftover process $pid ($(tr '\0' ' ' <"/proc/$pid/cmdline" 2>/dev/null | cut -c1-80))"
            kill -KILL "$pid" 2>/dev/null || true
        done
    fi
    if [ "$status" != 0 ] || [ -n "${XFACTOR_SLURM_KEEP:-}" ]; then
        say "logs and job folders kept in $tmp"
    else
        rm -rf "$tmp"
    fi
    exit "$status"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# --- the cluster ------------------------------------------------------------------------------
node="$(hostname -s)"
mkdir -p "$tmp/ctld" "$tmp/slurmd" "$tmp/log"
cat >"$SLURM_CONF" <<EOF
# A one-node cluster for scripts/test-slurm.sh: this machine is controller and compute node.
ClusterName=xfactor-test
SlurmctldHost=$node
SlurmctldPort=$slurm_port
SlurmdPort=$((slurm_port + 1))
SlurmUser=root
SlurmdUser=root
# No munge: no authentication or job credentials at all (a single trusted machine).
AuthType=auth/none
CredType=cred/none
# A requeued job may start again cred_expire + 1 s later (default 120; 5 is the minimum).
AuthInfo=cred_expire=5
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MailProg=/bin/true
SchedulerType=sched/backfill
# The main scheduler's periodic pass every second (60 s by default): what starts a requeued
# job once its BeginTime has passed.
SchedulerParameters=sched_interval=1
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
JobRequeue=1
KillWait=10
MinJobAge=300
ReturnToService=2
SlurmctldTimeout=10
SlurmdTimeout=10
StateSaveLocation=$tmp/ctld
SlurmdSpoolDir=$tmp/slurmd
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/log/slurmctld.log
SlurmdLogFile=$tmp/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
NodeName=$node CPUs=$(nproc) State=UNKNOWN
PartitionName=test Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF
for p in "$slurm_port" "$((slurm_port + 1))" "$port"; do
    if ss -Hltn "( sport = :$p )" | grep -q .; then
        fail "port $p is in use (another Slurm? set XFACTOR_SLURM_DAEMON_PORT / XFACTOR_SLURM_TEST_PORT)"
    fi
done
started=$(date +%s.%N)
setsid slurmctld -D -f "$SLURM_CONF" >"$tmp/log/slurmctld.out" 2>&1 </dev/null &
daemon_pids+=($!)
setsid slurmd -D -f "$SLURM_CONF" >"$tmp/log/slurmd.out" 2>&1 </dev/null &
daemon_pids+=($!)
for ((i = 0; ; i++)); do
    state="$(sinfo -h -n "$node" -o %T 2>/dev/null || true)"
    [ "$state" = idle ] && break
    for pid in "${daemon_pids[@]}"; do
        kill -0 "$pid" 2>/dev/null || { tail -n 20 "$tmp"/log/*; fail "a Slurm daemon exited"; }
    done
    [ "$i" -lt 120 ] || { tail -n 20 "$tmp"/log/*; fail "node $node not idle after 60 s (state: $state)"; }
    sleep 0.5
done
echo "slurm_version=$(sinfo -V | awk '{print $2}') node=$node cpus=$(nproc) cluster_up_s=$(elapsed "$started" "$(date +%s.%N)")"

# --- helpers ----------------------------------------------------------------------------------
job_field() { scontrol show job -o "$1" 2>/dev/null | tr ' ' '\n' | sed -n "s/^$2=//p" | head -n 1; }

# Waits until job $1 is in one of the states $2 (a regex) or $3 seconds pass.
wait_state() {
    local job="$1" states="$2" limit="$3" i state
    for ((i = 0; i < limit * 2; i++)); do
        state="$(job_field "$job" JobState)"
        [[ "$state" =~ ^($states)$ ]] && { echo "$state"; return 0; }
        sleep 0.5
    done
    echo "${state:-unknown}"
    return 1
}

# Waits until file $1 holds a line matching $2, up to $3 seconds.
wait_line() {
    local file="$1" pattern="$2" limit="$3" i
    for ((i = 0; i < limit * 5; i++)); do
        grep -qE "$pattern" "$file" 2>/dev/null && return 0
        sleep 0.2
    done
    return 1
}

# Epoch seconds logged on the first line of $1 that matches $2.
epoch_of() { grep -E "$2" "$1" | head -n 1 | sed -n 's/.*epoch=\([0-9.]*\).*/\1/p'; }

# Sets up job folder $1 with at least $2 stage-1 steps; prints its cluster YAML's path.
prepare() {
    local dir="$tmp/$1" steps="$2"
    mkdir -p "$dir"
    # A commit every 5 steps, so that a suspension finds one and stage 1 is still running.
    "$bin/xfactor-local" --prepare-only --dir "$dir" --port "$port" --listen-host 0.0.0.0 \
        --checkpoint-every 5 \
        --stage1-steps "$steps" --stage2-steps 10 --no-evaluate >"$dir/prepare.log" 2>&1 \
        || { cat "$dir/prepare.log" >&2; fail "xfactor-local --prepare-only failed"; }
    # Reachable on the node's name (what the workers dial), and the token from the
    # environment, which the sbatch script generates when none is given.
    sed -i -e "s/^listen: .*/listen: 0.0.0.0:$port/" \
        -e 's/^  token: .*/  token_env: XFACTOR_TOKEN/' "$dir/cluster.yaml"
    grep -q "^listen: 0.0.0.0:$port" "$dir/cluster.yaml" || fail "$dir/cluster.yaml has no listen: line"
    echo "$dir/cluster.yaml"
}

checkpoint_dir() { sed -n '/^checkpoint:/,/^[^ ]/ s/^  uri: *//p' "$1" | head -n 1; }

# Submits the sbatch script for folder $1 with two worker tasks on the one node; extra sbatch
# options follow. Prints the job id.
submit() {
    local dir="$tmp/$1"
    shift
    env -u XFACTOR_TOKEN -u XFACTOR_COORDINATOR \
        XFACTOR_CONFIG="$dir/cluster.yaml" XFACTOR_REPORT="$dir/report.json" XFACTOR_BIN="$bin" \
        XFACTOR_FAKE_DIR="$(checkpoint_dir "$dir/cluster.yaml")" XFACTOR_STEP_GRACE=5 \
        sbatch --parsable --nodes=1 --ntasks=2 --ntasks-per-node=2 --chdir="$dir" \
        --output="$dir/slurm-%j.out" "$@" "$repo/deploy/slurm/xfactor.sbatch"
}

show_failure() {
    local dir="$tmp/$1"
    say "--- $dir/slurm-*.out"
    tail -n 40 "$dir"/slurm-*.out >&2 || true
    say "--- slurmctld.log"
    tail -n 15 "$tmp/log/slurmctld.log" >&2 || true
}

# The newest committed step in job.json under the checkpoint folder $1.
committed_step() { jq -r '.last_commit.step // 0' "$1/job.json" 2>/dev/null || echo 0; }

# --- case: finish -----------------------------------------------------------------------------
case_finish() {
    local yaml job state out t0
    yaml="$(prepare finish 20)"
    t0=$(date +%s.%N)
    job="$(submit finish --time=10)"
    out="$tmp/finish/slurm-$job.out"
    state="$(wait_state "$job" "COMPLETED|FAILED|CANCELLED|TIMEOUT|NODE_FAIL|OUT_OF_MEMORY" 600)" \
        || { show_failure finish; fail "finish: job $job still $state after 600 s"; }
    [ "$state" = COMPLETED ] || { show_failure finish; fail "finish: job $job ended $state"; }
    [ "$(job_field "$job" ExitCode)" = 0:0 ] || { show_failure finish; fail "finish: exit code $(job_field "$job" ExitCode)"; }
    local outcome world names
    outcome="$(jq -r .outcome "$tmp/finish/report.json" 2>/dev/null || echo none)"
    [ "$outcome" = finished ] || { show_failure finish; fail "finish: report outcome $outcome"; }
    world="$(jq '[.generations[].world_size] | max' "$tmp/finish/report.json")"
    [ "$world" = 2 ] || { show_failure finish; fail "finish: largest group $world, expected both workers"; }
    # Both registered under their Slurm names, having found the coordinator from the node list.
    names=0
    for rank in 0 1; do grep -q "slurm-$job-$rank" "$out" && names=$((names + 1)); done
    [ "$names" = 2 ] || { show_failure finish; fail "finish: worker names slurm-$job-{0,1} not both in the log"; }
    grep -q "restart_count=0" "$out" || fail "finish: no start line"
    echo "case=finish job=$job state=$state outcome=$outcome workers=$world slurm_names=$names seconds=$(elapsed "$t0" "$(date +%s.%N)")"
}

# Checks a requeued job of folder $1 ($2: job id, $3: job.json's step when it suspended):
# the second run started with SLURM_RESTART_COUNT=1 and resumed from that step.
check_resumed() {
    local name="$1" job="$2" suspended="$3" out="$tmp/$1/slurm-$2.out"
    grep -q "coordinator exited status=75" "$out" || { show_failure "$name"; fail "$name: the coordinator did not exit 75"; }
    grep -q "requeue job=$job restart_count=0" "$out" || { show_failure "$name"; fail "$name: the script did not requeue"; }
    grep -q "start job=$job restart_count=1" "$out" || { show_failure "$name"; fail "$name: no run with SLURM_RESTART_COUNT=1"; }
    [ "$(grep -c "start job=$job restart_count=0" "$out")" = 1 ] \
        || fail "$name: the first run's output is missing (--open-mode=append)"
    requeue_delay=$(elapsed "$(epoch_of "$out" "requeue job=$job")" "$(epoch_of "$out" "start job=$job restart_count=1")")
    [ "$suspended" -gt 0 ] || fail "$name: nothing was committed before the suspension"
}

# The first step the final report records for the generation that resumed from the commit at
# $2 (job.json's last_commit.location when the job suspended); 0 when no generation did.
resumed_first_step() {
    local report="$1" location="$2"
    jq --arg base "${location##*/}" '
        [.generations[] | select(.resume_from != "" and (.resume_from | contains($base))) | .generation]
        as $resumed
        | [.steps[] | select(.stage == 1 and (.generation as $g | $resumed | index($g))) | .step]
        | min // 0' "$report"
}

# --- case: suspend ----------------------------------------------------------------------------
case_suspend() {
    local yaml job state out ckpt suspended location t_signal first restarts
    yaml="$(prepare suspend 400)"
    ckpt="$(checkpoint_dir "$yaml")"
    job="$(submit suspend --time=10)"
    out="$tmp/suspend/slurm-$job.out"
    # Suspend once a checkpoint past the first is committed.
    for ((i = 0; ; i++)); do
        [ "$(committed_step "$ckpt")" -ge 10 ] && break
        [ "$i" -lt 1200 ] || { show_failure suspend; fail "suspend: no commit at step 10 within 240 s"; }
        sleep 0.2
    done
    t_signal=$(date +%s.%N)
    scancel --batch --signal=USR1 "$job"
    wait_line "$out" "coordinator exited status=" 120 || { show_failure suspend; fail "suspend: the coordinator did not exit after USR1"; }
    cp "$ckpt/job.json" "$tmp/suspend/job-at-suspension.json"
    suspended="$(committed_step "$ckpt")"
    location="$(jq -r '.last_commit.location' "$tmp/suspend/job-at-suspension.json")"
    local t_exit
    t_exit="$(epoch_of "$out" "coordinator exited status=")"
    wait_line "$out" "start job=$job restart_count=1" 300 || { show_failure suspend; fail "suspend: the job did not start again"; }
    state="$(wait_state "$job" "COMPLETED|FAILED|CANCELLED|TIMEOUT|NODE_FAIL" 600)" \
        || { show_failure suspend; fail "suspend: job $job still $state"; }
    [ "$state" = COMPLETED ] || { show_failure suspend; fail "suspend: the resumed job ended $state"; }
    check_resumed suspend "$job" "$suspended"
    first="$(resumed_first_step "$tmp/suspend/report.json" "$location")"
    # Steps may count from 0 or 1: the resumed generation's first is the committed one or the
    # next, never 0 or 1 as from the start.
    [ "$first" -ge "$suspended" ] || { show_failure suspend; fail "suspend: no generation resumed from $location at step $suspended (first resumed step: $first)"; }
    [ "$(jq -r .outcome "$tmp/suspend/report.json")" = finished ] || fail "suspend: not finished after the resume"
    restarts="$(job_field "$job" Restarts)"
    [ "$restarts" = 1 ] || fail "suspend: Restarts=$restarts"
    echo "case=suspend job=$job state=$state restart_count=$restarts suspended_step=$suspended resumed_first_step=$first usr1_to_exit_s=$(elapsed "$t_signal" "$t_exit") requeue_to_restart_s=$requeue_delay"
}

# --- case: timelimit --------------------------------------------------------------------------
case_timelimit() {
    local yaml job state out ckpt suspended first t_start t_usr1 restarts
    # Long enough never to finish: the resumed run is cancelled.
    yaml="$(prepare timelimit 100000)"
    ckpt="$(checkpoint_dir "$yaml")"
    job="$(submit timelimit --time=3)"
    out="$tmp/timelimit/slurm-$job.out"
    # USR1 is due 90 s after the start (limit 180 s - 90 s). slurmctld checks the limits every
    # 30 s or so and signals early rather than late: at 60 to 90 s. (With --time=2 it would come
    # at once, before anything is committed.)
    wait_line "$out" "USR1: asking the coordinator to suspend" 200 || { show_failure timelimit; fail "timelimit: no USR1 from --signal=B:USR1@90"; }
    t_start="$(epoch_of "$out" "start job=$job restart_count=0")"
    t_usr1="$(epoch_of "$out" "USR1: asking")"
    wait_line "$out" "coordinator exited status=" 80 || { show_failure timelimit; fail "timelimit: the coordinator did not exit"; }
    suspended="$(committed_step "$ckpt")"
    # A longer limit for the second run, while it waits to start, so it is not suspended again.
    if wait_line "$out" "requeue job=$job" 30; then
        scontrol update JobId="$job" TimeLimit=30 2>/dev/null || true
    fi
    wait_line "$out" "start job=$job restart_count=1" 300 || { show_failure timelimit; fail "timelimit: the job did not start again"; }
    check_resumed timelimit "$job" "$suspended"
    # The resumed run must train from the commit: wait for a newer commit, then keep the time
    # limit from suspending it again and cancel it (SIGTERM to every process of the job).
    local now
    for ((i = 0; ; i++)); do
        now="$(committed_step "$ckpt")"
        [ "$now" -ge "$suspended" ] || { show_failure timelimit; fail "timelimit: job.json went back to step $now (from $suspended): the resumed run started over"; }
        [ "$now" -gt "$suspended" ] && break
        [ "$i" -lt 1200 ] || { show_failure timelimit; fail "timelimit: the resumed run committed nothing"; }
        sleep 0.2
    done
    first="$(committed_step "$ckpt")"
    scancel "$job"
    state="$(wait_state "$job" "CANCELLED|COMPLETED|FAILED|TIMEOUT" 60)" || { show_failure timelimit; fail "timelimit: still $state after scancel"; }
    grep -q "TERM: stopping the coordinator" "$out" || { show_failure timelimit; fail "timelimit: the script saw no TERM"; }
    grep -q "coordinator exited status=" <(sed -n '/restart_count=1/,$p' "$out") \
        || { show_failure timelimit; fail "timelimit: the coordinator did not stop on SIGTERM"; }
    sleep 8 # a requeue would show up as PENDING within cred_expire + 1 s
    state="$(job_field "$job" JobState)"
    restarts="$(job_field "$job" Restarts)"
    if [ "$state" != CANCELLED ] || [ "$restarts" != 1 ]; then
        fail "timelimit: after scancel state=$state restarts=$restarts (expected CANCELLED, 1)"
    fi
    [ "$(committed_step "$ckpt")" -ge "$first" ] || fail "timelimit: job.json went back after SIGTERM"
    echo "case=timelimit job=$job state=$state restart_count=$restarts suspended_step=$suspended resumed_commit=$first usr1_after_start_s=$(elapsed "$t_start" "$t_usr1") requeue_to_restart_s=$requeue_delay"
}

# --- case: noworkers --------------------------------------------------------------------------
case_noworkers() {
    local job state out t0
    prepare noworkers 20 >/dev/null
    t0=$(date +%s.%N)
    job="$(submit noworkers --time=10 --export=ALL,XFACTOR_WORKER_ARGS=--no-such-flag)"
    out="$tmp/noworkers/slurm-$job.out"
    state="$(wait_state "$job" "COMPLETED|FAILED|CANCELLED|TIMEOUT" 120)" || { show_failure noworkers; fail "noworkers: job still $state after 120 s"; }
    grep -q "the worker step ended" "$out" || { show_failure noworkers; fail "noworkers: the script did not notice"; }
    [ "$state" != COMPLETED ] || fail "noworkers: a job without workers completed"
    echo "case=noworkers job=$job state=$state seconds=$(elapsed "$t0" "$(date +%s.%N)")"
}

for name in $cases; do
    say "case $name"
    "case_$name"
done
say "all cases passed"
