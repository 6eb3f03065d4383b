//! Helpers shared by integration tests.

pub mod cluster;
pub mod garage;
pub mod postgres;
pub mod serve;
pub mod tus;
