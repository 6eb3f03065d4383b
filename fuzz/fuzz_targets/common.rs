// Shared by the ingest targets (included with `include!`, as each target is its own crate root).
use voxstream::pipeline::read::{MeshFormat, read_mesh_bytes};

/// Reads `data` as `format` and checks the reader's promise: every index is in range.
/// Errors are fine; panics, aborts, out-of-memory and out-of-range indices are findings.
fn check_ingest(data: &[u8], format: MeshFormat) {
    if let Ok(mesh) = read_mesh_bytes(data, format) {
        let n = mesh.positions.len();
        assert!(!mesh.triangles.is_empty(), "{format}: Ok with no triangles");
        for t in &mesh.triangles {
            assert!(t.iter().all(|&i| (i as usize) < n), "{format}: index out of range in {t:?} ({n} vertices)");
        }
    }
}
