//! Decoding off the main thread: a pool of module Web Workers
//! (web/decode-worker.js) that load this same wasm, fetch a block and decode
//! and check it ([`decode_block_for_worker`]); the main thread receives the
//! voxels as a transferred buffer and only copies them into the upload batch.

use std::cell::RefCell;

use bytemuck::Zeroable;
use rustc_hash::FxHashMap as HashMap;
use voxstream_format::{Block, BlockKey, PackedVoxel};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;

use crate::decode::{DecodedBlock, decode_checked};

/// Workers in the pool: decoding is short next to a fetch, two keep up.
const WORKERS: usize = 2;

/// Runs in a worker: the voxels of the block `key` in `bytes` as raw
/// PackedVoxel bytes, after the same checks as the main-thread path
/// (`voxels` < 0: no manifest count to check; `hash` empty: no hash to check).
#[wasm_bindgen]
pub fn decode_block_for_worker(key: &str, bytes: &[u8], voxels: i32, hash: &str) -> Result<Vec<u8>, JsValue> {
    let key: BlockKey = key.parse().map_err(|e| JsValue::from_str(&format!("block key {key}: {e}")))?;
    let expected = u32::try_from(voxels).ok();
    let hash = Some(hash).filter(|h| !h.is_empty());
    let block = decode_checked(key, expected, hash, bytes).map_err(|e| JsValue::from_str(&e.to_string()))?;
    Ok(DecodedBlock::new(block).to_message())
}

/// Runs in the occupancy worker: the AO volume splatted from an
/// [`crate::ao::encode_sources`] payload, all mips back to back.
#[wasm_bindgen]
pub fn occupancy_for_worker(grid_resolution: u32, sources: &[u8]) -> Result<Vec<u8>, JsValue> {
    let blocks = crate::ao::decode_sources(sources).map_err(|e| JsValue::from_str(&e))?;
    Ok(crate::ao::OccupancyVolume::build(grid_resolution, &blocks).into_bytes())
}

/// Builds the AO occupancy volume in a worker (web/occupancy-worker.js): the
/// splat, the enclosed-space fill and the mips cost hundreds of milliseconds
/// in wasm, which the main thread must never spend.
pub struct OccupancyWorker {
    worker: web_sys::Worker,
    next_id: u32,
}

thread_local! {
    static ON_VOLUME: RefCell<Option<Box<dyn Fn(u32, Result<Vec<u8>, String>)>>> = const { RefCell::new(None) };
}

impl OccupancyWorker {
    /// Starts the worker; `on_volume(id, mips)` runs on the main thread for each answer.
    pub fn new(on_volume: impl Fn(u32, Result<Vec<u8>, String>) + 'static) -> Result<Self, String> {
        ON_VOLUME.with(|r| *r.borrow_mut() = Some(Box::new(on_volume)));
        let options = web_sys::WorkerOptions::new();
        options.set_type(web_sys::WorkerType::Module);
        let worker = web_sys::Worker::new_with_options("./occupancy-worker.js", &options)
            .map_err(|e| format!("occupancy worker: {e:?}"))?;
        let onmessage = Closure::<dyn FnMut(web_sys::MessageEvent)>::new(|e: web_sys::MessageEvent| {
            let data = e.data();
            let get = |name: &str| js_sys::Reflect::get(&data, &JsValue::from_str(name)).ok();
            let Some(id) = get("id").and_then(|v| v.as_f64()) else { return };
            let result = match get("mips").and_then(|m| m.dyn_into::<js_sys::ArrayBuffer>().ok()) {
                Some(buffer) => Ok(js_sys::Uint8Array::new(&buffer).to_vec()),
                None => Err(get("error")
                    .and_then(|e| e.as_string())
                    .unwrap_or_else(|| "occupancy worker failed".into())),
            };
            ON_VOLUME.with(|r| {
                if let Some(f) = r.borrow().as_ref() {
                    f(id as u32, result);
                }
            });
        });
        worker.set_onmessage(Some(onmessage.as_ref().unchecked_ref()));
        // The worker lives as long as the page.
        onmessage.forget();
        Ok(Self { worker, next_id: 0 })
    }

    /// Sends a payload (transferred, not copied); the answer comes with the returned id.
    pub fn submit(&mut self, grid_resolution: u32, sources: Vec<u8>) -> Result<u32, String> {
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        let bytes = js_sys::Uint8Array::from(sources.as_slice());
        let msg = js_sys::Object::new();
        for (k, v) in [
            ("id", JsValue::from(id)),
            ("grid", JsValue::from(grid_resolution)),
            ("sources", bytes.buffer().into()),
        ] {
            let _ = js_sys::Reflect::set(&msg, &JsValue::from_str(k), &v);
        }
        let transfer = js_sys::Array::of1(&bytes.buffer());
        self.worker
            .post_message_with_transfer(&msg, &transfer)
            .map_err(|e| format!("occupancy worker: {e:?}"))?;
        Ok(id)
    }
}

/// What a worker answered.
pub struct WorkerResult {
    pub key: BlockKey,
    /// Bytes of the response body.
    pub fetched: u64,
    pub block: Result<DecodedBlock, String>,
}

pub struct DecodePool {
    workers: Vec<web_sys::Worker>,
    next_id: u32,
    next_worker: usize,
    /// Request id → worker index, to route aborts.
    owner: HashMap<u32, usize>,
    ids: HashMap<BlockKey, u32>,
}

