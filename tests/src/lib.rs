//! Shared support for the end-to-end tests (tests/tests/*.rs): the CPU
//! coverage reference both the native render test and the browser test
//! compare rendered silhouettes against.

pub mod coverage;
