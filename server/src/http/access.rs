//! Who may do what: [`WriteAccess`] and [`ReadAccess`] are extractors that
//! handlers take first, so a route's access rule is in its signature; the
//! per-IP token bucket limits how fast one client can start uploads.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, FromRequestParts};
use axum::http::request::Parts;
use axum::http::{HeaderValue, StatusCode, header};

use super::{ApiError, AppState};

fn bearer_ok(parts: &Parts, token: &str) -> bool {
    let Some(given) = parts
        .headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer ").or_else(|| v.strip_prefix("bearer ")))
    else {
        return false;
    };
    // Constant time in the token's content (the length is not secret).
    given.len() == token.len() && given.bytes().zip(token.bytes()).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0
}

fn unauthorized(what: &str) -> ApiError {
    ApiError::new(StatusCode::UNAUTHORIZED, format!("{what} needs the header Authorization: Bearer <token>"))
        .with_header(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"voxstream\""))
}

/// Uploads, renames, deletes and cancels: refused on a read-only server,
/// otherwise need the bearer token when one is configured.
pub struct WriteAccess;

impl FromRequestParts<AppState> for WriteAccess {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        if let crate::catalog::SceneStore::Bucket(_) = state.catalog.scene_store()
            && state.cluster().is_none()
        {
            return Err(ApiError::new(StatusCode::FORBIDDEN, crate::catalog::READ_ONLY_BUCKET_HINT));
        }
        if state.config.read_only {
            return Err(ApiError::new(StatusCode::FORBIDDEN, "this server is read-only (--read-only)"));
        }
        match &state.config.token {
            Some(token) if !bearer_ok(parts, token) => Err(unauthorized("changing scenes")),
            _ => Ok(WriteAccess),
        }
    }
}

/// Everything else: public unless `--protect-read`.
pub struct ReadAccess;

impl FromRequestParts<AppState> for ReadAccess {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        match &state.config.token {
            Some(token) if state.config.protect_read && !bearer_ok(parts, token) => {
                Err(unauthorized("reading"))
            }
            _ => Ok(ReadAccess),
        }
    }
}

/// A permit to start one upload, from the client IP's token bucket.
pub struct UploadPermit;

impl FromRequestParts<AppState> for UploadPermit {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        // Servers started without connect info (in-process tests) share one bucket.
        let ip = parts
            .extensions
            .get::<ConnectInfo<SocketAddr>>()
            .map_or(IpAddr::V4(Ipv4Addr::UNSPECIFIED), |c| c.0.ip());
        state.upload_limiter.take(ip).map(|()| UploadPermit).map_err(|wait| {
            let secs = wait.as_secs().max(1);
            ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "too many uploads from {ip}: at most {} a minute; try again in {secs} s",
                    state.upload_limiter.per_minute
                ),
            )
            .with_header(header::RETRY_AFTER, HeaderValue::from(secs))
        })
    }
}

/// Token buckets per client IP: `per_minute` tokens of burst, refilled evenly.
pub struct RateLimiter {
    pub per_minute: u32,
    buckets: Mutex<HashMap<IpAddr, (f64, Instant)>>,
}

impl RateLimiter {
    pub fn new(per_minute: u32) -> Self {
        Self { per_minute, buckets: Mutex::new(HashMap::new()) }
    }

    /// Takes one token, or says how long until one is there. 0 per minute = no limit.
    pub fn take(&self, ip: IpAddr) -> Result<(), Duration> {
        self.take_at(ip, Instant::now())
    }

    fn take_at(&self, ip: IpAddr, now: Instant) -> Result<(), Duration> {
        if self.per_minute == 0 {
            return Ok(());
        }
        let capacity = self.per_minute as f64;
        let per_sec = capacity / 60.0;
        let mut buckets = self.buckets.lock().expect("rate limiter lock");
        if buckets.len() > 10_000 {
            // Forget clients whose buckets have refilled: they are back at the default.
            buckets.retain(|_, (tokens, at)| {
                *tokens + now.duration_since(*at).as_secs_f64() * per_sec < capacity
            });
        }
        let (tokens, at) = buckets.entry(ip).or_insert((capacity, now));
        *tokens = (*tokens + now.duration_since(*at).as_secs_f64() * per_sec).min(capacity);
        *at = now;
        if *tokens >= 1.0 {
            *tokens -= 1.0;
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - *tokens) / per_sec))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_refill_per_client() {
        let limiter = RateLimiter::new(2);
        let (a, b) = (IpAddr::from([10, 0, 0, 1]), IpAddr::from([10, 0, 0, 2]));
        let t0 = Instant::now();
        assert!(limiter.take_at(a, t0).is_ok());
        assert!(limiter.take_at(a, t0).is_ok());
        let wait = limiter.take_at(a, t0).unwrap_err();
        assert!((29.0..=30.5).contains(&wait.as_secs_f64()), "{wait:?}");
        assert!(limiter.take_at(b, t0).is_ok(), "another client has its own bucket");
        assert!(limiter.take_at(a, t0 + Duration::from_secs(31)).is_ok());
        assert!(RateLimiter::new(0).take_at(a, t0).is_ok());
    }
}
