//! Episodes live only if their CreateEpisode answer is sent. The handler puts the create's
//! [`Unanswered`] guard in the response's extensions; [`Answered`], around the service, moves
//! it into the response body, which marks it answered once the whole answer has been written
//! (the trailers with `grpc-status: 0`). A call given up before that — the client's deadline
//! expires or it cancels while the episode renders (the handler future is dropped) or while
//! the answer travels (the body is dropped) — drops the guard, which closes the episode if no
//! call has named it yet. The body also tells the guard when the answer's observation (its
//! images: the scene) starts to leave — when the transport asks for the observation's bytes
//! beyond its first, which it does only once the client's flow-control window has room past
//! the episode id and the spec — and an episode closed after that is a run: recorded, its
//! attempt spent. A client can read the id from an answer's first bytes and hold the rest
//! back; once it uses the episode, the episode is its run and stays (see `Unanswered`).

use std::collections::VecDeque;
use std::convert::Infallible;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use bytes::Bytes;
use http_body::Frame;
use tonic::body::Body;
use tonic::codegen::{BoxFuture, Service, http};
use tonic::server::NamedService;

use crate::episodes::Unanswered;

/// A service whose responses' [`Unanswered`] guards are marked seen when their body's
/// observation starts to leave, and answered when it ends with a successful status.
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
                response = response.map(|body| Body::new(GuardedBody::new(body, guard)));
            }
            Ok(response)
        })
    }
}

/// The size of the pieces a guarded answer is handed to the transport in. The transport
/// polls a body for more only when it has room to send (flow control and its send buffer); an
/// answer handed over whole (tonic encodes a message into one chunk) would be "written" the
/// moment its handler returned.
const PIECE: usize = 16 * 1024;

/// The field of `CreateEpisodeResponse` that holds the observation (the images).
const OBSERVATION_FIELD: u64 = 3;

/// Where, in a gRPC frame `chunk` (a flag byte, a 4-byte length, the message), the top-level
/// field `field` or any later one begins; None if the frame is compressed, cut short or not
/// made of length-delimited and varint fields up to there.
fn field_offset(chunk: &[u8], field: u64) -> Option<usize> {
    fn varint(bytes: &[u8], at: &mut usize) -> Option<u64> {
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let byte = *bytes.get(*at)?;
            *at += 1;
            value |= u64::from(byte & 0x7f) << shift;
            if byte & 0x80 == 0 {
                return Some(value);
            }
        }
        None
    }
    if chunk.first() != Some(&0) || chunk.len() < 5 {
        return None;
    }
    let mut at = 5;
    while at < chunk.len() {
        let start = at;
        let tag = varint(chunk, &mut at)?;
        if tag >> 3 >= field {
            return Some(start);
        }
        match tag & 7 {
            0 => {
                varint(chunk, &mut at)?;
            }
            2 => {
                let len = usize::try_from(varint(chunk, &mut at)?).ok()?;
                at = at.checked_add(len)?;
            }
            _ => return None,
        }
    }
    None
}

/// The pieces a guarded answer's first data chunk is handed over in: everything before the
/// observation (the frame's head, the episode id, the spec), the observation's first byte (its
/// tag: no pixel), then the rest in [`PIECE`]s. A frame that cannot be read is cut after its
/// 5-byte head instead (nothing of the message is taken as safe to hold back).
fn first_pieces(mut chunk: Bytes) -> VecDeque<Bytes> {
    let head = field_offset(&chunk, OBSERVATION_FIELD).unwrap_or(5).min(chunk.len());
    let mut pieces = VecDeque::from([chunk.split_to(head)]);
    if !chunk.is_empty() {
        pieces.push_back(chunk.split_to(1));
    }
    pieces.extend(rest_pieces(chunk));
    pieces
}

/// `chunk` in [`PIECE`]s.
fn rest_pieces(mut chunk: Bytes) -> VecDeque<Bytes> {
    let mut pieces = VecDeque::new();
    while !chunk.is_empty() {
        pieces.push_back(chunk.split_to(PIECE.min(chunk.len())));
    }
    pieces
}

