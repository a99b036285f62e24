//! Data parallelism inside one process: a batch split into shards whose forward and backward
//! passes run on separate threads, with their gradients summed.
//!
//! burn's CPU kernels for element-wise ops run on one thread, so a single backward pass keeps
//! about one core busy; shards on separate threads use the others. The same machinery is the
//! gradient accumulation that makes the global batch independent of what one device holds.

use std::sync::{Mutex, PoisonError};

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{StreamId, Tensor};

/// Gives every parameter of a copy its own autodiff leaf, so threads never share a graph node
/// (shared leaves serialise, and can deadlock, concurrent backward passes). Parameter ids are
/// kept, so gradients still match the original model's parameters.
struct DetachParameters;

impl ModuleMapper for DetachParameters {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        param.map(|tensor| {
            let requires_grad = tensor.is_require_grad();
            tensor.detach().set_require_grad(requires_grad)
        })
    }
}

/// Sums, parameter by parameter, the gradients of several shards.
struct SumShards {
    shards: Vec<GradientsParams>,
    total: GradientsParams,
}

impl ModuleVisitor for SumShards {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let sum = self
            .shards
            .iter_mut()
            .filter_map(|shard| shard.remove::<D>(param.id))
            .reduce(|sum, grad| sum + grad);
        if let Some(sum) = sum {
            self.total.register(param.id, sum);
        }
    }
}

/// Adds two sets of gradients of `model`'s parameters (gradient accumulation across
/// micro-batches).
pub fn add_gradients<M: Module>(
    model: &M,
    first: GradientsParams,
    second: GradientsParams,
) -> GradientsParams {
    let mut sum = SumShards {
        shards: vec![first, second],
        total: GradientsParams::new(),
    };
    model.visit(&mut sum);
    sum.total
}

/// The device stream each of `shards` shards runs on: the calling thread's for the first (where
/// the model and batch were made), and for the others streams allocated once per process and
/// reused by every later call.
///
/// cubecl gives every new OS thread a new stream (up to 128), each with memory pools of its
/// own, and hands a stream's released pages back to the driver only when that stream is used
/// again. Shards on fresh scoped threads made new streams every step, whose memory stayed
/// held: the likeliest reason an H200 showed 92.5 GB used at batch 8 while the pools counted
/// 12.5 GB (the driver's figure is now printed beside the pools' to check it).
fn shard_streams(shards: usize) -> Vec<StreamId> {
    static EXTRA: Mutex<Vec<StreamId>> = Mutex::new(Vec::new());
    let mut extra = EXTRA.lock().unwrap_or_else(PoisonError::into_inner);
    while extra.len() + 1 < shards {
        extra.push(StreamId::allocate());
    }
    std::iter::once(StreamId::current())
        .chain(extra.iter().copied())
        .take(shards)
        .collect()
}

/// Runs `work` on the device stream of replica `index` of this worker, one stream per
/// replica allocated on first use and kept for the process (as the shards' are: a stream per
/// fresh thread would hold its memory pools after the thread ends). A worker runs each
/// replica's step on a thread of its own, so the replicas' kernels queue on separate streams
/// and none waits for another's.
pub fn on_replica_stream<T>(index: usize, work: impl FnOnce() -> T) -> T {
    static REPLICAS: Mutex<Vec<StreamId>> = Mutex::new(Vec::new());
    let stream = {
        let mut streams = REPLICAS.lock().unwrap_or_else(PoisonError::into_inner);
        while streams.len() <= index {
            streams.push(StreamId::allocate());
        }
        streams[index]
    };
    stream.executes(work)
}

