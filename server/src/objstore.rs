//! S3-compatible object storage (AWS S3, Cloudflare R2, MinIO, Garage) through the `object_store`
//! crate: where a target is named, `s3://bucket/prefix` means a bucket, anything else a local path.
//!
//! Configuration comes from the usual `AWS_*` environment variables (`AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`, `AWS_ENDPOINT_URL` for anything but AWS itself,
//! `AWS_ALLOW_HTTP=true` for a plain-http endpoint such as a local Garage), or from a file of such
//! `KEY=value` lines named by `VOXSTREAM_S3_ENV_FILE` (the environment wins). Never from the
//! command line, and never logged: errors name the endpoint, the bucket and the cause only.
//!
//! [`connect`] checks the bucket before anything else (one list request, a few seconds at most),
//! so a wrong endpoint, wrong credentials or a missing bucket is one clear error at start.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::path::Path as ObjectPath;
use object_store::{Attribute, Attributes, ClientOptions, ObjectStore, PutOptions, PutPayload, RetryConfig};

/// How long `serve --store s3://…` and `build --out s3://…` wait for the bucket to answer at start:
/// a blackholed endpoint fails within this, not after every connect retry.
pub const START_CHECK_DEADLINE: Duration = Duration::from_secs(5);

/// Where a command reads or writes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    Local(std::path::PathBuf),
    S3 { bucket: String, prefix: String },
}

/// `s3://bucket/prefix` → a bucket and a prefix without slashes at its ends; other URL schemes are
/// refused; anything else is a local path.
pub fn parse_location(text: &str) -> Result<Location, String> {
    if let Some(rest) = text.strip_prefix("s3://") {
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let ok = (3..=63).contains(&bucket.len())
            && bucket.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'.')
            && !bucket.starts_with(['-', '.'])
            && !bucket.ends_with(['-', '.']);
        if !ok {
            return Err(format!(
                "{text:?}: the bucket name must be 3–63 characters of a-z, 0-9, '-' and '.' (s3://bucket/prefix)"
            ));
        }
        let prefix = prefix.trim_matches('/').to_string();
        if prefix.split('/').any(|p| p == ".." || p == ".") || prefix.contains("//") {
            return Err(format!("{text:?}: the prefix may not contain '.', '..' or empty segments"));
        }
        return Ok(Location::S3 { bucket: bucket.to_string(), prefix });
    }
    if let Some((scheme, _)) = text.split_once("://") {
        return Err(format!(
            "{text:?}: {scheme}:// is not supported; give a local path or s3://bucket/prefix"
        ));
    }
    if text.is_empty() {
        return Err("an empty path".into());
    }
    Ok(Location::Local(text.into()))
}

/// A bucket (and prefix) that answered.
#[derive(Clone)]
pub struct Bucket {
    pub store: Arc<dyn ObjectStore>,
    pub bucket: String,
    pub prefix: String,
    /// The endpoint, for messages (never credentials).
    pub endpoint: String,
}

impl Bucket {
    /// `prefix/rel` as an object path.
    pub fn path(&self, rel: &str) -> ObjectPath {
        if self.prefix.is_empty() {
            ObjectPath::from(rel)
        } else {
            ObjectPath::from(format!("{}/{rel}", self.prefix))
        }
    }

    /// Writes one object with its Content-Type and Cache-Control.
    pub async fn put(
        &self,
        rel: &str,
        bytes: Vec<u8>,
        content_type: &'static str,
        cache: &'static str,
    ) -> anyhow::Result<()> {
        let mut attributes = Attributes::new();
        attributes.insert(Attribute::ContentType, content_type.into());
        attributes.insert(Attribute::CacheControl, cache.into());
        let opts = PutOptions { attributes, ..Default::default() };
        self.store.put_opts(&self.path(rel), PutPayload::from(bytes), opts).await.map(|_| ()).map_err(|e| {
            anyhow::anyhow!("writing s3://{}/{} at {}: {e}", self.bucket, self.path(rel), self.endpoint)
        })
    }
}

/// `KEY=value` lines (comments with `#`, optional `export `) of a credentials file.
pub fn parse_env_file(text: &str) -> Vec<(String, String)> {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .filter_map(|l| {
            let l = l.strip_prefix("export ").unwrap_or(l);
            let (k, v) = l.split_once('=')?;
            let v = v.trim().trim_matches('"').trim_matches('\'');
            Some((k.trim().to_string(), v.to_string()))
        })
        .collect()
}

/// The S3 settings: `VOXSTREAM_S3_ENV_FILE`'s lines, then the `AWS_*` environment over them.
fn settings() -> anyhow::Result<Vec<(String, String)>> {
    let mut all = Vec::new();
    if let Some(file) = std::env::var_os("VOXSTREAM_S3_ENV_FILE") {
        let text = std::fs::read_to_string(&file).with_context(|| {
            format!("cannot read VOXSTREAM_S3_ENV_FILE {}", std::path::Path::new(&file).display())
        })?;
        all.extend(parse_env_file(&text).into_iter().filter(|(k, _)| k.starts_with("AWS_")));
    }
    for (k, v) in std::env::vars() {
        if k.starts_with("AWS_") {
            all.retain(|(key, _)| key != &k);
            all.push((k, v));
        }
    }
    Ok(all)
}

