//! Progress of a long run on stderr: nothing for the first seconds (short runs stay quiet),
//! then a bar on a terminal (indicatif, as the optimization's) or a line every few seconds in a
//! log. The engine reports the steps done at its host checks.

use std::io::{IsTerminal, Write};
use std::time::{Duration, Instant};

/// When a run's progress starts to show.
pub const SHOW_AFTER: Duration = Duration::from_secs(3);
/// How often a log (not a terminal) gets a progress line.
pub const LOG_EVERY: Duration = Duration::from_secs(10);

pub struct Progress {
    label: String,
    start: Instant,
    show_after: Duration,
    every: Duration,
    /// A terminal's bar, once shown, and the phase it counts.
    bar: Option<(indicatif::ProgressBar, String)>,
    /// Where log lines go when stderr is not a terminal.
    log: Option<Box<dyn Write + Send>>,
    last_line: Option<Instant>,
}

impl std::fmt::Debug for Progress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Progress")
            .field("label", &self.label)
            .finish()
    }
}

impl Progress {
    /// Progress of the run `label` (the script's name) on stderr.
    pub fn new(label: impl Into<String>) -> Progress {
        let log: Option<Box<dyn Write + Send>> = if std::io::stderr().is_terminal() {
            None
        } else {
            Some(Box::new(std::io::stderr()))
        };
        Progress {
            label: label.into(),
            start: Instant::now(),
            show_after: SHOW_AFTER,
            every: LOG_EVERY,
            bar: None,
            log,
            last_line: None,
        }
    }

    /// Progress as log lines into `out`, shown after `show_after`, one every `every` (tests).
    pub fn to_log(
        label: impl Into<String>,
        out: Box<dyn Write + Send>,
        show_after: Duration,
        every: Duration,
    ) -> Progress {
        let mut p = Progress::new(label);
        (p.show_after, p.every, p.log) = (show_after, every, Some(out));
        p
    }

    /// `done` of `total` steps of `phase` (`forward`, `backward`) are done.
    pub fn update(&mut self, phase: &str, done: u64, total: u64) {
        let elapsed = self.start.elapsed();
        if elapsed < self.show_after {
            return;
        }
        match &mut self.log {
            Some(out) => {
                if self.last_line.is_some_and(|t| t.elapsed() < self.every) && done < total {
                    return;
                }
                self.last_line = Some(Instant::now());
                let fraction = done as f64 / total.max(1) as f64;
                let left = if fraction > 0.0 {
                    format!(
                        ", ~{} left",
                        human(elapsed.as_secs_f64() * (1.0 - fraction) / fraction)
                    )
                } else {
                    String::new()
                };
                let _ = writeln!(
                    out,
                    "{}: {phase} step {done}/{total} ({:.1} %), {:.0} s elapsed{left}",
                    self.label,
                    100.0 * fraction,
                    elapsed.as_secs_f64()
                );
            }
            None => {
                if self.bar.as_ref().is_none_or(|(_, p)| p != phase) {
                    if let Some((b, _)) = self.bar.take() {
                        b.finish_and_clear();
                    }
                    let b = indicatif::ProgressBar::new(total);
                    b.set_style(
                        indicatif::ProgressStyle::with_template(
                            "{msg} {bar:30} {pos}/{len} steps, {elapsed} elapsed, ~{eta} left",
                        )
                        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
                    );
                    b.set_message(format!("{} ({phase})", self.label));
                    self.bar = Some((b, phase.to_string()));
                }
                if let Some((b, _)) = &self.bar {
                    b.set_position(done);
                }
            }
        }
    }
}

impl Progress {
    /// What the run is doing within a step (a static solve's load step and Newton iteration):
    /// a log line at most every `every` (after `show_after`), or the bar's message.
    pub fn note(&mut self, detail: &str) {
        let elapsed = self.start.elapsed();
        if elapsed < self.show_after {
            return;
        }
        match &mut self.log {
            Some(out) => {
                if self.last_line.is_some_and(|t| t.elapsed() < self.every) {
                    return;
                }
                self.last_line = Some(Instant::now());
                let _ = writeln!(
                    out,
                    "{}: {detail}, {:.0} s elapsed",
                    self.label,
                    elapsed.as_secs_f64()
                );
            }
            None => {
                if let Some((b, phase)) = &self.bar {
                    b.set_message(format!("{} ({phase}: {detail})", self.label));
                }
            }
        }
    }
}

/// A time left in the unit a reader takes in at a glance: `42 s`, `12 min`, `3.4 h`,
/// `5.2 days`, `1.3 years` (a run of 10⁹ static steps should not read `42368149 s`).
fn human(seconds: f64) -> String {
    // (unit, name, from how many of it on)
    const UNITS: [(f64, &str, f64); 4] = [
        (365.25 * 86400.0, "years", 1.0),
        (86400.0, "days", 2.0),
        (3600.0, "h", 2.0),
        (60.0, "min", 2.0),
    ];
    match UNITS.iter().find(|(size, _, from)| seconds >= from * size) {
        Some((size, name, _)) => format!("{:.1} {name}", seconds / size),
        None => format!("{seconds:.0} s"),
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        if let Some((b, _)) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}

impl crate::engine::ProgressReport for Progress {
    fn update(&mut self, phase: &str, done: u64, total: u64) {
        Progress::update(self, phase, done, total)
    }

    fn note(&mut self, detail: &str) {
        Progress::note(self, detail)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    #[derive(Clone, Default)]
    struct Shared(Arc<Mutex<Vec<u8>>>);
    impl Write for Shared {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_long_run_shows_its_progress_and_a_short_one_does_not() {
        let sink = Shared::default();
        let mut quiet = Progress::to_log(
            "short.soft",
            Box::new(sink.clone()),
            Duration::from_secs(3600),
            Duration::ZERO,
        );
        quiet.update("forward", 50, 100);
        assert!(sink.0.lock().unwrap().is_empty());
        let mut long = Progress::to_log(
            "long.soft",
            Box::new(sink.clone()),
            Duration::ZERO,
            Duration::from_secs(3600),
        );
        long.update("forward", 50, 200);
        long.update("forward", 100, 200); // within `every` of the last line: not shown
        long.update("forward", 200, 200); // the end always is
        let text = String::from_utf8(sink.0.lock().unwrap().clone()).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2, "{text}");
        assert!(
            lines[0].starts_with("long.soft: forward step 50/200 (25.0 %)"),
            "{text}"
        );
        assert!(lines[1].contains("step 200/200 (100.0 %)"), "{text}");
    }

    #[test]
    fn the_time_left_reads_in_a_fitting_unit() {
        assert_eq!(human(42.4), "42 s");
        assert_eq!(human(119.0), "119 s");
        assert_eq!(human(720.0), "12.0 min");
        assert_eq!(human(3.4 * 3600.0), "3.4 h");
        assert_eq!(human(42_368_149.0), "1.3 years");
    }
}
