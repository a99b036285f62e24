#!/usr/bin/env python3
"""The soak: a job trained under a random schedule of faults, its invariants checked afterwards.

A coordinator (in the root namespace) and four workers, each in a network namespace of its own
behind a veth on one bridge, train the tiny model through both stages with checkpoints in
moto's S3, while a schedule drawn from `--seed` injects faults of every kind the README's
failure table names:

  worker_kill       SIGKILL a worker, start it again after a pause
  worker_stop       SIGSTOP a worker past the heartbeat timeout, then SIGCONT
  partition         a worker's link down (no coordinator, no ring, no store), then up
  throttle          a worker's link shaped to a trickle (a slow worker), then freed
  store_outage      the checkpoint store frozen (SIGSTOP moto), then thawed
  coordinator_kill  SIGKILL the coordinator, start it again (it waits out its lease)
  diverge           a worker restarted with the divergence drill (its replica drifts from a
                    step a little ahead), then restarted without it
  flood             thousands of strangers' connections on a worker's collective port

Faults overlap in time (never two on one target). The schedule (times, kinds, targets,
durations) is a function of the seed alone, so a rerun with the same seed injects the same
schedule. Once the window ends no new fault starts, every fault in progress is undone, and the
job must finish. The checker then reads the report, the step history in the store and a capture
of worker 0's ring traffic, and fails on any broken invariant:

  finished       the job's outcome is "finished"
  steps          the history holds every step of both stages, no record twice
  commits        each stage's commits are in increasing step order, and each is verified: its
                 step's record holds one checksum per rank of its generation, all equal
  final          each stage's final step has equal checksums on every replica
  exits          no process exited except those the schedule killed (or after the job ended)
  token          the job token never crossed worker 0's collective port (and lanes did)

It prints the seed, the faults by kind, what each cost (seconds from its start until the job
moved past the step it was on, read from the coordinator's /metrics every quarter second) and
the steps redone, as key=value lines.

Run it through scripts/soak.sh (root: namespaces, tc and tcpdump).
"""

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import boto3

WORKERS = 4
# The instance (`--instance`) picks the subnet 10.78.<instance>.0/24 and the interface and
# namespace names, so several soaks can run side by side.
INSTANCE = 0
BRIDGE = "xfsoak0"
HOST_IP = "10.78.0.254"
FLOOD_IPS = ["10.78.0.200", "10.78.0.201"]


def use_instance(instance):
    global INSTANCE, BRIDGE, HOST_IP, FLOOD_IPS
    INSTANCE = instance
    BRIDGE = f"xfsoak{instance}"
    HOST_IP = f"10.78.{instance}.254"
    FLOOD_IPS = [f"10.78.{instance}.200", f"10.78.{instance}.201"]


def veth(index):
    return f"xf{INSTANCE}v{index}"
COLLECTIVE_PORT = 7300
COORDINATOR_PORT = 50551
METRICS_PORT = 50552
MOTO_PORT = 50553
BUCKET = "xfactor"
KINDS = [
    "worker_kill",
    "worker_stop",
    "partition",
    "throttle",
    "store_outage",
    "coordinator_kill",
    "diverge",
    "flood",
]
GLOBAL_KINDS = {"store_outage", "coordinator_kill"}


def worker_ip(index):
    return f"10.78.{INSTANCE}.{index + 1}"


def namespace(index):
    return f"xfs{INSTANCE}n{index}"


def run(*command, check=True):
    return subprocess.run(command, check=check, capture_output=True, text=True)


@dataclass
class Fault:
    start: float
    kind: str
    target: int
    duration: float
    cost_s: float = None
    began_at_progress: int = None
    ended: bool = False
    started: bool = False


