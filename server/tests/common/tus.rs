//! The official tus clients' harnesses (`tests/tus/tuspy_client.py`, `tests/browser/tus_client.mjs`):
//! where they and their runtimes are.

#![allow(dead_code)] // each test binary uses part of the common helpers

use std::path::{Path, PathBuf};
use std::process::Command;

pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// The Python tools venv holding tuspy (made by scripts/setup.sh).
pub fn tools_venv() -> PathBuf {
    let out = Command::new("bash")
        .arg(root().join("scripts/schemathesis.sh"))
        .arg("--check")
        .output()
        .expect("bash runs");
    assert!(
        out.status.success(),
        "the Python tools venv (tuspy) is missing: run bash scripts/setup.sh (or bash scripts/schemathesis.sh --install)"
    );
    PathBuf::from(String::from_utf8(out.stdout).unwrap().trim())
}

/// `tuspy_client.py ARGS…` with the venv's Python.
pub fn tuspy(args: &[&str]) -> Command {
    let mut c = Command::new(tools_venv().join("bin/python"));
    c.arg(root().join("tests/tus/tuspy_client.py")).args(args);
    c
}

/// `node tus_client.mjs ARGS…` (tus-js-client from tests/browser/node_modules).
pub fn tus_js(args: &[&str]) -> Command {
    let module = root().join("tests/browser/node_modules/tus-js-client/package.json");
    assert!(
        module.is_file(),
        "{} is missing: run bash scripts/setup.sh (npm ci in tests/browser)",
        module.display()
    );
    let mut c = Command::new("node");
    c.arg(root().join("tests/browser/tus_client.mjs")).args(args);
    c
}

/// Runs a client step in the repository root; its stdout's last line.
pub fn run(mut cmd: Command, what: &str) -> String {
    let out = cmd.current_dir(root()).output().unwrap_or_else(|e| panic!("cannot start {what}: {e}"));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{what} failed ({}):\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout.lines().last().unwrap_or_default().trim().to_string()
}
