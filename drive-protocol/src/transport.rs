//! The byte transports of the drive protocol: UDP (one datagram per frame) and a serial
//! line (COBS-framed, 0x00-delimited), behind one interface for the bridge and the
//! emulated drive. Receiving tells three things apart: a frame, nothing yet (silence), and
//! a peer that is gone ([`WireError`]: a serial line that hung up, a UDP peer whose port
//! answers "unreachable").

use crate::{cobs_decode, cobs_encode, MAX_FRAME};
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::path::Path;

/// Bytes taken from the line per read.
const READ_CHUNK: usize = 1024;

/// The peer is gone, as opposed to silent.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("the serial line hung up")]
    HungUp,
    #[error("nothing listens there (the host answers \"port unreachable\")")]
    Refused,
    #[error("receive failed")]
    Io(#[source] io::Error),
}

/// COBS frames out of a byte stream: bytes in as they come, whole frames out, decoded. The
/// buffer is sized once; bytes without a delimiter cannot grow it without bound.
pub struct Deframer {
    rx: Vec<u8>,
    /// Frames dropped because their COBS encoding was broken, and runs of bytes dropped for
    /// want of a delimiter.
    pub framing_errors: u64,
}

/// The most a [`Deframer`] holds before it gives up on finding a delimiter.
const DEFRAMER_LIMIT: usize = 16 * MAX_FRAME;

impl Default for Deframer {
    fn default() -> Self {
        Self {
            // The most it holds before the guard below clears it: never regrown.
            rx: Vec::with_capacity(DEFRAMER_LIMIT + READ_CHUNK),
            framing_errors: 0,
        }
    }
}

impl Deframer {
    /// Bytes read from the line.
    pub fn push(&mut self, bytes: &[u8]) {
        self.rx.extend_from_slice(bytes);
        if self.rx.len() > DEFRAMER_LIMIT && !self.rx.contains(&0) {
            self.rx.clear();
            self.framing_errors += 1;
        }
    }

    /// The next complete frame, decoded into `out`; its length.
    pub fn next_frame(&mut self, out: &mut [u8]) -> Option<usize> {
        while let Some(end) = self.rx.iter().position(|&b| b == 0) {
            // Decoded in place, then dropped from the buffer: no allocation per frame.
            let decoded = cobs_decode(&self.rx[..end], out);
            self.rx.drain(..=end);
            match decoded {
                Ok(n) if n > 0 => return Some(n),
                _ => self.framing_errors += 1,
            }
        }
        None
    }
}

/// A raw serial line (a UART or a pseudo-terminal), non-blocking, with COBS framing.
pub struct SerialPort {
    fd: OwnedFd,
    deframer: Deframer,
}