def draw_schedule(seed, window_s):
    """Faults at roughly every 27 s of the window, kinds dealt so that every kind comes
    early, targets chosen so that no target has two faults at once, all from `seed`."""
    rng = random.Random(seed)
    count = max(len(KINDS) if window_s >= 150 else 4, int(window_s / 27))
    slot = window_s / count
    deck = []
    faults = []
    busy = {}
    for i in range(count):
        if not deck:
            deck = KINDS[:]
            rng.shuffle(deck)
        kind = deck.pop()
        start = 10.0 + i * slot + rng.uniform(0, slot * 0.5)
        scale = min(1.0, window_s / 1200)
        duration = {
            "worker_kill": rng.uniform(2, 8),
            "worker_stop": rng.uniform(5, 12),
            "partition": rng.uniform(5, max(8, 60 * scale)),
            "throttle": rng.uniform(10, max(12, 40 * scale)),
            "store_outage": rng.uniform(max(10, 30 * scale), max(20, 120 * scale)),
            "coordinator_kill": rng.uniform(1, 5),
            "diverge": rng.uniform(10, 30),
            "flood": rng.uniform(5, 20),
        }[kind]
        targets = ["global"] if kind in GLOBAL_KINDS else list(range(WORKERS))
        rng.shuffle(targets)
        free = [t for t in targets if busy.get(t, 0) <= start]
        target = free[0] if free else targets[0]
        start = max(start, busy.get(target, 0))
        busy[target] = start + duration + 5
        faults.append(Fault(start, kind, -1 if target == "global" else target, duration))
    return sorted(faults, key=lambda f: f.start)


class Network:
    """The bridge and one namespace per worker."""

    def up(self):
        self.down()
        run("ip", "link", "add", BRIDGE, "type", "bridge")
        run("ip", "addr", "add", f"{HOST_IP}/24", "dev", BRIDGE)
        for ip in FLOOD_IPS:
            run("ip", "addr", "add", f"{ip}/24", "dev", BRIDGE)
        run("ip", "link", "set", BRIDGE, "up")
        for i in range(WORKERS):
            ns = namespace(i)
            run("ip", "netns", "add", ns)
            run("ip", "link", "add", veth(i), "type", "veth", "peer", "name", "eth0", "netns", ns)
            run("ip", "link", "set", veth(i), "master", BRIDGE, "up")
            run("ip", "-n", ns, "addr", "add", f"{worker_ip(i)}/24", "dev", "eth0")
            run("ip", "-n", ns, "link", "set", "eth0", "up")
            run("ip", "-n", ns, "link", "set", "lo", "up")

    def down(self):
        for i in range(WORKERS):
            run("ip", "netns", "del", namespace(i), check=False)
        run("ip", "link", "del", BRIDGE, check=False)


@dataclass
class Processes:
    """Every process the soak started, and which exits the schedule caused."""

    dir: Path
    binaries: Path
    token: str
    store_env: dict
    coordinator: subprocess.Popen = None
    moto: subprocess.Popen = None
    workers: list = field(default_factory=lambda: [None] * WORKERS)
    expected_exit: set = field(default_factory=set)
    exits: list = field(default_factory=list)
    starts: int = 0

    def log(self, name):
        return open(self.dir / f"{name}.log", "a")

    def start_moto(self, python):
        self.moto = subprocess.Popen(
            [str(Path(python).parent / "moto_server"), "-H", HOST_IP, "-p", str(MOTO_PORT)],
            stdout=subprocess.DEVNULL, stderr=self.log("moto"))
        for _ in range(600):
            try:
                urllib.request.urlopen(f"http://{HOST_IP}:{MOTO_PORT}/", timeout=1)
                break
            except OSError:
                time.sleep(0.1)
        boto3.client("s3", endpoint_url=f"http://{HOST_IP}:{MOTO_PORT}", **s3_credentials()).create_bucket(Bucket=BUCKET)

    def start_coordinator(self):
        self.coordinator = subprocess.Popen(
            [str(self.binaries / "xfactor-coordinator"), "run", "--config", str(self.dir / "cluster.yaml"),
             "--report", str(self.dir / "report.json"), "--metrics-address", f"{HOST_IP}:{METRICS_PORT}"],
            env={**os.environ, **self.store_env}, stdout=subprocess.DEVNULL, stderr=self.log("coordinator"))

    def start_worker(self, index, extra=()):
        self.starts += 1
        command = ["ip", "netns", "exec", namespace(index), str(self.binaries / "xfactor-worker"),
                   "--coordinator", f"http://{HOST_IP}:{COORDINATOR_PORT}", "--token", self.token,
                   "--name", f"soak-{index}", "--listen", f"{worker_ip(index)}:{COLLECTIVE_PORT}",
                   "--scratch", str(self.dir / f"scratch-{index}"), *extra]
        self.workers[index] = subprocess.Popen(
            command, env={**os.environ, **self.store_env}, stdout=subprocess.DEVNULL,
            stderr=self.log(f"worker-{index}"))

    def kill(self, process):
        self.expected_exit.add(process.pid)
        process.kill()
        process.wait()

    def check_exits(self):
        """Records every process that exited without the schedule killing it."""
        named = [("coordinator", self.coordinator)] + [(f"worker-{i}", w) for i, w in enumerate(self.workers)]
        for name, process in named:
            if process is None or process.poll() is None or process.pid in self.expected_exit:
                continue
            self.expected_exit.add(process.pid)
            self.exits.append((name, process.pid, process.returncode))

    def unexpected(self, finished):
        """The exits the schedule did not cause: any but a clean exit once the job finished
        (workers leave with 0 when told the job is over, the coordinator when it is)."""
        return [f"{name} pid {pid} exited {code}" for name, pid, code in self.exits
                if code != 0 or not finished]

    def stop_all(self):
        for process in [self.coordinator, self.moto, *self.workers]:
            if process is not None and process.poll() is None:
                process.kill()
                process.wait()


