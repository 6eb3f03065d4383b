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

/// `voxstream publish` writes a static site: the store's packs as they are (`packs/<hash>.vxp`,
/// bytes that hash to that name, no per-block file), every page named `<key>.<hash>`, the
/// manifest as stored, index.html naming the scene and marking the site static; it replaces an
/// earlier publish whole, refuses anything else, and refuses a damaged pack.
#[test]
fn publish_writes_a_static_site_and_refuses_bad_targets() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh =
        write(&dir, "tri.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n");
    let (ok, _, err) = voxstream(&["build", &mesh, "--out", store.to_str().unwrap(), "--resolution", "256"]);
    assert!(ok, "{err}");
    let site = dir.path().join("site");
    let (s, t) = (store.to_str().unwrap(), site.to_str().unwrap());
    let web = concat!(env!("CARGO_MANIFEST_DIR"), "/../viewer-wasm/dist");
    let viewer = if voxstream::http::web::has_embedded_viewer() { vec![] } else { vec!["--web", web] };
    let mut args = vec!["publish", "tri", "--store", s, "--to", t];
    args.extend(&viewer);
    let (ok, out, err) = voxstream(&args);
    assert!(ok, "publish failed: {err}");
    assert!(out.contains("published scene \"tri\""), "{out}");
    let scene = site.join("api/scenes/tri");
    let manifest = std::fs::read(scene.join("manifest")).unwrap();
    assert_eq!(manifest, std::fs::read(store.join("tri/manifest.json")).unwrap());
    let index = std::fs::read_to_string(site.join("index.html")).unwrap();
    assert!(index.contains("<meta name=\"voxstream-scene\" content=\"tri\">"), "{index}");
    assert!(site.join("pkg/voxstream_viewer_bg.wasm").is_file());
    assert!(index.contains("<meta name=\"voxstream-static\" content=\"packs\">"), "{index}");
    let m = voxstream_format::Manifest::from_json(&manifest).unwrap();
    assert!(!scene.join("blocks").exists(), "no per-block files");
    let mut packs = Vec::new();
    for entry in std::fs::read_dir(scene.join("packs")).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_str().unwrap().to_string();
        let hash = name.strip_suffix(".vxp").expect("packs are <hash>.vxp");
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), hash, "{name}");
        assert_eq!(bytes, std::fs::read(store.join("tri/packs").join(&name)).unwrap(), "{name} as stored");
        packs.push(name);
    }
    assert_eq!(packs.len(), std::fs::read_dir(store.join("tri/packs")).unwrap().count(), "every pack");
    assert!(m.block_count() > 0);
    let root_page = m.root_page.as_ref().expect("a scene on 3 levels has a root page");
    let page = scene.join("pages").join(format!("{}.{}", root_page.root, root_page.hash));
    assert_eq!(blake3::hash(&std::fs::read(page).unwrap()).to_hex().as_str(), root_page.hash);
    // Again: the earlier publish is replaced whole, no temp folder stays behind.
    let (ok, _, err) = voxstream(&args);
    assert!(ok, "republish failed: {err}");
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    // Refusals: a folder that is not a publish, an unknown scene, a missing store.
    let precious = dir.path().join("precious");
    std::fs::create_dir(&precious).unwrap();
    std::fs::write(precious.join("thesis.tex"), b"keep me").unwrap();
    for (scene, store, to, expected) in [
        ("tri", s, precious.to_str().unwrap(), "not a voxstream publish"),
        ("nope", s, t, "cannot open scene \"nope\""),
        ("tri", "/nonexistent/store", t, "cannot open scene"),
        ("../x", s, t, "invalid"),
    ] {
        let mut args = vec!["publish", scene, "--store", store, "--to", to];
        args.extend(&viewer);
        let (ok, _, err) = voxstream(&args);
        assert!(!ok, "publish {scene} {store} -> {to} succeeded");
        assert!(err.contains(expected), "expected {expected:?} in {err:?}");
    }
    assert_eq!(std::fs::read(precious.join("thesis.tex")).unwrap(), b"keep me");
    // A truncated pack in the store: the publish fails naming the pack, and the earlier site stays.
    let pack = std::fs::read_dir(store.join("tri/packs")).unwrap().next().unwrap().unwrap().path();
    std::fs::OpenOptions::new().write(true).open(&pack).unwrap().set_len(1).unwrap();
    let (ok, _, err) = voxstream(&args);
    assert!(!ok, "a publish from a truncated pack succeeded");
    let name = pack.file_name().unwrap().to_str().unwrap();
    assert!(err.contains("truncated") && err.contains(name), "{err}");
    assert_eq!(std::fs::read(scene.join("manifest")).unwrap(), manifest, "the earlier publish stays");
    // A pack of the right length with one byte changed fails its hash.
    let good = std::fs::read(site.join("api/scenes/tri/packs").join(name)).unwrap();
    let mut bad = good.clone();
    bad[good.len() / 2] ^= 1;
    std::fs::write(&pack, &bad).unwrap();
    let (ok, _, err) = voxstream(&args);
    assert!(!ok, "a publish from a damaged pack succeeded");
    assert!(err.contains("does not match its hash") && err.contains(name), "{err}");
}

