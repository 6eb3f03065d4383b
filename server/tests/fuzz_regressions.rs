//! Inputs the fuzz targets (fuzz/, `bash scripts/fuzz.sh`) found that made a
//! reader panic, minimized and embedded. Each is an invalid mesh: the reader
//! must return an error naming the problem, never panic.

use std::panic::{AssertUnwindSafe, catch_unwind};

use voxstream::pipeline::read::{IngestError, MeshFormat, TriangleMesh, read_mesh_bytes};

fn read_without_panic(bytes: &[u8], format: MeshFormat) -> Result<TriangleMesh, IngestError> {
    match catch_unwind(AssertUnwindSafe(|| read_mesh_bytes(bytes, format))) {
        Ok(r) => r,
        Err(panic) => {
            let message = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            panic!(
                "read_mesh_bytes({format}) panicked: {message}\ninput: {:?}",
                String::from_utf8_lossy(bytes)
            )
        }
    }
}

/// fuzz target ingest_obj: a negative normal index reaching before the first
/// normal underflows inside tobj 4.0.5 (`vn * 3` overflows at lib.rs:1096; a
/// panic wherever overflow checks are on, as in `cargo test` and the fuzz build).
#[test]
fn obj_negative_normal_index_before_the_first_normal_is_an_error() {
    let obj = b"v 0 0 0\nv 0 1 0\nv 0 0 1\nvn 0 0 1\nf 2 3 1/1/-4\n";
    let e = read_without_panic(obj, MeshFormat::Obj).unwrap_err();
    assert!(matches!(e, IngestError::Parse { format: MeshFormat::Obj, .. }), "{e}");
}

/// fuzz target ingest_obj: the same underflow for texture coordinates (`vt * 2`
/// overflows at tobj 4.0.5 lib.rs:1055).
#[test]
fn obj_negative_texcoord_index_before_the_first_texcoord_is_an_error() {
    let obj = b"v 0 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nf 1/-3 2/1 3/1\n";
    let e = read_without_panic(obj, MeshFormat::Obj).unwrap_err();
    assert!(matches!(e, IngestError::Parse { format: MeshFormat::Obj, .. }), "{e}");
}

/// fuzz target ingest_gltf: a primitive whose POSITION names an accessor that
/// does not exist; gltf-json 1.4.1's own validation indexes `root.accessors`
/// with it before checking (mesh.rs:151), called from pipeline/read/gltf.rs `validate`.
#[test]
fn gltf_position_naming_a_missing_accessor_is_an_error() {
    let gltf = br#"{"asset":{"version":"2.0"},"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}]}"#;
    let e = read_without_panic(gltf, MeshFormat::Gltf).unwrap_err();
    assert!(e.to_string().contains("accessor"), "{e}");
    // The same document inside a GLB container takes the same path.
    let mut json = gltf.to_vec();
    json.resize(json.len().next_multiple_of(4), b' ');
    let mut glb = b"glTF".to_vec();
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&(12 + 8 + json.len() as u32).to_le_bytes());
    glb.extend_from_slice(&(json.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json);
    let e = read_without_panic(&glb, MeshFormat::Glb).unwrap_err();
    assert!(e.to_string().contains("accessor"), "{e}");
}