def s3_credentials():
    return {"aws_access_key_id": "testing", "aws_secret_access_key": "testing", "region_name": "us-east-1"}


def progress():
    """The coordinator's (stage, step) as one number, or None while it does not answer."""
    try:
        text = urllib.request.urlopen(f"http://{HOST_IP}:{METRICS_PORT}/metrics", timeout=1).read().decode()
    except OSError:
        return None
    values = dict(re.findall(r"^(xfactor_stage|xfactor_step) ([0-9.e+]+)$", text, re.M))
    if "xfactor_stage" not in values or "xfactor_step" not in values:
        return None
    return int(float(values["xfactor_stage"])) * 1_000_000 + int(float(values["xfactor_step"]))


class Injector:
    """Starts and undoes each kind of fault."""

    def __init__(self, processes, flood_script, log):
        self.p = processes
        self.flood_script = flood_script
        self.floods = {}
        self.log = log

    def begin(self, fault, now_progress):
        kind, i = fault.kind, fault.target
        if kind == "worker_kill":
            self.p.kill(self.p.workers[i])
        elif kind == "worker_stop":
            os.kill(self.p.workers[i].pid, signal.SIGSTOP)
        elif kind == "partition":
            run("ip", "-n", namespace(i), "link", "set", "eth0", "down")
        elif kind == "throttle":
            run("tc", "-n", namespace(i), "qdisc", "replace", "dev", "eth0", "root", "tbf",
                "rate", "1mbit", "burst", "32kbit", "latency", "400ms")
        elif kind == "store_outage":
            os.kill(self.p.moto.pid, signal.SIGSTOP)
        elif kind == "coordinator_kill":
            self.p.kill(self.p.coordinator)
        elif kind == "diverge":
            self.p.kill(self.p.workers[i])
            step = (now_progress or 0) % 1_000_000
            self.p.start_worker(i, ["--drill-diverge-from-step", str(step + 3)])
        elif kind == "flood":
            self.floods[i] = subprocess.Popen(
                [sys.executable, self.flood_script, f"{worker_ip(i)}:{COLLECTIVE_PORT}",
                 f"{fault.duration:.1f}", "300", *FLOOD_IPS],
                stdout=self.log, stderr=subprocess.STDOUT)

    def end(self, fault):
        kind, i = fault.kind, fault.target
        if kind == "worker_kill":
            self.p.start_worker(i)
        elif kind == "worker_stop":
            os.kill(self.p.workers[i].pid, signal.SIGCONT)
        elif kind == "partition":
            run("ip", "-n", namespace(i), "link", "set", "eth0", "up")
        elif kind == "throttle":
            run("tc", "-n", namespace(i), "qdisc", "del", "dev", "eth0", "root", check=False)
        elif kind == "store_outage":
            os.kill(self.p.moto.pid, signal.SIGCONT)
        elif kind == "coordinator_kill":
            self.p.start_coordinator()
        elif kind == "diverge":
            self.p.kill(self.p.workers[i])
            self.p.start_worker(i)
        elif kind == "flood":
            flood = self.floods.pop(i)
            flood.wait()


