//! The request queue. Rebuilt from each frame's traversal: what is needed and
//! neither loaded, in flight nor failed, pages before blocks (they decide what
//! is wanted), then by projected error, largest first, so coarse stand-ins
//! (larger error) come before their children and the view fills in root first.
//! A cap bounds requests in flight; an in-flight request the view no longer
//! needs is reported stale so the caller can abort it (AbortController in the
//! browser) and its slot goes to a useful one.

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};

use voxstream_format::{BlockKey, PageRef};

/// Requests in flight at once: browsers open ~6 HTTP/1.1 connections per origin.
pub const DEFAULT_MAX_IN_FLIGHT: usize = 6;

/// One thing to fetch.
#[derive(Debug, Clone, PartialEq)]
pub enum Request {
    Page(PageRef),
    Block(BlockKey),
}

impl Request {
    /// Pages are keyed by their root block, which is never a block request's key space clash:
    /// the two kinds live in separate maps.
    fn id(&self) -> (bool, BlockKey) {
        match self {
            Request::Page(p) => (true, p.root),
            Request::Block(k) => (false, *k),
        }
    }
}

/// The blocks a view needs loaded, with their projected error, and the order
/// they are asked for in: largest error first, coarser first on ties (infinite
/// error near the eye), then by key. Made once per traversal, not per arrival:
/// an arrival changes what is loaded, which [`RequestQueue::plan`] filters by,
/// never what is needed.
#[derive(Debug, Clone, Default)]
pub struct NeededBlocks {
    pub by_key: HashMap<BlockKey, f32>,
    order: Vec<(BlockKey, f32)>,
}

impl NeededBlocks {
    pub fn new(by_key: HashMap<BlockKey, f32>) -> Self {
        let mut order: Vec<(BlockKey, f32)> = by_key.iter().map(|(k, p)| (*k, *p)).collect();
        order.sort_by(|a, b| b.1.total_cmp(&a.1).then(b.0.level.cmp(&a.0.level)).then(a.0.cmp(&b.0)));
        Self { by_key, order }
    }

    /// The needed blocks in request order.
    pub fn in_order(&self) -> impl Iterator<Item = &(BlockKey, f32)> {
        self.order.iter()
    }
}

#[derive(Debug, Default)]
pub struct RequestQueue {
    pub max_in_flight: usize,
    /// Ordered, most wanted first; replaced by every [`RequestQueue::plan`].
    queue: Vec<Request>,
    in_flight: HashSet<(bool, BlockKey)>,
    /// In-flight requests the last plan no longer needs.
    stale: Vec<Request>,
    in_flight_requests: HashMap<(bool, BlockKey), Request>,
}

impl RequestQueue {
    pub fn new(max_in_flight: usize) -> Self {
        Self { max_in_flight, ..Default::default() }
    }

    /// Replaces the queue. `pages` are needed pages (most needed first),
    /// `blocks` needed blocks in request order; `done` says which are loaded or
    /// failed (they are skipped). In-flight requests neither names are stale.
    pub fn plan(
        &mut self,
        pages: &[PageRef],
        blocks: &NeededBlocks,
        done_page: impl Fn(&BlockKey) -> bool,
        done_block: impl Fn(&BlockKey) -> bool,
    ) {
        self.queue = pages
            .iter()
            .filter(|p| !done_page(&p.root))
            .cloned()
            .map(Request::Page)
            .chain(blocks.order.iter().filter(|(k, _)| !done_block(k)).map(|(k, _)| Request::Block(*k)))
            .filter(|r| !self.in_flight.contains(&r.id()))
            .collect();
        // At most the in-flight cap of these: a scan of the pages each is cheap.
        let needed = |id: &(bool, BlockKey)| match id {
            (true, root) => pages.iter().any(|p| p.root == *root),
            (false, key) => blocks.by_key.contains_key(key) && !done_block(key),
        };
        self.stale =
            self.in_flight_requests.iter().filter(|(id, _)| !needed(id)).map(|(_, r)| r.clone()).collect();
    }

    /// The next requests to start, within the cap; they count as in flight.
    pub fn start(&mut self) -> Vec<Request> {
        self.start_where(|_| true)
    }

    /// Like [`RequestQueue::start`], only requests `pick` accepts.
    pub fn start_where(&mut self, pick: impl Fn(&Request) -> bool) -> Vec<Request> {
        let mut free = self.max_in_flight.saturating_sub(self.in_flight.len());
        let mut started = Vec::new();
        self.queue.retain(|r| {
            if free > 0 && pick(r) {
                free -= 1;
                started.push(r.clone());
                false
            } else {
                true
            }
        });
        for r in &started {
            self.in_flight.insert(r.id());
            self.in_flight_requests.insert(r.id(), r.clone());
        }
        started
    }

    /// In-flight requests the view no longer needs; they stop counting as in
    /// flight (the caller aborts them; a late answer is still accepted).
    pub fn take_stale(&mut self) -> Vec<Request> {
        let stale = std::mem::take(&mut self.stale);
        for r in &stale {
            self.in_flight.remove(&r.id());
            self.in_flight_requests.remove(&r.id());
        }
        stale
    }

    /// A request finished (either way).
    pub fn finished(&mut self, request: &Request) {
        self.in_flight.remove(&request.id());
        self.in_flight_requests.remove(&request.id());
    }

    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    pub fn is_in_flight(&self, request: &Request) -> bool {
        self.in_flight.contains(&request.id())
    }

    /// Requests waiting (not in flight).
    pub fn queued(&self) -> usize {
        self.queue.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(level: u8, x: u32) -> BlockKey {
        BlockKey::new(level, x, 0, 0)
    }

    #[test]
    fn queue_orders_by_error_caps_and_drops_stale() {
        let mut q = RequestQueue::new(2);
        let blocks: HashMap<BlockKey, f32> =
            [(key(2, 0), 8.0), (key(1, 0), 4.0), (key(1, 1), 6.0), (key(0, 0), 2.0)].into_iter().collect();
        let page = PageRef { root: key(1, 1), hash: "a".repeat(64), bytes: 10, location: Default::default() };
        q.plan(std::slice::from_ref(&page), &NeededBlocks::new(blocks), |_| false, |k| *k == key(2, 0));
        // Page first, then the largest error; the loaded root is skipped; cap 2.
        assert_eq!(q.start(), vec![Request::Page(page.clone()), Request::Block(key(1, 1))]);
        assert_eq!(q.in_flight(), 2);
        assert!(q.start().is_empty(), "the cap holds");
        // The camera moved: key(1, 1) is no longer needed, the page still is.
        let moved = NeededBlocks::new([(key(1, 0), 4.0)].into_iter().collect());
        q.plan(std::slice::from_ref(&page), &moved, |_| false, |_| false);
        assert_eq!(q.take_stale(), vec![Request::Block(key(1, 1))]);
        assert_eq!(q.in_flight(), 1);
        // The freed slot goes to what is needed now, and nothing is asked twice.
        assert_eq!(q.start(), vec![Request::Block(key(1, 0))]);
        q.finished(&Request::Page(page));
        assert_eq!(q.in_flight(), 1);
        // Control: with the view unchanged nothing is stale.
        q.plan(&[], &moved, |_| false, |_| false);
        assert!(q.take_stale().is_empty());
    }
}