/// Runs `shard_loss(model_copy, shard)` for `shard in 0..shards`, each on its own thread, and
/// returns the sum of the losses and of their gradients with respect to `model`'s parameters.
///
/// Each closure call must return its shard's contribution to the total loss (for a mean over the
/// batch: the shard's mean times its share of the samples), so the sum is the loss of the whole
/// batch and the gradients equal one backward pass over it. Shard `i`'s work depends only on
/// `i`, never on which thread runs it.
pub fn sharded_gradients<M, F>(model: &M, shards: usize, shard_loss: F) -> (f32, GradientsParams)
where
    M: Module,
    F: Fn(&M, usize) -> Tensor<1> + Sync,
{
    let shards = shards.max(1);
    let streams = shard_streams(shards);
    let results: Vec<(f32, GradientsParams)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..shards)
            .zip(streams)
            .map(|(shard, stream)| {
                let copy = model.clone().map(&mut DetachParameters);
                let shard_loss = &shard_loss;
                scope.spawn(move || {
                    stream.executes(|| {
                        let loss = shard_loss(&copy, shard);
                        let value = loss.clone().into_scalar::<f32>();
                        let grads = GradientsParams::from_grads(loss.backward(), &copy);
                        (value, grads)
                    })
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|handle| match handle.join() {
                Ok(result) => result,
                Err(panic) => std::panic::resume_unwind(panic),
            })
            .collect()
    });
    let loss = results.iter().map(|(value, _)| value).sum();
    let mut sum = SumShards {
        shards: results.into_iter().map(|(_, grads)| grads).collect(),
        total: GradientsParams::new(),
    };
    model.visit(&mut sum);
    (loss, sum.total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_reuse_the_same_streams_from_one_step_to_the_next() {
        let first = shard_streams(3);
        assert_eq!(first.len(), 3);
        assert_eq!(
            first[0],
            StreamId::current(),
            "shard 0 stays on the caller's stream"
        );
        assert_eq!(shard_streams(3), first);
        assert_eq!(shard_streams(2), first[..2]);
        let distinct: std::collections::BTreeSet<u64> = first.iter().map(|s| s.value).collect();
        assert_eq!(distinct.len(), 3, "{first:?}");
    }

    #[test]
    fn each_replica_keeps_its_own_stream() {
        let current = || StreamId::current();
        let first = on_replica_stream(0, current);
        let second = on_replica_stream(1, current);
        assert_ne!(first, second);
        assert_eq!(on_replica_stream(0, current), first);
        let elsewhere = std::thread::spawn(move || on_replica_stream(1, current));
        assert_eq!(elsewhere.join().unwrap(), second, "the same on any thread");
    }
    use crate::model::PoseLatents;
    use crate::{XFactor, XFactorConfig};
    use burn::tensor::{Device, TensorData};
    use data::rng::Stream;

    #[test]
    fn two_shards_give_the_gradients_of_one_batch() {
        let config = XFactorConfig::tiny(16);
        let device = Device::flex().autodiff();
        let model = XFactor::new(&config, 5, &device).unwrap();
        let batch = 4;
        let mut stream = Stream::new(&[11]);
        let values: Vec<f32> = (0..batch * 2 * 16 * 16 * 3)
            .map(|_| stream.uniform_in(-1.0, 1.0) as f32)
            .collect();
        let pair = Tensor::<5>::from_data(TensorData::new(values, [batch, 2, 16, 16, 3]), &device);
        let loss_of = |model: &XFactor, start: usize, count: usize| {
            let pair = pair.clone().narrow(0, start, count);
            let poses = model.pose_enc.forward(pair.clone());
            let image = model.render.forward(
                pair.clone().narrow(1, 0, 1),
                PoseLatents::Single(poses),
                None,
            );
            let target = pair.narrow(1, 1, 1).reshape([count, 16, 16, 3]);
            (target - image).abs().mean() * (count as f64 / batch as f64)
        };
        let (whole_loss, whole) = sharded_gradients(&model, 1, |m, _| loss_of(m, 0, batch));
        let (split_loss, split) = sharded_gradients(&model, 2, |m, i| loss_of(m, 2 * i, 2));
        assert!((whole_loss - split_loss).abs() < 1e-6);
        let kernel = |grads: &GradientsParams| -> Vec<f32> {
            grads
                .get::<2>(model.pose_enc.layers[0].qkv.kernel.id)
                .unwrap()
                .try_into_vec_as::<f32>()
                .unwrap()
        };
        let (a, b) = (kernel(&whole), kernel(&split));
        let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let error = a
            .iter()
            .zip(&b)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(
            scale > 0.0 && error <= 1e-5 * scale,
            "error {error} of {scale}"
        );
        assert_eq!(whole.len(), split.len());
    }
}
