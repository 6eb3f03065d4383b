//! `voxstream serve` settings: every flag has an environment variable, and the
//! same struct configures the server in tests.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::Args;

/// Flags of `voxstream serve` (each also read from the `VOXSTREAM_*` variable named).
#[derive(Debug, Clone, Args)]
pub struct ServeArgs {
    /// The store: a directory (scenes, plus .jobs/ and .uploads/ for the server's own state), or
    /// s3://bucket/prefix, served from the bucket (endpoint and credentials from AWS_* variables
    /// or VOXSTREAM_S3_ENV_FILE; see --cache-size), read-only unless --coordinator is given.
    #[arg(long, env = "VOXSTREAM_STORE")]
    pub store: PathBuf,
    /// With an s3:// store: bytes of hot hierarchy pages and blocks kept in memory (K/M/G
    /// suffixes: 256MiB, 1G); hits and misses are in /metrics.
    #[arg(long, env = "VOXSTREAM_CACHE_SIZE", default_value = "256MiB",
        value_parser = crate::pipeline::parse_byte_size)]
    pub cache_size: u64,
    /// With an s3:// store: seconds between listings of the bucket's scenes (an id not listed yet
    /// is also looked up when asked for).
    #[arg(long, env = "VOXSTREAM_RELIST_SECS", default_value_t = 5)]
    pub relist_secs: u64,
    /// With an s3:// store: postgres://user@host:port/database of the coordinator the replicas
    /// share; with it they take uploads and build each once (without it they are read-only). The
    /// password comes from PGPASSWORD or the file VOXSTREAM_PG_ENV_FILE names, never from here.
    #[arg(long, env = "VOXSTREAM_COORDINATOR")]
    pub coordinator: Option<String>,
    /// With --coordinator: seconds a build's claim lasts without renewal; a replica that dies
    /// while building loses its job to another after this.
    #[arg(long, env = "VOXSTREAM_LEASE_SECS", default_value_t = 30)]
    pub lease_secs: u64,
    /// With --coordinator: seconds between garbage collections of the bucket (packs no manifest
    /// names, objects of failed builds, parts of ended uploads), one replica at a time; also run
    /// a grace period after each build this replica publishes. 0 = never collect.
    #[arg(long, env = "VOXSTREAM_GC_INTERVAL_SECS", default_value_t = 3600)]
    pub gc_interval_secs: u64,
    /// With --coordinator: the collector keeps objects younger than this (seconds), and a scene's
    /// unreferenced packs while its manifest is younger than this: replicas serve a replaced
    /// manifest until their next listing and browsers keep asking for its blocks, and a
    /// `voxstream build --out s3://…` uploads its packs before its manifest.
    #[arg(long, env = "VOXSTREAM_GC_GRACE_SECS", default_value_t = 3600)]
    pub gc_grace_secs: u64,
    #[arg(long, env = "VOXSTREAM_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Directory of the built viewer (index.html, pkg/, upload.html).
    #[arg(long, env = "VOXSTREAM_WEB")]
    pub web: Option<PathBuf>,
    /// Bearer token for uploads, renames, deletes and cancels (and for reading with --protect-read).
    /// Without one, writing is only allowed on a loopback address.
    #[arg(long, env = "VOXSTREAM_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Serve scenes only: every write route answers 403.
    #[arg(long, env = "VOXSTREAM_READ_ONLY")]
    pub read_only: bool,
    /// Require the token for reading too (catalog, manifests, blocks, jobs, metrics).
    #[arg(long, env = "VOXSTREAM_PROTECT_READ")]
    pub protect_read: bool,
    /// Largest accepted upload in bytes.
    #[arg(long, env = "VOXSTREAM_MAX_UPLOAD_BYTES", default_value_t = 16 << 30)]
    pub max_upload_bytes: u64,
    /// Builds running at once (each also uses rayon's threads inside).
    #[arg(long, env = "VOXSTREAM_BUILD_WORKERS", default_value_t = 1)]
    pub build_workers: usize,
    /// Resolution of uploaded scenes unless the upload asks for another; when
    /// unset, matched to each scan (auto, up to --max-resolution).
    #[arg(long, env = "VOXSTREAM_RESOLUTION")]
    pub resolution: Option<u32>,
    /// Highest resolution an upload may ask for, and the most auto picks.
    #[arg(long, env = "VOXSTREAM_MAX_RESOLUTION", default_value_t = 16384)]
    pub max_resolution: u32,
    /// Origins allowed to call the API from other sites (comma-separated, or "*"); none by default.
    #[arg(long, env = "VOXSTREAM_CORS_ORIGINS", value_delimiter = ',')]
    pub cors_origins: Vec<String>,
    /// Uploads (POST /api/scenes, POST /api/uploads) one client IP may start per minute; 0 = no limit.
    #[arg(long, env = "VOXSTREAM_UPLOADS_PER_MINUTE", default_value_t = 30)]
    pub uploads_per_minute: u32,
    /// Most blocks one batch request may ask for.
    #[arg(long, env = "VOXSTREAM_BATCH_MAX", default_value_t = 256)]
    pub batch_max: usize,
    /// Largest total of request header bytes.
    #[arg(long, env = "VOXSTREAM_MAX_HEADER_BYTES", default_value_t = 16 * 1024)]
    pub max_header_bytes: usize,
    /// An upload whose body sends nothing for this long is cut off (seconds).
    #[arg(long, env = "VOXSTREAM_UPLOAD_IDLE_SECS", default_value_t = 60)]
    pub upload_idle_secs: u64,
    /// How long shutdown waits for requests and builds to stop (seconds).
    #[arg(long, env = "VOXSTREAM_SHUTDOWN_SECS", default_value_t = 10)]
    pub shutdown_secs: u64,
}

