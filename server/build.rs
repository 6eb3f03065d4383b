//! Picks the folder whose files `voxstream` embeds as its viewer (rust-embed, see
//! `src/http/web.rs`): `viewer-wasm/dist` when `scripts/build-web.sh` has built it (it has an
//! `index.html`), else an empty folder under OUT_DIR, so a plain `cargo build` works before the
//! viewer is built; that binary then answers `/` with a page saying how to build the viewer.
//! `VOXSTREAM_EMBED_WEB=<dir>` embeds another folder.

use std::path::PathBuf;

fn main() {
    let manifest_dir =
        PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let dist = manifest_dir.join("../viewer-wasm/dist");
    println!("cargo:rerun-if-env-changed=VOXSTREAM_EMBED_WEB");
    // A directory: cargo re-runs this script when anything below it changes (or it appears).
    println!("cargo:rerun-if-changed={}", dist.display());
    println!("cargo:rerun-if-changed=build.rs");
    let chosen = match std::env::var_os("VOXSTREAM_EMBED_WEB") {
        Some(dir) => PathBuf::from(dir),
        None if dist.join("index.html").is_file() => dist,
        None => {
            let empty =
                PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR")).join("no-viewer");
            std::fs::create_dir_all(&empty).expect("creating an empty viewer folder in OUT_DIR");
            println!(
                "cargo:warning=viewer-wasm/dist/index.html is missing: this voxstream binary embeds no viewer \
                 (run scripts/build-web.sh, then build again; or serve with --web)"
            );
            empty
        }
    };
    let chosen = chosen.canonicalize().unwrap_or(chosen);
    println!("cargo:rustc-env=VOXSTREAM_EMBED_WEB_DIR={}", chosen.display());
}
