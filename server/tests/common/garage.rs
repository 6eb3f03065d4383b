//! A real Garage (S3-compatible object store) for tests: one node, `db_engine = "sqlite"`,
//! replication factor 1, on loopback ports that were free a moment before, with its own temp
//! folder. Found (and, on a cold machine, installed) by `scripts/garage.sh`. Buckets and keys are
//! made with the `garage` CLI, as an operator would. Dropping it kills the node.

#![allow(dead_code)] // each test binary uses part of it

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use object_store::ObjectStore;
use object_store::aws::AmazonS3Builder;

/// Website requests name their bucket in the Host header: `<bucket>` + this.
pub const WEB_ROOT_DOMAIN: &str = ".web.garage.localhost";

pub struct Garage {
    child: Child,
    bin: PathBuf,
    config: PathBuf,
    _dir: tempfile::TempDir,
    /// `http://127.0.0.1:<port>` of the S3 API.
    pub endpoint: String,
    /// `http://127.0.0.1:<port>` of the website endpoint: a bucket with website access
    /// ([`Garage::allow_website`]) is served there to requests with `Host: <bucket>` + [`WEB_ROOT_DOMAIN`].
    pub web_endpoint: String,
    pub key_id: String,
    pub secret: String,
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The Garage binary, installed by the project's script when missing.
pub fn garage_bin() -> PathBuf {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/garage.sh");
    let out = Command::new("bash")
        .arg(script)
        .stderr(Stdio::inherit())
        .output()
        .expect("running scripts/garage.sh");
    assert!(out.status.success(), "scripts/garage.sh failed");
    PathBuf::from(String::from_utf8(out.stdout).unwrap().trim())
}

impl Garage {
    /// Starts a node, applies a one-node layout and creates a key allowed on every bucket made with
    /// [`Garage::create_bucket`].
    pub fn start() -> Garage {
        let bin = garage_bin();
        let dir = tempfile::tempdir().unwrap();
        let (rpc, s3, admin, web) = (free_port(), free_port(), free_port(), free_port());
        let secret: String = (0..32).map(|_| format!("{:02x}", rand::random::<u8>())).collect();
        let config = dir.path().join("garage.toml");
        std::fs::write(
            &config,
            format!(
                "metadata_dir = \"{meta}\"\ndata_dir = \"{data}\"\ndb_engine = \"sqlite\"\n\
                 replication_factor = 1\nrpc_bind_addr = \"127.0.0.1:{rpc}\"\n\
                 rpc_public_addr = \"127.0.0.1:{rpc}\"\nrpc_secret = \"{secret}\"\n\
                 [s3_api]\ns3_region = \"garage\"\napi_bind_addr = \"127.0.0.1:{s3}\"\n\
                 root_domain = \".s3.garage.localhost\"\n[admin]\napi_bind_addr = \"127.0.0.1:{admin}\"\n\
                 [s3_web]\nbind_addr = \"127.0.0.1:{web}\"\nroot_domain = \"{WEB_ROOT_DOMAIN}\"\n",
                meta = dir.path().join("meta").display(),
                data = dir.path().join("data").display(),
            ),
        )
        .unwrap();
        let log = std::fs::File::create(dir.path().join("garage.log")).unwrap();
        let child = Command::new(&bin)
            .arg("-c")
            .arg(&config)
            .arg("server")
            .env("RUST_LOG", "warn")
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .expect("starting garage");
        let mut garage = Garage {
            child,
            bin,
            config,
            _dir: dir,
            endpoint: format!("http://127.0.0.1:{s3}"),
            web_endpoint: format!("http://127.0.0.1:{web}"),
            key_id: String::new(),
            secret: String::new(),
        };
        let started = Instant::now();
        let node = loop {
            if let Ok(id) = garage.try_cli(&["node", "id", "-q"]) {
                break id.trim().split('@').next().unwrap().to_string();
            }
            assert!(started.elapsed() < Duration::from_secs(30), "garage did not start: {}", garage.log());
            std::thread::sleep(Duration::from_millis(100));
        };
        garage.cli(&["layout", "assign", "-z", "dc1", "-c", "1G", &node]);
        garage.cli(&["layout", "apply", "--version", "1"]);
        let key = garage.cli(&["key", "create", "voxstream-test"]);
        let field = |name: &str| {
            key.lines()
                .find_map(|l| l.strip_prefix(name).map(|v| v.trim().to_string()))
                .unwrap_or_else(|| panic!("no {name} in {key}"))
        };
        garage.key_id = field("Key ID:");
        garage.secret = field("Secret key:");
        garage
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self._dir.path().join("garage.log")).unwrap_or_default()
    }

