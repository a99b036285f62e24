//! Target-independent names cubecl-cuda uses.

pub mod lowered_features;
