//! The coordinator's cost per step report at paper length: the real `xfactor-coordinator`
//! process, driven over gRPC by simulated workers (register, await the assignment, report every
//! step with a checksum, rank 0 commits every `--commit-every` steps). The coordinator's CPU
//! time (from `/proc/PID/stat`) and resident memory (`VmRSS`) are sampled `--samples` times
//! over the run; the line it prints compares the first window with the last, so a cost that
//! grows with the steps shows.
//!
//!     cargo bench -p coordinator --bench bookkeeping [-- --workers 2,64 --steps 100000]

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use proto::v1::assignment::Work;
use proto::v1::coordinator_client::CoordinatorClient;
use proto::v1::{
    AwaitAssignmentRequest, CheckpointCommit, LossTerms, Phase, RegisterRequest, StepReport,
};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

type Client = CoordinatorClient<InterceptedService<Channel, proto::AttachToken>>;

const TOKEN: &str = "bookkeeping-bench";

/// One simulated worker: its client, id, session, rank and generation.
struct Simulated {
    client: Client,
    id: u64,
    session: String,
    rank: u32,
    generation: u64,
}

/// The coordinator's CPU seconds (user + system) and resident megabytes.
fn usage(pid: u32) -> anyhow::Result<(f64, f64)> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // Fields after the command name (which may hold spaces) start at field 3.
    let after = stat.rsplit_once(')').map_or("", |(_, rest)| rest);
    let fields: Vec<&str> = after.split_whitespace().collect();
    // utime and stime, fields 14 and 15 of the whole line.
    let ticks: f64 = match fields.get(11..13) {
        Some([user, system]) => user.parse::<f64>()? + system.parse::<f64>()?,
        _ => bail!("/proc/{pid}/stat has no CPU times"),
    };
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let rss_kb: f64 = status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .context("no VmRSS")?
        .parse()?;
    // Linux reports CPU time in USER_HZ ticks, 100 per second on every mainstream build.
    Ok((ticks / 100.0, rss_kb / 1024.0))
}

/// The bench job: generated data, a stage 1 of `steps` over a group of `workers`, and liveness
/// limits no simulated worker can cross.
fn yaml(port: u16, workers: usize, steps: u64, commit_every: u64, checkpoints: &Path) -> String {
    format!(
        "job: bookkeeping-bench
listen: 127.0.0.1:{port}
auth: {{token: {TOKEN}}}
model: {{preset: tiny}}
data:
  generated: {{scenes: 1, trajectories: 1, frames: 6}}
stage1: {{steps: {steps}, global_batch: {workers}, micro_batch: 1, lpips_weight: 0}}
stage2: {{steps: 1, global_batch: {workers}, micro_batch: 1, lpips_weight: 0}}
checkpoint: {{uri: {}, every: {commit_every}}}
workers:
  expected: {workers}
  minimum: {workers}
  heartbeat_timeout_s: 86400
  stall_timeout_s: 86400
",
        checkpoints.display()
    )
}

