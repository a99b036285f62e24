//! The job on a web page: a snapshot of the job (`job/snapshot.rs`), drawn as a self-refreshing
//! HTML page (`page.rs`) and served with its JSON twin on the metrics port to holders of the
//! job token (`routes.rs`).

pub mod page;
pub mod routes;
