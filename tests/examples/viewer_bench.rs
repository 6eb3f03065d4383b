//! Streaming bench for the viewer, native (lavapipe or a GPU): streams a
//! stored scene frame by frame as the browser would (pages, then blocks by
//! projected error, 6 requests started per frame as in the browser, whose
//! answers arrive before the next frame: a fast network) and prints one JSON line
//! per measurement. Numbers go to docs/streaming.md; nothing here asserts.
//!
//!   cargo run -p voxstream-e2e --example viewer_bench -- <store>/<scene> [default|inside|close] [WxH]
//!
//! - converge: bytes fetched, frames and wall time to the first image and to
//!   a converged view (nothing left to fetch or upload), at 1 px, with
//!   occlusion culling and without (the savings: bytes and faces drawn).
//! - `--bytes-only`: the bytes the view needs by frustum and error alone, and
//!   within the default budget (no frames drawn, so fast at any size).
//! - `--budget-only`: just the budget path; `--culled-only`: no run without culling.
//! - `--png <file>`: also save the converged view with occlusion culling.
//! - `--oracle`: also the most block-level occlusion culling could save on the
//!   view (the drawn blocks with no pixel on screen, from the G-buffer).
//! - budget: a scripted orbit-and-zoom path with a 64 MiB budget: the most
//!   resident bytes ÷ budget.
//! - `--main-thread`: each streaming frame's main-thread CPU time (Linux's
//!   per-thread schedstat, so time spent waiting for the GPU does not count),
//!   with uploads paced as the browser paces them and the scene's phase
//!   clock running: the longest, the median and the frames over 4 ms, and
//!   the longest each phase took. The viewer's own share of the browser's
//!   longest main-thread task, natively.
//! - `--frame-times N`: also N frames of the converged view (with occlusion
//!   culling) with AO and N without: median wall time and, where the adapter
//!   has timestamp queries, each pass's median GPU time; and, while streaming,
//!   the GPU time of the longest frame (uploads' expansion and the clipmap's
//!   update included).

use std::path::Path;
use std::time::Instant;

use voxstream_format::BlockKey;
use voxstream_viewer::OrbitCamera;
use voxstream_viewer::offscreen::{Offscreen, RenderOptions};

struct Converged {
    bytes: u64,
    faces: u64,
    blocks: u32,
    frames: usize,
    first_image_ms: f64,
    converged_ms: f64,
    peak: u64,
    budget: u64,
    culled_occlusion: u32,
    /// The most GPU time one streaming frame took (all its timed passes), ms.
    longest_gpu_frame_ms: Option<f64>,
    /// Each frame's main-thread CPU time, ms (where the OS says).
    frame_cpu_ms: Vec<f64>,
}

/// This thread's CPU time so far, ms: the first field of Linux's
/// /proc/thread-self/schedstat (ns on a CPU); None elsewhere.
fn thread_cpu_ms() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    Some(text.split_whitespace().next()?.parse::<f64>().ok()? / 1e6)
}

/// Milliseconds since the first call: the scene's phase clock natively.
fn bench_clock() -> f64 {
    static START: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    START.get_or_init(Instant::now).elapsed().as_secs_f64() * 1e3
}

/// `--main-thread`: the frames' CPU times and the scene's longest phases (one JSON line).
fn print_main_thread(o: &Offscreen, scene: &Path, kind: &str, (w, h): (u32, u32), c: &Converged) {
    let mut ms = c.frame_cpu_ms.clone();
    ms.sort_by(f64::total_cmp);
    let median = ms.get(ms.len() / 2).copied().unwrap_or(f64::NAN);
    let longest = ms.last().copied().unwrap_or(f64::NAN);
    let over = ms.iter().filter(|&&m| m > 4.0).count();
    let total: f64 = ms.iter().sum();
    let phases: Vec<String> =
        o.scene.stats.longest_phases_ms.iter().map(|(k, v)| format!("{k:?}:{v:.3}")).collect();
    println!(
        "{{\"measure\":\"main_thread\",\"scene\":{:?},\"view\":{kind:?},\"size\":\"{w}x{h}\",\"frames\":{},\
         \"longest_frame_cpu_ms\":{longest:.3},\"median_frame_cpu_ms\":{median:.3},\"frames_over_4ms\":{over},\
         \"frames_cpu_ms\":{total:.1},\"longest_traversal_ms\":{:.3},\"longest_phases_ms\":{{{}}},\"adapter\":{:?}}}",
        scene.display().to_string(),
        ms.len(),
        o.scene.stats.longest_traversal_ms,
        phases.join(","),
        o.adapter_name()
    );
}

