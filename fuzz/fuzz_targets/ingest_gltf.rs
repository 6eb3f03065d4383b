#![no_main]
include!("common.rs");

// One reader serves both: it tells GLB from JSON by the magic, so feed every input as each.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    check_ingest(data, MeshFormat::Gltf);
    check_ingest(data, MeshFormat::Glb);
});
