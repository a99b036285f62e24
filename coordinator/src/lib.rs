//! The coordinator that schedules XFactor's two training stages across worker daemons.
//!
//! Built with the distributed runtime (issue 5); the crate holds no code yet.
