//! The terminal progress bar of a render, in process or followed through the coordinator's events.
//! A job with a known number of passes counts tiles; a job that a time budget ends has no tile
//! total until its last pass is planned, so its bar counts the budget's seconds instead.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// What the bar measures.
enum Measure {
    /// Tiles out of a known total.
    Tiles,
    /// Seconds of a time budget; tiles are counted in the message.
    Budget {
        seconds: f64,
        started: Instant,
        tiles: u64,
        spp: Option<u32>,
        relmse: Option<f64>,
    },
}

/// A render's progress bar.
pub(crate) struct RenderProgress {
    bar: ProgressBar,
    // Tiles finish on the render's threads.
    measure: Mutex<Measure>,
}

impl RenderProgress {
    /// `total_tiles` when the pass count is known; otherwise `time_budget_s` (seconds already
    /// spent: `elapsed_s`) measures the bar. Hidden when `quiet` or when stderr is no terminal.
    pub(crate) fn new(
        total_tiles: Option<u64>,
        time_budget_s: Option<f64>,
        elapsed_s: f64,
        quiet: bool,
    ) -> RenderProgress {
        let shown = !quiet && std::io::IsTerminal::is_terminal(&std::io::stderr());
        let (len, template, measure) = match (total_tiles, time_budget_s) {
            (n, None) | (n @ Some(_), Some(_)) => (
                n.unwrap_or(0),
                "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} tiles {msg} ETA {eta}",
                Measure::Tiles,
            ),
            (None, Some(seconds)) => (
                (seconds * 10.0).ceil() as u64,
                "{spinner} [{elapsed_precise}] {bar:40} {msg}",
                Measure::Budget {
                    seconds,
                    started: Instant::now() - Duration::from_secs_f64(elapsed_s.max(0.0)),
                    tiles: 0,
                    spp: None,
                    relmse: None,
                },
            ),
        };
        let p = RenderProgress {
            bar: bar(len, template, shown),
            measure: Mutex::new(measure),
        };
        p.refresh();
        p
    }

    /// The bar of a sequence: its frames that have ended out of `total`.
    pub(crate) fn frames(total: u64, quiet: bool) -> RenderProgress {
        let shown = !quiet && std::io::IsTerminal::is_terminal(&std::io::stderr());
        RenderProgress {
            bar: bar(
                total,
                "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} frames ETA {eta}",
                shown,
            ),
            measure: Mutex::new(Measure::Tiles),
        }
    }

    /// `n` frames of a sequence have ended.
    pub(crate) fn frames_ended(&self, n: u64) {
        self.bar.set_position(n);
    }

    /// `n` more tiles finished.
    pub(crate) fn tiles_done(&self, n: u64) {
        match &mut *self.lock() {
            Measure::Tiles => self.bar.inc(n),
            Measure::Budget { tiles, .. } => *tiles += n,
        }
        self.refresh();
    }

    /// A pass was merged: `spp` samples per pixel so far, relMSE against the reference if any.
    pub(crate) fn pass_done(&self, spp_so_far: u32, relmse_now: Option<f64>) {
        match &mut *self.lock() {
            Measure::Tiles => self.bar.set_message(match relmse_now {
                Some(r) => format!("{spp_so_far} spp, relMSE {r:.3e}"),
                None => format!("{spp_so_far} spp"),
            }),
            Measure::Budget { spp, relmse, .. } => {
                *spp = Some(spp_so_far);
                *relmse = relmse_now;
            }
        }
        self.refresh();
    }

    /// Brings a budget bar's time and message up to date.
    fn refresh(&self) {
        if let Measure::Budget {
            seconds,
            started,
            tiles,
            spp,
            relmse,
        } = &*self.lock()
        {
            let spent = started.elapsed().as_secs_f64().min(*seconds);
            self.bar.set_position((spent * 10.0) as u64);
            let mut msg = format!("{spent:.0}/{seconds:.0} s of the budget, {tiles} tiles");
            if let Some(s) = spp {
                msg.push_str(&format!(", {s} spp"));
            }
            if let Some(r) = relmse {
                msg.push_str(&format!(", relMSE {r:.3e}"));
            }
            msg.push_str(&format!(", {:.0} s left", seconds - spent));
            self.bar.set_message(msg);
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Measure> {
        // A panic while drawing leaves nothing half-updated that matters to a progress bar.
        self.measure.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Removes the bar.
    pub(crate) fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// A bar of `len` steps drawn with `template` on stderr, or hidden.
fn bar(len: u64, template: &str, shown: bool) -> ProgressBar {
    let target = if shown {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    };
    let bar = ProgressBar::with_draw_target(Some(len), target);
    bar.set_style(ProgressStyle::with_template(template).expect("valid template"));
    bar
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_time_budget_bar_counts_seconds_and_tiles_never_exceed_a_total() {
        let p = RenderProgress::new(None, Some(10.0), 2.0, true);
        assert_eq!(p.bar.length(), Some(100));
        let at = p.bar.position();
        assert!((20..30).contains(&at), "position {at} after 2 s of 10");
        p.tiles_done(44);
        p.pass_done(3, Some(0.25));
        let msg = p.bar.message();
        assert!(
            msg.starts_with("2/10 s of the budget, 44 tiles, 3 spp"),
            "{msg}"
        );
        assert!(
            msg.contains("relMSE 2.500e-1") && msg.ends_with("8 s left"),
            "{msg}"
        );

        let p = RenderProgress::new(Some(33), None, 0.0, true);
        p.tiles_done(33);
        p.pass_done(4, None);
        assert_eq!((p.bar.position(), p.bar.length()), (33, Some(33)));
        assert_eq!(p.bar.message(), "4 spp");
    }
}
