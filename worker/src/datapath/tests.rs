use std::sync::Mutex;
use std::sync::mpsc::{Receiver, Sender};
use std::time::{Duration, Instant};

use data::spec::RankSource;
use settings::data::{DataSource, DataSpec, SamplerConfig};
use settings::objective::Stage1Config;
use settings::optim::{AdamWConfig, Schedule};
use settings::train::{StageObjective, TrainConfig};
use settings::{DeviceSet, XFactorConfig};
use trainer_core::XFactor;
use trainer_core::backend::{Backend, BackendDevices};
use trainer_core::flat::{flatten_parameters, parameter_checksum};
use trainer_core::trainer::Trainer;

use super::*;
use crate::collective::{CollectiveService, Link, RingKeys, WireFormat};

/// A ring of one on a fresh runtime: the data path without peers.
fn lone_ring(runtime: &Runtime) -> Ring {
    let link = Link {
        token: "token".into(),
        timeout: Duration::from_secs(5),
        tls: None,
        lanes: 1,
    };
    let mailbox = CollectiveService::default().mailbox();
    let peers = ["127.0.0.1:1".to_string()];
    runtime
        .block_on(Ring::connect(
            &mailbox,
            0,
            &peers,
            1,
            &RingKeys::default(),
            &link,
            tokio_util::sync::CancellationToken::new(),
        ))
        .unwrap()
}

fn every_step() -> ChecksumPlan {
    ChecksumPlan {
        every: ChecksumEvery::Steps(1),
        commit_every: 100,
        total_steps: 100,
    }
}

/// A replica that computes nothing: it waits, optionally meets its partner (proving it runs
/// while the other does), and writes `value` everywhere.
struct Waiting {
    step: u64,
    parameters: usize,
    value: f32,
    wait: Duration,
    meet: Option<(Sender<()>, Mutex<Receiver<()>>)>,
    checksum: u32,
    applied: Vec<f32>,
}

impl Waiting {
    fn new(value: f32, wait: Duration) -> Self {
        Self {
            step: 0,
            parameters: 5,
            value,
            wait,
            meet: None,
            checksum: 7,
            applied: Vec::new(),
        }
    }
}

impl ReplicaModel for Waiting {
    fn step(&self) -> u64 {
        self.step
    }

    fn parameter_count(&self) -> usize {
        self.parameters
    }

    fn gradients_into(
        &self,
        _source: &dyn BatchSource,
        out: &mut [f32],
    ) -> Result<Computed, ReplicaError> {
        if let Some((tell, hear)) = &self.meet {
            tell.send(()).unwrap();
            let partner = hear.lock().unwrap().recv_timeout(Duration::from_secs(20));
            assert!(
                partner.is_ok(),
                "the other replica never ran beside this one"
            );
        }
        std::thread::sleep(self.wait);
        out.fill(self.value);
        Ok(Computed {
            loss: SliceLoss {
                total: self.value,
                l1: 1.0,
                lpips: f32::NAN,
            },
            copy_s: 0.0,
        })
    }

    fn apply(&mut self, sum: &[f32], _loss: f32) -> Result<Applied, ReplicaError> {
        self.applied = sum.to_vec();
        self.step += 1;
        Ok(Applied {
            metrics: StepMetrics {
                step: self.step - 1,
                loss: 0.0,
                learning_rate: 0.0,
                grad_norm: 0.0,
                applied: true,
            },
            upload_s: 0.0,
        })
    }

    fn checksum(&self) -> u32 {
        self.checksum
    }
}

/// No samples: the waiting replicas never read any.
struct NoData;

impl BatchSource for NoData {
    fn samples(&self, _: u64, _: u64, _: usize) -> Result<data::Samples, data::SampleError> {
        Ok(data::Samples::Pairs(Vec::new()))
    }
}

fn step_once(path: &mut DataPath, runtime: &Runtime, replicas: &mut [Waiting]) -> StepFigures {
    path.step(runtime, replicas, &NoData, &Progress::new())
        .unwrap()
}

#[test]
fn replicas_compute_side_by_side() {
    let runtime = Runtime::new().unwrap();
    let (to_second, from_first) = std::sync::mpsc::channel();
    let (to_first, from_second) = std::sync::mpsc::channel();
    let mut first = Waiting::new(1.0, Duration::ZERO);
    first.meet = Some((to_second, Mutex::new(from_second)));
    let mut second = Waiting::new(2.0, Duration::ZERO);
    second.meet = Some((to_first, Mutex::new(from_first)));
    let mut path = DataPath::new(lone_ring(&runtime), every_step(), None);
    let figures = step_once(&mut path, &runtime, &mut [first, second]);
    assert_eq!(figures.checksum, Some(7));
}

