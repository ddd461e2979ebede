//! SocketCAN adapter: a raw CAN socket driven by tokio.
//!
//! Contract: the receive buffer is asked for 8 MiB (`SO_RCVBUFFORCE`, which needs
//! CAP_NET_ADMIN, else `SO_RCVBUF`, capped by `net.core.rmem_max`); every received frame carries
//! the kernel's software receive timestamp (`SO_TIMESTAMPNS`, wall clock), falling back to the
//! time of the read when the kernel sends none; [`Transport::dropped`] is the kernel's count of
//! frames dropped on this socket for lack of buffer space (`SO_RXQ_OVFL`). CAN error frames are
//! not delivered (the socket's error mask is empty by default). Frames move in batches of up
//! to 64 per system call (`recvmmsg`, `sendmmsg`); a full interface queue (`ENOBUFS`) is waited
//! out for up to about a second before it is reported.

use crate::{BusError, Clock, Frame, Received, Transport};
use embedded_can::{ExtendedId, Frame as _, Id, StandardId};
use socketcan::{Socket, SocketOptions};
use std::collections::VecDeque;
use std::os::fd::AsRawFd;
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

/// Receive buffer asked for.
pub const RCVBUF_BYTES: i32 = 8 << 20;

/// A SocketCAN interface (`can0`, `vcan0`, …).
pub struct SocketCan {
    fd: AsyncFd<socketcan::CanSocket>,
    /// Frames read by the last `recvmmsg` and not yet returned (keeps `recv` cancel-safe).
    pending: VecDeque<RawRx>,
    /// The buffers `recvmmsg` reads into, allocated once.
    rx: Box<RecvBuffers>,
    dropped: u64,
    iface: String,
}

impl std::fmt::Debug for SocketCan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SocketCan")
            .field("iface", &self.iface)
            .field("dropped", &self.dropped)
            .finish()
    }
}

impl SocketCan {
    /// Opens `iface`. Must be called inside a tokio runtime with I/O enabled.
    pub fn open(iface: &str) -> Result<Self, BusError> {
        let sock = socketcan::CanSocket::open(iface).map_err(|e| {
            BusError::Io(std::io::Error::new(
                e.kind(),
                format!("cannot open CAN interface {iface}: {e}"),
            ))
        })?;
        sock.set_nonblocking(true)?;
        if sock
            .set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUFFORCE, RCVBUF_BYTES)
            .is_err()
        {
            sock.set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUF, RCVBUF_BYTES)?;
        }
        sock.set_socket_option_int(libc::SOL_SOCKET, libc::SO_RXQ_OVFL, 1)?;
        sock.set_recv_timestamp(true)?;
        // SAFETY: `socketcan::CanSocket` owns its descriptor (an `OwnedFd` inside a
        // `socket2::Socket`) and always returns that same descriptor from `as_raw_fd`; it stays
        // open until the `AsyncFd` and the socket inside it are dropped together.
        #[allow(unsafe_code)]
        let fd = unsafe { AsyncFd::register(sock) }.map_err(|e| BusError::Io(e.into()))?;
        Ok(SocketCan {
            fd,
            pending: VecDeque::new(),
            rx: Box::new(RecvBuffers::new()),
            dropped: 0,
            iface: iface.to_string(),
        })
    }

    /// The interface name.
    pub fn iface(&self) -> &str {
        &self.iface
    }

    /// The receive buffer the kernel granted, bytes (the kernel doubles the value asked).
    pub fn rcvbuf(&self) -> Result<usize, BusError> {
        Ok(getsockopt_rcvbuf(self.fd.get_ref().as_raw_fd())?)
    }
}

fn getsockopt_rcvbuf(fd: i32) -> std::io::Result<usize> {
    let mut val: libc::c_int = 0;
    let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
    // SAFETY: `val` and `len` are valid for writes of the sizes given; `fd` is an open socket.
    #[allow(unsafe_code)]
    let rc = unsafe {
        libc::getsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&mut val as *mut libc::c_int).cast(),
            &mut len,
        )
    };
    if rc < 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(val as usize)
}

/// Frames per `recvmmsg`/`sendmmsg` call.
const BATCH: usize = 64;
/// Control buffer per message: room for a timespec and a u32 control message, 8-byte aligned.
const CONTROL_WORDS: usize = 16;

/// One raw frame, its timestamp and the drop counter if the kernel sent them.
struct RawRx {
    frame: [u8; 16],
    timestamp: Option<Duration>,
    overflow: Option<u32>,
}

/// What `recvmmsg` reads into: [`BATCH`] frames and control buffers and their headers. Kept
/// with the socket (boxed, so it never moves) instead of zeroed on the stack for every call: a
/// call that finds a frame or two, and the one that then finds none, would clear 13 kB each.
struct RecvBuffers {
    frames: [[u8; 16]; BATCH],
    control: [[u64; CONTROL_WORDS]; BATCH],
    iovs: [libc::iovec; BATCH],
    hdrs: [libc::mmsghdr; BATCH],
}