    fn try_cli(&self, args: &[&str]) -> Result<String, String> {
        let out = Command::new(&self.bin).arg("-c").arg(&self.config).args(args).output().unwrap();
        if out.status.success() {
            Ok(String::from_utf8_lossy(&out.stdout).into_owned())
        } else {
            Err(String::from_utf8_lossy(&out.stderr).into_owned())
        }
    }

    /// Runs the `garage` CLI against this node; panics with its output and the node's log when it
    /// still fails after 5 s. A node that has just started (or applied its layout) can refuse an
    /// admin command for a moment; CI saw that once in `static_ranges`.
    pub fn cli(&self, args: &[&str]) -> String {
        let started = Instant::now();
        loop {
            match self.try_cli(args) {
                Ok(out) => return out,
                Err(e) if started.elapsed() >= Duration::from_secs(5) => {
                    panic!("garage {args:?}: {e}\nnode log:\n{}", self.log())
                }
                Err(e) => {
                    eprintln!("garage {args:?} failed, trying again: {e}");
                    std::thread::sleep(Duration::from_millis(200));
                }
            }
        }
    }

    /// Creates a bucket the test key may read and write.
    pub fn create_bucket(&self, name: &str) {
        self.cli(&["bucket", "create", name]);
        self.cli(&["bucket", "allow", "--read", "--write", "--owner", name, "--key", &self.key_id]);
    }

    /// Serves `bucket` as a static website on [`Garage::web_endpoint`] (`index.html` as index).
    pub fn allow_website(&self, bucket: &str) {
        self.cli(&["bucket", "website", "--allow", bucket]);
    }

    /// The `AWS_*` variables a voxstream process needs for this node (in its environment, never
    /// on its command line).
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint.clone()),
            ("AWS_ALLOW_HTTP", "true".into()),
            ("AWS_REGION", "garage".into()),
            ("AWS_ACCESS_KEY_ID", self.key_id.clone()),
            ("AWS_SECRET_ACCESS_KEY", self.secret.clone()),
        ]
    }

    /// A client of `bucket` for the test itself (to look at objects).
    pub fn client(&self, bucket: &str) -> Arc<dyn ObjectStore> {
        Arc::new(
            AmazonS3Builder::new()
                .with_endpoint(&self.endpoint)
                .with_allow_http(true)
                .with_region("garage")
                .with_bucket_name(bucket)
                .with_access_key_id(&self.key_id)
                .with_secret_access_key(&self.secret)
                .build()
                .unwrap(),
        )
    }
}

impl Drop for Garage {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `voxstream` command with this node's settings in its environment and no inherited `AWS_*`.
pub fn voxstream_with(garage: Option<&Garage>, env: &[(&str, String)]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_voxstream"));
    for (k, _) in std::env::vars().filter(|(k, _)| k.starts_with("AWS_")) {
        cmd.env_remove(k);
    }
    cmd.env_remove("VOXSTREAM_S3_ENV_FILE").env_remove("VOXSTREAM_STORE");
    if let Some(g) = garage {
        cmd.envs(g.env());
    }
    cmd.envs(env.iter().map(|(k, v)| (*k, v.as_str())));
    cmd
}

/// `data/koala.obj` in the repository.
pub fn koala() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../data/koala.obj"))
}
