//! `esrp_native`: the optional native transport of the `esrp` Python client.
//!
//! grpcio spends about twice the Rust client's CPU on each unary call, and for one agent
//! stepping one episode that per-call cost is most of a step. This module lets the Python
//! client send the calls of its hot path (Step, Reset, StepBatch) over the Rust client's
//! channel instead: the same tuned connection (`esrp_client::Client`: no Nagle, large HTTP/2
//! windows and frames; TCP or a Unix domain socket), driven by a current-thread Tokio runtime on the calling thread while the GIL is
//! released. It moves serialized messages only: Python builds and parses the protobufs as it
//! does for grpcio, so both transports share every conversion and check.
//!
//! Python API (used by `esrp._native`, not meant to be called directly):
//! `Channel(url, token=None, connect_timeout=10.0)`, `Channel.unary(method, request,
//! timeout=None, response=None)` (the answer: bytes, or parsed by `response`), `unary_all(calls,
//! response=None)` (several calls at once, possibly over several channels), and
//! `CallError(code, message)` for a call that failed with a gRPC status (`code` is the status's
//! number).

use std::sync::{Mutex, RwLock};
use std::time::Duration;

use bytes::{Buf, BufMut, Bytes};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyTypeError, PyValueError};
use pyo3::ffi;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBytes, PyType};
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::metadata::{Ascii, MetadataValue};
use tonic::{Code, Status};

create_exception!(
    esrp_native,
    CallError,
    PyException,
    "A call that failed with a gRPC status: args are (code, message), code the status's number."
);

/// Passes serialized messages through unchanged (Python encodes and decodes them).
#[derive(Clone, Copy, Default)]
struct RawCodec;

impl Codec for RawCodec {
    type Encode = Bytes;
    type Decode = Bytes;
    type Encoder = RawCodec;
    type Decoder = RawCodec;

    fn encoder(&mut self) -> Self::Encoder {
        RawCodec
    }