fn view(offscreen: &Offscreen, kind: &str) -> OrbitCamera {
    let mut c = offscreen.scene.camera;
    // The browser's ?view=x,y,z,yaw,pitch,distance.
    if let Some(v) = kind.strip_prefix("view=") {
        assert!(c.apply_url(v), "bad view {v:?}");
        return c;
    }
    match kind {
        // Eye near the middle of the scene, looking along the default direction.
        "inside" => {
            c.distance = c.scene_radius * 0.02;
        }
        "close" => {
            c.distance *= 0.3;
        }
        _ => {}
    }
    c
}

fn stream(offscreen: &mut Offscreen, max_frames: usize) -> Converged {
    let start = Instant::now();
    let mut first_image_ms = None;
    let mut frames = 0;
    let mut last = None;
    let mut longest_gpu = None;
    let mut frame_cpu_ms = Vec::new();
    for _ in 0..max_frames {
        frames += 1;
        let requests = offscreen.scene.start_requests();
        offscreen.fetch(&requests);
        let cpu_from = thread_cpu_ms();
        let frame = offscreen.draw_frame_at(bench_clock()).expect("frame");
        if let (Some(from), Some(to)) = (cpu_from, thread_cpu_ms()) {
            frame_cpu_ms.push(to - from);
        }
        if let Some(passes) = offscreen.last_pass_times().expect("pass times") {
            let total: f64 = passes.iter().map(|p| p.ms).filter(|ms| ms.is_finite()).sum();
            longest_gpu = Some(longest_gpu.map_or(total, |l: f64| l.max(total)));
        }
        if first_image_ms.is_none() && !frame.drawn.is_empty() {
            first_image_ms = Some(start.elapsed().as_secs_f64() * 1e3);
        }
        let done = requests.is_empty() && frame.complete && !offscreen.scene.needs_another_frame();
        last = Some(frame);
        if done {
            break;
        }
    }
    let s = &offscreen.scene.stats;
    let _ = last;
    Converged {
        bytes: s.bytes_fetched,
        faces: s.faces_drawn,
        blocks: s.blocks_drawn,
        frames,
        first_image_ms: first_image_ms.unwrap_or(f64::NAN),
        converged_ms: start.elapsed().as_secs_f64() * 1e3,
        peak: s.peak_resident_bytes,
        budget: s.budget_bytes,
        culled_occlusion: s.culled_occlusion,
        longest_gpu_frame_ms: longest_gpu,
        frame_cpu_ms,
    }
}

/// `--frame-times N`: the converged view's frames with AO and without (one JSON line).
fn print_frame_times(o: &mut Offscreen, scene: &Path, kind: &str, (w, h): (u32, u32), runs: usize) {
    let with = o.time_frames(1.0, runs).expect("frames with AO");
    let without = o.time_frames(0.0, runs).expect("frames without AO");
    let passes = |t: &voxstream_viewer::offscreen::FrameTiming| match &t.gpu_passes {
        Some(p) => format!(
            "{{{}}}",
            p.iter().map(|x| format!("{:?}:{:.4}", x.label, x.ms)).collect::<Vec<_>>().join(",")
        ),
        None => "null".into(),
    };
    let gpu_total = |t: &voxstream_viewer::offscreen::FrameTiming| {
        t.gpu_passes.as_ref().map_or("null".into(), |p| format!("{:.4}", p.iter().map(|x| x.ms).sum::<f64>()))
    };
    println!(
        "{{\"measure\":\"frame_times\",\"scene\":{:?},\"view\":{kind:?},\"size\":\"{w}x{h}\",\"runs\":{runs},\
         \"frame_ms\":{:.3},\"frame_no_ao_ms\":{:.3},\"gpu_frame_ms\":{},\"gpu_frame_no_ao_ms\":{},\
         \"gpu_passes_ms\":{},\"gpu_passes_no_ao_ms\":{},\"faces\":{},\"blocks\":{},\"adapter\":{:?}}}",
        scene.display().to_string(),
        with.cpu_ms,
        without.cpu_ms,
        gpu_total(&with),
        gpu_total(&without),
        passes(&with),
        passes(&without),
        o.scene.stats.faces_drawn,
        o.scene.stats.blocks_drawn,
        o.adapter_name()
    );
}

