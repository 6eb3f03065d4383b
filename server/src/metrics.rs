//! Prometheus metrics (prometheus-client, OpenMetrics text at `GET /metrics`).

use std::sync::atomic::AtomicI64;

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

type Labels = Vec<(String, String)>;
type HistogramFamily = Family<Labels, Histogram, fn() -> Histogram>;

pub struct Metrics {
    registry: Registry,
    /// By method, route template and status.
    pub http_requests: Family<Labels, Counter>,
    pub http_request_seconds: HistogramFamily,
    /// Response body bytes with a known length.
    pub http_response_bytes: Counter,
    pub blocks_served: Counter,
    pub block_bytes_served: Counter,
    pub upload_bytes: Counter,
    /// Build durations by outcome (done, failed, cancelled).
    pub job_seconds: HistogramFamily,
    pub jobs_running: Gauge<i64, AtomicI64>,
    pub jobs_queued: Gauge<i64, AtomicI64>,
    /// Builds this process started (with a coordinator, the replicas' sum counts every build).
    pub builds_started: Counter,
    pub sse_streams: Gauge<i64, AtomicI64>,
    /// Objects and bytes the bucket's garbage collector removed (this replica's passes).
    pub gc: crate::gc::GcMetrics,
}

fn request_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.0005, 2.0, 16))
}

fn job_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.1, 2.0, 16))
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("voxstream");
        let m = Metrics {
            http_requests: Family::default(),
            http_request_seconds: Family::new_with_constructor(request_histogram),
            http_response_bytes: Counter::default(),
            blocks_served: Counter::default(),
            block_bytes_served: Counter::default(),
            upload_bytes: Counter::default(),
            job_seconds: Family::new_with_constructor(job_histogram),
            jobs_running: Gauge::default(),
            jobs_queued: Gauge::default(),
            builds_started: Counter::default(),
            sse_streams: Gauge::default(),
            gc: crate::gc::GcMetrics::default(),
            registry: Registry::default(),
        };
        registry.register(
            "http_requests",
            "HTTP requests by method, route and status",
            m.http_requests.clone(),
        );
        registry.register(
            "http_request_seconds",
            "HTTP request handling time by route (until the response head)",
            m.http_request_seconds.clone(),
        );
        registry.register("http_response_bytes", "Response body bytes served", m.http_response_bytes.clone());
        registry.register("blocks_served", "Blocks served (single and batch)", m.blocks_served.clone());
        registry.register("block_bytes_served", "Block bytes served", m.block_bytes_served.clone());
        registry.register("upload_bytes", "Upload bytes received", m.upload_bytes.clone());
        registry.register("job_seconds", "Build job durations by outcome", m.job_seconds.clone());
        registry.register("jobs_running", "Builds running now", m.jobs_running.clone());
        registry.register("jobs_queued", "Builds waiting for a worker", m.jobs_queued.clone());
        registry.register("builds_started", "Builds this process started", m.builds_started.clone());
        registry.register("sse_streams", "Open job event streams", m.sse_streams.clone());
        registry.register(
            "gc_objects_deleted",
            "Unreferenced bucket objects the garbage collector removed",
            m.gc.objects.clone(),
        );
        registry.register(
            "gc_bytes_deleted",
            "Bytes of unreferenced bucket objects the garbage collector removed",
            m.gc.bytes.clone(),
        );
        Metrics { registry, ..m }
    }

    /// Registers a bucket replica's cache: hits and misses by kind (page, block), its bound and
    /// what it holds, in bytes.
    pub fn register_store_cache(&mut self, cache: &crate::bucket_store::CacheMetrics) {
        self.registry.register(
            "store_cache_hits",
            "Pages and blocks served from the replica's in-process cache, by kind",
            cache.hits.clone(),
        );
        self.registry.register(
            "store_cache_misses",
            "Pages and blocks the replica's cache did not hold (read from the bucket), by kind",
            cache.misses.clone(),
        );
        self.registry.register(
            "store_cache_capacity_bytes",
            "Bound of the replica's cache of pages and blocks (--cache-size)",
            cache.capacity_bytes.clone(),
        );
        self.registry.register(
            "store_cache_bytes",
            "Bytes of pages and blocks in the replica's cache",
            cache.cached_bytes.clone(),
        );
    }

    pub fn labels(pairs: &[(&str, &str)]) -> Labels {
        pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect()
    }

    pub fn render(&self) -> String {
        let mut out = String::new();
        encode(&mut out, &self.registry).expect("writing to a String cannot fail");
        out
    }
}
