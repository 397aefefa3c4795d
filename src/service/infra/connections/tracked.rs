//! A request's body as its connection sees it ([`Tracked`]): whether it
//! was left unread, and its arrival held to the least rate (module docs of
//! [`super`]).

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

use axum::body::{Bytes, HttpBody};
use http_body::{Frame, SizeHint};
use hyper::body::Incoming;

use super::body_rate::{BodyRate, BodyTooSlow, Meter};
use super::registry::Connection;
/// A request's body, noting on its connection whether it was left unread,
/// and holding it to the least rate ([`BodyRate`]).
pub(super) struct Tracked {
    pub(super) body: Incoming,
    pub(super) connection: Arc<Connection>,
    pub(super) ended: bool,
    /// Its arrival, as the connection limit sees it.
    pub(super) meter: Arc<Meter>,
    pub(super) rate: Option<BodyRate>,
    /// Wakes the body at the end of the current rate window.
    pub(super) timer: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl HttpBody for Tracked {
    type Data = Bytes;
    type Error = axum::BoxError;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::BoxError>>> {
        let this = &mut *self;
        if this.ended {
            return Poll::Ready(None);
        }
        loop {
            if let Some(error) = this.meter.evicted() {
                return this.too_slow(error);
            }
            let polled = Pin::new(&mut this.body).poll_frame(cx);
            let now = Instant::now();
            match polled {
                Poll::Pending => {}
                Poll::Ready(None) => {
                    this.ended = true;
                    this.meter.arrived(now, 0, true);
                    return Poll::Ready(None);
                }
                Poll::Ready(Some(Ok(frame))) => {
                    let length = frame.data_ref().map_or(0, |data| data.len() as u64);
                    this.meter.arrived(now, length, false);
                    return Poll::Ready(Some(Ok(frame)));
                }
                Poll::Ready(Some(Err(error))) => {
                    this.meter.arrived(now, 0, true);
                    // Read no further: hyper's body ends after an error,
                    // which would look like a whole body. What the client
                    // still sends is lingered over.
                    this.ended = true;
                    this.connection.unread_body.store(true, Ordering::Relaxed);
                    return Poll::Ready(Some(Err(error.into())));
                }
            }
            let Some(rate) = this.rate else {
                this.meter.waiting(now, cx.waker());
                return Poll::Pending;
            };
            let left = match this.meter.waiting_checked(now, cx.waker(), &rate) {
                Ok(left) => left,
                Err(error) => return this.too_slow(error),
            };
            let deadline = tokio::time::Instant::from_std(now + left);
            let timer = this
                .timer
                .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(deadline)));
            if timer.deadline() != deadline {
                timer.as_mut().reset(deadline);
            }
            if timer.as_mut().poll(cx).is_pending() {
                return Poll::Pending;
            }
            // The window ended meanwhile: look again.
        }
    }

    fn is_end_stream(&self) -> bool {
        self.ended || self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

impl Tracked {
    /// Ends the body with `error`, marking the connection for a short
    /// lingering close.
    pub(super) fn too_slow(
        &mut self,
        error: BodyTooSlow,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::BoxError>>> {
        self.ended = true;
        self.timer = None;
        self.meter.arrived(Instant::now(), 0, true);
        self.connection.too_slow.store(true, Ordering::Relaxed);
        self.connection.unread_body.store(true, Ordering::Relaxed);
        Poll::Ready(Some(Err(Box::new(error))))
    }
}

impl Drop for Tracked {
    fn drop(&mut self) {
        self.meter.arrived(Instant::now(), 0, true);
        if !self.ended && !self.body.is_end_stream() {
            self.connection.unread_body.store(true, Ordering::Relaxed);
        }
    }
}
