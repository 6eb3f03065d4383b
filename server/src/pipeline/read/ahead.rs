//! Read-ahead for the streamed readers: the file is read on its own thread,
//! in blocks, while the reader parses the block before. A reader's file
//! reads (system time: the page cache copied out, about a second for a
//! 1.9 GB PLY) otherwise run on the thread that hands work to the others,
//! with the other cores idle.
//!
//! Memory: at most `AHEAD` blocks wait, one is being filled and one is
//! being parsed: `(AHEAD + 2) · BLOCK` = 4 MiB, in pass 1 only, where the
//! pyramid stage's reserve (at least 67 MiB, see `MemoryPlan`) is unused.
//! Blocks are recycled, so a long file costs no page faults past the first
//! four blocks.

use std::io::{BufRead, Read};
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError, sync_channel};

/// Bytes a block: the size of the `BufReader` this replaces.
const BLOCK: usize = 1 << 20;
/// Blocks read and waiting at most.
const AHEAD: usize = 2;
/// The most bytes read-ahead holds at once: the 4 MiB the budget model counts
/// (ARCHITECTURE.md, "pipeline/bin.rs", pass 1).
const READ_AHEAD_BYTES: u64 = ((AHEAD + 2) * BLOCK) as u64;
const _: () = assert!(READ_AHEAD_BYTES <= 4 << 20);

/// A `BufRead` over blocks read by a scoped thread, in order.
pub struct ReadAhead {
    blocks: Receiver<std::io::Result<Vec<u8>>>,
    spent: SyncSender<Vec<u8>>,
    block: Vec<u8>,
    at: usize,
    done: bool,
}

impl ReadAhead {
    /// Starts reading `inner` on a thread of `scope`.
    pub fn spawn<'scope, R: Read + Send + 'scope>(
        scope: &'scope std::thread::Scope<'scope, '_>,
        mut inner: R,
    ) -> std::io::Result<Self> {
        let (tx, blocks) = sync_channel::<std::io::Result<Vec<u8>>>(AHEAD);
        let (spent, recycled) = sync_channel::<Vec<u8>>(AHEAD + 2);
        std::thread::Builder::new().name("read-ahead".into()).spawn_scoped(scope, move || {
            loop {
                let mut buf = match recycled.try_recv() {
                    Ok(b) => b,
                    Err(TryRecvError::Empty) => Vec::new(),
                    // The reader is gone.
                    Err(TryRecvError::Disconnected) => return,
                };
                buf.clear();
                buf.reserve_exact(BLOCK);
                // Up to a full block, or the file's end; on an error, what was read is kept.
                let read = (&mut inner).take(BLOCK as u64).read_to_end(&mut buf).map(drop);
                let n = buf.len();
                let last = n == 0 || read.is_err();
                let sent = match read {
                    // An error after some bytes: the bytes first, then the error.
                    Err(e) if n > 0 => tx.send(Ok(buf)).and_then(|()| tx.send(Err(e))),
                    Err(e) => tx.send(Err(e)),
                    Ok(()) if n > 0 => tx.send(Ok(buf)),
                    Ok(()) => Ok(()),
                };
                if last || sent.is_err() {
                    return;
                }
            }
        })?;
        Ok(Self { blocks, spent, block: Vec::new(), at: 0, done: false })
    }
}

impl BufRead for ReadAhead {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        if self.at == self.block.len() && !self.done {
            match self.blocks.recv() {
                Ok(Ok(next)) => {
                    let old = std::mem::replace(&mut self.block, next);
                    self.at = 0;
                    if old.capacity() > 0 {
                        // Full or gone: the thread allocates instead.
                        let _ = self.spent.try_send(old);
                    }
                }
                Ok(Err(e)) => {
                    self.done = true;
                    return Err(e);
                }
                // The file's end.
                Err(_) => self.done = true,
            }
        }
        Ok(&self.block[self.at..])
    }

    fn consume(&mut self, amt: usize) {
        self.at = (self.at + amt).min(self.block.len());
    }
}

impl Read for ReadAhead {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let avail = self.fill_buf()?;
        let n = avail.len().min(buf.len());
        buf[..n].copy_from_slice(&avail[..n]);
        self.consume(n);
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A reader handing out `step` bytes a call, failing at `fail_at` if set.
    struct Trickle {
        data: Vec<u8>,
        at: usize,
        step: usize,
        fail_at: Option<usize>,
    }

    impl Read for Trickle {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            if self.fail_at.is_some_and(|f| self.at >= f) {
                return Err(std::io::Error::other("disk on fire"));
            }
            let n = self.step.min(buf.len()).min(self.data.len() - self.at);
            buf[..n].copy_from_slice(&self.data[self.at..self.at + n]);
            self.at += n;
            Ok(n)
        }
    }

    #[test]
    fn reads_every_byte_in_order_then_the_error() {
        let data: Vec<u8> = (0..3 * BLOCK + 12345).map(|i| (i * 7 % 251) as u8).collect();
        for step in [1 << 16, 1000, BLOCK + 1] {
            let got = std::thread::scope(|s| {
                let inner = Trickle { data: data.clone(), at: 0, step, fail_at: None };
                let mut r = ReadAhead::spawn(s, inner).unwrap();
                let mut got = Vec::new();
                // Mixed use, as the PLY reader does: lines, exact reads, consumed buffers.
                let mut line = Vec::new();
                r.read_until(b'\n', &mut line).unwrap();
                got.extend_from_slice(&line);
                let mut exact = [0u8; 777];
                r.read_exact(&mut exact).unwrap();
                got.extend_from_slice(&exact);
                r.read_to_end(&mut got).unwrap();
                got
            });
            assert!(got == data, "step {step}");
        }
        let err = std::thread::scope(|s| {
            let inner = Trickle { data: data.clone(), at: 0, step: 4096, fail_at: Some(BLOCK + 8192) };
            let mut r = ReadAhead::spawn(s, inner).unwrap();
            let mut got = Vec::new();
            let e = r.read_to_end(&mut got).unwrap_err();
            assert_eq!(&got[..], &data[..got.len()]);
            e
        });
        assert_eq!(err.to_string(), "disk on fire");
        // A reader dropped early stops the thread (the scope would hang otherwise).
        std::thread::scope(|s| {
            let inner = Trickle { data: data.clone(), at: 0, step: 1 << 16, fail_at: None };
            let mut r = ReadAhead::spawn(s, inner).unwrap();
            r.fill_buf().unwrap();
        });
    }
}
