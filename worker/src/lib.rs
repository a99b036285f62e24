//! The worker daemon that trains XFactor data-parallel under a coordinator.
//!
//! Built with the distributed runtime (issue 5); the crate holds no code yet.