def run_schedule(processes, injector, faults, window_s, finish_limit_s):
    """Injects `faults` over the window, then waits for the job to finish."""
    started = time.monotonic()
    best = None
    history = []
    while True:
        now = time.monotonic() - started
        current = progress()
        if current is not None:
            best = current if best is None else max(best, current)
            history.append((now, best))
        for fault in faults:
            if not fault.started and fault.start <= now and now < window_s and processes.coordinator.poll() is None:
                fault.started, fault.began_at_progress = True, best
                injector.begin(fault, best)
                print(f"fault start t={now:.1f} kind={fault.kind} target={fault.target} duration_s={fault.duration:.1f}", flush=True)
            if fault.started and not fault.ended and (now >= fault.start + fault.duration or now >= window_s):
                fault.ended = True
                injector.end(fault)
        for fault in faults:
            moved = best is not None and best > (fault.began_at_progress or -1)
            if fault.started and fault.cost_s is None and moved:
                fault.cost_s = max(0.0, now - fault.start)
        over = processes.coordinator.poll() == 0 and processes.coordinator.pid not in processes.expected_exit
        processes.check_exits()
        if over and all(f.ended or not f.started for f in faults):
            return now
        if now > window_s + finish_limit_s:
            raise SystemExit(f"soak: the job did not finish within {finish_limit_s:.0f} s after the window")
        time.sleep(0.25)


def read_history(endpoint):
    s3 = boto3.client("s3", endpoint_url=endpoint, **s3_credentials())
    records = []
    listed = s3.list_objects_v2(Bucket=BUCKET, Prefix="soak/checkpoints/history/")
    for item in sorted(listed.get("Contents", []), key=lambda o: o["Key"]):
        body = s3.get_object(Bucket=BUCKET, Key=item["Key"])["Body"].read().decode()
        records.extend(json.loads(line) for line in body.splitlines() if line.strip())
    return records


def verified(record):
    checksums = list(record["checksums"].values())
    return len(checksums) == record["world_size"] and len(set(checksums)) == 1


def check(report, records, steps_by_stage, capture, token, unexpected):
    """Every broken invariant, as one line each."""
    broken = []
    if report.get("outcome") != "finished":
        broken.append(f"finished: outcome {report.get('outcome')!r}")
    keys = [(r["stage"], r["step"], r["generation"]) for r in records]
    if len(keys) != len(set(keys)):
        broken.append(f"steps: {len(keys) - len(set(keys))} records written twice")
    by_key = dict(zip(keys, records))
    for stage, steps in steps_by_stage.items():
        seen = {r["step"] for r in records if r["stage"] == stage}
        missing = sorted(set(range(steps)) - seen)
        if missing:
            broken.append(f"steps: stage {stage} misses {len(missing)} steps, first {missing[:5]}")
        commits = [c for c in report.get("commits", []) if c["stage"] == stage]
        if any(b["step"] <= a["step"] for a, b in zip(commits, commits[1:])):
            broken.append(f"commits: stage {stage} out of order {[c['step'] for c in commits]}")
        for commit in commits:
            generation = int(commit["location"].rsplit("-g", 1)[1])
            record = by_key.get((stage, commit["step"] - 1, generation))
            if record is None or not verified(record):
                broken.append(f"commits: stage {stage} step {commit['step']} not verified: {record}")
        final = [r for r in records if r["stage"] == stage and r["step"] == steps - 1]
        if not any(verified(r) for r in final):
            broken.append(f"final: stage {stage}'s last step has no full set of equal checksums: {final}")
    broken.extend(f"exits: {line}" for line in unexpected)
    traffic = capture.read_bytes() if capture.exists() else b""
    if token.encode() in traffic:
        broken.append("token: the job token crossed worker 0's collective port")
    if b"XFLANE01" not in traffic:
        broken.append("token: the capture saw no lane opening, so it proves nothing")
    return broken


def stop_on_signal(number, _frame):
    """SIGTERM or SIGINT (ignored by background jobs otherwise) end the soak through its
    clean-up: processes killed, namespaces and the bridge removed."""
    raise SystemExit(f"soak: stopped by signal {number}")