#[test]
fn two_waiting_replicas_take_about_one_replicas_time() {
    let runtime = Runtime::new().unwrap();
    let wait = Duration::from_millis(400);
    let mut path = DataPath::new(lone_ring(&runtime), every_step(), None);
    let timed = |path: &mut DataPath, replicas: &mut [Waiting]| {
        let started = Instant::now();
        step_once(path, &runtime, replicas);
        started.elapsed().as_secs_f64()
    };
    let one = timed(&mut path, &mut [Waiting::new(1.0, wait)]);
    let mut two = [Waiting::new(1.0, wait), Waiting::new(2.0, wait)];
    let both = timed(&mut path, &mut two);
    println!(
        "one_replica_s={one:.3} two_replicas_s={both:.3} ratio={:.3}",
        both / one
    );
    assert!(
        both <= 1.2 * one,
        "two replicas {both:.3} s against one {one:.3} s"
    );
    assert_eq!(two[0].applied, [3.0; 5], "both replicas' gradients summed");
    assert_eq!(two[1].applied, two[0].applied);
}

#[test]
fn the_sum_carries_the_loss_terms_and_the_buffers_are_kept() {
    let runtime = Runtime::new().unwrap();
    let mut path = DataPath::new(lone_ring(&runtime), every_step(), None);
    let mut replicas = [
        Waiting::new(0.5, Duration::ZERO),
        Waiting::new(0.25, Duration::ZERO),
    ];
    let figures = step_once(&mut path, &runtime, &mut replicas);
    assert_eq!(figures.metrics.step, 0);
    assert_eq!((figures.l1, figures.reduced_bytes), (2.0, 8 * 4));
    assert!(figures.lpips.is_nan());
    let buffers = |path: &DataPath| {
        let mut all: Vec<usize> = path.staging.iter().map(|b| b.as_ptr() as usize).collect();
        all.push(path.sum.as_ptr() as usize);
        all.sort_unstable();
        all
    };
    let before = buffers(&path);
    step_once(&mut path, &runtime, &mut replicas);
    assert_eq!(
        buffers(&path),
        before,
        "no buffer allocated after the first step"
    );
    assert_eq!(replicas[0].applied, [0.75; 5]);
}

#[test]
fn replicas_that_disagree_after_the_update_fail_the_step() {
    let runtime = Runtime::new().unwrap();
    let mut path = DataPath::new(lone_ring(&runtime), every_step(), None);
    let mut odd = Waiting::new(1.0, Duration::ZERO);
    odd.checksum = 8;
    let error = path
        .step(
            &runtime,
            &mut [Waiting::new(1.0, Duration::ZERO), odd],
            &NoData,
            &Progress::new(),
        )
        .unwrap_err();
    assert!(
        matches!(&error, StepError::ReplicasDiverged { step: 0, checksums } if checksums == &[7, 8]),
        "{error}"
    );
}

#[test]
fn checksums_fall_every_n_steps_and_after_the_last() {
    let plan = ChecksumPlan {
        every: ChecksumEvery::Steps(4),
        commit_every: 100,
        total_steps: 10,
    };
    let due: Vec<u64> = (1..=10).filter(|&done| plan.due(done, 1000)).collect();
    assert_eq!(due, [4, 8, 10]);
    let auto = ChecksumPlan {
        every: ChecksumEvery::Auto,
        commit_every: 1000,
        total_steps: 100,
    };
    assert!(auto.due(3, 1000), "a small model is checked every step");
    let paper = 305_178_624;
    let due: Vec<u64> = (1..=40).filter(|&done| auto.due(done, paper)).collect();
    assert_eq!(due, [19, 38], "the paper's model about every 19 steps");
}

#[test]
fn every_commit_step_is_a_checksum_step_off_the_interval_too() {
    let plan = ChecksumPlan {
        every: ChecksumEvery::Steps(19),
        commit_every: 5,
        total_steps: 42,
    };
    let due: Vec<u64> = (1..=42).filter(|&done| plan.due(done, 1000)).collect();
    assert_eq!(due, [5, 10, 15, 19, 20, 25, 30, 35, 38, 40, 42]);
    let schedule = crate::commits::CommitSchedule {
        every: plan.commit_every,
        total_steps: plan.total_steps,
    };
    for done in 1..=42 {
        let commits =
            schedule.decide(0, done, false, false) != crate::commits::CommitDecision::Nothing;
        assert!(
            !commits || plan.due(done, 1000),
            "step {done} commits unhashed"
        );
    }
}

