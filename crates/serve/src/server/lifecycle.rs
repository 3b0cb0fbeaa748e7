//! Drain support: the count of requests in flight, the signal that tells streams to end, and the
//! process signals (SIGTERM/Ctrl-C drain, SIGHUP reloads).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::middleware::Next;
use axum::response::Response;
use futures::{Stream, StreamExt};
use tokio_util::sync::CancellationToken;

/// Requests whose response has not been produced yet (streams count until their headers go).
#[derive(Default)]
pub struct InFlight(AtomicUsize);

impl InFlight {
    /// Requests in flight now.
    pub fn get(&self) -> usize {
        self.0.load(Ordering::SeqCst)
    }
}

struct Leave(Arc<InFlight>);

impl Drop for Leave {
    fn drop(&mut self) {
        let n = self.0 .0.fetch_sub(1, Ordering::SeqCst) - 1;
        metrics::gauge!("posefuse_requests_in_flight").set(n as f64);
    }
}

/// Middleware counting requests in flight (the `posefuse_requests_in_flight` gauge).
pub async fn count_in_flight(State(counter): State<Arc<InFlight>>, req: Request, next: Next) -> Response {
    let n = counter.0.fetch_add(1, Ordering::SeqCst) + 1;
    metrics::gauge!("posefuse_requests_in_flight").set(n as f64);
    let _leave = Leave(counter);
    next.run(req).await
}

/// Passes `input` through until the drain starts, then yields `last()` once and ends: a stream's
/// requests in hand finish, no further input is read.
pub fn end_on_drain<S, F>(input: S, drain: CancellationToken, last: F) -> impl Stream<Item = S::Item> + Send
where
    S: Stream + Send + 'static,
    S::Item: Send,
    F: FnOnce() -> S::Item + Send + 'static,
{
    let state = (Box::pin(input), drain, Some(last));
    futures::stream::unfold(state, |(mut input, drain, mut last)| async move {
        last.as_ref()?;
        tokio::select! {
            biased;
            item = input.next() => item.map(|i| (i, (input, drain, last))),
            _ = drain.cancelled() => {
                let l = last.take()?;
                Some((l(), (input, drain, None)))
            }
        }
    })
}

/// Completes on SIGTERM or Ctrl-C.
pub async fn terminate() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

/// Reloads the bundle on every SIGHUP (instead of the default: exit). Call before loading, so
/// that an early SIGHUP does not kill the process; reloads start once `reloader` is set.
#[cfg(unix)]
pub fn reload_on_hangup(
    reloader: tokio::sync::watch::Receiver<Option<Arc<super::reload::Reloader>>>,
) -> std::io::Result<()> {
    let mut hup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())?;
    tokio::spawn(async move {
        while hup.recv().await.is_some() {
            let r = reloader.borrow().clone();
            match r {
                Some(r) => {
                    tracing::info!("SIGHUP: reloading the bundle");
                    // The outcome is logged by the reload itself.
                    let _ = r.reload(None).await;
                }
                None => tracing::warn!("SIGHUP during start-up: ignored"),
            }
        }
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_stream_ends_with_its_last_item_once_the_drain_starts() {
        let drain = CancellationToken::new();
        let (tx, rx) = futures::channel::mpsc::unbounded::<i32>();
        let mut s = Box::pin(end_on_drain(rx, drain.clone(), || -1));
        tx.unbounded_send(1).unwrap();
        assert_eq!(s.next().await, Some(1));
        drain.cancel();
        tx.unbounded_send(2).unwrap();
        // Input already there still goes first (biased); then the last item and the end.
        assert_eq!(s.next().await, Some(2));
        assert_eq!(s.next().await, Some(-1));
        assert_eq!(s.next().await, None);
    }
}
