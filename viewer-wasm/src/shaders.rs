//! The WGSL sources, kept once in the repository's `shaders/` directory and
//! compiled into the viewer for both targets.

pub const EXPAND_WGSL: &str = include_str!("../../shaders/expand.wgsl");
pub const FACE_ARENA_WGSL: &str = include_str!("../../shaders/face_arena.wgsl");
pub const FRAME_WGSL: &str = include_str!("../../shaders/frame.wgsl");
pub const SCREEN_WGSL: &str = include_str!("../../shaders/screen.wgsl");
pub const VOXEL_WGSL: &str = include_str!("../../shaders/voxel.wgsl");
pub const AO_WGSL: &str = include_str!("../../shaders/ao.wgsl");
pub const DEPTH_REDUCE_WGSL: &str = include_str!("../../shaders/depth_reduce.wgsl");
pub const AO_TRACE_WGSL: &str = include_str!("../../shaders/ao_trace.wgsl");
pub const AO_UPSAMPLE_WGSL: &str = include_str!("../../shaders/ao_upsample.wgsl");
pub const AO_RETRACE_WGSL: &str = include_str!("../../shaders/ao_retrace.wgsl");
pub const AO_TEMPORAL_WGSL: &str = include_str!("../../shaders/ao_temporal.wgsl");
pub const AO_COMPOSITE_WGSL: &str = include_str!("../../shaders/ao_composite.wgsl");
pub const CLIPMAP_CLEAR_WGSL: &str = include_str!("../../shaders/clipmap_clear.wgsl");
pub const CLIPMAP_SPLAT_WGSL: &str = include_str!("../../shaders/clipmap_splat.wgsl");
pub const CLIPMAP_TEXELS_WGSL: &str = include_str!("../../shaders/clipmap_texels.wgsl");

/// Every file in `shaders/`, by name (a test checks that this list is complete).
pub const SHADER_FILES: &[(&str, &str)] = &[
    ("expand.wgsl", EXPAND_WGSL),
    ("face_arena.wgsl", FACE_ARENA_WGSL),
    ("frame.wgsl", FRAME_WGSL),
    ("screen.wgsl", SCREEN_WGSL),
    ("voxel.wgsl", VOXEL_WGSL),
    ("ao.wgsl", AO_WGSL),
    ("ao_trace.wgsl", AO_TRACE_WGSL),
    ("ao_upsample.wgsl", AO_UPSAMPLE_WGSL),
    ("ao_retrace.wgsl", AO_RETRACE_WGSL),
    ("ao_temporal.wgsl", AO_TEMPORAL_WGSL),
    ("ao_composite.wgsl", AO_COMPOSITE_WGSL),
    ("depth_reduce.wgsl", DEPTH_REDUCE_WGSL),
    ("clipmap_clear.wgsl", CLIPMAP_CLEAR_WGSL),
    ("clipmap_splat.wgsl", CLIPMAP_SPLAT_WGSL),
    ("clipmap_texels.wgsl", CLIPMAP_TEXELS_WGSL),
];

/// The AO's full-screen passes, one shader (and one module) a pass, in frame order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AoPass {
    /// Cone tracing at 1/f resolution (ao_trace.wgsl with ao.wgsl).
    Trace,
    /// Joint bilateral upsampling to full resolution (ao_upsample.wgsl with
    /// ao.wgsl: it traces the pixels no traced texel matches).
    Upsample,
    /// The pixels the upsample could not match, traced at full resolution
    /// (ao_retrace.wgsl with ao.wgsl; indirect, from the upsample's queue).
    Retrace,
    /// Reprojection and exponential accumulation (ao_temporal.wgsl).
    Temporal,
    /// Colour × V into the frame's target (ao_composite.wgsl).
    Composite,
}

impl AoPass {
    pub const ALL: [AoPass; 5] =
        [AoPass::Trace, AoPass::Upsample, AoPass::Retrace, AoPass::Temporal, AoPass::Composite];