/// A response body holding its episode's guard until the answer is written.
struct GuardedBody {
    body: Body,
    guard: Option<Unanswered>,
    /// The data pieces not handed over yet.
    pieces: VecDeque<Bytes>,
    /// How many data pieces were handed over.
    handed: usize,
}

impl GuardedBody {
    fn new(body: Body, guard: Unanswered) -> Self {
        Self { body, guard: Some(guard), pieces: VecDeque::new(), handed: 0 }
    }

    /// Hands over the next piece. The third (the observation past its first byte) is asked for
    /// only once the transport could send the second: the client's window has room beyond the
    /// id and the spec, so the images leave from here on: the episode was seen.
    fn hand(&mut self) -> Option<Bytes> {
        let piece = self.pieces.pop_front()?;
        self.handed += 1;
        if self.handed == 3
            && let Some(guard) = &self.guard
        {
            guard.seen();
        }
        Some(piece)
    }
}

impl http_body::Body for GuardedBody {
    type Data = <Body as http_body::Body>::Data;
    type Error = <Body as http_body::Body>::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        if let Some(piece) = self.hand() {
            return Poll::Ready(Some(Ok(Frame::data(piece))));
        }
        let frame = ready!(Pin::new(&mut self.body).poll_frame(cx));
        let frame = match frame {
            Some(Ok(frame)) => frame,
            other => return Poll::Ready(other),
        };
        let frame = match frame.into_data() {
            Ok(data) => {
                self.pieces = if self.handed == 0 { first_pieces(data) } else { rest_pieces(data) };
                return Poll::Ready(self.hand().map(|piece| Ok(Frame::data(piece))).or_else(|| {
                    // An empty data chunk: handed over as it is.
                    Some(Ok(Frame::data(Bytes::new())))
                }));
            }
            Err(frame) => frame,
        };
        if let Some(trailers) = frame.trailers_ref()
            && trailers.get("grpc-status").is_some_and(|status| status == "0")
            && let Some(guard) = self.guard.take()
        {
            guard.answered();
        }
        Poll::Ready(Some(Ok(frame)))
    }

    fn is_end_stream(&self) -> bool {
        self.pieces.is_empty() && self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        let (inner, rest) = (self.body.size_hint(), self.pieces.iter().map(|p| p.len() as u64).sum::<u64>());
        let mut hint = http_body::SizeHint::new();
        hint.set_lower(inner.lower() + rest);
        if let Some(upper) = inner.upper() {
            hint.set_upper(upper + rest);
        }
        hint
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A gRPC frame of `message`.
    fn framed(message: &[u8]) -> Bytes {
        let mut out = vec![0u8];
        out.extend_from_slice(&(message.len() as u32).to_be_bytes());
        out.extend_from_slice(message);
        out.into()
    }

    #[test]
    fn the_first_chunk_is_cut_before_the_observation() {
        // Field 1 (an id of 3 bytes), field 2 (a spec of 2), field 3 (an observation of 40 000).
        let mut message = vec![0x0a, 3, b'a', b'b', b'c', 0x12, 2, 0, 0, 0x1a, 0xc0, 0xb8, 0x02];
        message.extend(std::iter::repeat_n(7u8, 40_000));
        let chunk = framed(&message);
        assert_eq!(field_offset(&chunk, OBSERVATION_FIELD), Some(5 + 9));
        let pieces = first_pieces(chunk.clone());
        let lens: Vec<usize> = pieces.iter().map(Bytes::len).collect();
        assert_eq!(lens[..2], [5 + 9, 1], "the head, then the observation's tag");
        assert!(lens[2..].iter().all(|&n| n <= PIECE));
        assert_eq!(pieces.iter().flat_map(|p| p.iter().copied()).collect::<Vec<_>>(), chunk.to_vec());
        // A compressed frame, or one cut short, is held back after its head only.
        let mut compressed = chunk.to_vec();
        compressed[0] = 1;
        assert_eq!(field_offset(&compressed, OBSERVATION_FIELD), None);
        assert_eq!(first_pieces(Bytes::from(compressed))[0].len(), 5);
        assert_eq!(field_offset(&chunk[..8], OBSERVATION_FIELD), None);
    }
}
