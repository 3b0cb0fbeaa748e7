//! Whether a connection's client has hung up, asked of the socket without reading from it.
//!
//! A frame waiting in the admission line has not had its body read, so hyper does not read
//! its HTTP/1 connection and would not notice a client that closed it until the frame's turn
//! came. The kernel knows: a peer's FIN or reset marks the socket (`POLLRDHUP`, `POLLHUP`,
//! `POLLERR`) even while unread body bytes sit before it. HTTP/2 needs none of this: hyper
//! drops a stream's work when the stream is reset or its connection ends.

use std::os::fd::RawFd;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// A connection's socket, as the requests on it may ask about it. The connection clears it
/// before it closes the socket, so a descriptor number is never asked about after it may have
/// been reused.
pub struct Peer {
    fd: Mutex<Option<RawFd>>,
}

impl Peer {
    /// How often a waiting frame asks.
    pub const EVERY: Duration = Duration::from_millis(100);

    pub(super) fn new(fd: RawFd) -> Arc<Peer> {
        Arc::new(Peer { fd: Mutex::new(Some(fd)) })
    }

    /// The connection is closing its socket: from now on the peer counts as gone.
    pub(super) fn closed(&self) {
        if let Ok(mut fd) = self.fd.lock() {
            *fd = None;
        }
    }

    /// True once the client has closed or reset the connection (or the server has closed it).
    pub fn hung_up(&self) -> bool {
        let Ok(fd) = self.fd.lock() else { return false };
        fd.is_none_or(peer_closed)
    }

    /// Resolves once [`Peer::hung_up`], asking every [`Peer::EVERY`].
    pub async fn until_hung_up(&self) {
        while !self.hung_up() {
            tokio::time::sleep(Peer::EVERY).await;
        }
    }
}

#[cfg(any(target_os = "linux", target_os = "android"))]
fn peer_closed(fd: RawFd) -> bool {
    let mut p = libc::pollfd { fd, events: libc::POLLRDHUP, revents: 0 };
    // SAFETY: poll reads and writes the one struct passed; a zero timeout never blocks. The
    // caller holds the lock that keeps `fd` open.
    // Asked only for POLLRDHUP, poll reports the socket only with POLLRDHUP or one of POLLHUP,
    // POLLERR and POLLNVAL (never masked), each of which means the client is gone.
    unsafe { libc::poll(&mut p, 1, 0) > 0 }
}

/// Without `POLLRDHUP` a waiting HTTP/1 client that hangs up is noticed at its turn.
#[cfg(not(any(target_os = "linux", target_os = "android")))]
fn peer_closed(_fd: RawFd) -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::fd::AsRawFd;
    use tokio::io::AsyncWriteExt;
    use tokio::net::{TcpListener, TcpStream};

    async fn pair() -> (TcpStream, TcpStream) {
        let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let client = TcpStream::connect(l.local_addr().unwrap()).await.unwrap();
        (client, l.accept().await.unwrap().0)
    }

    #[tokio::test]
    async fn a_hang_up_is_seen_behind_unread_bytes_and_a_live_client_is_not() {
        let (mut client, server) = pair().await;
        let peer = Peer::new(server.as_raw_fd());
        client.write_all(b"POST / HTTP/1.1\r\nContent-Length: 5\r\n\r\nhello").await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!peer.hung_up(), "unread bytes from a live client");
        drop(client);
        tokio::time::timeout(Duration::from_secs(2), peer.until_hung_up()).await.expect("the hang-up was not seen");
        peer.closed();
        assert!(peer.hung_up());
    }

    #[tokio::test]
    async fn a_connection_the_server_closes_counts_as_gone() {
        let (_client, server) = pair().await;
        let peer = Peer::new(server.as_raw_fd());
        assert!(!peer.hung_up());
        peer.closed();
        assert!(peer.hung_up(), "a closed connection has nobody waiting on it");
    }

    #[tokio::test]
    async fn a_client_that_only_stops_writing_is_gone_too() {
        let (mut client, server) = pair().await;
        let peer = Peer::new(server.as_raw_fd());
        assert!(!peer.hung_up());
        client.shutdown().await.unwrap();
        tokio::time::timeout(Duration::from_secs(2), peer.until_hung_up()).await.expect("the FIN was not seen");
    }
}
