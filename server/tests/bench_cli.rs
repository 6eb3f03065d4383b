//! `voxstream bench` end to end on tiny inputs: the JSON's shape and its
//! numbers' consistency, not speed (speed is what the bench itself reports).

use std::path::Path;
use std::process::Command;

use serde_json::Value;

fn bench(args: &[&str], work: &Path) -> (bool, Value, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_voxstream"))
        .arg("bench")
        .args(args)
        .arg("--work-dir")
        .arg(work)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let json = serde_json::from_slice(&out.stdout).unwrap_or(Value::Null);
    (out.status.success(), json, stderr)
}

#[test]
fn bench_reports_voxstream_and_meshopt_on_the_koala_and_a_synthetic_scan() {
    let work = tempfile::tempdir().unwrap();
    let koala = concat!(env!("CARGO_MANIFEST_DIR"), "/../data/koala.obj");
    let (koala_64, koala_auto) = (format!("{koala}@64"), format!("{koala}@auto"));
    let (ok, v, stderr) = bench(
        &[
            "--input",
            &koala_64,
            "--input",
            &koala_auto,
            "--synth-triangles",
            "5000",
            "--synth-resolution",
            "128",
            "--runs",
            "2",
            "--threads",
            "1,2",
        ],
        work.path(),
    );
    assert!(ok, "{stderr}");
    assert_eq!(v["config"]["runs"], 2);
    assert!(v["machine"]["cores"].as_u64().unwrap() >= 1);
    let inputs = v["inputs"].as_array().unwrap();
    assert_eq!(inputs.len(), 3);
    let cases: Vec<&str> = inputs.iter().map(|i| i["case"].as_str().unwrap()).collect();
    assert_eq!(cases[..2], ["koala@64", "koala@auto"]);
    assert!(cases[2].starts_with("synth_sphere_5000@128"), "{cases:?}");
    // Each case builds at its own resolution.
    assert_eq!(inputs[0]["voxstream"]["resolution"], 64);
    assert_eq!(inputs[0]["voxstream"]["requested_resolution"], "64");
    assert_eq!(inputs[1]["voxstream"]["requested_resolution"], "auto");
    assert!(inputs[1]["voxstream"]["resolution"].as_u64().unwrap() > 64);
    assert!(inputs[1]["voxstream"]["resolution_reason"].as_str().unwrap().contains("median"));
    assert_eq!(inputs[2]["voxstream"]["resolution"], 128);
    // The peer runs once per mesh; the second koala case reports that run.
    assert_eq!(inputs[0]["meshopt"]["measured_in_case"], "koala@64");
    assert_eq!(inputs[1]["meshopt"], inputs[0]["meshopt"]);
    assert_eq!(inputs[0]["name"], "koala");
    assert_eq!(inputs[0]["triangles"], 99994);
    assert!(inputs[2]["triangles"].as_u64().unwrap() >= 5000);
    for input in inputs {
        let vox = &input["voxstream"];
        for n in ["1", "2"] {
            let t = &vox["threads"][n];
            assert_eq!(t["runs"], 2, "{t}");
            assert_eq!(t["failures"].as_array().unwrap().len(), 0);
            let rate = t["tri_per_s_median"].as_f64().unwrap();
            let tris = input["triangles"].as_f64().unwrap();
            let walls: Vec<f64> =
                t["wall_seconds"].as_array().unwrap().iter().map(|w| w.as_f64().unwrap()).collect();
            // The median rate lies between the rates of the fastest and slowest run.
            let (lo, hi) =
                walls.iter().fold((f64::MAX, 0.0f64), |(l, h), &w| (l.min(tris / w), h.max(tris / w)));
            assert!(rate >= lo * 0.999 && rate <= hi * 1.001, "{rate} {walls:?}");
            assert!(t["peak_rss_bytes_max"].as_u64().unwrap() > 1 << 20);
            let peer = &input["meshopt"]["threads"][n];
            assert_eq!(peer["partitions"].as_u64().unwrap(), n.parse::<u64>().unwrap(), "{peer}");
            assert!(peer["clod_seconds_median"].as_f64().unwrap() > 0.0);
            assert!(peer["peak_rss_bytes_max"].as_u64().unwrap() > 1 << 20);
            assert!(input["ratio_voxstream_over_meshopt"]["tri_per_s"][n].as_f64().unwrap() > 0.0);
        }
        // Size is measured from the published scene on disk.
        let bytes = vox["scene_bytes"].as_f64().unwrap();
        let bpt = vox["bytes_per_triangle"].as_f64().unwrap();
        assert!((bytes / input["triangles"].as_f64().unwrap() - bpt).abs() < 1e-9);
        let voxels = vox["voxels_level0"].as_f64().unwrap();
        assert!(voxels > 0.0);
        assert!((bytes / voxels - vox["bytes_per_level0_voxel"].as_f64().unwrap()).abs() < 1e-9);
        let f = &vox["files"];
        let part = |k: &str| f[k].as_u64().unwrap();
        assert_eq!(
            part("manifest_bytes") + part("page_bytes") + part("block_bytes") + part("other_bytes"),
            bytes as u64
        );
        // Blocks and pages live in packs of PACK_MAX_ITEMS items; the last page layers may close a
        // few more.
        let (blocks, pages) = (vox["blocks"].as_u64().unwrap(), part("pages"));
        let full = (blocks + pages).div_ceil(voxstream::pipeline::write::PACK_MAX_ITEMS as u64);
        assert!((full..=full + 3).contains(&part("block_files")), "a pack per PACK_MAX_ITEMS items: {f}");
        assert!(pages >= 1 || blocks == 1, "{f}");
        assert!(part("block_files") < vox["blocks"].as_u64().unwrap() || vox["blocks"].as_u64() == Some(1));
        assert!(part("manifest_bytes") > 100 && part("manifest_bytes") <= 64 << 10);
        assert_eq!(
            vox["manifest_plus_page_bytes"].as_u64().unwrap(),
            part("manifest_bytes") + part("page_bytes")
        );
        for n in ["1", "2"] {
            let t = &vox["threads"][n];
            let per_thread = voxels / t["wall_seconds_median"].as_f64().unwrap() / n.parse::<f64>().unwrap();
            assert!((t["voxels_per_s_per_thread"].as_f64().unwrap() / per_thread - 1.0).abs() < 1e-9);
        }
        let per_level: u64 =
            vox["blocks_per_level"].as_array().unwrap().iter().map(|b| b.as_u64().unwrap()).sum();
        assert_eq!(per_level, vox["blocks"].as_u64().unwrap());
        assert_eq!(input["meshopt"]["dag"]["level0_triangles"], input["triangles"]);
        assert!(input["goals"]["all_runs_succeeded"].as_bool().unwrap());
    }
    assert!(v["goals"]["tri_per_s_per_core_2M"].is_boolean());
    assert!(v["goals"]["voxels_per_s_per_core_10M"].is_boolean());
    assert!(v["goals"]["peak_rss_within_budget"].is_null());
    // Scratch stores and the synthetic scan are removed afterwards.
    assert_eq!(std::fs::read_dir(work.path()).unwrap().count(), 0);
}