/// Opens `s3://bucket/prefix` and checks that it answers (one LIST of the prefix), within
/// `deadline`. Errors name the endpoint, the bucket and the cause.
pub async fn connect(bucket: &str, prefix: &str, deadline: Duration) -> anyhow::Result<Bucket> {
    let settings = settings()?;
    let get = |name: &str| settings.iter().rev().find(|(k, _)| k == name).map(|(_, v)| v.clone());
    let endpoint = get("AWS_ENDPOINT_URL").or_else(|| get("AWS_ENDPOINT")).unwrap_or_else(|| {
        format!(
            "AWS S3 ({})",
            get("AWS_REGION").or_else(|| get("AWS_DEFAULT_REGION")).unwrap_or("us-east-1".into())
        )
    });
    let anonymous = get("AWS_SKIP_SIGNATURE").is_some_and(|v| v == "true" || v == "1");
    if !anonymous && (get("AWS_ACCESS_KEY_ID").is_none() || get("AWS_SECRET_ACCESS_KEY").is_none()) {
        bail!(
            "no credentials for s3://{bucket} at {endpoint}: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY in the \
             environment or in the file VOXSTREAM_S3_ENV_FILE names (AWS_SKIP_SIGNATURE=true for a public bucket)"
        );
    }
    // Client options first: with_client_options replaces them whole, and AWS_ALLOW_HTTP (a client
    // option) comes from the settings below.
    let mut builder = AmazonS3Builder::new()
        .with_client_options(
            ClientOptions::new()
                .with_connect_timeout(Duration::from_secs(3))
                .with_timeout(Duration::from_secs(60)),
        )
        .with_retry(RetryConfig {
            max_retries: 3,
            retry_timeout: Duration::from_secs(20),
            ..Default::default()
        });
    for (k, v) in &settings {
        if let Ok(key) = k.to_ascii_lowercase().parse::<AmazonS3ConfigKey>() {
            builder = builder.with_config(key, v.clone());
        }
    }
    if get("AWS_REGION").is_none() && get("AWS_DEFAULT_REGION").is_none() {
        // Garage and MinIO take any region name; AWS's default otherwise.
        builder = builder.with_region("us-east-1");
    }
    let builder = builder.with_bucket_name(bucket);
    let store =
        builder.build().map_err(|e| anyhow::anyhow!("object store s3://{bucket} at {endpoint}: {e}"))?;
    let b =
        Bucket { store: Arc::new(store), bucket: bucket.to_string(), prefix: prefix.to_string(), endpoint };
    let probe = if prefix.is_empty() { None } else { Some(ObjectPath::from(prefix)) };
    match tokio::time::timeout(deadline, b.store.list_with_delimiter(probe.as_ref())).await {
        Err(_) => {
            bail!("object store at {} did not answer within {deadline:?} (bucket {bucket})", b.endpoint)
        }
        Ok(Err(e)) => bail!("object store at {} refused bucket {bucket:?}: {}", b.endpoint, explain(&e)),
        Ok(Ok(_)) => Ok(b),
    }
}

/// The error with a hint for the usual causes.
fn explain(e: &object_store::Error) -> String {
    // The whole chain: the cause (connection refused, DNS, TLS) sits in the innermost source.
    let mut text = e.to_string();
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        let more = s.to_string();
        if !text.contains(&more) {
            text = format!("{text}: {more}");
        }
        source = s.source();
    }
    let hint = if text.contains("NoSuchBucket") || matches!(e, object_store::Error::NotFound { .. }) {
        " (the bucket does not exist: create it, or fix the name)"
    } else if text.contains("InvalidAccessKeyId")
        || text.contains("SignatureDoesNotMatch")
        || text.contains("AccessDenied")
        || text.contains("403")
    {
        " (credentials refused: check AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY and the key's rights on the bucket)"
    } else if text.contains("onnect") || text.contains("dns") || text.contains("timed out") {
        " (cannot connect: check AWS_ENDPOINT_URL, and AWS_ALLOW_HTTP=true for an http:// endpoint)"
    } else {
        ""
    };
    format!("{text}{hint}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations() {
        assert_eq!(parse_location("store"), Ok(Location::Local("store".into())));
        assert_eq!(parse_location("/a/b"), Ok(Location::Local("/a/b".into())));
        assert_eq!(
            parse_location("s3://scans/site/koala/"),
            Ok(Location::S3 { bucket: "scans".into(), prefix: "site/koala".into() })
        );
        assert_eq!(
            parse_location("s3://scans"),
            Ok(Location::S3 { bucket: "scans".into(), prefix: String::new() })
        );
        for bad in
            ["s3://", "s3://A", "s3://ab", "s3://-abc/x", "s3://abc/../x", "gs://abc/x", "http://h/x", ""]
        {
            assert!(parse_location(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn env_files() {
        let v = parse_env_file(
            "# garage\nexport AWS_ACCESS_KEY_ID=GK1\nAWS_SECRET_ACCESS_KEY = \"s\"\n\nbad line\n",
        );
        assert_eq!(
            v,
            vec![("AWS_ACCESS_KEY_ID".into(), "GK1".into()), ("AWS_SECRET_ACCESS_KEY".into(), "s".into())]
        );
    }
}
