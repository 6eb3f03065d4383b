//! Uploaded meshes on disk, before and while they are built.
//!
//! `<store>/.uploads/<id>/upload.json` describes an upload ([`UploadRecord`],
//! written by temp file + rename) and `<store>/.uploads/<id>/data` receives its
//! bytes; the offset of a resumable upload is the length of `data`. A complete
//! upload's `data` is renamed to `<scene-id>.<format>` (the name the manifest
//! records as its source) and a build job of the same id takes it over; the
//! job removes the directory when it ends.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::pipeline::read::MeshFormat;

pub const UPLOADS_DIR: &str = ".uploads";
const RECORD: &str = "upload.json";
const DATA: &str = "data";

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct UploadRecord {
    pub id: String,
    /// Total bytes announced (tus `Upload-Length`); `None` for a plain POST
    /// without Content-Length.
    pub length: Option<u64>,
    pub file_name: Option<String>,
    pub content_type: Option<String>,
    pub scene_id: String,
    /// `None`: auto.
    #[serde(default)]
    pub resolution: Option<u32>,
    pub topology: String,
    /// Replace an existing scene of the same id.
    pub replace: bool,
    /// A tus upload survives restarts and dropped connections; a plain POST does not.
    pub resumable: bool,
    pub created_at: u64,
}

/// Upload directories of one store.
#[derive(Debug, Clone)]
pub struct Uploads {
    dir: PathBuf,
}

pub fn write_json_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let tmp = path.with_extension("json.tmp");
    {
        let mut f = fs::File::create(&tmp)?;
        io::Write::write_all(&mut f, bytes)?;
        f.sync_all()?;
    }
    fs::rename(&tmp, path)?;
    if let Some(parent) = path.parent() {
        fs::File::open(parent)?.sync_all()?;
    }
    Ok(())
}

impl Uploads {
    pub fn new(store: &Path) -> Self {
        Self { dir: store.join(UPLOADS_DIR) }
    }

    pub fn upload_dir(&self, id: &str) -> PathBuf {
        self.dir.join(id)
    }

    pub fn data_path(&self, id: &str) -> PathBuf {
        self.dir.join(id).join(DATA)
    }

    /// Creates the directory, the record and an empty data file.
    pub fn create(&self, record: &UploadRecord) -> io::Result<()> {
        let dir = self.upload_dir(&record.id);
        fs::create_dir_all(&dir)?;
        fs::File::create(dir.join(DATA))?;
        self.save(record)
    }

    pub fn save(&self, record: &UploadRecord) -> io::Result<()> {
        let json = serde_json::to_vec_pretty(record).expect("upload record serialises");
        write_json_atomic(&self.upload_dir(&record.id).join(RECORD), &json)
    }

    /// The record of an upload still receiving bytes (its data file exists).
    pub fn load(&self, id: &str) -> Option<UploadRecord> {
        if !self.data_path(id).is_file() {
            return None;
        }
        let bytes = fs::read(self.upload_dir(id).join(RECORD)).ok()?;
        serde_json::from_slice(&bytes).ok()
    }

    /// Bytes received so far.
    pub fn offset(&self, id: &str) -> io::Result<u64> {
        Ok(fs::metadata(self.data_path(id))?.len())
    }

    pub fn remove(&self, id: &str) {
        let dir = self.upload_dir(id);
        if let Err(e) = fs::remove_dir_all(&dir)
            && e.kind() != io::ErrorKind::NotFound
        {
            tracing::warn!(dir = %dir.display(), error = %e, "cannot remove upload");
        }
    }

    /// Names the complete upload's file after its scene and format so the
    /// build reads it by its true type. Returns the input path.
    pub fn finish(&self, record: &UploadRecord) -> Result<PathBuf, String> {
        let data = self.data_path(&record.id);
        let mut head = [0u8; 64];
        let n = {
            let mut f = fs::File::open(&data).map_err(|e| format!("cannot read the upload: {e}"))?;
            read_up_to(&mut f, &mut head).map_err(|e| format!("cannot read the upload: {e}"))?
        };
        if n == 0 {
            return Err("the upload is empty".into());
        }
        let format = detect_format(&head[..n], record.file_name.as_deref(), record.content_type.as_deref())?;
        let input = self.upload_dir(&record.id).join(format!("{}.{format}", record.scene_id));
        fs::rename(&data, &input).map_err(|e| format!("cannot keep the upload: {e}"))?;
        Ok(input)
    }

    /// Ids of the upload directories present.
    pub fn ids(&self) -> Vec<String> {
        let Ok(entries) = fs::read_dir(&self.dir) else { return Vec::new() };
        entries.flatten().filter_map(|e| e.file_name().to_str().map(str::to_string)).collect()
    }
}

fn read_up_to(f: &mut fs::File, buf: &mut [u8]) -> io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match io::Read::read(f, &mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// The mesh format of an upload: magic bytes, then the file name's extension,
/// then the Content-Type, then a look at the first bytes of text formats.
pub fn detect_format(
    head: &[u8],
    file_name: Option<&str>,
    content_type: Option<&str>,
) -> Result<MeshFormat, String> {
    if let Ok(f) = MeshFormat::detect(Path::new(file_name.unwrap_or("")), head) {
        return Ok(f);
    }
    let mime = content_type.unwrap_or("").split(';').next().unwrap_or("").trim().to_ascii_lowercase();
    let by_type = match mime.as_str() {
        "model/obj" | "text/x-obj" | "application/x-tgif" => Some(MeshFormat::Obj),
        "model/stl"
        | "application/sla"
        | "model/x.stl-binary"
        | "model/x.stl-ascii"
        | "application/vnd.ms-pki.stl" => Some(MeshFormat::Stl),
        "application/ply" | "model/ply" | "application/x-ply" => Some(MeshFormat::Ply),
        "model/gltf+json" => Some(MeshFormat::Gltf),
        "model/gltf-binary" => Some(MeshFormat::Glb),
        _ => None,
    };
    if let Some(f) = by_type {
        return Ok(f);
    }
    let text = String::from_utf8_lossy(head);
    let first = text.trim_start();
    if first.starts_with("solid") {
        return Ok(MeshFormat::Stl);
    }
    if first.starts_with('{') {
        return Ok(MeshFormat::Gltf);
    }
    if ["v ", "vn ", "vt ", "f ", "o ", "g ", "mtllib", "# "].iter().any(|p| first.starts_with(p)) {
        return Ok(MeshFormat::Obj);
    }
    Err(format!(
        "cannot tell the mesh format of the upload: name the file (.obj, .ply, .stl, .gltf, .glb) \
         with ?filename= or the Upload-Metadata filename, or send a model/* Content-Type \
         (got {:?})",
        content_type.unwrap_or("none")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_from_magic_name_type_and_text() {
        assert_eq!(detect_format(b"ply\nformat", None, None).unwrap(), MeshFormat::Ply);
        assert_eq!(detect_format(b"glTF\x02\0\0\0", Some("x.obj"), None).unwrap(), MeshFormat::Glb);
        assert_eq!(detect_format(b"\0\0\0\0", Some("Scan.STL"), None).unwrap(), MeshFormat::Stl);
        assert_eq!(detect_format(b"\0\0\0\0", None, Some("model/gltf-binary")).unwrap(), MeshFormat::Glb);
        assert_eq!(detect_format(b"# made by\nv 1 2 3", None, None).unwrap(), MeshFormat::Obj);
        let e = detect_format(b"\x89PNG\r\n", Some("photo.png"), Some("image/png")).unwrap_err();
        assert!(e.contains("image/png"), "{e}");
    }
}