impl SerialPort {
    pub fn open(path: &Path) -> io::Result<Self> {
        let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes())
            .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "NUL in path"))?;
        // SAFETY: valid C string; the returned fd is owned below.
        let fd =
            unsafe { libc::open(c.as_ptr(), libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK) };
        if fd < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: `fd` was just opened and is owned by nobody else.
        let fd = unsafe { OwnedFd::from_raw_fd(fd) };
        // Raw 8N1, no echo, no line discipline; the speed matters only on a real UART.
        // SAFETY: termios is plain data filled by tcgetattr.
        unsafe {
            let mut t: libc::termios = std::mem::zeroed();
            if libc::tcgetattr(fd.as_raw_fd(), &mut t) == 0 {
                libc::cfmakeraw(&mut t);
                libc::cfsetspeed(&mut t, libc::B921600);
                libc::tcsetattr(fd.as_raw_fd(), libc::TCSANOW, &t);
            }
        }
        Ok(Self {
            fd,
            deframer: Deframer::default(),
        })
    }

    pub fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        let mut enc = [0u8; 2 * MAX_FRAME + 2];
        let n = cobs_encode(frame, &mut enc);
        let mut at = 0;
        while at < n {
            // SAFETY: writing from a valid buffer slice to our own fd.
            let w = unsafe { libc::write(self.fd.as_raw_fd(), enc[at..n].as_ptr().cast(), n - at) };
            if w < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::WouldBlock {
                    // A full line buffer drops the rest of the frame; the 0x00 delimiter
                    // of the next one resynchronises the receiver.
                    return Ok(());
                }
                return Err(e);
            }
            at += w as usize;
        }
        Ok(())
    }

    /// Next complete frame (decoded) into `out`, waiting up to `wait_ms` for bytes.
    pub fn recv(&mut self, out: &mut [u8], wait_ms: i32) -> Result<Option<usize>, WireError> {
        loop {
            if let Some(n) = self.deframer.next_frame(out) {
                return Ok(Some(n));
            }
            let mut pfd = libc::pollfd {
                fd: self.fd.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            };
            // SAFETY: one valid pollfd.
            if unsafe { libc::poll(&mut pfd, 1, wait_ms) } <= 0 {
                return Ok(None);
            }
            let mut buf = [0u8; READ_CHUNK];
            // SAFETY: reading into a valid buffer from our own fd.
            let r = unsafe { libc::read(self.fd.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
            if r == 0 {
                return Err(WireError::HungUp);
            }
            if r < 0 {
                let e = io::Error::last_os_error();
                return match e.raw_os_error() {
                    Some(libc::EAGAIN) | Some(libc::EINTR) => Ok(None),
                    // A pseudo-terminal whose other side closed, a UART unplugged.
                    Some(libc::EIO) | Some(libc::ENXIO) | Some(libc::ENODEV) => {
                        Err(WireError::HungUp)
                    }
                    _ => Err(WireError::Io(e)),
                };
            }
            self.deframer.push(&buf[..r as usize]);
        }
    }
}

/// Where a drive or a host sends and receives frames.
pub enum Wire {
    /// Host side: a socket connected to the drive. Drive side: a bound socket that answers
    /// whoever sent the last HELLO (`peer`).
    Udp {
        sock: UdpSocket,
        peer: Option<SocketAddr>,
    },
    Serial(SerialPort),
}

impl Wire {
    /// The host's side: a socket connected to the drive at `drive`, with room for ~100 ms
    /// of frames queued.
    pub fn connect_udp(drive: SocketAddr) -> io::Result<Self> {
        let local = match (drive.is_ipv4(), drive.ip().is_loopback()) {
            (true, true) => "127.0.0.1:0",
            (true, false) => "0.0.0.0:0",
            (false, true) => "[::1]:0",
            (false, false) => "[::]:0",
        };
        let sock = UdpSocket::bind(local)?;
        sock.connect(drive)?;
        sock.set_nonblocking(true)?;
        let granted = enlarge_receive_buffer(&sock, RECEIVE_BUFFER_BYTES);
        tracing::debug!(bytes = granted, "drive socket receive buffer");
        Ok(Wire::Udp { sock, peer: None })
    }

    /// A drive's side: bound to `listen`, answering whoever sent the last HELLO.
    pub fn bind_udp(listen: SocketAddr) -> io::Result<Self> {
        let sock = UdpSocket::bind(listen)?;
        sock.set_nonblocking(true)?;
        enlarge_receive_buffer(&sock, RECEIVE_BUFFER_BYTES);
        Ok(Wire::Udp { sock, peer: None })
    }

    pub fn open_serial(path: &Path) -> io::Result<Self> {
        SerialPort::open(path).map(Wire::Serial)
    }

    /// Receives one frame into `buf`, waiting up to `wait_ms` (0: do not wait).
    /// Returns its length and, on UDP, its source; `None` when nothing came.
    pub fn recv(
        &mut self,
        buf: &mut [u8],
        wait_ms: i32,
    ) -> Result<Option<(usize, Option<SocketAddr>)>, WireError> {
        match self {
            Wire::Udp { sock, .. } => {
                let flags = if wait_ms > 0 { 0 } else { libc::MSG_DONTWAIT };
                // SAFETY: sockaddr_storage is plain data; all zeroes is a valid value.
                let mut addr: libc::sockaddr_storage = unsafe { std::mem::zeroed() };
                let mut len = std::mem::size_of::<libc::sockaddr_storage>() as libc::socklen_t;
                // SAFETY: valid buffer and address storage for recvfrom.
                let n = unsafe {
                    libc::recvfrom(
                        sock.as_raw_fd(),
                        buf.as_mut_ptr().cast(),
                        buf.len(),
                        flags,
                        (&mut addr as *mut libc::sockaddr_storage).cast(),
                        &mut len,
                    )
                };
                if n < 0 {
                    let e = io::Error::last_os_error();
                    return match e.raw_os_error() {
                        Some(libc::EAGAIN) | Some(libc::EINTR) => Ok(None),
                        // A connected socket learns from ICMP that no one listens.
                        Some(libc::ECONNREFUSED) => Err(WireError::Refused),
                        _ => Err(WireError::Io(e)),
                    };
                }
                Ok(Some((n as usize, sockaddr_to_std(&addr))))
            }
            Wire::Serial(p) => Ok(p.recv(buf, wait_ms)?.map(|n| (n, None))),
        }
    }

    /// Sends one frame to the peer (dropped if there is none yet or the line is full).
    pub fn send(&mut self, frame: &[u8]) {
        match self {
            Wire::Udp { sock, peer } => {
                let _ = match peer {
                    Some(p) => sock.send_to(frame, *p),
                    None => sock.send(frame),
                };
            }
            Wire::Serial(p) => {
                let _ = p.send(frame);
            }
        }
    }

    /// A host whose drive was never heard: whether the drive's host sends from another
    /// port instead (§2 forbids it; the connected socket's kernel discards such datagrams
    /// unseen). The socket is disconnected, `hello` sent to `drive`, datagrams read for up
    /// to `wait_ms`, and the socket connected to `drive` again (for the DISABLE that
    /// follows): the first source other than `drive` on its address.
    pub fn listen_elsewhere(
        &mut self,
        drive: SocketAddr,
        hello: &[u8],
        wait_ms: i32,
    ) -> Option<SocketAddr> {
        let Wire::Udp { sock, .. } = self else {
            return None;
        };
        // SAFETY: sockaddr with family AF_UNSPEC dissolves the association (connect(2)).
        let unspec = libc::sockaddr {
            sa_family: libc::AF_UNSPEC as libc::sa_family_t,
            sa_data: [0; 14],
        };
        // SAFETY: a valid sockaddr of its own size on our own socket.
        let rc = unsafe {
            libc::connect(
                sock.as_raw_fd(),
                &unspec,
                std::mem::size_of::<libc::sockaddr>() as libc::socklen_t,
            )
        };
        if rc != 0 {
            return None;
        }
        let _ = sock.send_to(hello, drive);
        let found = Self::first_source_other_than(sock, drive, wait_ms);
        let _ = sock.connect(drive);
        found
    }

    fn first_source_other_than(
        sock: &UdpSocket,
        drive: SocketAddr,
        wait_ms: i32,
    ) -> Option<SocketAddr> {
        let deadline =
            std::time::Instant::now() + std::time::Duration::from_millis(wait_ms.max(0) as u64);
        let mut buf = [0u8; 64];
        while std::time::Instant::now() < deadline {
            let mut pfd = libc::pollfd {
                fd: sock.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            };
            // SAFETY: one valid pollfd.
            if unsafe { libc::poll(&mut pfd, 1, 5) } <= 0 {
                continue;
            }
            match sock.recv_from(&mut buf) {
                // A datagram too long for the buffer is still one whose source tells.
                Ok((_, from)) if from != drive && from.ip() == drive.ip() => return Some(from),
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(_) => return None,
            }
        }
        None
    }

    /// The descriptor to `poll()` for incoming frames.
    pub fn raw_fd(&self) -> RawFd {
        match self {
            Wire::Udp { sock, .. } => sock.as_raw_fd(),
            Wire::Serial(p) => p.fd.as_raw_fd(),
        }
    }
}

/// Room for ~100 ms of frames at 20 kHz, so that a stalled receiver finds them queued
/// instead of lost (the default, ~200 KB, holds a few hundred).
pub const RECEIVE_BUFFER_BYTES: usize = 4 << 20;

/// Asks for a `bytes` receive buffer (SO_RCVBUFFORCE as root, else SO_RCVBUF up to the
/// system's rmem_max); returns what the kernel granted.
pub fn enlarge_receive_buffer(sock: &UdpSocket, bytes: usize) -> usize {
    let fd = sock.as_raw_fd();
    let want = bytes.min(i32::MAX as usize) as libc::c_int;
    let size = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
    for opt in [libc::SO_RCVBUFFORCE, libc::SO_RCVBUF] {
        // SAFETY: setsockopt with a valid int option value.
        let rc = unsafe {
            libc::setsockopt(
                fd,
                libc::SOL_SOCKET,
                opt,
                (&want as *const libc::c_int).cast(),
                size,
            )
        };
        if rc == 0 {
            break;
        }
    }
    let mut got: libc::c_int = 0;
    let mut len = size;
    // SAFETY: getsockopt into a valid int.
    unsafe {
        libc::getsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&mut got as *mut libc::c_int).cast(),
            &mut len,
        )
    };
    got.max(0) as usize
}

