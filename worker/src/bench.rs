//! One rank of the all-reduce benchmark: joins a fixed ring on loopback and times all-reduces
//! of several sizes. `benches/allreduce.rs` starts the processes and prints the figures.

use std::time::Duration;

use anyhow::Context;
use telemetry::cli::Flags;
use tokio::sync::watch;

use crate::collective::{CollectiveService, Link, Ring, spawn_server};

/// Token of the benchmark's private ring.
const BENCH_TOKEN: &str = "allreduce-bench";

/// Runs rank `--rank` of the ring `--peers`; rank 0 prints `size_mb=.. seconds=..` per size:
/// the median of at least `--repeats` runs (more for small sizes) after one warm-up, on a
/// runtime of `--threads` I/O threads (1, as the worker daemon uses).
pub fn run_rank(flags: &Flags) -> anyhow::Result<()> {
    let rank: usize = flags.require("rank").map_err(anyhow::Error::msg)?.parse()?;
    let peers: Vec<String> = flags
        .require("peers")
        .map_err(anyhow::Error::msg)?
        .split(',')
        .map(str::to_string)
        .collect();
    let sizes: Vec<f64> = flags
        .get("sizes-mb")
        .unwrap_or("1,16,64,100")
        .split(',')
        .map(|s| s.parse::<f64>().with_context(|| format!("size `{s}`")))
        .collect::<Result<_, _>>()?;
    let repeats: usize = flags.get("repeats").unwrap_or("5").parse()?;
    let chunk_values: Option<usize> = flags.get("chunk-values").map(str::parse).transpose()?;
    let threads: usize = flags.get("threads").unwrap_or("1").parse()?;
    if threads == 0 {
        anyhow::bail!("--threads must be at least 1");
    }
    if rank >= peers.len() {
        anyhow::bail!("--rank {rank} is not below the {} peers given", peers.len());
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads)
        .enable_all()
        .build()?;
    let peers_owned = peers.clone();
    let task = runtime.spawn(async move {
        let peers = peers_owned;
        let service = CollectiveService::default();
        let mailbox = service.mailbox();
        let listener = tokio::net::TcpListener::bind(&peers[rank]).await?;
        let link = Link {
            token: BENCH_TOKEN.into(),
            timeout: Duration::from_secs(60),
            tls: None,
        };
        spawn_server(listener, service, &link)?;
        let (_cancel, cancelled) = watch::channel(false);
        let mut ring = Ring::connect(&mailbox, rank, &peers, 1, &link, cancelled).await?;
        if let Some(values) = chunk_values {
            ring.set_chunk_values(values);
        }
        for size in sizes {
            let values = ((size * 1e6) / 4.0) as usize;
            let mut buffer: Vec<f32> = (0..values)
                .map(|i| (i % 1000) as f32 + rank as f32)
                .collect();
            // Small sizes are latency-bound and noisy: time at least 64 MB's worth of them.
            let runs = repeats.max((64.0 / size).ceil() as usize).min(500);
            let mut times = Vec::new();
            for run in 0..=runs {
                // A one-value all-reduce lines the ranks up first (the peer benchmark calls
                // MPI_Barrier), so a run is not charged for the other rank's lag.
                ring.all_reduce(&mut [0.0]).await?;
                let stats = ring.all_reduce(&mut buffer).await?;
                if run > 0 {
                    times.push(stats.seconds);
                }
            }
            times.sort_by(f64::total_cmp);
            let median = times[times.len() / 2];
            if rank == 0 {
                println!("size_mb={size} seconds={median:.6} runs={runs}");
            }
        }
        anyhow::Ok(())
    });
    runtime.block_on(task)??;
    // Let the peer finish reading before the streams close.
    std::thread::sleep(Duration::from_millis(300));
    Ok(())
}