thread_local! {
    static ON_RESULT: RefCell<Option<Box<dyn Fn(WorkerResult)>>> = const { RefCell::new(None) };
}

fn parse_message(data: &JsValue) -> Option<(u32, WorkerResult)> {
    let get = |name: &str| js_sys::Reflect::get(data, &JsValue::from_str(name)).ok();
    let id = get("id")?.as_f64()? as u32;
    let key: BlockKey = get("key")?.as_string()?.parse().ok()?;
    let fetched = get("fetched").and_then(|v| v.as_f64()).unwrap_or(0.0) as u64;
    let block = if get("ok")?.as_bool()? {
        let buffer: js_sys::ArrayBuffer = get("voxels")?.dyn_into().ok()?;
        from_answer(key, &js_sys::Uint8Array::new(&buffer))
    } else {
        Err(get("error").and_then(|e| e.as_string()).unwrap_or_else(|| format!("block {key}: worker failed")))
    };
    Some((id, WorkerResult { key, fetched, block }))
}

/// The block in a worker's answer ([`DecodedBlock::to_message`]), its voxels
/// copied once, straight into their place in wasm memory.
fn from_answer(key: BlockKey, answer: &js_sys::Uint8Array) -> Result<DecodedBlock, String> {
    let len = answer.length() as usize;
    let n = DecodedBlock::message_voxels(key, len)?;
    let mut voxels = vec![PackedVoxel::zeroed(); n];
    let voxel_bytes = (n * size_of::<PackedVoxel>()) as u32;
    answer.subarray(0, voxel_bytes).copy_to(bytemuck::cast_slice_mut(&mut voxels));
    let mut trailer = [0u8; DecodedBlock::TRAILER_BYTES];
    answer.subarray(voxel_bytes, len as u32).copy_to(&mut trailer);
    DecodedBlock::from_message(Block { key, voxels }, &trailer)
}

impl DecodePool {
    /// Starts the workers; `on_result` runs on the main thread for each answer.
    pub fn new(on_result: impl Fn(WorkerResult) + 'static) -> Result<Self, String> {
        ON_RESULT.with(|r| *r.borrow_mut() = Some(Box::new(on_result)));
        let options = web_sys::WorkerOptions::new();
        options.set_type(web_sys::WorkerType::Module);
        let mut workers = Vec::new();
        for _ in 0..WORKERS {
            let worker = web_sys::Worker::new_with_options("./decode-worker.js", &options)
                .map_err(|e| format!("decode worker: {e:?}"))?;
            let onmessage = Closure::<dyn FnMut(web_sys::MessageEvent)>::new(|e: web_sys::MessageEvent| {
                if let Some((_, result)) = parse_message(&e.data()) {
                    ON_RESULT.with(|r| {
                        if let Some(f) = r.borrow().as_ref() {
                            f(result);
                        }
                    });
                }
            });
            worker.set_onmessage(Some(onmessage.as_ref().unchecked_ref()));
            // The workers live as long as the page.
            onmessage.forget();
            workers.push(worker);
        }
        Ok(Self { workers, next_id: 0, next_worker: 0, owner: HashMap::default(), ids: HashMap::default() })
    }

    /// Asks a worker to fetch `request` and decode block `key`, checking its voxel count and
    /// content hash when the hierarchy states them.
    pub fn submit(
        &mut self,
        key: BlockKey,
        request: &crate::fetch::BlockRequest,
        voxels: Option<u32>,
        hash: Option<&str>,
    ) {
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        let w = self.next_worker;
        self.next_worker = (self.next_worker + 1) % self.workers.len();
        let msg = js_sys::Object::new();
        let set = |k: &str, v: JsValue| {
            let _ = js_sys::Reflect::set(&msg, &JsValue::from_str(k), &v);
        };
        set("id", JsValue::from(id));
        set("url", JsValue::from_str(&request.url));
        if let Some((start, end)) = request.range {
            // Numbers in JS: exact below 2^53, far beyond any pack.
            set("start", JsValue::from(start as f64));
            set("end", JsValue::from(end as f64));
        }
        set("key", JsValue::from_str(&key.to_string()));
        set("voxels", JsValue::from(voxels.map_or(-1, |v| v as i32)));
        set("hash", JsValue::from_str(hash.unwrap_or("")));
        if self.workers[w].post_message(&msg).is_ok() {
            self.owner.insert(id, w);
            self.ids.insert(key, id);
        }
    }

    /// The view no longer needs `key`: its worker aborts the fetch.
    pub fn abort(&mut self, key: &BlockKey) {
        let Some(id) = self.ids.remove(key) else { return };
        if let Some(w) = self.owner.remove(&id) {
            let msg = js_sys::Object::new();
            let _ = js_sys::Reflect::set(&msg, &JsValue::from_str("abort"), &JsValue::from(id));
            let _ = self.workers[w].post_message(&msg);
        }
    }

    /// A result for `key` arrived; false when it was aborted meanwhile (ignore it).
    pub fn done(&mut self, key: &BlockKey) -> bool {
        match self.ids.remove(key) {
            Some(id) => {
                self.owner.remove(&id);
                true
            }
            None => false,
        }
    }
}