    /// The entry point: a compute one for the passes that write a texture of
    /// their own, the fragment one of a full-screen triangle (`vs_fullscreen`)
    /// for the composite, which writes the frame's target.
    pub fn entry_point(self) -> &'static str {
        match self {
            AoPass::Trace => "cs_trace",
            AoPass::Upsample => "cs_upsample",
            AoPass::Retrace => "cs_retrace",
            AoPass::Temporal => "cs_temporal",
            AoPass::Composite => "fs_composite",
        }
    }

    /// The passes that run only with AO on (the composite runs without it
    /// too): their GPU time is what the AO costs a frame.
    pub const AO_ONLY: [AoPass; 4] = [AoPass::Trace, AoPass::Upsample, AoPass::Retrace, AoPass::Temporal];

    /// Whether a timed pass's label is one of [`AoPass::AO_ONLY`].
    pub fn is_ao_only_label(label: &str) -> bool {
        Self::AO_ONLY.iter().any(|p| p.entry_point() == label)
    }

    /// Whether the pass runs in compute (every pass but the composite).
    pub fn is_compute(self) -> bool {
        self != AoPass::Composite
    }

    /// The pass's module: frame.wgsl and screen.wgsl, then its own file
    /// (the trace and upsample passes with ao.wgsl before it).
    pub fn module_source(self) -> String {
        match self {
            AoPass::Trace => {
                let (ao, trace) = trace_sources();
                format!("{FRAME_WGSL}\n{SCREEN_WGSL}\n{ao}\n{trace}")
            }
            AoPass::Upsample => {
                let (ao, _) = trace_sources();
                let upsample = dev_file("ao_upsample.wgsl", false)
                    .unwrap_or(std::borrow::Cow::Borrowed(AO_UPSAMPLE_WGSL));
                format!("{FRAME_WGSL}\n{SCREEN_WGSL}\n{ao}\n{upsample}")
            }
            AoPass::Retrace => {
                let (ao, _) = trace_sources();
                format!("{FRAME_WGSL}\n{SCREEN_WGSL}\n{ao}\n{AO_RETRACE_WGSL}")
            }
            AoPass::Temporal => format!("{FRAME_WGSL}\n{SCREEN_WGSL}\n{AO_TEMPORAL_WGSL}"),
            AoPass::Composite => format!("{FRAME_WGSL}\n{SCREEN_WGSL}\n{AO_COMPOSITE_WGSL}"),
        }
    }
}

/// Environment variable (native builds only) naming a directory whose
/// `ao.wgsl` and `ao_trace.wgsl` replace the built-in ones when a trace (or
/// upsample) pipeline is created, and whose `voxel.wgsl` and
/// `ao_upsample.wgsl`, where it holds them, replace the draw's and the
/// upsample's: to try a change to the tracer or the shading without
/// rebuilding (a release build takes minutes), and for tests whose negative
/// control is a deliberately different shader (`tests/tests/ao_axis_opacity.rs`,
/// `tests/tests/ao_winding.rs`).
pub const DEV_AO_WGSL_ENV: &str = "VOXSTREAM_DEV_AO_WGSL";

/// The trace pass's ao.wgsl and ao_trace.wgsl: the built-in ones, or those in
/// [`DEV_AO_WGSL_ENV`]'s directory (a file that cannot be read is a panic
/// naming it: a developer asked for it).
fn trace_sources() -> (std::borrow::Cow<'static, str>, std::borrow::Cow<'static, str>) {
    let read = |name, built_in| dev_file(name, true).unwrap_or(std::borrow::Cow::Borrowed(built_in));
    (read("ao.wgsl", AO_WGSL), read("ao_trace.wgsl", AO_TRACE_WGSL))
}

/// `name` from [`DEV_AO_WGSL_ENV`]'s directory (native builds, with the
/// variable set): always when `required`, else where the directory holds
/// it. A file that cannot be read is a panic naming it.
fn dev_file(name: &str, required: bool) -> Option<std::borrow::Cow<'static, str>> {
    #[cfg(not(target_arch = "wasm32"))]
    if let Some(dir) = std::env::var_os(DEV_AO_WGSL_ENV) {
        let path = std::path::Path::new(&dir).join(name);
        if required || path.is_file() {
            let text = std::fs::read_to_string(&path)
                .unwrap_or_else(|e| panic!("{DEV_AO_WGSL_ENV}: reading {}: {e}", path.display()));
            return Some(std::borrow::Cow::Owned(text));
        }
    }
    let _ = (name, required);
    None
}

