//! Where gRPC is served: the TCP address of `--listen` and, with `--listen-unix PATH`, a Unix
//! domain socket beside it, both answered by one server ([`incoming`]).
//!
//! The socket is for clients on the same machine (`unix:PATH` in the Rust, Python and grpcio
//! clients): a step's 49 KB observation crosses it with about half the kernel work of loopback
//! TCP (docs/performance.md). Who may connect is decided by the socket file's permissions (set by
//! the server's umask: with the usual 022, its own user only), and `--token` applies as on TCP.
//!
//! [`UnixSocket::bind`] replaces a socket file that a killed server left behind (nothing
//! answers on it), refuses one a live server answers on and any file that is not a socket, and
//! the socket file is removed when its [`SocketFile`] is dropped (as the server stops), if it is
//! still the one bound.

use std::io;
use std::os::unix::fs::{FileTypeExt, MetadataExt};
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::task::{Context, Poll};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream, UnixListener, UnixStream};
use tokio_stream::wrappers::UnixListenerStream;
use tokio_stream::{Stream, StreamExt};
use tonic::transport::server::{Connected, TcpConnectInfo, TcpIncoming, UdsConnectInfo};

/// Why a Unix domain socket cannot be served.
#[derive(Debug, thiserror::Error)]
pub enum UnixSocketError {
    /// A server already answers on the socket.
    #[error("--listen-unix {}: another server is listening on this socket", .0.display())]
    InUse(PathBuf),
    /// The path names a file that is not a socket (it is not replaced).
    #[error("--listen-unix {}: the path exists and is not a socket (not replaced)", .0.display())]
    NotASocket(PathBuf),
    /// The path is too long for a socket address (at most 107 bytes on Linux).
    #[error("--listen-unix {}: a socket's path must be shorter than {max} bytes (give a shorter or relative path)", .path.display())]
    TooLong {
        /// The path given.
        path: PathBuf,
        /// The limit of the platform's socket address.
        max: usize,
    },
    /// Binding, or checking or replacing an old socket file, failed.
    #[error("--listen-unix {}: {what}: {source}", .path.display())]
    Io {
        /// The path given.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// The error.
        source: io::Error,
    },
}

/// Room for a path in `sockaddr_un` (`sun_path`, with its terminating zero) on Linux and the BSDs'
/// larger one alike: the smaller, Linux's 108.
const SUN_PATH_BYTES: usize = 108;

/// A bound Unix domain socket: its listener, and its file (removed on drop).
#[derive(Debug)]
pub struct UnixSocket {
    listener: UnixListener,
    file: SocketFile,
}

/// The file of a bound Unix domain socket, removed when this is dropped if it is still the file
/// that was bound (another server may have replaced it since).
#[derive(Debug)]
pub struct SocketFile {
    path: PathBuf,
    /// The socket file's device and inode.
    id: (u64, u64),
}

impl UnixSocket {
    /// Binds `path` (in a Tokio runtime), replacing a socket file nothing answers on (left by a
    /// server that was killed).
    pub fn bind(path: &Path) -> Result<Self, UnixSocketError> {
        let io_error = |what, source| UnixSocketError::Io { path: path.to_path_buf(), what, source };
        if path.as_os_str().len() >= SUN_PATH_BYTES {
            return Err(UnixSocketError::TooLong { path: path.to_path_buf(), max: SUN_PATH_BYTES });
        }
        match std::fs::symlink_metadata(path) {
            Ok(meta) if !meta.file_type().is_socket() => return Err(UnixSocketError::NotASocket(path.to_path_buf())),
            Ok(_) => match std::os::unix::net::UnixStream::connect(path) {
                Ok(_) => return Err(UnixSocketError::InUse(path.to_path_buf())),
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => {
                    std::fs::remove_file(path).map_err(|e| io_error("cannot remove the old socket file", e))?;
                    tracing::info!(path = %path.display(), "replaced a socket file nothing answered on");
                }
                Err(e) => return Err(io_error("cannot check the existing socket file", e)),
            },
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_error("cannot check the path", e)),
        }
        let listener = UnixListener::bind(path).map_err(|e| io_error("cannot listen", e))?;
        let meta = std::fs::symlink_metadata(path).map_err(|e| io_error("cannot read the new socket file", e))?;
        Ok(UnixSocket { listener, file: SocketFile { path: path.to_path_buf(), id: (meta.dev(), meta.ino()) } })
    }

    /// The socket's path, as given.
    pub fn path(&self) -> &Path {
        &self.file.path
    }

    /// The listener, and the file to drop when the server no longer listens.
    pub fn into_parts(self) -> (UnixListener, SocketFile) {
        (self.listener, self.file)
    }
}

