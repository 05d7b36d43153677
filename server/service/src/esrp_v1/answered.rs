//! Episodes live only if their CreateEpisode answer is sent. The handler puts the create's
//! [`Unanswered`] guard in the response's extensions; [`Answered`], around the service, moves
//! it into the response body, which marks it answered once the whole answer has been written
//! (the trailers with `grpc-status: 0`). A call given up before that — the client's deadline
//! expires or it cancels while the episode renders (the handler future is dropped) or while
//! the answer travels (the body is dropped) — drops the guard, which closes the episode if no
//! call has named it yet. A client can read the id from an answer's first bytes and hold the
//! rest back; once it uses the episode, the episode is its run and stays (see `Unanswered`).

use std::convert::Infallible;
use std::pin::Pin;
use std::task::{Context, Poll};

use bytes::Bytes;
use http_body::Frame;
use tonic::body::Body;
use tonic::codegen::{BoxFuture, Service, http};
use tonic::server::NamedService;

use crate::episodes::Unanswered;

/// A service whose responses' [`Unanswered`] guards are marked answered when their body ends
/// with a successful status.
#[derive(Clone, Debug)]
pub struct Answered<S>(S);

impl<S> Answered<S> {
    /// `inner` with its guards moved into its response bodies.
    pub fn new(inner: S) -> Self {
        Self(inner)
    }
}

impl<S: NamedService> NamedService for Answered<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, B> Service<http::Request<B>> for Answered<S>
where
    S: Service<http::Request<B>, Response = http::Response<Body>, Error = Infallible>,
    S::Future: Send + 'static,
{
    type Response = http::Response<Body>;
    type Error = Infallible;
    type Future = BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let response = self.0.call(request);
        Box::pin(async move {
            let mut response = response.await?;
            // No await between the handler's answer and this: the guard is never lost.
            if let Some(guard) = response.extensions_mut().remove::<Unanswered>() {
                response = response.map(|body| Body::new(GuardedBody { body, guard: Some(guard), rest: Bytes::new() }));
            }
            Ok(response)
        })
    }
}

/// The size of the pieces a guarded answer is handed to the transport in. The transport
/// polls a body for more only when it has room to send (flow control and its send buffer),
/// so the guard is marked answered only once all but about a send buffer of the answer has
/// left; handed over whole (tonic encodes a message into one chunk), a 4 MB answer would be
/// "written" the moment its handler returned.
const PIECE: usize = 16 * 1024;

/// A response body holding its episode's guard until the answer is written.
struct GuardedBody {
    body: Body,
    guard: Option<Unanswered>,
    /// The rest of a data chunk, handed over in pieces.
    rest: Bytes,
}

impl http_body::Body for GuardedBody {
    type Data = <Body as http_body::Body>::Data;
    type Error = <Body as http_body::Body>::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        if !self.rest.is_empty() {
            let piece = self.rest.len().min(PIECE);
            return Poll::Ready(Some(Ok(Frame::data(self.rest.split_to(piece)))));
        }
        let mut frame = Pin::new(&mut self.body).poll_frame(cx);
        if let Poll::Ready(Some(Ok(data))) = &mut frame
            && let Some(bytes) = data.data_mut()
            && bytes.len() > PIECE
        {
            self.rest = bytes.split_off(PIECE);
        }
        if let Poll::Ready(Some(Ok(frame))) = &frame
            && let Some(trailers) = frame.trailers_ref()
            && trailers.get("grpc-status").is_some_and(|status| status == "0")
            && let Some(guard) = self.guard.take()
        {
            guard.answered();
        }
        frame
    }

    fn is_end_stream(&self) -> bool {
        self.rest.is_empty() && self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        let (inner, rest) = (self.body.size_hint(), self.rest.len() as u64);
        let mut hint = http_body::SizeHint::new();
        hint.set_lower(inner.lower() + rest);
        if let Some(upper) = inner.upper() {
            hint.set_upper(upper + rest);
        }
        hint
    }
}
