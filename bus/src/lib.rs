//! exocal-bus: the CAN transport shared by the hil emulator and the daemon.
//!
//! One trait, [`Transport`]: send a classic CAN [`Frame`], receive a [`Received`] frame with its
//! receive timestamp, and count frames the receiver dropped. Two implementations:
//!
//! - [`InProcessBus`] / [`Endpoint`]: every frame an endpoint sends is delivered to every other
//!   attached endpoint (not to itself), like a CAN bus with SocketCAN's default loopback.
//!   Timestamps come from the bus's [`Clock`]: the wall clock by default, or a [`SimClock`]
//!   given to [`InProcessBus::with_clock`]. An endpoint that falls more than
//!   the bus capacity behind loses the newest frames (as a full socket buffer would) and
//!   counts them in [`Transport::dropped`].
//! - `SocketCan` (feature `socketcan`): a raw CAN socket with an 8 MiB receive buffer, kernel
//!   receive timestamps (`SO_TIMESTAMPNS`) and the kernel's drop counter (`SO_RXQ_OVFL`); it
//!   sends and receives in batches (`sendmmsg`/`recvmmsg`), one system call per up to 64 frames.
//!
//! [`FaultInjector`] wraps either with a seeded faulty wire (drop, corrupt, delay, reorder,
//! duplicate: [`fault`]), its time passed in; the emulated suit draws its wire faults from the
//! same [`Faults`].
//!
//! Both `recv` futures are cancel-safe, so they can sit in a `tokio::select!` next to a timer.
//!
//! [`Clock`] is the one notion of time shared by the bus, the emulator and the daemon: the wall
//! clock, or simulated time ([`SimClock`], `speed` × the tokio runtime's clock). On a paused
//! tokio runtime simulated time is virtual — it advances only when every task waits — so a
//! session on the in-process bus is reproducible bit for bit. On SocketCAN the kernel stamps
//! frames and reproducibility is up to the kernel.

#![warn(missing_docs)]

use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

mod clock;
pub use clock::{Clock, SimClock};

pub mod fault;
pub use fault::{FaultConfig, FaultInjector, Faults};

pub use embedded_can;
/// The frame types live with the protocol (sans I/O): re-exported here for the transports.
pub use exocal_dbc::frame::{Frame, Received};

pub mod interface;

#[cfg(feature = "socketcan")]
mod socket;
#[cfg(feature = "socketcan")]
pub use socket::SocketCan;

/// Why a transport operation failed.
#[derive(Debug)]
pub enum BusError {
    /// The operating system refused (socket errors, interface missing, buffer full, …).
    Io(std::io::Error),
    /// The bus is gone.
    Closed,
}

impl std::fmt::Display for BusError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BusError::Io(e) => write!(f, "CAN I/O: {e}"),
            BusError::Closed => f.write_str("the CAN bus is closed"),
        }
    }
}

impl std::error::Error for BusError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            BusError::Io(e) => Some(e),
            BusError::Closed => None,
        }
    }
}

impl From<std::io::Error> for BusError {
    fn from(e: std::io::Error) -> Self {
        BusError::Io(e)
    }
}

/// A CAN interface: frames out, timestamped frames in.
pub trait Transport: Send {
    /// Sends one frame.
    fn send(&mut self, frame: &Frame) -> impl Future<Output = Result<(), BusError>> + Send;
    /// Sends frames in order; transports that can batch (SocketCAN: `sendmmsg`) do.
    fn send_all(&mut self, frames: &[Frame]) -> impl Future<Output = Result<(), BusError>> + Send {
        async move {
            for f in frames {
                self.send(f).await?;
            }
            Ok(())
        }
    }
    /// Waits for the next frame sent by someone else. Cancel-safe.
    fn recv(&mut self) -> impl Future<Output = Result<Received, BusError>> + Send;
    /// Frames lost by this receiver so far (receive queue overflow).
    fn dropped(&self) -> u64;
}

struct Port {
    id: u64,
    tx: tokio::sync::mpsc::Sender<Received>,
    dropped: Arc<AtomicU64>,
}

struct Shared {
    ports: std::sync::Mutex<Vec<Port>>,
    next_endpoint: AtomicU64,
    capacity: usize,
    clock: Clock,
}

/// An in-process CAN bus; cheap to clone (clones share the bus).
#[derive(Clone)]
pub struct InProcessBus {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for InProcessBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let n = self.shared.ports.lock().map_or(0, |p| p.len());
        f.debug_struct("InProcessBus")
            .field("endpoints", &n)
            .finish()
    }
}

impl InProcessBus {
    /// Frames each endpoint may have waiting before new ones are dropped, by default.
    pub const DEFAULT_CAPACITY: usize = 65_536;

    /// A bus stamping frames with the wall clock.
    pub fn new() -> Self {
        Self::with_clock(Self::DEFAULT_CAPACITY, Clock::Wall)
    }

