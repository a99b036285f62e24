//! All-reduce time and algorithmic bandwidth (buffer size / time) between two worker processes
//! on loopback, for 1, 16, 64 and 100 MB of float32.
//!
//! `cargo bench -p worker --bench allreduce [-- --repeats N]`

use std::process::{Command, Stdio};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let repeats = args
        .iter()
        .position(|a| a == "--repeats")
        .and_then(|i| args.get(i + 1))
        .cloned()
        .unwrap_or_else(|| "5".into());
    let sizes = "1,16,64,100";
    let peers = format!("127.0.0.1:{},127.0.0.1:{}", free_port(), free_port());
    let binary = env!("CARGO_BIN_EXE_xfactor-worker");
    let spawn = |rank: usize| {
        Command::new(binary)
            .args([
                "allreduce-bench",
                "--rank",
                &rank.to_string(),
                "--peers",
                &peers,
            ])
            .args(["--sizes-mb", sizes, "--repeats", &repeats])
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
        let field = |key: &str| {
            line.split_whitespace()
                .find_map(|kv| kv.strip_prefix(key))
                .and_then(|v| v.parse::<f64>().ok())
        };
        if let (Some(size), Some(seconds)) = (field("size_mb="), field("seconds=")) {
            figures.push(format!(
                "time_ms_{size}mb={:.3} algbw_gbs_{size}mb={:.3}",
                seconds * 1e3,
                size / 1e3 / seconds
            ));
        }
    }
    println!(
        "bench=allreduce ranks=2 transport=grpc-loopback chunk_mib=1 repeats={repeats} {}",
        figures.join(" ")
    );
}
