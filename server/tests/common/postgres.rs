//! A PostgreSQL of its own for a test (`scripts/cluster.sh postgres start` in a temp folder), the
//! coordinator's database, and the queued job an upload's completion writes into it. Dropping it
//! stops the server.

#![allow(dead_code)] // each test binary uses part of the common helpers

use std::path::PathBuf;
use std::process::Command;

use voxstream::jobs::{Job, JobState};

use super::cluster::script;

pub struct Postgres {
    pub dir: tempfile::TempDir,
    /// `postgres://voxstream@host:port/voxstream`: no password in it.
    pub url: String,
}

impl Postgres {
    pub fn start() -> Postgres {
        let dir = tempfile::tempdir().unwrap();
        let out =
            Command::new("bash").arg(script()).args(["postgres", "start"]).arg(dir.path()).output().unwrap();
        assert!(out.status.success(), "starting PostgreSQL: {}", String::from_utf8_lossy(&out.stderr));
        let url = String::from_utf8(out.stdout).unwrap().trim().to_string();
        Postgres { dir, url }
    }

    /// The `PGPASSWORD=` file the script wrote (what `VOXSTREAM_PG_ENV_FILE` names).
    pub fn password_file(&self) -> PathBuf {
        self.dir.path().join("pg.env")
    }

    pub fn password(&self) -> String {
        password_in(&std::fs::read_to_string(self.password_file()).unwrap())
    }

    /// A direct SQL connection as the `voxstream` role.
    pub async fn client(&self) -> tokio_postgres::Client {
        let url = self.url.replacen("voxstream@", &format!("voxstream:{}@", self.password()), 1);
        let (client, connection) = tokio_postgres::connect(&url, tokio_postgres::NoTls).await.unwrap();
        tokio::spawn(connection);
        client
    }
}

impl Drop for Postgres {
    fn drop(&mut self) {
        let _ = Command::new("bash").arg(script()).args(["postgres", "stop"]).arg(self.dir.path()).output();
    }
}

/// The password of a `PGPASSWORD=…` file's text.
pub fn password_in(pg_env: &str) -> String {
    pg_env.trim().strip_prefix("PGPASSWORD=").expect("a PGPASSWORD= line").to_string()
}

/// A queued job of scene `scene`, as an upload's completion writes it.
pub fn queued_job(id: &str, scene: &str) -> Job {
    Job {
        id: id.into(),
        scene_id: scene.into(),
        state: JobState::Queued,
        stage: None,
        fraction: 0.0,
        eta_seconds: None,
        triangles_per_second: 0.0,
        error: None,
        input_file: format!("{scene}.obj"),
        input_bytes: 1,
        resolution: Some(64),
        max_resolution: 16384,
        topology: "conservative".into(),
        created_at: 1,
        started_at: None,
        finished_at: None,
        attempts: 0,
        builder: None,
        input_blake3: None,
    }
}
