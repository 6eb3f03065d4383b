//! The clock of a replica's background loops (bucket relist, lease heartbeat, garbage
//! collection).

use std::time::Duration;

use tokio::time::{Interval, MissedTickBehavior, interval};

/// An interval of `every` whose immediate first tick has been taken, so the loop's first round
/// runs one period from now, and whose late ticks are delayed rather than fired in a burst (a
/// stalled replica must not relist or collect several times in a row when it wakes up).
pub async fn every(every: Duration) -> Interval {
    let mut tick = interval(every);
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    tick.tick().await;
    tick
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    #[tokio::test]
    async fn the_first_round_waits_one_period() {
        let period = Duration::from_millis(60);
        let mut tick = super::every(period).await;
        let started = Instant::now();
        tick.tick().await;
        assert!(started.elapsed() >= period / 2, "ticked after {:?}", started.elapsed());
        // Control: a plain interval ticks at once.
        let mut plain = tokio::time::interval(period);
        let started = Instant::now();
        plain.tick().await;
        assert!(started.elapsed() < period / 2, "ticked after {:?}", started.elapsed());
    }
}