impl Drop for SocketFile {
    fn drop(&mut self) {
        let ours = std::fs::symlink_metadata(&self.path).is_ok_and(|meta| (meta.dev(), meta.ino()) == self.id);
        if ours && let Err(e) = std::fs::remove_file(&self.path) {
            tracing::warn!(path = %self.path.display(), "cannot remove the socket file: {e}");
        }
    }
}

/// One gRPC connection: over TCP or the Unix domain socket.
#[derive(Debug)]
pub enum Connection {
    /// From `--listen`.
    Tcp(TcpStream),
    /// From `--listen-unix`.
    Unix(UnixStream),
}

/// Who is on the other end of a [`Connection`] (in each request's extensions, as tonic's own).
#[derive(Clone, Debug)]
pub enum ConnectionInfo {
    /// A TCP peer.
    Tcp(TcpConnectInfo),
    /// A Unix domain socket peer (its process's credentials).
    Unix(UdsConnectInfo),
}

impl Connected for Connection {
    type ConnectInfo = ConnectionInfo;

    fn connect_info(&self) -> ConnectionInfo {
        match self {
            Connection::Tcp(stream) => ConnectionInfo::Tcp(stream.connect_info()),
            Connection::Unix(stream) => ConnectionInfo::Unix(stream.connect_info()),
        }
    }
}

/// Forwards each I/O call to the stream inside.
macro_rules! forward {
    ($self:ident, $stream:ident => $call:expr) => {
        match $self.get_mut() {
            Connection::Tcp($stream) => {
                let $stream = Pin::new($stream);
                $call
            }
            Connection::Unix($stream) => {
                let $stream = Pin::new($stream);
                $call
            }
        }
    };
}

impl AsyncRead for Connection {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        forward!(self, stream => stream.poll_read(cx, buf))
    }
}

impl AsyncWrite for Connection {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        forward!(self, stream => stream.poll_write(cx, buf))
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        forward!(self, stream => stream.poll_write_vectored(cx, bufs))
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            Connection::Tcp(stream) => stream.is_write_vectored(),
            Connection::Unix(stream) => stream.is_write_vectored(),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        forward!(self, stream => stream.poll_flush(cx))
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        forward!(self, stream => stream.poll_shutdown(cx))
    }
}

/// The connections accepted on `tcp` (with TCP_NODELAY: an agent waits for each answer, so Nagle
/// and delayed ACKs would add ~40 ms a step) and, where given, on `unix`, as they come.
pub fn incoming(
    tcp: TcpListener,
    unix: Option<UnixListener>,
) -> impl Stream<Item = io::Result<Connection>> + Send + 'static {
    let tcp = TcpIncoming::from(tcp).with_nodelay(Some(true)).map(|c| c.map(Connection::Tcp));
    let unix: Pin<Box<dyn Stream<Item = io::Result<Connection>> + Send>> = match unix {
        Some(listener) => Box::pin(UnixListenerStream::new(listener).map(|c| c.map(Connection::Unix))),
        None => Box::pin(tokio_stream::empty()),
    };
    tcp.merge(unix)
}