    /// A bus with its own per-endpoint receive-queue capacity and timestamp clock.
    pub fn with_clock(capacity: usize, clock: Clock) -> Self {
        InProcessBus {
            shared: Arc::new(Shared {
                ports: std::sync::Mutex::new(Vec::new()),
                next_endpoint: AtomicU64::new(0),
                capacity: capacity.max(1),
                clock,
            }),
        }
    }

    /// Attaches a new endpoint; it receives frames sent after this call.
    pub fn attach(&self) -> Endpoint {
        let id = self.shared.next_endpoint.fetch_add(1, Ordering::Relaxed);
        let (tx, rx) = tokio::sync::mpsc::channel(self.shared.capacity);
        let dropped = Arc::new(AtomicU64::new(0));
        let port = Port {
            id,
            tx,
            dropped: dropped.clone(),
        };
        self.shared
            .ports
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(port);
        Endpoint {
            id,
            shared: self.shared.clone(),
            rx,
            dropped,
        }
    }
}

impl Default for InProcessBus {
    fn default() -> Self {
        Self::new()
    }
}

/// One node's connection to an [`InProcessBus`]. Dropping it detaches it.
pub struct Endpoint {
    id: u64,
    shared: Arc<Shared>,
    rx: tokio::sync::mpsc::Receiver<Received>,
    dropped: Arc<AtomicU64>,
}

impl Endpoint {
    /// Sends without waiting (the in-process bus never blocks): every other endpoint gets the
    /// frame, or counts it as dropped if its queue is full.
    pub fn send_now(&self, frame: &Frame) {
        let rx = Received {
            frame: *frame,
            timestamp: self.shared.clock.now(),
        };
        let mut ports = self.shared.ports.lock().unwrap_or_else(|e| e.into_inner());
        ports.retain(|p| {
            if p.id == self.id {
                return true;
            }
            match p.tx.try_send(rx) {
                Ok(()) => true,
                Err(tokio::sync::mpsc::error::TrySendError::Full(_)) => {
                    p.dropped.fetch_add(1, Ordering::Relaxed);
                    true
                }
                // The endpoint is gone: detach it.
                Err(tokio::sync::mpsc::error::TrySendError::Closed(_)) => false,
            }
        });
    }

    /// The next frame if one is waiting, without blocking.
    pub fn try_recv(&mut self) -> Option<Received> {
        self.rx.try_recv().ok()
    }
}

impl Transport for Endpoint {
    async fn send(&mut self, frame: &Frame) -> Result<(), BusError> {
        self.send_now(frame);
        Ok(())
    }

    async fn recv(&mut self) -> Result<Received, BusError> {
        // Our own port holds the sender, so the channel never closes while we exist.
        self.rx.recv().await.ok_or(BusError::Closed)
    }

    fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::{Frame as _, StandardId};

    fn frame(id: u16, byte: u8) -> Frame {
        Frame::new(StandardId::new(id).unwrap(), &[byte; 8]).unwrap()
    }

    #[tokio::test]
    async fn frames_reach_every_other_endpoint_but_not_the_sender() {
        let bus = InProcessBus::new();
        let mut a = bus.attach();
        let mut b = bus.attach();
        let mut c = bus.attach();
        a.send(&frame(0x101, 1)).await.unwrap();
        b.send(&frame(0x102, 2)).await.unwrap();
        assert_eq!(b.recv().await.unwrap().frame, frame(0x101, 1));
        assert_eq!(c.recv().await.unwrap().frame, frame(0x101, 1));
        assert_eq!(c.recv().await.unwrap().frame, frame(0x102, 2));
        assert_eq!(a.recv().await.unwrap().frame, frame(0x102, 2));
        assert!(a.try_recv().is_none(), "the sender does not hear itself");
    }

    #[tokio::test(start_paused = true)]
    async fn a_slow_endpoint_counts_what_it_lost() {
        let clock = SimClock::new(1.0).unwrap().bus_clock();
        let bus = InProcessBus::with_clock(4, clock);
        let tx = bus.attach();
        let mut rx = bus.attach();
        for i in 0..10 {
            tx.send_now(&frame(0x100, i));
        }
        assert_eq!(rx.dropped(), 6);
        let first = rx.recv().await.unwrap();
        assert_eq!(first.frame, frame(0x100, 0));
        assert_eq!(first.timestamp, clock.now(), "stamped in simulated time");
        assert_eq!(tx.dropped(), 0, "the sender queues nothing for itself");
    }

    #[tokio::test]
    async fn dropped_endpoints_detach() {
        let bus = InProcessBus::new();
        let a = bus.attach();
        drop(bus.attach());
        a.send_now(&frame(1, 1));
        assert_eq!(format!("{bus:?}"), "InProcessBus { endpoints: 1 }");
    }
}