/// Bad object-storage configuration is one clear error and a non-zero exit within seconds, naming
/// the endpoint and the cause and never the secret: no credentials, an endpoint nobody listens
/// on (for publish, serve and build), a malformed bucket URL, and a store URL where only a folder
/// works. Negative control: a
/// `publish --to s3://` that hung on the dead endpoint (connect retries without a deadline) fails
/// the time bound; one that printed the secret fails the last check.
#[test]
fn object_store_misconfiguration_fails_fast_and_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mesh = write(&dir, "tri.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    let (ok, _, err) = voxstream(&["build", &mesh, "--out", store.to_str().unwrap(), "--resolution", "64"]);
    assert!(ok, "{err}");
    let s = store.to_str().unwrap();
    // A port that was free a moment ago: nothing listens there.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let endpoint = format!("http://127.0.0.1:{port}");
    let secret = "very-secret-key-0123456789";
    let run = |env: &[(&str, &str)], args: &[&str]| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_voxstream"));
        cmd.args(args);
        for (k, _) in std::env::vars().filter(|(k, _)| k.starts_with("AWS_")) {
            cmd.env_remove(k);
        }
        cmd.env_remove("VOXSTREAM_S3_ENV_FILE");
        cmd.envs(env.iter().copied());
        let t = std::time::Instant::now();
        let out = cmd.output().unwrap();
        (out.status.success(), String::from_utf8_lossy(&out.stderr).to_string(), t.elapsed())
    };
    let publish = ["publish", "tri", "--store", s, "--to", "s3://scans/site"];
    let (ok, err, _) = run(&[("AWS_ENDPOINT_URL", &endpoint), ("AWS_ALLOW_HTTP", "true")], &publish);
    assert!(!ok && err.contains("no credentials") && err.contains(&endpoint), "{err}");
    let keys = [
        ("AWS_ENDPOINT_URL", endpoint.as_str()),
        ("AWS_ALLOW_HTTP", "true"),
        ("AWS_ACCESS_KEY_ID", "GKtest"),
        ("AWS_SECRET_ACCESS_KEY", secret),
    ];
    let (ok, err, took) = run(&keys, &publish);
    assert!(!ok, "publish to a dead endpoint succeeded");
    assert!(err.contains(&endpoint) && err.contains("scans"), "names the endpoint and bucket: {err}");
    assert!(err.contains("connect"), "names the cause: {err}");
    assert!(took < std::time::Duration::from_secs(30), "took {took:?}: {err}");
    assert!(!err.contains(secret), "the secret was printed: {err}");
    // The same settings from a file.
    let env_file = write(
        &dir,
        "s3.env",
        format!("export AWS_ACCESS_KEY_ID=GKtest\nAWS_SECRET_ACCESS_KEY={secret}\n").as_bytes(),
    );
    let (ok, err, _) = run(
        &[("AWS_ENDPOINT_URL", &endpoint), ("AWS_ALLOW_HTTP", "true"), ("VOXSTREAM_S3_ENV_FILE", &env_file)],
        &publish,
    );
    assert!(!ok && !err.contains("no credentials") && err.contains(&endpoint), "{err}");
    for (args, expected) in [
        (vec!["publish", "tri", "--store", s, "--to", "s3://A_B/x"], "bucket name"),
        (vec!["publish", "tri", "--store", s, "--to", "gs://bucket/x"], "not supported"),
        (vec!["publish", "tri", "--store", "s3://scans/store", "--to", "site"], "not supported yet"),
        (vec!["serve", "--store", "s3://scans/store", "--addr", "127.0.0.1:0"], "connect"),
        (vec!["build", &mesh, "--out", "s3://scans/store"], "connect"),
    ] {
        let (ok, err, took) = run(&keys, &args);
        assert!(!ok && err.contains(expected), "{args:?}: expected {expected:?} in {err:?}");
        assert!(took < std::time::Duration::from_secs(30), "{args:?} took {took:?}: {err}");
        assert!(!err.contains(secret), "the secret was printed: {err}");
    }
}

