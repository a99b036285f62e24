//! Offline stand-in for cubecl-llvm 0.11.3 (see README.md): the types cubecl-cuda names,
//! and a compiler that refuses every LLVM compile, because this build compiles kernels with
//! NVRTC (cubecl-cuda's `cpp` feature) and has no LLVM.

use core::fmt;

use cubecl_core::prelude::KernelDefinition;
use cubecl_environment::backtrace::BackTrace;
use cubecl_server::compiler::{CompilationError, Compiler};
use cubecl_server::kernel::BufferIOAttr;

pub mod nvptx;
pub mod shared;

/// The LLVM targets cubecl-llvm lowers to; only their names exist here.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LlvmTarget {
    /// The host CPU.
    #[default]
    Cpu,
    /// AMD GPUs.
    AmdGpu,
    /// NVIDIA GPUs (PTX).
    Nvptx,
}

/// Options of an LLVM compile, with the fields cubecl-cuda sets.
#[derive(Clone, Debug, Default)]
pub struct PlironOptions {
    /// AMDGPU architecture; never set for CUDA.
    pub arch: Option<String>,
    /// NVPTX architecture, as the runtime read the device's compute capability.
    #[cfg(feature = "nvptx")]
    pub sm_arch: Option<cubecl_core::ir::nvidia::SmArch>,
    /// PTX version to emit.
    pub ptx_version: Option<nvptx::ptx_version::PtxVersion>,
    /// Scalars and metadata in the kernel parameter block.
    pub grid_constants: bool,
}

/// A PTX module as cubecl-llvm would emit it; this crate never makes one.
#[derive(Clone, Debug)]
pub struct NvptxModule {
    /// NUL-terminated PTX assembly.
    pub ptx: Vec<core::ffi::c_char>,
    /// Kernel entry point symbol.
    pub entrypoint: String,
    /// IR for logging and cache keys.
    pub ir: String,
    /// Shared memory required per launch, in bytes.
    pub shared_memory_size: usize,
    /// Buffer access modes in binding order.
    pub io: Vec<BufferIOAttr>,
}

/// What an LLVM compile produces.
#[derive(Clone, Debug)]
pub enum PlironArtifact {
    /// A PTX module for the CUDA driver.
    NvptxCode(NvptxModule),
    /// Any other target's artifact, which cubecl-cuda never asks for.
    Other,
}

impl fmt::Display for PlironArtifact {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NvptxCode(module) => f.write_str(&module.ir),
            Self::Other => f.write_str("(no artifact)"),
        }
    }
}

/// The LLVM compiler's place in cubecl-cuda's `CudaCompiler`; every compile is refused.
#[derive(Clone, Debug, Default)]
pub struct PlironCompiler {
    /// The target it would compile for.
    pub target: LlvmTarget,
}

impl Compiler for PlironCompiler {
    type Representation = PlironArtifact;
    type CompilationOptions = PlironOptions;

    fn compile(
        &mut self,
        _kernel: KernelDefinition,
        _options: &Self::CompilationOptions,
    ) -> Result<Self::Representation, CompilationError> {
        Err(CompilationError::Generic {
            reason: "this build has no LLVM (cubecl-llvm is the offline stand-in of \
                     vendor/cubecl-llvm-standin): build cubecl-cuda with its `cpp` feature so \
                     kernels compile with NVRTC"
                .to_string(),
            backtrace: BackTrace::capture(),
        })
    }

    fn extension(&self) -> &'static str {
        "ll"
    }

    fn lang_tag(&self) -> &'static str {
        match self.target {
            LlvmTarget::Cpu => "mlir",
            LlvmTarget::AmdGpu | LlvmTarget::Nvptx => "llvm",
        }
    }
}
