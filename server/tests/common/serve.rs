//! A `voxstream serve` child that reports where it listens.

#![allow(dead_code)] // each test binary uses part of the common helpers

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

/// Spawns `cmd` (a `voxstream serve … --addr 127.0.0.1:0` command, stderr set by the caller)
/// with its stdout piped, and reads the "listening on <base>" line it prints first.
pub fn spawn_listening(mut cmd: Command) -> (Child, String) {
    let mut child = cmd.stdout(Stdio::piped()).spawn().expect("starting voxstream serve");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    match line.trim().strip_prefix("listening on ") {
        Some(base) => (child, base.to_string()),
        None => {
            let _ = child.kill();
            let _ = child.wait();
            panic!("voxstream serve did not say where it listens: {line:?}")
        }
    }
}