/// `voxstream render` without AO flags renders the viewer's own default
/// setting (what a still view converges to in the browser), and each flag
/// overrides its part (the control: the same command with flags differs).
#[test]
fn a_plain_render_shows_the_viewers_default_ao() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    // A box 2 units a side: 12 triangles.
    let cube = b"v 0 0 0\nv 2 0 0\nv 2 2 0\nv 0 2 0\nv 0 0 2\nv 2 0 2\nv 2 2 2\nv 0 2 2\n\
f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 4 7 3\nf 4 8 7\nf 1 5 8\nf 1 8 4\nf 2 3 7\nf 2 7 6\n";
    let mesh = write(&dir, "cube.obj", cube);
    let (ok, _, err) = voxstream(&[
        "build",
        &mesh,
        "--out",
        store.to_str().unwrap(),
        "--name",
        "cube",
        "--resolution",
        "64",
    ]);
    assert!(ok, "build: {err}");
    let camera = write(
        &dir,
        "camera.json",
        br#"{"eye":[5,4,6],"target":[1,1,1],"up":[0,1,0],"fov_y_deg":40,"near":0.05,"far":50}"#,
    );
    let scene = store.join("cube");
    let render = |out: &str, extra: &[&str]| -> serde_json::Value {
        let out = dir.path().join(out);
        let mut args = vec![
            "render",
            "--scene",
            scene.to_str().unwrap(),
            "--camera",
            &camera,
            "--width",
            "32",
            "--height",
            "24",
            "--timing-runs",
            "0",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let (ok, _, err) = voxstream(&args);
        assert!(ok, "render {extra:?}: {err}");
        serde_json::from_slice(&std::fs::read(out.join("render.json")).unwrap()).unwrap()
    };
    let plain = render("plain", &[]);
    let d = voxstream_viewer::ao::AoSettings::default();
    let ao = &plain["ao"];
    assert_eq!(ao["cones"], d.cones, "{ao}");
    assert_eq!(ao["step"], d.step as f64, "{ao}");
    assert_eq!(ao["trace_downscale"], d.trace_downscale, "{ao}");
    assert_eq!(ao["frames"], d.temporal_frames, "{ao}");
    assert_eq!(ao["empty_skip"], d.empty_skip, "{ao}");
    let flagged = render(
        "flagged",
        &["--cones", "16", "--step", "0.5", "--ao-downscale", "1", "--ao-frames", "1", "--empty-skip"],
    );
    let ao = &flagged["ao"];
    assert_eq!((ao["cones"].as_u64(), ao["step"].as_f64()), (Some(16), Some(0.5)), "{ao}");
    assert_eq!((ao["trace_downscale"].as_u64(), ao["frames"].as_u64()), (Some(1), Some(1)), "{ao}");
    assert_eq!(ao["empty_skip"], true, "{ao}");
}