/// A client of the coordinator on `port`, retrying for 30 s while it starts.
async fn connect(port: u16) -> anyhow::Result<Client> {
    let endpoint = tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{port}"))?;
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match endpoint.connect().await {
            Ok(channel) => {
                return Ok(CoordinatorClient::with_interceptor(
                    channel,
                    proto::AttachToken::new(TOKEN)?,
                ));
            }
            Err(e) if Instant::now() > deadline => bail!("coordinator unreachable: {e}"),
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

/// Registers `workers` simulated workers and waits for the group to form.
async fn form_group(port: u16, workers: usize) -> anyhow::Result<Vec<Simulated>> {
    let mut registered = Vec::new();
    for index in 0..workers {
        let mut client = connect(port).await?;
        let reply = client
            .register(RegisterRequest {
                protocol_version: proto::PROTOCOL_VERSION,
                model_config_version: settings::XFactorConfig::SCHEMA_VERSION,
                worker_name: format!("sim-{index}"),
                collective_address: format!("127.0.0.1:{}", 20000 + index),
                ..RegisterRequest::default()
            })
            .await?
            .into_inner();
        registered.push((client, reply.worker_id, reply.session));
    }
    let waits = registered
        .into_iter()
        .map(|(mut client, id, session)| async move {
            let assignment = client
                .await_assignment(AwaitAssignmentRequest {
                    worker_id: id,
                    after_generation: 0,
                    session: session.clone(),
                    failure: None,
                })
                .await?
                .into_inner();
            let Some(Work::Train(train)) = assignment.work else {
                bail!("expected a training assignment");
            };
            Ok(Simulated {
                client,
                id,
                session,
                rank: train.rank,
                generation: assignment.generation,
            })
        });
    let mut group = futures::future::try_join_all(waits).await?;
    group.sort_by_key(|w| w.rank);
    Ok(group)
}

/// A committed checkpoint of no files, which the coordinator verifies like any other.
fn empty_commit(dir: &Path, step: u64) -> anyhow::Result<String> {
    let location = dir.join(format!("step-{step:08}"));
    std::fs::create_dir_all(&location)?;
    std::fs::write(
        location.join(settings::commit::MANIFEST_NAME),
        format!("{{\"stage\": 1, \"step\": {step}, \"files\": []}}"),
    )?;
    Ok(location.display().to_string())
}

/// What the command line asks the bench to run.
struct Options {
    workers: Vec<usize>,
    steps: u64,
    samples: u64,
    commit_every: u64,
}

/// Reads the command line over the defaults (a 2- and a 64-worker group, the paper's 100k
/// steps, 10 windows, a commit every 2000 steps).
fn options() -> anyhow::Result<Options> {
    let mut options = Options {
        workers: vec![2, 64],
        steps: 100_000,
        samples: 10,
        commit_every: 2000,
    };
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        let mut value = || args.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--workers" => {
                options.workers = value()?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()?
            }
            "--steps" => options.steps = value()?.parse()?,
            "--samples" => options.samples = value()?.parse()?,
            "--commit-every" => options.commit_every = value()?.parse()?,
            // `cargo bench` passes `--bench`.
            "--bench" => {}
            other => bail!("unknown flag {other} (--workers, --steps, --samples, --commit-every)"),
        }
    }
    if options.steps < options.samples || options.samples < 2 {
        bail!("--steps must be at least --samples, and --samples at least 2");
    }
    Ok(options)
}

/// The coordinator's usage at one point of the run.
struct Sample {
    /// Steps every worker has reported.
    step: u64,
    /// CPU seconds (user + system) so far.
    cpu_s: f64,
    /// Resident megabytes.
    rss_mb: f64,
    /// When it was taken.
    at: Instant,
}

impl Sample {
    /// The coordinator `pid`'s usage now, after `step` steps.
    fn take(pid: u32, step: u64) -> anyhow::Result<Self> {
        let (cpu_s, rss_mb) = usage(pid)?;
        Ok(Self {
            step,
            cpu_s,
            rss_mb,
            at: Instant::now(),
        })
    }
}

/// Runs one coordinator for a group of `workers` through `options.steps` steps; returns the
/// line that compares its cost per report across the run.
fn run(workers: usize, options: &Options) -> anyhow::Result<String> {
    let scratch = tempfile::tempdir()?;
    let port = coordinator::local::free_port()?;
    let mut coordinator = start_coordinator(scratch.path(), port, workers, options)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let commits = scratch.path().join("commits");
    let driven = runtime.block_on(drive(port, coordinator.id(), workers, options, &commits));
    let _ = coordinator.kill();
    let _ = coordinator.wait();
    Ok(summary(workers, options, &driven?))
}

/// Writes the bench job's YAML under `scratch` and starts `xfactor-coordinator` on it, quiet
/// so its logging costs nothing the bench would measure.
fn start_coordinator(
    scratch: &Path,
    port: u16,
    workers: usize,
    options: &Options,
) -> anyhow::Result<Child> {
    let config = scratch.join("cluster.yaml");
    let checkpoints = scratch.join("checkpoints");
    std::fs::write(
        &config,
        yaml(
            port,
            workers,
            options.steps,
            options.commit_every,
            &checkpoints,
        ),
    )?;
    let child = Command::new(env!("CARGO_BIN_EXE_xfactor-coordinator"))
        .args(["run", "--config"])
        .arg(&config)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()?;
    Ok(child)
}

