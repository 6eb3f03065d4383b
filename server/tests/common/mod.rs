//! Helpers shared by integration tests.

pub mod garage;
pub mod serve;