/// `keys` and all their ancestors up to the `coarsest` level: what a view must
/// fetch to draw them (ancestors stand in while finer blocks load).
fn with_ancestors(
    keys: impl IntoIterator<Item = BlockKey>,
    coarsest: u8,
) -> std::collections::BTreeSet<BlockKey> {
    let mut set = std::collections::BTreeSet::new();
    for k in keys {
        let mut a = k;
        while set.insert(a) && a.level < coarsest {
            a = a.parent();
        }
    }
    set
}

fn flag_value<'a>(args: &'a [String], flag: &str) -> Option<&'a str> {
    args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).map(String::as_str)
}

/// The converged view as drawn, to see what the numbers are about.
fn save_png(o: &Offscreen, path: &Path, (w, h): (u32, u32)) {
    let rgba = o.read_pixels().expect("read the frame back");
    let file = std::io::BufWriter::new(std::fs::File::create(path).expect("create the PNG"));
    let mut encoder = png::Encoder::new(file, w, h);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.write_header().and_then(|mut writer| writer.write_image_data(&rgba)).expect("write the PNG");
}

/// The most any block-level occlusion culling could save on this view: of the
/// blocks the converged view draws without culling, those with no pixel on
/// screen (each surface pixel's position is credited to every drawn block whose
/// bounds, grown by half a voxel, hold it), and the bytes that would then not
/// be needed: the unseen blocks and the ancestors that only they need.
fn print_oracle(o: &mut Offscreen, scene: &Path, kind: &str, (w, h): (u32, u32)) {
    let g = o.render_gbuffer(1).expect("G-buffer");
    let drawn = o.scene.drawn().to_vec();
    let bounds: Vec<([f64; 3], [f64; 3])> = drawn
        .iter()
        .map(|k| {
            let (lo, hi) =
                o.scene.index.block(k).expect("drawn blocks are indexed").bounds.grid_units(k.level);
            let pad = 0.5 * (1u64 << k.level) as f64;
            (lo.map(|v| v - pad), hi.map(|v| v + pad))
        })
        .collect();
    let index: std::collections::HashMap<BlockKey, usize> =
        drawn.iter().enumerate().map(|(i, k)| (*k, i)).collect();
    let levels: std::collections::BTreeSet<u8> = drawn.iter().map(|k| k.level).collect();
    let block_size = o.scene.manifest.block_size as f64;
    let mut seen = vec![false; drawn.len()];
    for (p, n) in g.position_ao.iter().zip(&g.normal) {
        if n[3] < 0.5 {
            continue;
        }
        let p = [p[0] as f64, p[1] as f64, p[2] as f64];
        for &level in &levels {
            // The blocks of this level within half a voxel of the point.
            let (side, pad) = (block_size * (1u64 << level) as f64, 0.5 * (1u64 << level) as f64);
            let range = |a: usize| {
                ((p[a] - pad) / side).floor().max(0.0) as u32..=((p[a] + pad) / side).floor().max(0.0) as u32
            };
            for x in range(0) {
                for y in range(1) {
                    for z in range(2) {
                        let Some(&i) = index.get(&BlockKey { level, x, y, z }) else { continue };
                        let (lo, hi) = bounds[i];
                        seen[i] |= (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
                    }
                }
            }
        }
    }
    let coarsest = o.scene.manifest.coarsest_level();
    let bytes = |keys: std::collections::BTreeSet<BlockKey>| {
        keys.iter().filter_map(|k| o.scene.index.block(k)).map(|e| e.bytes as u64).sum::<u64>()
    };
    let all = bytes(with_ancestors(drawn.iter().copied(), coarsest));
    let visible =
        bytes(with_ancestors(drawn.iter().zip(&seen).filter(|(_, s)| **s).map(|(k, _)| *k), coarsest));
    println!(
        "{{\"measure\":\"occlusion_oracle\",\"scene\":{:?},\"view\":{kind:?},\"size\":\"{w}x{h}\",\"blocks_drawn\":{},\
         \"blocks_seen\":{},\"block_bytes\":{all},\"block_bytes_seen\":{visible},\"most_saved\":{:.3}}}",
        scene.display().to_string(),
        drawn.len(),
        seen.iter().filter(|s| **s).count(),
        1.0 - visible as f64 / all.max(1) as f64
    );
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let scene =
        Path::new(args.first().expect("usage: viewer_bench <scene dir> [default|inside|close] [WxH]"));
    let kind = args.get(1).map_or("default", String::as_str);
    let skip_budget = args.iter().any(|a| a == "--no-budget-path");
    let (w, h) = args
        .get(2)
        .and_then(|s| s.split_once('x'))
        .map(|(w, h)| (w.parse().unwrap(), h.parse().unwrap()))
        .unwrap_or((1920, 1080));
    let manifest_bytes = std::fs::metadata(scene.join("manifest.json")).map_or(0, |m| m.len());
    if args.iter().any(|a| a == "--bytes-only") {
        // No frames: the bytes the view needs (blocks wanted, their ancestors, the pages that
        // lead to them), by frustum and 1 px error alone ("1px": the budget lifted) and as the
        // viewer settles within its default GPU budget ("default-budget": blocks whose
        // refinement would pass it stay coarser, `held_by_budget`).
        for (limit, budget) in [("1px", Some(u64::MAX / 4)), ("default-budget", None)] {
            let mut o = Offscreen::open(scene, &RenderOptions::new(w, h)).expect("open scene");
            if let Some(b) = budget {
                o.scene.set_budget_bytes(b);
            }
            o.scene.camera = view(&o, kind);
            o.load_pages();
            let needed = with_ancestors(o.scene.wanted().to_vec(), o.scene.manifest.coarsest_level());
            let held = o.scene.traversal().held_by_budget;
            // Faces the converged view draws: the wanted blocks' (ancestors are replaced).
            let faces: u64 = o
                .scene
                .wanted()
                .to_vec()
                .iter()
                .filter_map(|k| o.scene.index.block(k))
                .map(|e| e.faces as u64)
                .sum();
            let block_bytes: u64 =
                needed.iter().filter_map(|k| o.scene.index.block(k)).map(|e| e.bytes as u64).sum();
            let page_bytes = o.scene.index.page_bytes_loaded();
            // Per level: [blocks, bytes, of them wanted (the rest are ancestors)].
            let wanted: std::collections::HashSet<_> = o.scene.wanted().iter().copied().collect();
            let mut levels = std::collections::BTreeMap::<u8, [u64; 3]>::new();
            for k in &needed {
                let l = levels.entry(k.level).or_default();
                l[0] += 1;
                l[1] += o.scene.index.block(k).map_or(0, |e| e.bytes as u64);
                l[2] += wanted.contains(k) as u64;
            }
            eprintln!("{limit}: levels (level: [blocks, bytes, wanted]): {levels:?}");
            println!(
                "{{\"measure\":\"bytes_to_converge\",\"limit\":{limit:?},\"scene\":{:?},\"view\":{kind:?},\"size\":\"{w}x{h}\",\"resolution\":{},\"blocks\":{},\"held_by_budget\":{held},\"faces_drawn\":{faces},\"block_bytes\":{block_bytes},\"page_bytes\":{page_bytes},\"manifest_bytes\":{manifest_bytes},\"total\":{}}}",
                scene.display().to_string(),
                o.scene.manifest.grid.resolution,
                needed.len(),
                block_bytes + page_bytes + manifest_bytes
            );
        }
        return;
    }
    let budget_only = args.iter().any(|a| a == "--budget-only");
    let culled_only = args.iter().any(|a| a == "--culled-only");
    for occlusion in [true, false].into_iter().filter(|o| !budget_only && (*o || !culled_only)) {
        let mut o = Offscreen::open(scene, &RenderOptions::new(w, h)).expect("open scene");
        o.scene.camera = view(&o, kind);
        o.scene.occlusion_culling = occlusion;
        // As many in flight per frame as the browser: feedback needs frames to act.
        o.scene.set_max_in_flight(6);
        o.scene.record_bytes_fetched(manifest_bytes);
        let main_thread = args.iter().any(|a| a == "--main-thread");
        if main_thread {
            // As the page: uploads paced to 2 ms of main thread, the phases timed.
            o.scene.pace_uploads(2.0);
            o.scene.clock = bench_clock;
        }
        let c = stream(&mut o, 400);
        if occlusion && main_thread {
            print_main_thread(&o, scene, kind, (w, h), &c);
        }
        // Blocks the converged view finds hidden that were fetched all the same (before their
        // feedback came): what the request order lost.
        let hidden = o.scene.traversal().hidden.clone();
        let hidden_fetched: u64 = hidden
            .iter()
            .filter(|k| o.scene.is_cached(k))
            .filter_map(|k| o.scene.index.block(k))
            .map(|e| e.bytes as u64)
            .sum();
        if let (true, Some(path)) = (occlusion, flag_value(&args, "--png")) {
            save_png(&o, Path::new(path), (w, h));
        }
        if let (true, Some(n)) = (occlusion, flag_value(&args, "--frame-times")) {
            let runs = n.parse().expect("--frame-times takes a frame count");
            print_frame_times(&mut o, scene, kind, (w, h), runs);
        }
        if !occlusion && args.iter().any(|a| a == "--oracle") {
            print_oracle(&mut o, scene, kind, (w, h));
        }
        println!(
            "{{\"measure\":\"converge\",\"scene\":{:?},\"view\":{kind:?},\"size\":\"{w}x{h}\",\"occlusion\":{occlusion},\
             \"bytes\":{},\"faces\":{},\"blocks\":{},\"frames\":{},\"first_image_ms\":{:.0},\"converged_ms\":{:.0},\
             \"peak_resident\":{},\"budget\":{},\"culled_occlusion\":{},\"hidden_fetched_bytes\":{hidden_fetched},\
             \"longest_gpu_frame_ms\":{},\"adapter\":{:?}}}",
            scene.display().to_string(),
            c.bytes,
            c.faces,
            c.blocks,
            c.frames,
            c.first_image_ms,
            c.converged_ms,
            c.peak,
            c.budget,
            c.culled_occlusion,
            c.longest_gpu_frame_ms.map_or("null".into(), |ms| format!("{ms:.4}")),
            o.adapter_name()
        );
    }
    if skip_budget {
        return;
    }
    // The budget path: orbit around and zoom in, 64 MiB.
    let mut o = Offscreen::open(scene, &RenderOptions::new(w, h)).expect("open scene");
    o.scene.set_budget_bytes(64 << 20);
    o.scene.set_max_in_flight(32);
    let start = o.scene.camera;
    let mut worst: f64 = 0.0;
    for i in 0..12 {
        let mut c = start;
        c.orbit(90.0 * i as f32, 15.0 * (i % 4) as f32);
        c.zoom(1.0 - 0.07 * i as f32);
        o.scene.camera = c;
        let r = stream(&mut o, 60);
        worst = worst.max(r.peak as f64 / r.budget as f64);
    }
    println!(
        "{{\"measure\":\"budget_path\",\"scene\":{:?},\"budget\":{},\"max_resident_over_budget\":{worst:.3},\"uploads_refused\":{}}}",
        scene.display().to_string(),
        64u64 << 20,
        o.scene.stats.uploads_refused
    );
}
