//! All-reduce time and algorithmic bandwidth (buffer size / time) between two worker processes
//! on loopback, for 1, 16, 64 and 100 MB of float32, on one TCP lane (the default transport)
//! and on the gRPC stream (the peer); then the per-step time of the benchmark
//! model trained by 1 and by 2 worker processes (through the real coordinator), and the share
//! of the 2-worker step spent in the all-reduce.
//!
//! `scripts/bench-allreduce.sh` (builds the binaries it starts, then
//! `cargo bench -p worker --bench allreduce [-- --repeats N --model-steps N]`).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

fn flag(args: &[String], name: &str, default: &str) -> String {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .cloned()
        .unwrap_or_else(|| default.into())
}

/// `key=value` fields of a line.
fn field(line: &str, key: &str) -> Option<f64> {
    line.split_whitespace()
        .find_map(|kv| kv.strip_prefix(key)?.strip_prefix('='))
        .and_then(|v| v.parse::<f64>().ok())
}

/// Figures of the ring on `lanes` lanes (0: the gRPC stream), their keys ending in `label`.
fn all_reduce_figures(worker: &Path, repeats: &str, lanes: usize, label: &str) -> Vec<String> {
    let sizes = "1,16,64,100";
    let peers = format!("127.0.0.1:{},127.0.0.1:{}", free_port(), free_port());
    let spawn = |rank: usize| {
        Command::new(worker)
            .args([
                "allreduce-bench",
                "--rank",
                &rank.to_string(),
                "--peers",
                &peers,
            ])
            .args(["--sizes-mb", sizes, "--repeats", repeats])
            .args(["--lanes", &lanes.to_string()])
            .stdout(Stdio::piped())
            .spawn()
            .expect("start a benchmark rank")
    };
    let ranks: Vec<_> = (0..2).map(spawn).collect();
    let mut outputs = Vec::new();
    for rank in ranks {
        let output = rank.wait_with_output().expect("benchmark rank output");
        assert!(output.status.success(), "a benchmark rank failed");
        outputs.push(String::from_utf8_lossy(&output.stdout).into_owned());
    }
    let mut figures = Vec::new();
    for line in outputs[0].lines() {
        if let (Some(size), Some(seconds)) = (field(line, "size_mb"), field(line, "seconds")) {
            figures.push(format!(
                "time_ms_{size}mb_{label}={:.3} algbw_gbs_{size}mb_{label}={:.3}",
                seconds * 1e3,
                size / 1e3 / seconds
            ));
        }
    }
    figures
}

/// Runs `xfactor-local` with the benchmark model and returns its stage-1 step and all-reduce
/// times.
fn model_step(local: &Path, workers: usize, steps: &str) -> (f64, f64) {
    let dir = tempfile::tempdir().expect("a scratch folder");
    let output = Command::new(local)
        .args(["--dir", &dir.path().display().to_string()])
        .args(["--workers", &workers.to_string()])
        .args(["--preset", "benchmark", "--image-size", "64"])
        .args([
            "--global-batch",
            "8",
            "--micro-batch",
            &(8 / workers).to_string(),
        ])
        .args(["--stage1-steps", steps, "--stage2-steps", "1"])
        .stderr(Stdio::null())
        .output()
        .expect("run xfactor-local");
    let line = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(output.status.success(), "xfactor-local failed: {line}");
    match (
        field(&line, "stage1_step_s"),
        field(&line, "stage1_allreduce_s"),
    ) {
        (Some(step), Some(reduce)) => (step, reduce),
        _ => panic!("no step times in: {line}"),
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let repeats = flag(&args, "--repeats", "5");
    let model_steps = flag(&args, "--model-steps", "6");
    let worker = PathBuf::from(env!("CARGO_BIN_EXE_xfactor-worker"));
    let local = worker.with_file_name("xfactor-local");
    assert!(
        local.exists(),
        "{} is missing: run scripts/bench-allreduce.sh (it builds the coordinator's binaries too)",
        local.display()
    );
    let mut figures = all_reduce_figures(&worker, &repeats, 1, "lane");
    figures.extend(all_reduce_figures(&worker, &repeats, 0, "stream"));
    let (one, _) = model_step(&local, 1, &model_steps);
    let (two, reduce) = model_step(&local, 2, &model_steps);
    println!(
        "bench=allreduce ranks=2 transports=lane,stream link=loopback chunk_mib=1 io_threads=1 repeats={repeats} {} model=benchmark global_batch=8 model_steps={model_steps} step_s_1worker={one:.4} step_s_2workers={two:.4} speedup_2workers={:.2} allreduce_s_2workers={reduce:.4} comm_share_2workers={:.3}",
        figures.join(" "),
        one / two,
        reduce / two
    );
}
