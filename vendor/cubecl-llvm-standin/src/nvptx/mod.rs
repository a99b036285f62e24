//! The NVPTX names cubecl-cuda uses.

pub mod ptx_version;