def main():
    signal.signal(signal.SIGTERM, stop_on_signal)
    signal.signal(signal.SIGINT, stop_on_signal)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--minutes", type=float, default=20)
    parser.add_argument("--stage1-steps", type=int, default=0)
    parser.add_argument("--stage2-steps", type=int, default=0)
    parser.add_argument("--dir", type=Path)
    parser.add_argument("--binaries", type=Path)
    parser.add_argument("--plan-only", action="store_true", help="print the schedule and stop")
    parser.add_argument("--instance", type=int, default=0, help="0-9: runs beside other instances")
    args = parser.parse_args()
    use_instance(args.instance)
    window_s = args.minutes * 60
    faults = draw_schedule(args.seed, window_s)
    print(f"soak=config seed={args.seed} window_s={window_s:.0f} faults_planned={len(faults)} "
          f"workers={WORKERS} stage1_steps={args.stage1_steps} stage2_steps={args.stage2_steps}", flush=True)
    for fault in faults:
        print(f"planned t={fault.start:.1f} kind={fault.kind} target={fault.target} duration_s={fault.duration:.1f}")
    if args.plan_only:
        return
    args.dir.mkdir(parents=True, exist_ok=True)
    run(str(args.binaries / "xfactor-local"), "--dir", str(args.dir), "--prepare-only", "--workers", str(WORKERS),
        "--listen-host", HOST_IP, "--port", str(COORDINATOR_PORT), "--stage1-steps", str(args.stage1_steps),
        "--stage2-steps", str(args.stage2_steps), "--checkpoint-every", "20", "--no-evaluate")
    config = args.dir / "cluster.yaml"
    yaml = config.read_text()
    token = re.search(r"^  token: (\S+)$", yaml, re.M).group(1)
    yaml = re.sub(r"^checkpoint:\n  uri: \S+", f"checkpoint:\n  uri: s3://{BUCKET}/soak/checkpoints", yaml, flags=re.M)
    yaml = yaml.replace("stall_timeout_s: 60", "stall_timeout_s: 10")
    config.write_text(yaml)
    endpoint = f"http://{HOST_IP}:{MOTO_PORT}"
    store_env = {"AWS_ENDPOINT": endpoint, "AWS_ALLOW_HTTP": "true", "AWS_ACCESS_KEY_ID": "testing",
                 "AWS_SECRET_ACCESS_KEY": "testing", "AWS_REGION": "us-east-1"}
    network = Network()
    processes = Processes(args.dir, args.binaries, token, store_env)
    capture = args.dir / "worker-0-collective.pcap"
    tcpdump = None
    try:
        network.up()
        processes.start_moto(sys.executable)
        processes.start_coordinator()
        tcpdump = subprocess.Popen(["tcpdump", "-i", veth(0), "-U", "-s", "0", "-w", str(capture),
                                    f"tcp port {COLLECTIVE_PORT}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for i in range(WORKERS):
            processes.start_worker(i)
        with open(args.dir / "flood.log", "a") as flood_log:
            injector = Injector(processes, str(Path(__file__).parent.parent / "worker/tests/flood.py"), flood_log)
            seconds = run_schedule(processes, injector, faults, window_s, finish_limit_s=max(600, window_s))
        time.sleep(2)
        processes.check_exits()
        records = read_history(endpoint)
    finally:
        # Each step on its own, so that the namespaces go whatever failed before them.
        for clean_up in (lambda: tcpdump is not None and (tcpdump.terminate(), tcpdump.wait()),
                         processes.stop_all, network.down):
            try:
                clean_up()
            except (OSError, subprocess.SubprocessError, SystemExit) as error:
                print(f"soak: clean-up step failed: {error}", file=sys.stderr)
    report = json.loads((args.dir / "report.json").read_text())
    finished = report.get("outcome") == "finished"
    broken = check(report, records, {1: args.stage1_steps, 2: args.stage2_steps}, capture, token,
                   processes.unexpected(finished))
    injected = [f for f in faults if f.started]
    kinds = {kind: sum(1 for f in injected if f.kind == kind) for kind in KINDS}
    for fault in injected:
        cost = "unmeasured" if fault.cost_s is None else f"{fault.cost_s:.1f}"
        print(f"soak=fault kind={fault.kind} target={fault.target} t={fault.start:.1f} duration_s={fault.duration:.1f} cost_s={cost}")
    redone = len(records) - len({(r["stage"], r["step"]) for r in records})
    # The report holds only the last coordinator's counts; its log spans every restart.
    log = (args.dir / "coordinator.log").read_text(errors="replace")
    mismatches = log.count("checksums differ across ranks")
    rollbacks = log.count("abandoning generation") + log.count("the group rolls back")
    print(f"soak=result seed={args.seed} seconds={seconds:.0f} faults={len(injected)} kinds={sum(1 for v in kinds.values() if v)} "
          + " ".join(f"{k}={v}" for k, v in kinds.items())
          + f" steps_redone={redone} generations_ended={rollbacks} mismatches={mismatches} "
          f"commits={len(report.get('commits', []))} worker_starts={processes.starts} broken={len(broken)}")
    for line in broken:
        print(f"soak=broken {line}")
    sys.exit(1 if broken else 0)


if __name__ == "__main__":
    main()