// SAFETY: the raw pointers inside `iovs` and `hdrs` point into the same boxed value and are
// rewritten before every use (`recv_batch`), which takes it by `&mut`.
#[allow(unsafe_code)]
unsafe impl Send for RecvBuffers {}

impl RecvBuffers {
    fn new() -> RecvBuffers {
        // SAFETY: `iovec` and `mmsghdr` are plain data; all-zero is a valid value.
        #[allow(unsafe_code)]
        let (iovs, hdrs) = unsafe { (std::mem::zeroed(), std::mem::zeroed()) };
        RecvBuffers {
            frames: [[0; 16]; BATCH],
            control: [[0; CONTROL_WORDS]; BATCH],
            iovs,
            hdrs,
        }
    }
}

/// `recvmmsg` of up to [`BATCH`] `struct can_frame`s with their control messages into `b`,
/// appended to `out`; `WouldBlock` when none is waiting.
fn recv_batch(fd: i32, b: &mut RecvBuffers, out: &mut VecDeque<RawRx>) -> std::io::Result<usize> {
    // SAFETY (whole block): every pointer stored in the headers refers to `b.frames`,
    // `b.control` or `b.iovs`, which outlive the `recvmmsg` call and are not otherwise accessed
    // during it; each header's lengths are reset before the call (the kernel rewrites
    // `msg_controllen` and `msg_len`); the CMSG_* macros walk only the `msg_controllen` bytes
    // the kernel wrote into each control buffer, and each payload is read unaligned with the
    // size the kernel documents for its type.
    #[allow(unsafe_code)]
    unsafe {
        let RecvBuffers {
            frames,
            control,
            iovs,
            hdrs,
        } = b;
        for i in 0..BATCH {
            iovs[i] = libc::iovec {
                iov_base: frames[i].as_mut_ptr().cast(),
                iov_len: 16,
            };
            hdrs[i].msg_len = 0;
            let h = &mut hdrs[i].msg_hdr;
            h.msg_name = std::ptr::null_mut();
            h.msg_namelen = 0;
            h.msg_iov = &mut iovs[i];
            h.msg_iovlen = 1;
            h.msg_control = control[i].as_mut_ptr().cast();
            h.msg_controllen = std::mem::size_of_val(&control[i]) as _;
            h.msg_flags = 0;
        }
        let n = libc::recvmmsg(
            fd,
            hdrs.as_mut_ptr(),
            BATCH as u32,
            libc::MSG_DONTWAIT,
            std::ptr::null_mut(),
        );
        if n < 0 {
            return Err(std::io::Error::last_os_error());
        }
        for i in 0..n as usize {
            if (hdrs[i].msg_len as usize) < 16 {
                continue;
            }
            let mut rx = RawRx {
                frame: frames[i],
                timestamp: None,
                overflow: None,
            };
            let msg = &hdrs[i].msg_hdr;
            let mut cmsg = libc::CMSG_FIRSTHDR(msg);
            while !cmsg.is_null() {
                let data = libc::CMSG_DATA(cmsg);
                match ((*cmsg).cmsg_level, (*cmsg).cmsg_type) {
                    (libc::SOL_SOCKET, libc::SCM_TIMESTAMPNS) => {
                        let ts = std::ptr::read_unaligned(data as *const libc::timespec);
                        rx.timestamp = Some(Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32));
                    }
                    (libc::SOL_SOCKET, libc::SO_RXQ_OVFL) => {
                        rx.overflow = Some(std::ptr::read_unaligned(data as *const u32));
                    }
                    _ => {}
                }
                cmsg = libc::CMSG_NXTHDR(msg, cmsg);
            }
            out.push_back(rx);
        }
        Ok(n as usize)
    }
}

/// `sendmmsg` of raw `struct can_frame`s; returns how many the kernel took.
fn send_batch(fd: i32, frames: &[[u8; 16]]) -> std::io::Result<usize> {
    let n = frames.len().min(BATCH);
    // SAFETY (whole block): as in `recv_batch`; the kernel only reads the frames, through the
    // iovecs that point into `frames`, which outlives the call.
    #[allow(unsafe_code)]
    unsafe {
        let mut iovs: [libc::iovec; BATCH] = std::mem::zeroed();
        let mut hdrs: [libc::mmsghdr; BATCH] = std::mem::zeroed();
        for i in 0..n {
            iovs[i] = libc::iovec {
                iov_base: frames[i].as_ptr() as *mut libc::c_void,
                iov_len: 16,
            };
            hdrs[i].msg_hdr.msg_iov = &mut iovs[i];
            hdrs[i].msg_hdr.msg_iovlen = 1;
        }
        let sent = libc::sendmmsg(fd, hdrs.as_mut_ptr(), n as u32, libc::MSG_DONTWAIT);
        if sent < 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(sent as usize)
    }
}

