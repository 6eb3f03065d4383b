//! The coordinator's leases against a real PostgreSQL (`scripts/cluster.sh postgres start`): two
//! `Coordinator`s stand for two replicas. A job is claimed by exactly one of many concurrent
//! claims; a lease left to expire is taken over; and the replica that lost its lease can neither
//! renew it nor publish (fencing), while the new owner can.

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use voxstream::coordinator::{Claim, Coordinator, PublishError};
use voxstream::jobs::{Job, JobState};

use common::postgres::{Postgres, queued_job};

/// Queues `job` as an upload's completion does.
async fn queue(pg: &Postgres, job: &Job) {
    pg.client()
        .await
        .execute(
            "INSERT INTO voxstream_jobs (id, scene_id, state, created_at, job) VALUES ($1, $2, 'queued', $3, $4)",
            &[&job.id, &job.scene_id, &(job.created_at as i64), &serde_json::to_string(job).unwrap()],
        )
        .await
        .unwrap();
}

/// Publishes `claim` through `coordinator`; returns the outcome and whether the manifest PUT ran.
async fn publish(coordinator: &Coordinator, claim: &Claim) -> (Result<(), PublishError>, bool) {
    let ran = Arc::new(AtomicBool::new(false));
    let flag = ran.clone();
    let mut done = claim.job.clone();
    done.state = JobState::Done;
    let put = async move {
        flag.store(true, Ordering::SeqCst);
        anyhow::Ok(())
    };
    let result = coordinator.publish(claim, &done, put).await;
    (result, ran.load(Ordering::SeqCst))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leases_are_exclusive_expire_and_fence_publication() {
    let pg = Postgres::start();
    // SAFETY: this binary's only test, set before any thread reads the environment.
    unsafe { std::env::set_var("VOXSTREAM_PG_ENV_FILE", pg.password_file()) };
    let lease = Duration::from_millis(1500);
    let deadline = Duration::from_secs(5);
    let a = Arc::new(Coordinator::connect(&pg.url, lease, deadline).await.unwrap());
    let b = Arc::new(Coordinator::connect(&pg.url, lease, deadline).await.unwrap());
    assert_ne!(a.owner, b.owner);

    // Sixteen claims at once from both replicas: one wins.
    queue(&pg, &queued_job("00000000000000a1", "first")).await;
    let mut claims = Vec::new();
    for i in 0..16 {
        let c = if i % 2 == 0 { a.clone() } else { b.clone() };
        claims.push(tokio::spawn(
            async move { c.claim().await.unwrap().map(|claim| (c.owner.clone(), claim)) },
        ));
    }
    let mut won = Vec::new();
    for c in claims {
        if let Some(w) = c.await.unwrap() {
            won.push(w);
        }
    }
    assert_eq!(won.len(), 1, "claims won: {:?}", won.iter().map(|(o, c)| (o, c.lease)).collect::<Vec<_>>());
    let (winner, claim) = won.pop().unwrap();
    let (holder, other) = if winner == a.owner { (&a, &b) } else { (&b, &a) };
    assert_eq!(claim.job.attempts, 1);
    // Renewed while alive: not claimable by the other replica.
    tokio::time::sleep(lease / 2).await;
    assert_eq!(holder.heartbeat(&claim, &claim.job).await.unwrap(), Some(false));
    tokio::time::sleep(lease / 2 + Duration::from_millis(300)).await;
    assert!(other.claim().await.unwrap().is_none(), "a renewed lease was taken over");
    let (published, ran) = publish(holder, &claim).await;
    assert!(published.is_ok() && ran, "the holder publishes: {published:?}");
    assert_eq!(holder.job(&claim.job.id).await.unwrap().unwrap().state, JobState::Done);

    // A lease left to expire (its builder stalled or died) is taken over, and the old holder is
    // fenced off: it can neither renew nor publish, and its manifest PUT never runs.
    queue(&pg, &queued_job("00000000000000b2", "second")).await;
    let stale = a.claim().await.unwrap().expect("a claims the second job");
    assert!(b.claim().await.unwrap().is_none(), "claimed twice while the lease runs");
    tokio::time::sleep(lease + Duration::from_millis(300)).await;
    let fresh = b.claim().await.unwrap().expect("b takes the expired lease over");
    assert_eq!(fresh.job.attempts, 2, "the count sees the second build");
    assert_eq!(a.heartbeat(&stale, &stale.job).await.unwrap(), None, "the old holder renewed a lost lease");
    let (refused, ran) = publish(&a, &stale).await;
    assert!(matches!(refused, Err(PublishError::LeaseLost)), "{refused:?}");
    assert!(!ran, "the fenced replica wrote its manifest");
    let (published, ran) = publish(&b, &fresh).await;
    assert!(published.is_ok() && ran, "the new holder publishes: {published:?}");
    let done = b.job("00000000000000b2").await.unwrap().unwrap();
    assert_eq!(
        (done.state, done.attempts, done.builder.as_deref()),
        (JobState::Done, 2, Some(b.owner.as_str()))
    );

    // Control: an expired lease nobody took over still fences its holder (expiry, not only a new
    // owner, stops publication).
    queue(&pg, &queued_job("00000000000000c3", "third")).await;
    let late = a.claim().await.unwrap().unwrap();
    tokio::time::sleep(lease + Duration::from_millis(300)).await;
    let (refused, ran) = publish(&a, &late).await;
    assert!(matches!(refused, Err(PublishError::LeaseLost)) && !ran, "{refused:?}");
}
