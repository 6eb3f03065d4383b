//! The WGSL sources, kept once in the repository's `shaders/` directory and
//! compiled into the viewer for both targets.

pub const EXPAND_WGSL: &str = include_str!("../../shaders/expand.wgsl");
pub const VOXEL_WGSL: &str = include_str!("../../shaders/voxel.wgsl");
pub const AO_WGSL: &str = include_str!("../../shaders/ao.wgsl");
pub const DEPTH_REDUCE_WGSL: &str = include_str!("../../shaders/depth_reduce.wgsl");

/// Every file in `shaders/`, by name (a test checks that this list is complete).
pub const SHADER_FILES: &[(&str, &str)] = &[
    ("expand.wgsl", EXPAND_WGSL),
    ("voxel.wgsl", VOXEL_WGSL),
    ("ao.wgsl", AO_WGSL),
    ("depth_reduce.wgsl", DEPTH_REDUCE_WGSL),
];

/// The compute module that expands voxels into face records.
pub fn expand_module_source() -> &'static str {
    EXPAND_WGSL
}

/// The draw module: voxel.wgsl with the ambient-occlusion functions of ao.wgsl
/// appended (WGSL has no includes).
pub fn voxel_module_source() -> String {
    format!("{VOXEL_WGSL}\n{AO_WGSL}")
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
        let expand = validate("expand.wgsl", expand_module_source());
        assert_eq!(entry_points(&expand), vec![("expand_faces".to_string(), naga::ShaderStage::Compute)]);
        let reduce = validate("depth_reduce.wgsl", DEPTH_REDUCE_WGSL);
        assert_eq!(entry_points(&reduce), vec![("reduce_depth".to_string(), naga::ShaderStage::Compute)]);
        let voxel = validate("voxel.wgsl + ao.wgsl", &voxel_module_source());
        assert_eq!(
            entry_points(&voxel),
            vec![
                ("vs_main".to_string(), naga::ShaderStage::Vertex),
                ("fs_main".to_string(), naga::ShaderStage::Fragment),
                ("fs_fade".to_string(), naga::ShaderStage::Fragment),
                ("fs_gbuffer".to_string(), naga::ShaderStage::Fragment)
            ]
        );
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
        let broken = voxel_module_source().replace("fn ambient_visibility", "fn ambient_visibilty");
        assert!(naga::front::wgsl::parse_str(&broken).is_err(), "a missing function must not validate");
    }
}
