//! AdamW's arithmetic on buckets: the parameters that share a decay setting packed, in module
//! order, into flat tensors of up to [`BUCKET_VALUES`] values, so an update is a few dozen
//! element-wise operations on large tensors rather than fifteen on each of hundreds of small
//! ones (the paper model has 283 parameters; each operation's fixed cost, a kernel launch on
//! a GPU and an allocation on the CPU, dominated the update of a small model and of the data
//! path's scaled benchmark). Every element still goes through the same operations in the
//! same order as it would alone, so an update is bitwise the per-parameter one.

use std::collections::HashMap;

use burn::module::{ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::Tensor;

use super::is_decayed;
use crate::flax::flax_name;

/// The most values a bucket packs: 16 MiB of float32, large enough that an operation's fixed
/// cost is small beside its work, small enough that the update's temporaries stay a small
/// share of a device's memory. A parameter larger than this is a bucket of its own.
pub(super) const BUCKET_VALUES: usize = 1 << 22;

/// One parameter with a gradient, as the update packs it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Member {
    pub id: ParamId,
    pub len: usize,
}

/// Parameters packed together: same decay setting, consecutive in module order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Bucket {
    pub decayed: bool,
    pub members: Vec<Member>,
}

/// Where a parameter's values sit: its bucket and its range there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Place {
    pub bucket: usize,
    pub offset: usize,
    pub len: usize,
}

/// The buckets of one model, in the order their parameters first appear.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(super) struct Layout {
    pub buckets: Vec<Bucket>,
}

impl Layout {
    /// Packs `members` (module order, with their decay setting) into buckets of at most
    /// `limit` values: each decay setting fills its own open bucket, which is closed when the
    /// next member would overflow it.
    pub fn plan(members: &[(Member, bool)], limit: usize) -> Self {
        let mut buckets: Vec<Bucket> = Vec::new();
        let mut open: [Option<(usize, usize)>; 2] = [None, None];
        for &(member, decayed) in members {
            let slot = &mut open[usize::from(decayed)];
            match slot {
                Some((index, filled)) if *filled + member.len <= limit => {
                    buckets[*index].members.push(member);
                    *filled += member.len;
                }
                _ => {
                    *slot = Some((buckets.len(), member.len));
                    buckets.push(Bucket {
                        decayed,
                        members: vec![member],
                    });
                }
            }
        }
        Self { buckets }
    }

    /// Every member's place.
    pub fn places(&self) -> HashMap<ParamId, Place> {
        let mut places = HashMap::new();
        for (bucket, shape) in self.buckets.iter().enumerate() {
            let mut offset = 0;
            for member in &shape.members {
                places.insert(
                    member.id,
                    Place {
                        bucket,
                        offset,
                        len: member.len,
                    },
                );
                offset += member.len;
            }
        }
        places
    }
}

/// One parameter's values and gradient, flattened (the gradient not yet clipped).
pub(super) struct Flat {
    pub member: Member,
    pub decayed: bool,
    pub value: Tensor<1>,
    pub grad: Tensor<1>,
}

/// Collects every parameter that has a gradient, in module order.
pub(super) struct Gather<'a> {
    grads: &'a GradientsParams,
    path: Vec<String>,
    pub flats: Vec<Flat>,
}

impl<'a> Gather<'a> {
    pub fn new(grads: &'a GradientsParams) -> Self {
        Self {
            grads,
            path: Vec::new(),
            flats: Vec::new(),
        }
    }
}

impl ModuleVisitor for Gather<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let Some(grad) = self.grads.get::<D>(param.id) else {
            return;
        };
        let value = param.val();
        let value = if value.is_autodiff() {
            value.inner()
        } else {
            value
        };
        let len = value.shape().num_elements();
        self.flats.push(Flat {
            member: Member { id: param.id, len },
            decayed: is_decayed(&flax_name(&self.path)),
            value: value.reshape([len]),
            grad: grad.reshape([len]),
        });
    }
}

/// The bucket's tensors end to end (no copy for a bucket of one).
pub(super) fn concat(mut parts: Vec<Tensor<1>>) -> Tensor<1> {
    if parts.len() == 1 {
        parts.swap_remove(0)
    } else {
        Tensor::cat(parts, 0)
    }
}

/// Puts the updated parameters of one bucket back, keeping what each old tensor carried
/// (autodiff tracking, `require_grad`, the gradient checkpointing strategy).
pub(super) struct Scatter<'a> {
    pub bucket: usize,
    pub updated: Tensor<1>,
    pub places: &'a HashMap<ParamId, Place>,
}

impl ModuleMapper for Scatter<'_> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let Some(place) = self.places.get(&param.id).copied() else {
            return param;
        };
        if place.bucket != self.bucket {
            return param;
        }
        let values = self.updated.clone().narrow(0, place.offset, place.len);
        param.map(|tensor| {
            let shape = tensor.dims();
            let updated = values.reshape(shape);
            if !tensor.is_autodiff() {
                return updated;
            }
            let requires_grad = tensor.is_require_grad();
            // The device's gradient checkpointing rides on each tracked tensor; the updated
            // parameter must carry it on, or the next step mixes strategies.
            let strategy = tensor.gradient_checkpointing_strategy();
            let tracked = Tensor::from_inner(updated);
            let tracked = match strategy {
                Some(strategy) => tracked.with_gradient_checkpointing_strategy(strategy),
                None => tracked,
            };
            tracked.set_require_grad(requires_grad)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn member(len: usize) -> Member {
        Member {
            id: ParamId::new(),
            len,
        }
    }

    #[test]
    fn decay_settings_pack_apart_in_module_order_up_to_the_limit() {
        let [a, b, c, d, e] = [3, 2, 4, 1, 9].map(member);
        let layout = Layout::plan(
            &[(a, true), (b, false), (c, true), (d, false), (e, true)],
            8,
        );
        let shapes: Vec<(bool, Vec<ParamId>)> = layout
            .buckets
            .iter()
            .map(|bucket| {
                (
                    bucket.decayed,
                    bucket.members.iter().map(|m| m.id).collect(),
                )
            })
            .collect();
        assert_eq!(
            shapes,
            vec![
                (true, vec![a.id, c.id]),
                (false, vec![b.id, d.id]),
                (true, vec![e.id]),
            ],
            "a and c (7 values) share a bucket across b; e (9) is one of its own"
        );
        let places = layout.places();
        assert_eq!(
            places[&d.id],
            Place {
                bucket: 1,
                offset: 2,
                len: 1
            }
        );
        assert_eq!(places.len(), 5);
    }
}
