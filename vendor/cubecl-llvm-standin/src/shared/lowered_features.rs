//! Narrowing a device's advertised features to what the LLVM backend lowers.

use cubecl_core::ir::DeviceProperties;

/// The GPU target a device's features would be narrowed for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuTarget {
    /// NVIDIA GPUs.
    Nvptx,
}

/// cubecl-cuda calls this only when its LLVM backend is selected, which a build with this
/// stand-in never does (its `cpp` feature is on); the properties are left as the C++ backend
/// advertises them, and any LLVM compile is refused by [`crate::PlironCompiler`].
pub fn restrict_features(_props: &mut DeviceProperties, _target: GpuTarget) {}
