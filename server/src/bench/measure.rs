//! Measuring one child process: wall time, CPU time and peak resident memory
//! (from `wait4`'s rusage, which covers exactly that child), plus the small
//! readers of /proc the report needs.

use std::fs::File;
use std::io;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

/// What one measured child process did.
#[derive(Debug, Clone, PartialEq)]
pub struct ChildRun {
    pub wall_seconds: f64,
    pub user_seconds: f64,
    pub system_seconds: f64,
    /// The child's peak resident set (rusage `ru_maxrss`).
    pub peak_rss_bytes: u64,
    /// Exit code, or `None` when a signal ended it (`signal` says which).
    pub exit_code: Option<i32>,
    pub signal: Option<i32>,
    pub stdout: String,
    pub stderr: String,
}

impl ChildRun {
    pub fn succeeded(&self) -> bool {
        self.exit_code == Some(0)
    }

    /// One line saying how the child failed, with the end of its stderr.
    pub fn failure(&self) -> String {
        let how = match (self.exit_code, self.signal) {
            (Some(c), _) => format!("exit code {c}"),
            (None, Some(9)) => "killed by signal 9 (out of memory?)".to_string(),
            (None, Some(s)) => format!("killed by signal {s}"),
            (None, None) => "unknown exit status".to_string(),
        };
        let tail: String = {
            let t = self.stderr.trim();
            let start = t.char_indices().rev().nth(400).map_or(0, |(i, _)| i);
            t[start..].to_string()
        };
        format!("{how}: {tail}")
    }
}

/// `ru_maxrss` is in kibibytes on Linux.
pub fn maxrss_to_bytes(ru_maxrss: i64) -> u64 {
    (ru_maxrss.max(0) as u64) * 1024
}

fn timeval_seconds(t: libc::timeval) -> f64 {
    t.tv_sec as f64 + t.tv_usec as f64 * 1e-6
}

/// Runs `cmd` to completion with its output in files under `log_dir` (so a chatty
/// child can never block on a full pipe) and reaps it with `wait4`, whose rusage
/// is that child's alone, not the running maximum over all children.
pub fn run_child(cmd: &mut Command, log_dir: &Path) -> io::Result<ChildRun> {
    std::fs::create_dir_all(log_dir)?;
    let out_path = log_dir.join("stdout");
    let err_path = log_dir.join("stderr");
    cmd.stdin(Stdio::null())
        .stdout(Stdio::from(File::create(&out_path)?))
        .stderr(Stdio::from(File::create(&err_path)?));
    let start = Instant::now();
    let child = cmd.spawn()?;
    let pid = child.id() as libc::pid_t;
    let mut status: libc::c_int = 0;
    // SAFETY: rusage is plain old data; wait4 fills it for the child we own.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: pid is our unreaped child; status and usage point to live locals.
        let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
        if r == pid {
            break;
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
    let wall_seconds = start.elapsed().as_secs_f64();
    // Reaped above; dropping `child` neither waits nor kills.
    drop(child);
    let (exit_code, signal) = if libc::WIFEXITED(status) {
        (Some(libc::WEXITSTATUS(status)), None)
    } else if libc::WIFSIGNALED(status) {
        (None, Some(libc::WTERMSIG(status)))
    } else {
        (None, None)
    };
    Ok(ChildRun {
        wall_seconds,
        user_seconds: timeval_seconds(usage.ru_utime),
        system_seconds: timeval_seconds(usage.ru_stime),
        peak_rss_bytes: maxrss_to_bytes(usage.ru_maxrss),
        exit_code,
        signal,
        stdout: String::from_utf8_lossy(&std::fs::read(&out_path)?).into_owned(),
        stderr: String::from_utf8_lossy(&std::fs::read(&err_path)?).into_owned(),
    })
}

/// A `Key:   1234 kB` field of /proc/self/status or /proc/meminfo, in bytes.
pub fn proc_kib_field(text: &str, key: &str) -> Option<u64> {
    text.lines().find_map(|line| {
        let rest = line.strip_prefix(key)?.strip_prefix(':')?;
        let mut parts = rest.split_whitespace();
        let value: u64 = parts.next()?.parse().ok()?;
        match parts.next() {
            Some("kB") => Some(value * 1024),
            None => Some(value),
            Some(_) => None,
        }
    })
}

/// This process's peak resident set (`VmHWM`), where /proc has it.
pub fn own_peak_rss_bytes() -> Option<u64> {
    proc_kib_field(&std::fs::read_to_string("/proc/self/status").ok()?, "VmHWM")
}

/// Total bytes of the regular files under `dir`, recursively (symlinks not followed).
pub fn dir_size(dir: &Path) -> io::Result<u64> {
    let mut total = 0;
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let kind = entry.file_type()?;
        if kind.is_dir() {
            total += dir_size(&entry.path())?;
        } else if kind.is_file() {
            total += entry.metadata()?.len();
        }
    }
    Ok(total)
}