#[test]
fn a_suspensions_notice_hashes_the_next_step_only() {
    let runtime = Runtime::new().unwrap();
    let plan = ChecksumPlan {
        every: ChecksumEvery::Steps(1000),
        commit_every: 1000,
        total_steps: 1000,
    };
    let mut path = DataPath::new(lone_ring(&runtime), plan, None);
    let mut replicas = vec![Waiting::new(1.0, Duration::ZERO)];
    let first = step_once(&mut path, &runtime, &mut replicas);
    path.checksum_next_step();
    let noticed = step_once(&mut path, &runtime, &mut replicas);
    let after = step_once(&mut path, &runtime, &mut replicas);
    let hashed = [first.checksum, noticed.checksum, after.checksum].map(|c| c.is_some());
    assert_eq!(hashed, [false, true, false]);
}

#[test]
fn buffers_are_summed_in_replica_order_whoever_finishes_first() {
    let computed = |value: f32| Computed {
        loss: SliceLoss {
            total: value,
            l1: value,
            lpips: value,
        },
        copy_s: 0.0,
    };
    let mut order = InOrder::new(3);
    order.arrive(2, vec![3.0; 4], Ok(computed(3.0)));
    order.arrive(1, vec![3.0; 4], Ok(computed(2.0)));
    assert!(
        order.sum.is_empty(),
        "nothing added before replica 0 arrives"
    );
    order.arrive(0, vec![1e8; 4], Ok(computed(1.0)));
    // (1e8 + 3) + 3 rounds to 1e8 in float32; (3 + 3) + 1e8, the finishing order, to 1e8 + 8.
    let (sum, others, _, failure) = order.finish();
    assert_eq!(sum, [1e8, 6.0, 6.0, 6.0]);
    assert_eq!(others.len(), 2);
    assert!(failure.is_none());
}

const GLOBAL_BATCH: usize = 4;

fn train_config() -> TrainConfig {
    TrainConfig {
        seed: 5,
        objective: StageObjective::Stage1(Stage1Config {
            lpips_weight: 0.0,
            ..Stage1Config::default()
        }),
        global_batch: GLOBAL_BATCH,
        micro_batch: 1,
        shards: 1,
        schedule: Schedule::default(),
        optimizer: AdamWConfig::default(),
    }
}

/// One trainer per device of `set` on the CPU, from the same seed, each with an equal share
/// of the global batch.
fn replicas(set: &DeviceSet) -> Vec<Replica> {
    let model = XFactorConfig::tiny(16);
    let devices = Backend::Cpu.devices(set).unwrap();
    let share = GLOBAL_BATCH / devices.len();
    devices
        .into_iter()
        .enumerate()
        .map(|(index, device)| {
            let (first, count) = ((index * share) as u64, share);
            let device = device.autodiff();
            let xfactor = XFactor::new(&model, 5, &device).unwrap();
            let trainer =
                Trainer::new(train_config(), model.clone(), xfactor, None, &device).unwrap();
            Replica {
                trainer,
                index,
                first,
                count,
            }
        })
        .collect()
}

/// The generated data every test of real training reads.
fn spec() -> DataSpec {
    DataSpec {
        source: DataSource::Generated {
            scenes: 2,
            trajectories: 2,
            frames: 6,
        },
        sampler: SamplerConfig::stage1(),
        image_size: 16,
        seed: 5,
        global_batch: GLOBAL_BATCH,
    }
}

/// Parameters of every replica after `steps` steps, through a ring of one.
fn train(set: &DeviceSet, steps: usize) -> (Vec<Vec<f32>>, Vec<u32>) {
    let runtime = Runtime::new().unwrap();
    let source = runtime.block_on(RankSource::open(&spec(), 1, 0)).unwrap();
    let mut path = DataPath::new(lone_ring(&runtime), every_step(), None);
    let mut replicas = replicas(set);
    for _ in 0..steps {
        path.step(&runtime, &mut replicas, &source, &Progress::new())
            .unwrap();
    }
    let parameters = replicas
        .iter()
        .map(|r| flatten_parameters(r.trainer.model()))
        .collect();
    let checksums = replicas
        .iter()
        .map(|r| parameter_checksum(r.trainer.model()))
        .collect();
    (parameters, checksums)
}

