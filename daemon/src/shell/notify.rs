//! Live progress and systemd notifications.
//!
//! Contract: one [`Reporter`] per run, chosen by [`Reporter::detect`]:
//! - under systemd (`NOTIFY_SOCKET` set) progress goes to `STATUS=` (shown by
//!   `systemctl status`), plus a plain log line every [`PLAIN_EVERY_S`] seconds for the journal;
//! - on a terminal, an `indicatif` progress bar on stderr;
//! - otherwise plain lines on stderr every [`PLAIN_EVERY_S`] seconds.
//!
//! [`Notifier`] sends `READY=1`, `WATCHDOG=1`, `STATUS=` and `STOPPING=1` when running under
//! systemd and does nothing otherwise; the watchdog is fed at half the interval systemd asked
//! for (`WATCHDOG_USEC`). Failure to notify is logged once, never fatal.

use std::io::IsTerminal;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

use exocal_session::window::Progress;

/// Seconds between two plain progress lines.
pub const PLAIN_EVERY_S: f64 = 5.0;

/// Talks to systemd's notification socket, if there is one.
#[derive(Debug)]
pub struct Notifier {
    enabled: bool,
    watchdog: Option<Duration>,
    last_feed: Option<Duration>,
    warned: bool,
}

impl Notifier {
    /// Reads `NOTIFY_SOCKET` and `WATCHDOG_USEC` from the environment.
    pub fn from_env() -> Notifier {
        Notifier {
            enabled: std::env::var_os("NOTIFY_SOCKET").is_some(),
            watchdog: sd_notify::watchdog_enabled(),
            last_feed: None,
            warned: false,
        }
    }

    /// A notifier that never sends (tests, `demo`).
    pub fn disabled() -> Notifier {
        Notifier {
            enabled: false,
            watchdog: None,
            last_feed: None,
            warned: false,
        }
    }

    /// Whether we run under systemd with a notify socket.
    pub fn enabled(&self) -> bool {
        self.enabled
    }

    fn send(&mut self, state: &[sd_notify::NotifyState]) {
        if !self.enabled {
            return;
        }
        if let Err(e) = sd_notify::notify(state) {
            if !self.warned {
                eprintln!("exocald: cannot notify systemd: {e}");
                self.warned = true;
            }
        }
    }

    /// `READY=1`: the CAN socket is open.
    pub fn ready(&mut self, status: &str) {
        self.send(&[
            sd_notify::NotifyState::Ready,
            sd_notify::NotifyState::Status(status),
        ]);
    }

    /// `STATUS=…`.
    pub fn status(&mut self, status: &str) {
        self.send(&[sd_notify::NotifyState::Status(status)]);
    }

    /// `STOPPING=1`.
    pub fn stopping(&mut self) {
        self.send(&[sd_notify::NotifyState::Stopping]);
    }

    /// Feeds the watchdog if half its interval passed since the last feed; `now` is monotonic.
    /// Returns whether it fed.
    pub fn watchdog(&mut self, now: Duration) -> bool {
        let Some(interval) = self.watchdog else {
            return false;
        };
        // A reading before the last feed is another time base (a session's own clock after
        // the serve loop's): feed rather than wait for it to catch up.
        let due = self
            .last_feed
            .is_none_or(|last| now < last || now - last >= interval / 2);
        if due {
            self.send(&[sd_notify::NotifyState::Watchdog]);
            self.last_feed = Some(now);
        }
        due && self.enabled
    }
}

/// How progress is shown.
pub enum Reporter {
    /// A progress bar on the terminal.
    Bar(ProgressBar),
    /// `STATUS=` to systemd, and plain lines.
    Systemd {
        /// Elapsed time (s) of the last plain line; `None` before the first.
        last_line: Option<f64>,
    },
    /// Plain lines on stderr.
    Plain {
        /// Elapsed time (s) of the last plain line; `None` before the first.
        last_line: Option<f64>,
    },
    /// Nothing (`--quiet`, `--json`: stdout carries the result, stderr only errors).
    Quiet,
}

impl Reporter {
    /// Picks the reporter for this process (see the module docs).
    pub fn detect(notifier: &Notifier) -> Reporter {
        if notifier.enabled() {
            Reporter::Systemd { last_line: None }
        } else if std::io::stderr().is_terminal() {
            let bar = ProgressBar::new(1000);
            // `calibrating [============] ` is 27 columns: the message
            // (`Progress::short`) has the other 53 of an 80-column terminal.
            bar.set_style(
                ProgressStyle::with_template("{prefix:11} [{bar:12}] {wide_msg}")
                    .unwrap_or_else(|_| ProgressStyle::default_bar())
                    .progress_chars("=> "),
            );
            bar.set_prefix("collecting");
            Reporter::Bar(bar)
        } else {
            Reporter::Plain { last_line: None }
        }
    }

    /// Whether a plain line is due at `elapsed_s` (and records that it is printed).
    fn line_due(last_line: &mut Option<f64>, elapsed_s: f64) -> bool {
        let due = last_line.is_none_or(|t| elapsed_s - t >= PLAIN_EVERY_S);
        if due {
            *last_line = Some(elapsed_s);
        }
        due
    }