/// The median; the mean of the middle two for an even count. `None` when empty or
/// when a value is NaN.
pub fn median(values: &[f64]) -> Option<f64> {
    if values.is_empty() || values.iter().any(|v| v.is_nan()) {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let mid = v.len() / 2;
    Some(if v.len() % 2 == 1 { v[mid] } else { (v[mid - 1] + v[mid]) / 2.0 })
}

/// Median of integers, rounded down for an even count.
pub fn median_u64(values: &[u64]) -> Option<u64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_unstable();
    let mid = v.len() / 2;
    Some(if v.len() % 2 == 1 {
        v[mid]
    } else {
        v[mid - 1] / 2 + v[mid] / 2 + (v[mid - 1] % 2 + v[mid] % 2) / 2
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_of_odd_even_and_empty_sets() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&[7.5]), Some(7.5));
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[1.0, f64::NAN]), None);
        assert_eq!(median_u64(&[5, 1, 9]), Some(5));
        assert_eq!(median_u64(&[1, 4]), Some(2));
        assert_eq!(median_u64(&[3, 4]), Some(3));
        assert_eq!(median_u64(&[u64::MAX, u64::MAX]), Some(u64::MAX));
        assert_eq!(median_u64(&[]), None);
    }

    #[test]
    fn proc_fields_parse_in_bytes() {
        let status = "Name:\tvoxstream\nVmPeak:\t  204800 kB\nVmHWM:\t   51200 kB\nThreads:\t3\n";
        assert_eq!(proc_kib_field(status, "VmHWM"), Some(51200 * 1024));
        assert_eq!(proc_kib_field(status, "VmPeak"), Some(204800 * 1024));
        assert_eq!(proc_kib_field(status, "Threads"), Some(3));
        assert_eq!(proc_kib_field(status, "VmRSS"), None);
        // A key that is only a prefix of another must not match it.
        assert_eq!(proc_kib_field(status, "Vm"), None);
        assert_eq!(proc_kib_field("MemTotal: 12 MB\n", "MemTotal"), None);
    }

    #[test]
    fn own_peak_rss_is_read_from_proc() {
        let hwm = own_peak_rss_bytes().expect("Linux /proc/self/status has VmHWM");
        assert!(hwm > 1 << 20, "{hwm}");
    }

    #[test]
    fn child_peak_rss_and_exit_status_are_measured() {
        let dir = tempfile::tempdir().unwrap();
        // dd reads into one 64 MiB buffer, so its peak RSS is at least that.
        let run = run_child(
            Command::new("dd").args(["if=/dev/zero", "of=/dev/null", "bs=64M", "count=1"]),
            &dir.path().join("dd"),
        )
        .unwrap();
        assert!(run.succeeded(), "{}", run.failure());
        assert!(run.peak_rss_bytes >= 64 << 20, "{}", run.peak_rss_bytes);
        assert!(run.peak_rss_bytes < 1 << 30, "{}", run.peak_rss_bytes);
        assert!(run.stderr.contains("records in"), "{}", run.stderr);
        assert!(run.wall_seconds > 0.0);

        let run =
            run_child(Command::new("sh").args(["-c", "echo hi; echo oops >&2; exit 3"]), dir.path()).unwrap();
        assert!(!run.succeeded());
        assert_eq!((run.exit_code, run.signal), (Some(3), None));
        assert_eq!(run.stdout, "hi\n");
        assert!(run.failure().starts_with("exit code 3: oops"), "{}", run.failure());

        let run = run_child(Command::new("sh").args(["-c", "kill -9 $$"]), dir.path()).unwrap();
        assert_eq!((run.exit_code, run.signal), (None, Some(9)));
        assert!(run.failure().contains("signal 9"));
    }

    #[test]
    fn dir_size_sums_nested_files() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("a"), [0u8; 100]).unwrap();
        std::fs::create_dir_all(dir.path().join("b/c")).unwrap();
        std::fs::write(dir.path().join("b/c/d"), [0u8; 23]).unwrap();
        std::fs::write(dir.path().join("b/e"), []).unwrap();
        assert_eq!(dir_size(dir.path()).unwrap(), 123);
        assert!(dir_size(&dir.path().join("missing")).is_err());
    }

    #[test]
    fn maxrss_is_kibibytes() {
        assert_eq!(maxrss_to_bytes(2), 2048);
        assert_eq!(maxrss_to_bytes(-1), 0);
    }
}
