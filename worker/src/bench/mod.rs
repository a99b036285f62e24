//! The benchmarks' ranks: `allreduce-bench` joins a fixed ring and times all-reduces of
//! several sizes (`benches/allreduce.rs` starts the processes and prints the figures);
//! `path-bench` ([`path`]) steps the whole data path on a model's layout with the compute
//! replaced by a wait (`scripts/bench-scaling.sh` starts the ranks).

use std::time::Duration;

use tokio_util::sync::CancellationToken;

use crate::collective::{CollectiveService, Link, PeerTls, Ring, RingKeys, spawn_server};

pub mod path;

/// Token of the benchmark's private ring.
const BENCH_TOKEN: &str = "allreduce-bench";

/// Where a benchmark rank stands in its ring, and its runtime.
#[derive(Debug, Clone, clap::Args)]
pub struct RankArgs {
    /// This process's rank: its index in --peers
    #[arg(long, value_name = "R")]
    pub rank: usize,
    /// Every rank's HOST:PORT, comma-separated, in rank order
    #[arg(long, value_name = "A,B,...", value_delimiter = ',', required = true)]
    pub peers: Vec<String>,
    /// I/O threads of the runtime (1, as the worker daemon uses)
    #[arg(
        long,
        value_name = "N",
        default_value_t = 1,
        value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..)
    )]
    pub threads: usize,
    /// TCP lanes of the ring, each on a thread of its own (0: the gRPC stream)
    #[arg(
        long,
        value_name = "N",
        default_value_t = 1,
        value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=crate::collective::MAX_LANES as u64)
    )]
    pub lanes: usize,
    /// Runs the ring over TLS (on TLS lanes, or the gRPC stream with `--lanes 0`, as a job
    /// with `tls:` does) with the certificate `server.pem`, its key `server.key` and the CA
    /// `ca.pem` in this folder, valid for `localhost`
    #[arg(long, value_name = "DIR")]
    pub tls_dir: Option<std::path::PathBuf>,
}

impl RankArgs {
    /// The runtime of `--threads` I/O threads, after checking the rank is among the peers.
    fn runtime(&self) -> anyhow::Result<tokio::runtime::Runtime> {
        if self.rank >= self.peers.len() {
            anyhow::bail!(
                "--rank {} is not below the {} peers given",
                self.rank,
                self.peers.len()
            );
        }
        Ok(tokio::runtime::Builder::new_multi_thread()
            .worker_threads(self.threads)
            .enable_all()
            .build()?)
    }

    /// The ring's TLS from `--tls-dir`, if given.
    fn peer_tls(&self) -> anyhow::Result<Option<PeerTls>> {
        let Some(dir) = &self.tls_dir else {
            return Ok(None);
        };
        Ok(Some(PeerTls::from_files(
            &dir.join("server.pem"),
            &dir.join("server.key"),
            &dir.join("ca.pem"),
            Some("localhost".into()),
        )?))
    }

    /// Serves this rank's Collective service and joins the benchmark's ring (generation 1);
    /// every rank derives the same keys, where a job's come from the coordinator.
    async fn join(&self) -> anyhow::Result<Ring> {
        let (rank, peers) = (self.rank, &self.peers);
        let service = CollectiveService::default();
        let mailbox = service.mailbox();
        let listener = tokio::net::TcpListener::bind(&peers[rank]).await?;
        let link = Link {
            token: BENCH_TOKEN.into(),
            timeout: Duration::from_secs(60),
            tls: self.peer_tls()?,
            lanes: self.lanes,
        };
        spawn_server(listener, service, &link)?;
        let left = (rank + peers.len() - 1) % peers.len();
        let keys = RingKeys {
            own: format!("bench-rank-{rank}"),
            left: format!("bench-rank-{left}"),
        };
        let cancelled = CancellationToken::new();
        Ok(Ring::connect(&mailbox, rank, peers, 1, &keys, &link, cancelled).await?)
    }
}

/// The flags of `xfactor-worker allreduce-bench`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    /// Its place in the ring
    #[command(flatten)]
    pub ring: RankArgs,
    /// All-reduce sizes in MB, comma-separated
    #[arg(
        long,
        value_name = "MB,...",
        value_delimiter = ',',
        default_value = "1,16,64,100"
    )]
    pub sizes_mb: Vec<f64>,
    /// Timed runs per size, at least (small sizes run more)
    #[arg(long, value_name = "N", default_value_t = 5)]
    pub repeats: usize,
    /// Values per collective chunk (by default the ring's)
    #[arg(long, value_name = "N")]
    pub chunk_values: Option<usize>,
}

/// Runs rank `--rank` of the ring `--peers`; rank 0 prints `size_mb=.. seconds=..` per size:
/// the median of at least `--repeats` runs (more for small sizes) after one warm-up, on a
/// runtime of `--threads` I/O threads.
pub fn run_rank(args: &BenchArgs) -> anyhow::Result<()> {
    let BenchArgs {
        ring: place,
        sizes_mb: sizes,
        repeats,
        chunk_values,
    } = args.clone();
    if let Some(size) = sizes
        .iter()
        .find(|size| !(**size > 0.0 && size.is_finite()))
    {
        anyhow::bail!("--sizes-mb {size}: sizes must be above 0");
    }
    let runtime = place.runtime()?;
    let rank = place.rank;
    let task = runtime.spawn(async move {
        let mut ring = place.join().await?;
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
                ring.all_reduce(&mut [0.0], 0).await?;
                let stats = ring.all_reduce(&mut buffer, 0).await?;
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