/// [`Frame`] → `struct can_frame` bytes.
fn raw_frame(f: &Frame) -> [u8; 16] {
    let mut id = f.raw_id();
    if f.is_extended() {
        id |= libc::CAN_EFF_FLAG;
    }
    if f.is_remote_frame() {
        id |= libc::CAN_RTR_FLAG;
    }
    let mut out = [0u8; 16];
    out[..4].copy_from_slice(&id.to_ne_bytes());
    out[4] = f.dlc() as u8;
    out[8..8 + f.data().len()].copy_from_slice(f.data());
    out
}

/// `struct can_frame` bytes → [`Frame`]; `None` for error frames.
fn parse(raw: &[u8; 16]) -> Option<Frame> {
    let can_id = u32::from_ne_bytes([raw[0], raw[1], raw[2], raw[3]]);
    if can_id & libc::CAN_ERR_FLAG != 0 {
        return None;
    }
    let len = usize::from(raw[4]).min(8);
    let id: Id = if can_id & libc::CAN_EFF_FLAG != 0 {
        ExtendedId::new(can_id & libc::CAN_EFF_MASK)?.into()
    } else {
        StandardId::new((can_id & libc::CAN_SFF_MASK) as u16)?.into()
    };
    if can_id & libc::CAN_RTR_FLAG != 0 {
        Frame::new_remote(id, len)
    } else {
        Frame::new(id, &raw[8..8 + len])
    }
}

impl Transport for SocketCan {
    async fn send(&mut self, frame: &Frame) -> Result<(), BusError> {
        self.send_all(std::slice::from_ref(frame)).await
    }

    async fn send_all(&mut self, frames: &[Frame]) -> Result<(), BusError> {
        let raw: Vec<[u8; 16]> = frames.iter().map(raw_frame).collect();
        let fd = self.fd.get_ref().as_raw_fd();
        let (mut done, mut full) = (0, 0u32);
        while done < raw.len() {
            match self
                .fd
                .async_io(Interest::WRITABLE, |_| send_batch(fd, &raw[done..]))
                .await
            {
                Ok(n) => {
                    done += n;
                    full = 0;
                }
                // The interface queue is full (CAN reports ENOBUFS rather than blocking): wait
                // for it to drain, for up to about a second.
                Err(e) if e.raw_os_error() == Some(libc::ENOBUFS) && full < 5000 => {
                    full += 1;
                    tokio::time::sleep(Duration::from_micros(200)).await;
                }
                Err(e) => return Err(BusError::Io(e)),
            }
        }
        Ok(())
    }

    async fn recv(&mut self) -> Result<Received, BusError> {
        loop {
            if let Some(raw) = self.pending.pop_front() {
                if let Some(total) = raw.overflow {
                    // The kernel reports the socket's cumulative count.
                    self.dropped = u64::from(total);
                }
                if let Some(frame) = parse(&raw.frame) {
                    return Ok(Received {
                        frame,
                        timestamp: raw.timestamp.unwrap_or_else(|| Clock::Wall.now()),
                    });
                }
                continue;
            }
            let fd = self.fd.get_ref().as_raw_fd();
            let (pending, buffers) = (&mut self.pending, &mut *self.rx);
            self.fd
                .async_io(Interest::READABLE, |_| recv_batch(fd, buffers, pending))
                .await?;
        }
    }

    fn dropped(&self) -> u64 {
        self.dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_standard_extended_remote_and_skips_error_frames() {
        let mut raw = [0u8; 16];
        raw[..4].copy_from_slice(&0x123u32.to_ne_bytes());
        raw[4] = 3;
        raw[8..11].copy_from_slice(&[1, 2, 3]);
        let f = parse(&raw).unwrap();
        assert_eq!((f.raw_id(), f.data()), (0x123, &[1u8, 2, 3][..]));
        raw[..4].copy_from_slice(&(0x1234_5678 | libc::CAN_EFF_FLAG).to_ne_bytes());
        assert!(parse(&raw).unwrap().is_extended());
        raw[..4].copy_from_slice(&(0x12 | libc::CAN_RTR_FLAG).to_ne_bytes());
        assert!(parse(&raw).unwrap().is_remote_frame());
        raw[..4].copy_from_slice(&(libc::CAN_ERR_FLAG | 4).to_ne_bytes());
        assert!(parse(&raw).is_none());
        for f in [
            Frame::new(StandardId::new(0x7FF).unwrap(), &[9, 8, 7]).unwrap(),
            Frame::new(ExtendedId::new(0x1ABC_DEF0).unwrap(), &[1; 8]).unwrap(),
            Frame::new_remote(StandardId::new(0x12).unwrap(), 2).unwrap(),
        ] {
            assert_eq!(parse(&raw_frame(&f)), Some(f));
        }
    }

    #[tokio::test]
    async fn opening_a_missing_interface_names_it() {
        let err = SocketCan::open("exocal-none9").unwrap_err();
        assert!(err.to_string().contains("exocal-none9"), "{err}");
    }
}