/// The compute module that expands voxels into face records: face_arena.wgsl then expand.wgsl.
pub fn expand_module_source() -> String {
    format!("{FACE_ARENA_WGSL}\n{EXPAND_WGSL}")
}

/// The draw module: frame.wgsl, face_arena.wgsl, then voxel.wgsl (WGSL has no includes), or the
/// voxel.wgsl in [`DEV_AO_WGSL_ENV`]'s directory where it holds one (the
/// shading's negative controls; ao.wgsl and ao_trace.wgsl must be there too).
pub fn voxel_module_source() -> String {
    let voxel = dev_file("voxel.wgsl", false).unwrap_or(std::borrow::Cow::Borrowed(VOXEL_WGSL));
    format!("{FRAME_WGSL}\n{FACE_ARENA_WGSL}\n{voxel}")
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;

    /// Parses and validates like wgpu's native backends do. The browser backend
    /// hands WGSL straight to the browser, so this is where errors surface first.
    fn validate(name: &str, source: &str) -> naga::Module {
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{name} does not parse:\n{}", e.emit_to_string(source)));
        naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::empty())
            .validate(&module)
            .unwrap_or_else(|e| panic!("{name} does not validate:\n{}", e.emit_to_string(source)));
        module
    }

    fn entry_points(module: &naga::Module) -> Vec<(String, naga::ShaderStage)> {
        module.entry_points.iter().map(|e| (e.name.clone(), e.stage)).collect()
    }

    #[test]
    fn every_pipeline_module_validates_with_naga() {
        let expand = validate("face_arena.wgsl + expand.wgsl", &expand_module_source());
        assert_eq!(entry_points(&expand), vec![("expand_faces".to_string(), naga::ShaderStage::Compute)]);
        let reduce = validate("depth_reduce.wgsl", DEPTH_REDUCE_WGSL);
        assert_eq!(entry_points(&reduce), vec![("reduce_depth".to_string(), naga::ShaderStage::Compute)]);
        let clear = validate("clipmap_clear.wgsl", CLIPMAP_CLEAR_WGSL);
        assert_eq!(entry_points(&clear), vec![("clear_cells".to_string(), naga::ShaderStage::Compute)]);
        let splat = validate("clipmap_splat.wgsl", CLIPMAP_SPLAT_WGSL);
        assert_eq!(entry_points(&splat), vec![("splat_block".to_string(), naga::ShaderStage::Compute)]);
        let texels = validate("clipmap_texels.wgsl", CLIPMAP_TEXELS_WGSL);
        assert_eq!(entry_points(&texels), vec![("copy_texels".to_string(), naga::ShaderStage::Compute)]);
        let voxel = validate("frame.wgsl + face_arena.wgsl + voxel.wgsl", &voxel_module_source());
        assert_eq!(
            entry_points(&voxel),
            vec![
                ("vs_main".to_string(), naga::ShaderStage::Vertex),
                ("fs_gbuffer".to_string(), naga::ShaderStage::Fragment),
                ("fs_fade".to_string(), naga::ShaderStage::Fragment),
            ]
        );
        for pass in AoPass::ALL {
            let module = validate(pass.entry_point(), &pass.module_source());
            let stage =
                if pass.is_compute() { naga::ShaderStage::Compute } else { naga::ShaderStage::Fragment };
            assert_eq!(
                entry_points(&module),
                vec![
                    ("vs_fullscreen".to_string(), naga::ShaderStage::Vertex),
                    (pass.entry_point().to_string(), stage),
                ]
            );
        }
    }

    #[test]
    fn every_file_in_the_shader_directory_is_compiled_in() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shaders");
        let mut on_disk: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".wgsl"))
            .collect();
        on_disk.sort();
        let mut listed: Vec<String> = SHADER_FILES.iter().map(|(n, _)| n.to_string()).collect();
        listed.sort();
        assert_eq!(on_disk, listed, "shaders/ and SHADER_FILES disagree");
        for (name, source) in SHADER_FILES {
            assert_eq!(std::fs::read_to_string(dir.join(name)).unwrap(), *source, "{name} is stale");
        }
    }

    #[test]
    fn a_broken_shader_is_caught() {
        let broken = AoPass::Trace.module_source().replace("fn ambient_visibility", "fn ambient_visibilty");
        assert!(naga::front::wgsl::parse_str(&broken).is_err(), "a missing function must not validate");
    }
}