/// What the server runs with; [`ServeArgs`] minus the listen address.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    pub store: PathBuf,
    /// The scenes live in a bucket (set by the server): without a coordinator it is read-only.
    pub bucket_scenes: bool,
    pub web: Option<PathBuf>,
    pub token: Option<String>,
    pub read_only: bool,
    pub protect_read: bool,
    pub max_upload_bytes: u64,
    pub build_workers: usize,
    pub resolution: Option<u32>,
    pub max_resolution: u32,
    pub cors_origins: Vec<String>,
    pub uploads_per_minute: u32,
    pub batch_max: usize,
    pub max_header_bytes: usize,
    pub upload_idle: Duration,
    pub shutdown_timeout: Duration,
    /// Garbage collection of a bucket (with a coordinator).
    pub gc: crate::gc::GcSettings,
}

impl ServerConfig {
    /// Defaults for a store: writable without a token (loopback use), viewing public.
    pub fn new(store: impl Into<PathBuf>) -> Self {
        Self {
            store: store.into(),
            bucket_scenes: false,
            web: None,
            token: None,
            read_only: false,
            protect_read: false,
            max_upload_bytes: 16 << 30,
            build_workers: 1,
            resolution: None,
            max_resolution: 16384,
            cors_origins: Vec::new(),
            uploads_per_minute: 30,
            batch_max: 256,
            max_header_bytes: 16 * 1024,
            upload_idle: Duration::from_secs(60),
            shutdown_timeout: Duration::from_secs(10),
            gc: crate::gc::GcSettings::default(),
        }
    }
}

impl ServeArgs {
    pub fn config(&self) -> ServerConfig {
        ServerConfig {
            store: self.store.clone(),
            bucket_scenes: false,
            web: self.web.clone(),
            token: self.token.clone().filter(|t| !t.is_empty()),
            read_only: self.read_only,
            protect_read: self.protect_read,
            max_upload_bytes: self.max_upload_bytes,
            build_workers: self.build_workers.max(1),
            resolution: self.resolution,
            max_resolution: self.max_resolution,
            cors_origins: self
                .cors_origins
                .iter()
                .map(|o| o.trim().to_string())
                .filter(|o| !o.is_empty())
                .collect(),
            uploads_per_minute: self.uploads_per_minute,
            batch_max: self.batch_max.max(1),
            max_header_bytes: self.max_header_bytes,
            upload_idle: Duration::from_secs(self.upload_idle_secs.max(1)),
            shutdown_timeout: Duration::from_secs(self.shutdown_secs),
            gc: crate::gc::GcSettings {
                interval: (self.gc_interval_secs > 0).then(|| Duration::from_secs(self.gc_interval_secs)),
                grace: Duration::from_secs(self.gc_grace_secs),
            },
        }
    }

    /// Refuses settings that would expose writing to the network: a server
    /// that accepts uploads and deletes must have a token unless it listens on
    /// loopback only.
    pub fn check_exposure(&self) -> Result<(), String> {
        let config = self.config();
        if config.token.is_none() && !config.read_only && !self.addr.ip().is_loopback() {
            return Err(format!(
                "refusing to serve on {} with uploads, renames and deletes open to anyone: \
                 set --token (or VOXSTREAM_TOKEN), pass --read-only, or listen on 127.0.0.1",
                self.addr
            ));
        }
        if config.protect_read && config.token.is_none() {
            return Err("--protect-read needs --token (or VOXSTREAM_TOKEN)".into());
        }
        Ok(())
    }
}