#[test]
fn two_replicas_train_to_the_weights_of_one_with_the_same_global_batch() {
    let steps = 3;
    let (single, _) = train(&DeviceSet::Count(1), steps);
    let (pair, checksums) = train(&DeviceSet::Count(2), steps);
    assert_eq!(
        checksums[0], checksums[1],
        "the replicas stay bitwise identical"
    );
    let largest = single[0]
        .iter()
        .zip(&pair[0])
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    println!("replicas=2 steps={steps} max_abs_difference={largest:e}");
    assert!(largest <= 1e-5, "largest difference {largest:e}");
    assert_ne!(
        single[0],
        flatten_parameters(
            &XFactor::new(
                &XFactorConfig::tiny(16),
                5,
                &Backend::Cpu.device().unwrap().autodiff()
            )
            .unwrap()
        ),
        "training moved the weights"
    );
}

/// Two ranks of one replica each, in this process over loopback, train `steps` steps with
/// gradients carried as `wire`; each step's loss and both ranks' checksums.
fn train_two_ranks(wire: WireFormat, steps: usize) -> Vec<(f32, Option<u32>, Option<u32>)> {
    let runtime = Runtime::new().unwrap();
    let link = Link {
        token: "token".into(),
        timeout: Duration::from_secs(20),
        tls: None,
        lanes: 1,
    };
    let servers: Vec<(String, std::sync::Arc<crate::collective::Mailbox>)> = (0..2)
        .map(|_| {
            runtime.block_on(async {
                let service = CollectiveService::default();
                let mailbox = service.mailbox();
                let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
                let address = listener.local_addr().unwrap().to_string();
                crate::collective::spawn_server(listener, service, &link).unwrap();
                (address, mailbox)
            })
        })
        .collect();
    let peers: Vec<String> = servers.iter().map(|(address, _)| address.clone()).collect();
    let ranks: Vec<Vec<(f32, Option<u32>)>> = std::thread::scope(|scope| {
        let handles: Vec<_> = servers
            .iter()
            .enumerate()
            .map(|(rank, (_, mailbox))| {
                let (runtime, link, peers) = (&runtime, &link, &peers);
                scope.spawn(move || {
                    let keys = RingKeys {
                        own: format!("rank-{rank}"),
                        left: format!("rank-{}", 1 - rank),
                    };
                    let cancel = tokio_util::sync::CancellationToken::new();
                    let ring = runtime
                        .block_on(Ring::connect(mailbox, rank, peers, 1, &keys, link, cancel))
                        .unwrap()
                        .with_wire(wire);
                    let source = runtime
                        .block_on(RankSource::open(&spec(), 2, rank))
                        .unwrap();
                    let (first, count) = data::spec::rank_slice(GLOBAL_BATCH, 2, rank);
                    let mut replica = replicas(&DeviceSet::Count(1)).remove(0);
                    (replica.first, replica.count) = (first, count);
                    let mut path = DataPath::new(ring, every_step(), None);
                    let mut replicas = [replica];
                    (0..steps)
                        .map(|_| {
                            let figures = path
                                .step(runtime, &mut replicas, &source, &Progress::new())
                                .unwrap();
                            (figures.metrics.loss, figures.checksum)
                        })
                        .collect()
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    ranks[0]
        .iter()
        .zip(&ranks[1])
        .map(|(a, b)| (a.0, a.1, b.1))
        .collect()
}

#[test]
fn a_bf16_wire_trains_within_a_percent_of_float32_with_ranks_bitwise_equal() {
    let steps = 8;
    let exact = train_two_ranks(WireFormat::F32, steps);
    let halved = train_two_ranks(WireFormat::Bf16, steps);
    for (step, ((loss, a, b), (half_loss, half_a, half_b))) in exact.iter().zip(&halved).enumerate()
    {
        let relative = ((half_loss - loss) / loss).abs();
        println!(
            "step={step} loss_f32={loss:.6} loss_bf16_wire={half_loss:.6} relative={relative:.2e}"
        );
        assert!(relative <= 0.01, "step {step}: {half_loss} against {loss}");
        assert!(a.is_some() && a == b, "float32 ranks agree at step {step}");
        assert!(
            half_a.is_some() && half_a == half_b,
            "bf16-wire ranks agree at step {step}"
        );
    }
    assert_eq!(
        exact[0].0, halved[0].0,
        "the first step's loss is computed before any exchange"
    );
    assert_ne!(
        exact[steps - 1].1,
        halved[steps - 1].1,
        "the bf16 wire rounded something"
    );
}
