//! Counting the kernels a piece of work launches on cubecl's runtimes (wgpu, vulkan, cuda): a
//! measure of launch overhead and of what fusion saves that needs no GPU, since lavapipe
//! launches the same kernels a GPU would. burn's CPU backend and libtorch launch none.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};

use burn::cubecl::logging::{LaunchObservation, LaunchObserver};

/// Kernel launches by kernel name.
#[derive(Debug, Default)]
struct Launches(Mutex<BTreeMap<&'static str, u64>>);

impl LaunchObserver for Launches {
    fn launched(&self, kernel: &'static str) {
        let mut counts = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        *counts.entry(kernel).or_default() += 1;
    }
}

/// The kernels launched while `work` ran, by kind, most launched first. cubecl's observer is
/// process-wide: launches of other threads in that time are counted too.
pub fn count_kernels<T>(work: impl FnOnce() -> T) -> (T, KernelCounts) {
    let launches = Arc::new(Launches::default());
    let observation = LaunchObservation::new(launches.clone());
    let result = work();
    drop(observation);
    let counts = launches.0.lock().unwrap_or_else(PoisonError::into_inner);
    let mut by_kind: BTreeMap<String, u64> = BTreeMap::new();
    for (name, count) in counts.iter() {
        *by_kind.entry(kernel_kind(name)).or_default() += count;
    }
    let mut kinds: Vec<(String, u64)> = by_kind.into_iter().collect();
    kinds.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    (result, KernelCounts { kinds })
}

/// Kernel launches of some work, by kind.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct KernelCounts {
    /// (kind, launches), most launched first.
    pub kinds: Vec<(String, u64)>,
}

impl KernelCounts {
    /// Every launch.
    pub fn total(&self) -> u64 {
        self.kinds.iter().map(|(_, count)| count).sum()
    }

    /// `kind=count` for the `top` most launched kinds, `;`-separated (no spaces, so it is one
    /// `key=value` figure).
    pub fn top(&self, top: usize) -> String {
        let parts: Vec<String> = self
            .kinds
            .iter()
            .take(top)
            .map(|(kind, count)| format!("{kind}:{count}"))
            .collect();
        parts.join(";")
    }
}

/// A kernel's kind from cubecl's profile label (`Kind | f32 | ... _1a2b3c4d`): its first
/// field, without module paths, spaces or the hash.
pub(super) fn kernel_kind(label: &str) -> String {
    let first = label.split('|').next().unwrap_or(label).trim();
    let without_hash = match first.rsplit_once('_') {
        Some((head, hash)) if hash.len() == 8 && hash.chars().all(|c| c.is_ascii_hexdigit()) => {
            head
        }
        _ => first,
    };
    let head = without_hash.split('<').next().unwrap_or(without_hash);
    head.rsplit("::").next().unwrap_or(head).trim().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kind_is_the_label_first_field_without_paths_generics_or_hash() {
        assert_eq!(
            kernel_kind("UnaryNumeric | f32 | CubeTensor_1a2b3c4d"),
            "UnaryNumeric"
        );
        assert_eq!(
            kernel_kind("cubek::matmul::SimpleMatmul<f32>_0badcafe"),
            "SimpleMatmul"
        );
        assert_eq!(kernel_kind("reduce_sum_deadbeef"), "reduce_sum");
        assert_eq!(kernel_kind("fill"), "fill");
        assert_eq!(
            kernel_kind("burn_cubecl::kernel::KernelScalarBinop<f32, burn_cubecl::MulOp>"),
            "KernelScalarBinop"
        );
    }

    #[test]
    fn counts_sum_and_list_the_most_launched_kinds_first() {
        let counts = KernelCounts {
            kinds: vec![("Matmul".into(), 5), ("Add".into(), 3), ("Fill".into(), 1)],
        };
        assert_eq!(counts.total(), 9);
        assert_eq!(counts.top(2), "Matmul:5;Add:3");
    }
}
