//! voxstream server: turns meshes into sparse voxel LOD blocks and serves them.
//!
//! Data flows one way: [`ingest`] → [`voxelize`] → [`lod`] → [`store`] → [`http`];
//! [`build`] runs the first four as one call, reporting [`progress`];
//! [`synth`] writes synthetic scans for benchmarks. Large inputs travel
//! between the build's passes as a [`tristream`], binned out of core by [`bin_spill`].

pub mod bin_spill;
pub mod build;
pub mod http;
pub mod ingest;
pub mod lod;
pub mod progress;
pub mod store;
pub mod synth;
pub mod tristream;
pub mod voxelize;