/// Forms the group and reports every step from every worker, rank 0 committing every
/// `options.commit_every` steps; samples the coordinator `pid`'s usage at the start and after
/// each of `options.samples` equal windows.
async fn drive(
    port: u16,
    pid: u32,
    workers: usize,
    options: &Options,
    commits: &Path,
) -> anyhow::Result<Vec<Sample>> {
    let mut group = form_group(port, workers).await?;
    let window = options.steps / options.samples;
    let mut samples = vec![Sample::take(pid, 0)?];
    for step in 0..options.steps {
        report_step(&mut group, step).await?;
        let done = step + 1;
        if done % options.commit_every == 0 && done < options.steps {
            commit(&mut group[0], commits, done).await?;
        }
        if done % window == 0 {
            samples.push(Sample::take(pid, done)?);
        }
    }
    Ok(samples)
}

/// Every worker reports `step` at once, as a training group does; fails when the coordinator
/// says the generation ended.
async fn report_step(group: &mut [Simulated], step: u64) -> anyhow::Result<()> {
    let reports = group.iter_mut().map(|worker| {
        let report = StepReport {
            worker_id: worker.id,
            session: worker.session.clone(),
            generation: worker.generation,
            phase: Phase::Stage1 as i32,
            step,
            loss: Some(LossTerms {
                total: 1.0 / (1.0 + step as f32),
                learning_rate: 4e-4,
                grad_norm: 0.5,
                applied: true,
                l1: 1.0 / (1.0 + step as f32),
                lpips: f32::NAN,
            }),
            parameter_checksum: 0xC0FFEE,
            checksum_computed: true,
            samples_per_s: 100.0,
            step_s: 0.5,
            allreduce_s: 0.1,
            ..StepReport::default()
        };
        worker.client.report_step(report)
    });
    for ack in futures::future::join_all(reports).await {
        anyhow::ensure!(
            ack?.into_inner().generation_current,
            "generation ended at step {step}"
        );
    }
    Ok(())
}

/// Rank 0 commits an empty checkpoint after `done` steps; fails when the coordinator refuses.
async fn commit(rank0: &mut Simulated, commits: &Path, done: u64) -> anyhow::Result<()> {
    let location = empty_commit(commits, done)?;
    let ack = rank0
        .client
        .commit_checkpoint(CheckpointCommit {
            worker_id: rank0.id,
            session: rank0.session.clone(),
            generation: rank0.generation,
            phase: Phase::Stage1 as i32,
            step: done,
            location,
        })
        .await?
        .into_inner();
    anyhow::ensure!(ack.accepted, "commit refused: {}", ack.reason);
    Ok(())
}

/// The bench's line: CPU microseconds per step report in the first, the last and every window
/// and over the whole run, resident memory per window, and the steps per second.
fn summary(workers: usize, options: &Options, samples: &[Sample]) -> String {
    let per_report = |i: usize| {
        let (before, after) = (&samples[i - 1], &samples[i]);
        1e6 * (after.cpu_s - before.cpu_s) / ((after.step - before.step) as f64 * workers as f64)
    };
    let last = samples.len() - 1;
    let rss: Vec<f64> = samples.iter().map(|sample| sample.rss_mb).collect();
    let windows: Vec<String> = (1..=last)
        .map(|i| format!("{:.0}", per_report(i)))
        .collect();
    let rss_windows: Vec<String> = rss[1..].iter().map(|mb| format!("{mb:.1}")).collect();
    let wall = samples[last].at.duration_since(samples[0].at).as_secs_f64();
    let cpu = samples[last].cpu_s - samples[0].cpu_s;
    format!(
        "workers={workers} steps={} reports={} commit_every={} samples={} cpu_us_per_report_first={:.1} cpu_us_per_report_last={:.1} cpu_us_per_report_all={:.1} rss_mb_first={:.1} rss_mb_last={:.1} rss_mb_max={:.1} cpu_us_per_report_by_window={} rss_mb_by_window={} steps_per_s={:.0} wall_s={wall:.1}",
        options.steps,
        options.steps * workers as u64,
        options.commit_every,
        options.samples,
        per_report(1),
        per_report(last),
        1e6 * cpu / (options.steps as f64 * workers as f64),
        rss[1],
        rss[last],
        rss.iter().copied().fold(0.0, f64::max),
        windows.join(","),
        rss_windows.join(","),
        options.steps as f64 / wall,
    )
}

fn main() -> anyhow::Result<()> {
    let options = options()?;
    for &workers in &options.workers {
        println!("{}", run(workers, &options)?);
    }
    Ok(())
}