fn sockaddr_to_std(a: &libc::sockaddr_storage) -> Option<SocketAddr> {
    match i32::from(a.ss_family) {
        libc::AF_INET => {
            // SAFETY: the family says this storage holds a sockaddr_in.
            let v4: &libc::sockaddr_in = unsafe { &*(a as *const _ as *const libc::sockaddr_in) };
            let ip = std::net::Ipv4Addr::from(u32::from_be(v4.sin_addr.s_addr));
            Some(SocketAddr::new(ip.into(), u16::from_be(v4.sin_port)))
        }
        libc::AF_INET6 => {
            // SAFETY: the family says this storage holds a sockaddr_in6.
            let v6: &libc::sockaddr_in6 = unsafe { &*(a as *const _ as *const libc::sockaddr_in6) };
            let ip = std::net::Ipv6Addr::from(v6.sin6_addr.s6_addr);
            Some(SocketAddr::new(ip.into(), u16::from_be(v6.sin6_port)))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{encode, frame_bytes, Frame, Message};
    use proptest::prelude::*;

    proptest! {
        /// Frames COBS-encoded back to back, cut into arbitrary chunks: every frame comes
        /// out, whole and in order.
        #[test]
        fn frames_survive_any_chunking(
            seqs in proptest::collection::vec(any::<u32>(), 1..20),
            cuts in proptest::collection::vec(1usize..200, 1..40),
        ) {
            let mut stream = Vec::new();
            for &seq in &seqs {
                let raw = frame_bytes(seq, Message::Hello);
                let mut enc = [0u8; 2 * MAX_FRAME + 2];
                let n = cobs_encode(&raw, &mut enc);
                stream.extend_from_slice(&enc[..n]);
            }
            let mut d = Deframer::default();
            let mut got = Vec::new();
            let mut out = [0u8; MAX_FRAME];
            let mut at = 0;
            for cut in cuts.iter().cycle() {
                if at >= stream.len() {
                    break;
                }
                let end = (at + cut).min(stream.len());
                d.push(&stream[at..end]);
                at = end;
                while let Some(n) = d.next_frame(&mut out) {
                    got.push(crate::decode(&out[..n]).map(|f| f.seq));
                }
            }
            let want: Vec<Result<u32, crate::DecodeError>> = seqs.iter().map(|&s| Ok(s)).collect();
            prop_assert_eq!(got, want);
            prop_assert_eq!(d.framing_errors, 0);
        }

        /// Arbitrary bytes on the line: no panic; garbage never grows the buffer past its
        /// limit.
        #[test]
        fn garbage_on_the_line_never_panics(
            chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..2000), 1..30),
        ) {
            let mut d = Deframer::default();
            let mut out = [0u8; MAX_FRAME];
            for c in &chunks {
                d.push(c);
                while d.next_frame(&mut out).is_some() {}
                prop_assert!(d.rx.len() <= DEFRAMER_LIMIT + 2000);
            }
        }
    }

    #[test]
    fn a_frame_split_across_reads_is_whole() {
        let f = Frame {
            seq: 3,
            timestamp_ns: 9,
            message: Message::Hello,
        };
        let mut raw = [0u8; MAX_FRAME];
        let n = encode(&f, &mut raw);
        let mut enc = [0u8; 2 * MAX_FRAME + 2];
        let m = cobs_encode(&raw[..n], &mut enc);
        let mut d = Deframer::default();
        let mut out = [0u8; MAX_FRAME];
        d.push(&enc[..5]);
        assert_eq!(d.next_frame(&mut out), None);
        d.push(&enc[5..m]);
        assert_eq!(d.next_frame(&mut out), Some(n));
        assert_eq!(&out[..n], &raw[..n]);
    }
}