    fn decoder(&mut self) -> Self::Decoder {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Bytes;
    type Error = Status;

    fn encode(&mut self, item: Bytes, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put(item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Bytes;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Bytes>, Status> {
        let length = src.remaining();
        Ok(Some(src.copy_to_bytes(length)))
    }
}

/// The methods the channel carries: the Python client's hot path.
const METHODS: [&str; 3] = ["/esrp.v1.Esrp/Step", "/esrp.v1.Esrp/Reset", "/esrp.v1.Esrp/StepBatch"];

/// A connection to an ESRP server for unary calls of serialized messages.
#[pyclass(frozen, module = "esrp_native")]
struct Channel {
    /// Driven by whichever thread is in a call (calls from several Python threads take
    /// turns driving it; the connection is shared). The connection is its tasks', which run only
    /// while a call drives them: `close` drops it (None after), so that the connection closes
    /// then, not when Python collects the channel (a server shutting down would wait for it).
    runtime: RwLock<Option<tokio::runtime::Runtime>>,
    grpc: tonic::client::Grpc<tonic::transport::Channel>,
    authorization: Option<MetadataValue<Ascii>>,
    /// Closed channels refuse calls.
    closed: Mutex<bool>,
}

#[pymethods]
impl Channel {
    /// Connects lazily to `url` (`http://host:port`): the first call opens the connection.
    #[new]
    #[pyo3(signature = (url, token = None, connect_timeout = 10.0))]
    fn new(url: &str, token: Option<&str>, connect_timeout: f64) -> PyResult<Self> {
        let connect_timeout = duration(connect_timeout, "connect_timeout")?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| PyValueError::new_err(format!("cannot start the native transport's runtime: {e}")))?;
        let client = {
            // connect_lazy spawns nothing until the first call, but needs a runtime entered.
            let _entered = runtime.enter();
            esrp_client::Client::connect(url)
                .token_opt(token)
                .connect_timeout(connect_timeout)
                .connect_lazy()
                .map_err(|e| PyValueError::new_err(e.to_string()))?
        };
        let authorization = token
            .map(|t| format!("Bearer {t}").parse::<MetadataValue<Ascii>>())
            .transpose()
            .map_err(|_| PyValueError::new_err("the token must be printable ASCII (no control characters)"))?;
        let grpc = tonic::client::Grpc::new(client.channel())
            .max_decoding_message_size(esrp_client::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(esrp_client::MAX_MESSAGE_BYTES);
        Ok(Channel { runtime: RwLock::new(Some(runtime)), grpc, authorization, closed: Mutex::new(false) })
    }

    /// Calls `method` (`/esrp.v1.Esrp/Step`, `/esrp.v1.Esrp/Reset` or `/esrp.v1.Esrp/StepBatch`)
    /// with the serialized `request`; the serialized answer, or `CallError(code, message)`.
    /// `timeout` in seconds (None: none), sent to the server as the call's deadline too.
    ///
    /// With `response` (the answer's protobuf message class), the answer comes parsed: its
    /// `FromString` reads a read-only memoryview over the bytes as they were received, released
    /// once it returns. No copy of the answer into a `bytes` object, whose fresh allocation of a
    /// batch's megabytes costs more than the copy itself (page faults, as the allocator hands
    /// that memory back to the system between calls).
    #[pyo3(signature = (method, request, timeout = None, response = None))]
    fn unary<'py>(
        &self,
        py: Python<'py>,
        method: &str,
        request: &[u8],
        timeout: Option<f64>,
        response: Option<&Bound<'py, PyType>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        check_response(py, response)?;
        let call = self.prepare(method, request, timeout)?;
        let answer = py.detach(|| self.run(call));
        match answer {
            Ok(answer) => read_answer(py, answer, response),
            Err(status) => Err(call_error(&status)),
        }
    }

    /// Refuses further calls and closes the connection (at once, unless a call on another thread
    /// is running: then when the channel is dropped).
    fn close(&self) {
        *self.closed.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = true;
        if let Ok(mut runtime) = self.runtime.try_write()
            && let Some(runtime) = runtime.take()
        {
            runtime.shutdown_background(); // its tasks, the connection's among them, are dropped
        }
    }
}

/// A unary call checked and built, ready to run without the GIL.
struct Prepared {
    path: &'static str,
    message: tonic::Request<Bytes>,
    timeout: Option<Duration>,
}

impl Channel {
    /// Checks `method`, `timeout` and that the channel is open, and builds the call's request.
    fn prepare(&self, method: &str, request: &[u8], timeout: Option<f64>) -> PyResult<Prepared> {
        let Some(path) = METHODS.iter().find(|m| **m == method) else {
            return Err(PyValueError::new_err(format!("{method:?} is not one of {METHODS:?}")));
        };
        let timeout = timeout.map(|t| duration(t, "timeout")).transpose()?;
        if *self.closed.lock().unwrap_or_else(std::sync::PoisonError::into_inner) {
            return Err(CallError::new_err((Code::Cancelled as i32, "the channel is closed")));
        }
        let mut message = tonic::Request::new(Bytes::copy_from_slice(request));
        if let Some(value) = &self.authorization {
            message.metadata_mut().insert("authorization", value.clone());
        }
        if let Some(timeout) = timeout {
            message.set_timeout(timeout);
        }
        Ok(Prepared { path, message, timeout })
    }

    /// Runs `call` to its end on this channel's runtime, driven by the calling thread (which must
    /// not hold the GIL): the answer's bytes, or its status.
    fn run(&self, call: Prepared) -> Result<Bytes, Status> {
        let Prepared { path, message, timeout } = call;
        let mut grpc = self.grpc.clone();
        let call = async move {
            grpc.ready().await.map_err(|e| Status::unavailable(format!("cannot reach the server: {e}")))?;
            let path = tonic::codegen::http::uri::PathAndQuery::from_static(path);
            grpc.unary(message, path, RawCodec).await
        };
        let started = std::time::Instant::now();
        let runtime = self.runtime.read().unwrap_or_else(std::sync::PoisonError::into_inner);
        let Some(runtime) = runtime.as_ref() else {
            return Err(Status::cancelled("the channel is closed"));
        };
        let answer = runtime.block_on(async {
            match timeout {
                None => call.await,
                Some(limit) => match tokio::time::timeout(limit, call).await {
                    Ok(answer) => answer,
                    Err(_) => Err(Status::deadline_exceeded("Deadline Exceeded")),
                },
            }
        });
        // tonic ends a call whose deadline passed as CANCELLED ("Timeout expired"); grpcio, and
        // so the rest of the Python client, say DEADLINE_EXCEEDED. An answer that came after the
        // deadline is one too, as grpcio's: tokio's timers tick by the millisecond, so a shorter
        // deadline would otherwise pass unnoticed by a call as quick as a step.
        let late = timeout.is_some_and(|limit| started.elapsed() >= limit);
        match answer {
            Ok(_) if late => Err(Status::deadline_exceeded("Deadline Exceeded")),
            Err(status) if late && status.code() == Code::Cancelled => {
                Err(Status::deadline_exceeded("Deadline Exceeded"))
            }
            answer => answer.map(tonic::Response::into_inner),
        }
    }
}

/// A call of `unary_all`: the channel, the method, the serialized request and the timeout.
type UnaryArgs<'py> = (Bound<'py, Channel>, String, Vec<u8>, Option<f64>);

/// Makes several unary calls at once, each `(channel, method, request, timeout)` as
/// `Channel.unary`'s arguments (the channels may differ: a vector env's servers), and waits for
/// all of them; their answers in order, each parsed by `response` (or as bytes without it), or,
/// for a call that failed, its `CallError` (returned, not raised: every call has ended either way).
///
/// The GIL is released once for all of them: one call runs on the calling thread and the others
/// on threads of their own, each driving its channel's runtime; the answers are parsed afterwards
/// on the calling thread. Python threads making the calls instead (one each, parsing its answer
/// when it came) cost a vector env over two servers about a tenth more CPU per step, and as
/// much in steps/s (measured side by side on the 2-core VM).
#[pyfunction]
#[pyo3(signature = (calls, response = None))]
fn unary_all<'py>(
    py: Python<'py>,
    calls: Vec<UnaryArgs<'py>>,
    response: Option<&Bound<'py, PyType>>,
) -> PyResult<Vec<Bound<'py, PyAny>>> {
    check_response(py, response)?;
    let mut prepared = Vec::with_capacity(calls.len());
    for (channel, method, request, timeout) in &calls {
        prepared.push((channel.get(), channel.get().prepare(method, request, *timeout)?));
    }
    let answers: Vec<Result<Bytes, Status>> = py.detach(|| {
        let Some((channel, last)) = prepared.pop() else {
            return Vec::new();
        };
        std::thread::scope(|scope| {
            let others: Vec<_> =
                prepared.into_iter().map(|(channel, call)| scope.spawn(move || channel.run(call))).collect();
            let last = channel.run(last);
            let mut answers: Vec<_> = others
                .into_iter()
                .map(|thread| thread.join().unwrap_or_else(|_| Err(Status::internal("a call's thread panicked"))))
                .collect();
            answers.push(last);
            answers
        })
    });
    answers
        .into_iter()
        .map(|answer| match answer {
            Ok(answer) => read_answer(py, answer, response),
            Err(status) => Ok(call_error(&status).into_value(py).into_bound(py).into_any()),
        })
        .collect()
}

