//! voxstream server: turns meshes into sparse voxel LOD blocks and serves them.
//!
//! Data flows one way: [`ingest`] → [`voxelize`] → [`lod`] → [`store`] → [`http`];
//! [`build`] runs the first four as one call, reporting [`progress`];
//! [`synth`] writes synthetic scans for benchmarks; [`bench`] measures builds
//! against a peer (`voxstream bench`).

pub mod bench;
pub mod build;
pub mod http;
pub mod ingest;
pub mod lod;
pub mod progress;
pub mod store;
pub mod synth;
pub mod voxelize;
