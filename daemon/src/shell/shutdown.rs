//! Shutdown on SIGTERM/SIGINT, as a flag every part of a session can wait on.
//!
//! Contract: [`Shutdown::on_signals`] raises the flag on the first SIGTERM or SIGINT (inside a
//! tokio runtime); [`Shutdown::manual`] gives tests and the demo a flag raised by hand;
//! [`Shutdown::wait`] completes once the flag is up, for every clone, however late it is asked;
//! [`is_done`] tells, without waiting, whether a shutdown future has completed.

use std::future::Future;
use std::pin::Pin;

use tokio::signal::unix::{signal, SignalKind};

/// A flag raised by SIGTERM or SIGINT; [`Shutdown::wait`] completes once it is.
#[derive(Clone)]
pub struct Shutdown(tokio::sync::watch::Receiver<bool>);

impl Shutdown {
    /// Installs the signal handlers (inside a runtime).
    pub fn on_signals() -> Shutdown {
        let (tx, rx) = tokio::sync::watch::channel(false);
        tokio::spawn(async move {
            let term = async {
                match signal(SignalKind::terminate()) {
                    Ok(mut s) => {
                        s.recv().await;
                    }
                    Err(_) => std::future::pending().await,
                }
            };
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                () = term => {}
            }
            let _ = tx.send(true);
        });
        Shutdown(rx)
    }

    /// A flag raised by hand (tests, the demo).
    pub fn manual() -> (tokio::sync::watch::Sender<bool>, Shutdown) {
        let (tx, rx) = tokio::sync::watch::channel(false);
        (tx, Shutdown(rx))
    }

    /// Completes when the flag is raised.
    pub fn wait(&self) -> impl std::future::Future<Output = ()> + use<> {
        let mut rx = self.0.clone();
        async move {
            while !*rx.borrow_and_update() {
                if rx.changed().await.is_err() {
                    std::future::pending::<()>().await;
                }
            }
        }
    }
}

/// Whether a pinned future is already complete (polled once, without waiting).
pub fn is_done<F: Future<Output = ()>>(f: &mut Pin<&mut F>) -> bool {
    let waker = std::task::Waker::noop();
    let mut cx = std::task::Context::from_waker(waker);
    f.as_mut().poll(&mut cx).is_ready()
}