/// Refuses a `response` that is not a protobuf message class.
fn check_response(py: Python<'_>, response: Option<&Bound<'_, PyType>>) -> PyResult<()> {
    if let Some(class) = response
        && !class.is_subclass(PROTOBUF_MESSAGE.import(py, "google.protobuf.message", "Message")?)?
    {
        return Err(PyTypeError::new_err(format!("response must be a protobuf message class, got {class}")));
    }
    Ok(())
}

/// An answer as `Channel.unary` returns it: parsed by `response` in place, or its bytes.
fn read_answer<'py>(
    py: Python<'py>,
    answer: Bytes,
    response: Option<&Bound<'py, PyType>>,
) -> PyResult<Bound<'py, PyAny>> {
    match response {
        None => Ok(PyBytes::new(py, &answer).into_any()),
        Some(class) => parse_in_place(py, answer, class),
    }
}

/// The `CallError(code, message)` of a failed call: a connection that broke under it is
/// UNAVAILABLE, as grpcio says (tonic says UNKNOWN "transport error").
fn call_error(status: &Status) -> PyErr {
    let code = esrp_client::error::status_code(status);
    CallError::new_err((code as i32, esrp_client::error::status_message(status)))
}

/// The answer `body` parsed by the protobuf message class `class` (`class.FromString(view)`) from
/// a read-only memoryview over it. protobuf's parser copies what it keeps, so the view is released
/// before `body` is dropped; should that fail (an export of it is still held), `body` is leaked
/// rather than freed under the export, and the error is raised. The crate's one unsafe block:
/// pyo3 has no safe memoryview over borrowed memory (its buffer protocol wants Python 3.11).
#[allow(unsafe_code)]
fn parse_in_place<'py>(py: Python<'py>, body: Bytes, class: &Bound<'py, PyType>) -> PyResult<Bound<'py, PyAny>> {
    let length = ffi::Py_ssize_t::try_from(body.len())
        .map_err(|_| PyValueError::new_err(format!("an answer of {} bytes", body.len())))?;
    // SAFETY: the view is read-only (PyBUF_READ) and points into `body`, which lives until the
    // view is released below, or forever if it cannot be.
    let view = unsafe {
        Bound::from_owned_ptr_or_err(
            py,
            ffi::PyMemoryView_FromMemory(body.as_ptr().cast_mut().cast(), length, PYBUF_READ),
        )?
    };
    let parsed = class.call_method1("FromString", (&view,));
    if let Err(error) = view.call_method0("release") {
        std::mem::forget(body);
        return Err(error);
    }
    parsed
}

/// `google.protobuf.message.Message`, the base class of every message class.
static PROTOBUF_MESSAGE: PyOnceLock<Py<PyType>> = PyOnceLock::new();

/// `PyBUF_READ` of CPython's memoryobject.h (pyo3-ffi has it only beyond the limited API).
const PYBUF_READ: std::ffi::c_int = 0x100;

/// `seconds` as a duration, or a ValueError naming `what`.
fn duration(seconds: f64, what: &str) -> PyResult<Duration> {
    Duration::try_from_secs_f64(seconds)
        .map_err(|_| PyValueError::new_err(format!("{what} must be a non-negative number of seconds, got {seconds}")))
}

#[pymodule]
fn esrp_native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Channel>()?;
    m.add_function(wrap_pyfunction!(unary_all, m)?)?;
    m.add("CallError", m.py().get_type::<CallError>())?;
    m.add("METHODS", METHODS.to_vec())?;
    Ok(())
}