    /// Shows `progress`; `required` is the coverage required, for the text.
    pub fn update(&mut self, progress: &Progress, required: f64, notifier: &mut Notifier) {
        let line = progress.line(required);
        match self {
            Reporter::Bar(bar) => {
                bar.set_position((progress.readiness * 1000.0).round() as u64);
                bar.set_message(progress.short(required));
            }
            Reporter::Systemd { last_line } => {
                notifier.status(&line);
                if Self::line_due(last_line, progress.elapsed_s) {
                    eprintln!("exocald: {line}");
                }
            }
            Reporter::Plain { last_line } => {
                if Self::line_due(last_line, progress.elapsed_s) {
                    eprintln!("exocald: {line}");
                }
            }
            Reporter::Quiet => {}
        }
    }

    /// The window closed at `progress`: its line, unless this tick's was printed (the estimate
    /// that closed it, stopping when good enough, is in no line before). The bar shows it
    /// already.
    pub fn closed(&mut self, progress: &Progress, required: f64) {
        if let Reporter::Systemd { last_line } | Reporter::Plain { last_line } = self {
            if let Some(line) = Self::closing_line(last_line, progress, required) {
                eprintln!("exocald: {line}");
            }
        }
    }

    /// The line [`Reporter::closed`] prints, unless `last_line` was this tick's.
    fn closing_line(
        last_line: &mut Option<f64>,
        progress: &Progress,
        required: f64,
    ) -> Option<String> {
        let printed = *last_line == Some(progress.elapsed_s);
        *last_line = Some(progress.elapsed_s);
        (!printed).then(|| progress.line(required))
    }

    /// The session moved on to `phase` (`calibrating`, `pushing`): the bar says so in place of
    /// `collecting`, with `detail` beside it; otherwise `phase: detail` is printed.
    pub fn phase(&self, phase: &str, detail: &str) {
        match self {
            Reporter::Bar(bar) => {
                bar.set_prefix(phase.to_string());
                bar.set_message(detail.to_string());
            }
            Reporter::Quiet => {}
            _ => eprintln!("exocald: {phase}: {detail}"),
        }
    }

    /// Prints a message without garbling the bar.
    pub fn message(&self, text: &str) {
        match self {
            Reporter::Bar(bar) => bar.println(format!("exocald: {text}")),
            Reporter::Quiet => {}
            _ => eprintln!("exocald: {text}"),
        }
    }

    /// Removes the bar, if any.
    pub fn finish(&self) {
        if let Reporter::Bar(bar) = self {
            bar.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_lines_are_rate_limited() {
        let mut last = None;
        let due: Vec<bool> = [0.0, 1.0, 4.9, 5.0, 6.0, 10.1]
            .iter()
            .map(|&t| Reporter::line_due(&mut last, t))
            .collect();
        assert_eq!(due, [true, false, false, true, false, true]);
    }

    #[test]
    fn the_closing_tick_has_its_line_once() {
        let progress = |elapsed_s, mm| Progress {
            elapsed_s,
            samples: 5_500,
            coverage: vec![0.9; 7],
            condition_number: Some(25.0),
            expected: Some(exocal_session::validate::Expected {
                position_mm: mm,
                rotation_mrad: 5.0,
            }),
            guidance: None,
            readiness: 1.0,
            target: None,
        };
        // Lines at 50 and 55 s; the estimate that closes the window lands after 55 s.
        let mut last = None;
        assert!(Reporter::line_due(&mut last, 50.0));
        assert!(Reporter::line_due(&mut last, 55.0));
        assert!(!Reporter::line_due(&mut last, 55.01));
        let line = Reporter::closing_line(&mut last, &progress(55.01, 1.66), 0.5);
        assert!(
            line.as_deref()
                .is_some_and(|l| l.starts_with("collecting 55.0 s")
                    && l.contains("expected table error ±1.66 mm")),
            "{line:?}"
        );
        // A window closing on a tick whose line was printed: not twice.
        let mut last = None;
        assert!(Reporter::line_due(&mut last, 60.0));
        assert_eq!(
            Reporter::closing_line(&mut last, &progress(60.0, 1.3), 0.5),
            None
        );
    }

    #[test]
    fn watchdog_is_fed_at_half_its_interval() {
        let mut n = Notifier {
            enabled: true,
            watchdog: Some(Duration::from_secs(10)),
            last_feed: None,
            warned: false,
        };
        // Without NOTIFY_SOCKET in the environment, sd_notify sends nothing: this checks the
        // timing logic only.
        let fed: Vec<bool> = [0, 1, 4, 5, 9, 10, 16]
            .iter()
            .map(|&s| n.watchdog(Duration::from_secs(s)))
            .collect();
        assert_eq!(fed, [true, false, false, true, false, true, true]);
        // A time base that starts again (a session inside `exocald run`) feeds at once.
        assert!(n.watchdog(Duration::from_secs(2)));
        assert!(!n.watchdog(Duration::from_secs(3)));
        let mut off = Notifier::disabled();
        assert!(!off.watchdog(Duration::from_secs(100)));
    }
}
