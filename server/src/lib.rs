//! voxstream server: turns meshes into sparse voxel LOD blocks and serves them.
//!
//! Data flows one way: [`pipeline`] (read → stream → bin → voxelize →
//! pyramid → write, `voxstream build`) → [`store`] → [`http`];
//! [`render`] draws one view offscreen with the viewer's code and writes what
//! its AO saw; [`reference`] ray-traces the AO reference and compares.
//! [`synth`] writes synthetic scans for benchmarks; [`bench`] measures builds
//! against a peer (`voxstream bench`). The server side of
//! [`http`] keeps its state in [`catalog`] (published scenes), [`uploads`]
//! and [`jobs`] (builds of uploads), configured by [`config`], measured by
//! [`metrics`]; [`thumbnail`] draws catalog pictures on the CPU. Bucket replicas
//! with a [`coordinator`] (PostgreSQL) take uploads too: [`cluster_jobs`] builds them once.

pub mod bench;
pub mod bucket_build;
pub mod bucket_store;
pub mod catalog;
pub mod cluster_jobs;
pub mod config;
pub mod coordinator;
pub mod gc;
pub mod http;
pub mod jobs;
pub mod metrics;
pub mod objstore;
pub mod pipeline;
pub mod publish;
pub mod reference;
pub mod render;
pub mod store;
pub mod synth;
pub mod thumbnail;
pub mod ticker;
pub mod uploads;
