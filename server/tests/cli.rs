//! The `voxstream` binary: bad input gives a message naming the problem and a non-zero exit.

use std::process::Command;

fn voxstream(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_voxstream")).args(args).output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into(),
        String::from_utf8_lossy(&out.stderr).into(),
    )
}

#[test]
fn bad_inputs_fail_with_a_clear_message() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let store = store.to_str().unwrap();
    let cases: Vec<(String, &str)> = vec![
        (dir.path().join("missing.obj").display().to_string(), "cannot read"),
        (write(&dir, "notes.txt", b"hello"), "unsupported mesh format"),
        (write(&dir, "empty.obj", b"# nothing\n"), "no triangles"),
        (write(&dir, "flat.obj", b"v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n"), "no valid triangle"),
        (
            write(
                &dir,
                "trunc.ply",
                b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n",
            ),
            "not a valid ply",
        ),
        (write(&dir, "nan.obj", b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"), "no valid triangle"),
    ];
    for (input, expected) in cases {
        let (ok, _, err) = voxstream(&["build", &input, "--out", store]);
        assert!(!ok, "{input} succeeded");
        assert!(err.contains(expected), "{input}: expected {expected:?} in {err:?}");
    }
    let good = write(&dir, "tri.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    let (ok, _, err) = voxstream(&["build", &good, "--out", store, "--resolution", "300"]);
    assert!(!ok && err.contains("power of two"), "{err}");
    let (ok, _, err) = voxstream(&["build", &good, "--out", store, "--name", "../etc"]);
    assert!(!ok && err.contains("scene id"), "{err}");
    assert!(!std::path::Path::new(store).join("tri").exists());

    let (ok, out, err) = voxstream(&["build", &good, "--out", store, "--resolution", "64"]);
    assert!(ok, "{err}");
    assert!(out.contains("built scene \"tri\""), "{out}");
}

fn write(dir: &tempfile::TempDir, name: &str, bytes: &[u8]) -> String {
    let p = dir.path().join(name);
    std::fs::write(&p, bytes).unwrap();
    p.display().to_string()
}
