//! voxstream server: turns meshes into sparse voxel LOD blocks and serves them.
//!
//! Data flows one way: [`ingest`] → [`voxelize`] → [`lod`] → [`store`] → [`http`];
//! [`build`] runs the first four as one call, reporting [`progress`];
//! [`render`] draws one view offscreen with the viewer's code and writes what
//! its AO saw; [`reference`] ray-traces the AO reference and compares.
//! [`synth`] writes synthetic scans for benchmarks; [`bench`] measures builds
//! against a peer (`voxstream bench`). The server side of
//! [`http`] keeps its state in [`catalog`] (published scenes), [`uploads`]
//! and [`jobs`] (builds of uploads), configured by [`config`], measured by
//! [`metrics`]; [`thumbnail`] draws catalog pictures on the CPU. Large inputs travel
//! between the build's passes as a [`tristream`], binned out of core by [`bin_spill`].

pub mod bench;
pub mod bin_spill;
pub mod build;
pub mod catalog;
pub mod config;
pub mod http;
pub mod ingest;
pub mod jobs;
pub mod lod;
pub mod metrics;
pub mod progress;
pub mod reference;
pub mod render;
pub mod store;
pub mod synth;
pub mod thumbnail;
pub mod tristream;
pub mod uploads;
pub mod voxelize;