#[test]
fn a_failing_build_is_reported_not_hidden() {
    let work = tempfile::tempdir().unwrap();
    let bad = work.path().join("bad.obj");
    std::fs::write(&bad, "v 0 0 0\nf 1 2 3\n").unwrap();
    let (ok, v, stderr) = bench(
        &["--input", bad.to_str().unwrap(), "--synth-triangles", "0", "--runs", "1", "--threads", "1"],
        work.path(),
    );
    assert!(ok, "{stderr}");
    let input = &v["inputs"][0];
    let failures = input["voxstream"]["threads"]["1"]["failures"].as_array().unwrap();
    assert_eq!(failures.len(), 1);
    assert!(failures[0].as_str().unwrap().contains("exit code 1"), "{failures:?}");
    assert!(input["meshopt"]["skipped"].as_str().unwrap().contains("no voxstream build succeeded"));
    assert_eq!(v["goals"]["all_runs_succeeded"], false);
    assert_eq!(v["goals"]["tri_per_s_per_core_2M"], false);
}

#[test]
fn bad_arguments_are_refused_before_measuring() {
    let work = tempfile::tempdir().unwrap();
    let koala = concat!(env!("CARGO_MANIFEST_DIR"), "/../data/koala.obj");
    for (args, message) in [
        (&["--threads", "0"][..], "thread counts start at 1"),
        (&["--memory-budget", "lots"], "--memory-budget"),
        (&["--input", "/nonexistent/x.ply"], "is not a file"),
        (&["--resolution", "100"], "resolution"),
        (&["--input", "x.ply@100"], "power of two"),
        (&["--input", "x.ply@"], "after the last '@'"),
        (&["--input", "@4096"], "names no file"),
        (&["--synth-resolution", "3"], "--synth-resolution"),
        (&["--single-run-over", "0"], "seconds"),
    ] {
        // A tiny input and no synthetic scan, so a check that failed to refuse could not run long.
        let mut all = vec!["--synth-triangles", "0", "--no-meshopt", "--runs", "1"];
        if !args.iter().any(|a| a.starts_with("--input")) {
            all.extend(["--input", koala]);
        }
        all.extend(args);
        let (ok, _, stderr) = bench(&all, work.path());
        assert!(!ok);
        assert!(stderr.contains(message), "{args:?}: {stderr}");
    }
}

#[test]
fn a_case_listed_twice_is_refused_and_its_resolution_spelled_once() {
    let work = tempfile::tempdir().unwrap();
    let koala = concat!(env!("CARGO_MANIFEST_DIR"), "/../data/koala.obj");
    let at = format!("{koala}@64");
    let base = ["--synth-triangles", "0", "--no-meshopt", "--runs", "1", "--threads", "1"];
    // `koala` at --resolution 64 and `koala@64` are the same case.
    let twice = [&base[..], &["--resolution", "64", "--input", koala, "--input", &at]].concat();
    let (ok, _, stderr) = bench(&twice, work.path());
    assert!(!ok);
    assert!(stderr.contains("listed twice"), "{stderr}");
    // Control: the same mesh at two resolutions is two cases.
    let two = [&base[..], &["--input", koala, "--input", &at]].concat();
    let (ok, v, stderr) = bench(&two, work.path());
    assert!(ok, "{stderr}");
    assert_eq!(v["inputs"].as_array().unwrap().len(), 2);
    assert_eq!(v["config"]["cases"][1].as_str().unwrap(), at);
}
