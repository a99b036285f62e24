//! The gRPC contract between the coordinator and the workers.
//!
//! Its services and messages are defined with the distributed runtime (issue 5); until then the
//! crate holds no code, so nothing can depend on an unversioned message.
