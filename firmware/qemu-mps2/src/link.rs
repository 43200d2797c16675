//! The drive's two links to a host (docs/drive-protocol.md §2): COBS frames on UART0, and
//! UDP datagrams on the Ethernet controller. The session belongs to the link (and, on UDP,
//! the address) of the HELLO the drive last answered; its SAMPLEs go there.

use crate::eth::Lan9118;
use crate::uart::Uart;
use smoltcp::iface::{Interface, SocketHandle, SocketSet};
use smoltcp::socket::udp;
use smoltcp::time::Instant;
use smoltcp::wire::IpEndpoint;
use stepdrive_drive_protocol::{
    cobs_encode, encode, Frame, FrameCollector, MAX_ENCODED, MAX_FRAME,
};

/// Where a frame came from, or where the session's host is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Peer {
    Serial,
    Udp(IpEndpoint),
}

pub struct Net<'a> {
    pub eth: Lan9118,
    pub iface: Interface,
    pub sockets: SocketSet<'a>,
    pub udp: SocketHandle,
}

pub struct Links<'a> {
    pub line: Uart,
    pub net: Option<Net<'a>>,
    collector: FrameCollector,
    /// The session's host, once a HELLO was answered.
    pub peer: Option<Peer>,
    /// Bytes taken from the UART, and frames the links would not take.
    pub serial_bytes: u32,
    pub unsent: u32,
}

impl<'a> Links<'a> {
    pub fn new(line: Uart, net: Option<Net<'a>>) -> Self {
        Self {
            line,
            net,
            collector: FrameCollector::new(),
            peer: None,
            serial_bytes: 0,
            unsent: 0,
        }
    }

    pub fn framing_errors(&self) -> u32 {
        self.collector.framing_errors
    }

    /// Whether anything waits on either link (the main loop must not sleep).
    pub fn pending(&self) -> bool {
        self.line.received() || (self.net.is_some() && Lan9118::received())
    }

    /// The next frame received on either link into `out`, with where it came from.
    pub fn receive(&mut self, now: Instant, out: &mut [u8; MAX_FRAME]) -> Option<(usize, Peer)> {
        while let Some(byte) = self.line.read() {
            self.serial_bytes = self.serial_bytes.wrapping_add(1);
            if let Some(n) = self.collector.push(byte, out) {
                return Some((n, Peer::Serial));
            }
        }
        let net = self.net.as_mut()?;
        net.iface.poll(now, &mut net.eth, &mut net.sockets);
        let socket = net.sockets.get_mut::<udp::Socket>(net.udp);
        let (data, meta) = socket.recv().ok()?;
        // A datagram longer than any frame cannot be one: the core sees it cut, and
        // refuses it (its CRC).
        let n = data.len().min(MAX_FRAME);
        out[..n].copy_from_slice(&data[..n]);
        Some((n, Peer::Udp(meta.endpoint)))
    }

    /// Sends `frame` to `to`.
    pub fn send(&mut self, frame: &Frame, to: Peer, now: Instant) {
        let mut raw = [0u8; MAX_FRAME];
        let n = encode(frame, &mut raw);
        let sent = match (to, self.net.as_mut()) {
            (Peer::Serial, _) => {
                let mut cobs = [0u8; MAX_ENCODED];
                let m = cobs_encode(&raw[..n], &mut cobs);
                self.line.write(&cobs[..m])
            }
            (Peer::Udp(endpoint), Some(net)) => {
                let socket = net.sockets.get_mut::<udp::Socket>(net.udp);
                let queued = socket.send_slice(&raw[..n], endpoint).is_ok();
                net.iface.poll(now, &mut net.eth, &mut net.sockets);
                queued
            }
            (Peer::Udp(_), None) => false,
        };
        self.unsent = self.unsent.wrapping_add(u32::from(!sent));
    }
}
