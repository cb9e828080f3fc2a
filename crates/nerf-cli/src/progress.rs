//! Progress bars for long work, and the training display.

use std::io::{IsTerminal, Write};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle, TermLike};
use nerf::model::ModelConfig;
use nerf::train::run::Event;

/// Seconds between the lines that stand for a bar where there is no terminal to draw it
/// in (a log, CI): often enough to show long work is moving, rarely enough to read.
const LOG_EVERY: Duration = Duration::from_secs(30);

/// A bar counting `total` items of `what`, with rate and ETA. Where stderr is not a
/// terminal, the bar's line is written there every [`LOG_EVERY`] instead.
pub fn bar(total: u64, what: &str) -> ProgressBar {
    let pb = styled_bar(total, what);
    if !std::io::stderr().is_terminal() {
        let log = LogLines::new(Box::new(std::io::stderr()), LOG_EVERY);
        pb.set_draw_target(ProgressDrawTarget::term_like_with_hz(Box::new(log), 1));
    }
    pb
}

/// [`bar`] without the log lines (hidden where there is no terminal), for a display that
/// writes its own; the spinner only on a terminal, where it moves.
fn styled_bar(total: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(total);
    let spinner = match std::io::stderr().is_terminal() {
        true => "{spinner} ",
        false => "",
    };
    let template =
        format!("{spinner}{what} [{{bar:30}}] {{pos}}/{{len}} {{rate}} ETA {{eta}} {{msg}}");
    if let Ok(style) = ProgressStyle::with_template(&template) {
        let style = style.with_key(
            "rate",
            |state: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = w.write_str(&rate(state.per_sec(), ""));
            },
        );
        pb.set_style(style.progress_chars("=> "));
    }
    pb
}

/// A bar over the `seconds` of a timed schedule, with the time left.
fn seconds_bar(seconds: u64) -> ProgressBar {
    let pb = ProgressBar::new(seconds);
    let template = "{spinner} train [{bar:30}] {pos}/{len} s, {eta} left {msg}";
    if let Ok(style) = ProgressStyle::with_template(template) {
        pb.set_style(style.progress_chars("=> "));
    }
    pb
}

/// A bar's stand-in terminal for logs: it keeps what the bar draws and writes the line out
/// at most once every `every`, as a line of its own (no cursor moves, no redraws in place).
struct LogLines {
    out: Mutex<Box<dyn Write + Send>>,
    every: Duration,
    /// The line being drawn, and when a line was last written out.
    state: Mutex<(String, Instant)>,
}

impl std::fmt::Debug for LogLines {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LogLines")
            .field("every", &self.every)
            .finish()
    }
}

impl LogLines {
    /// The first line is written `every` after this, so short work leaves no lines.
    fn new(out: Box<dyn Write + Send>, every: Duration) -> Self {
        LogLines {
            out: Mutex::new(out),
            every,
            state: Mutex::new((String::new(), Instant::now())),
        }
    }
}

impl TermLike for LogLines {
    fn width(&self) -> u16 {
        120
    }
    fn move_cursor_up(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_down(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_right(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_left(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn write_line(&self, s: &str) -> std::io::Result<()> {
        self.write_str(s)
    }
    fn write_str(&self, s: &str) -> std::io::Result<()> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.0.push_str(s.trim_start_matches('\r'));
        Ok(())
    }
    fn clear_line(&self) -> std::io::Result<()> {
        self.state
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .0
            .clear();
        Ok(())
    }
    fn flush(&self) -> std::io::Result<()> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let line = std::mem::take(&mut state.0);
        let line = line.trim();
        if line.is_empty() || state.1.elapsed() < self.every {
            return Ok(());
        }
        state.1 = Instant::now();
        let mut out = self.out.lock().unwrap_or_else(|e| e.into_inner());
        writeln!(out, "{line}")?;
        out.flush()
    }
}

/// A rate in the one format every command prints: three significant figures at most
/// below 1000, whole numbers above, no thousands separators (`26.8/s`, `46341 rays/s`).
pub fn rate(per_second: f64, unit: &str) -> String {
    let unit = if unit.is_empty() {
        "/s".to_string()
    } else {
        format!(" {unit}/s")
    };
    match per_second {
        v if !v.is_finite() => format!("-{unit}"),
        v if v < 10.0 => format!("{v:.2}{unit}"),
        v if v < 100.0 => format!("{v:.1}{unit}"),
        v => format!("{v:.0}{unit}"),
    }
}

/// Seconds over which the shown training rate is averaged: long enough that the slow step
/// of an occupancy-grid refresh does not make it jump.
const RATE_WINDOW_S: f64 = 5.0;

/// A rate averaged over about [`RATE_WINDOW_S`] seconds: counts are gathered for a second,
/// then folded into an exponential average, so one slow step (an occupancy-grid refresh)
/// moves the figure a little instead of making it jump.
#[derive(Debug, Default)]
pub struct SmoothedRate {
    pub per_second: f64,
    count: usize,
    seconds: f64,
}

impl SmoothedRate {
    /// `count` more items that took `seconds`.
    pub fn add(&mut self, count: usize, seconds: f64) {
        self.count += count;
        self.seconds += seconds;
        if self.seconds < 1.0 {
            return;
        }
        let now = self.count as f64 / self.seconds;
        let a = if self.per_second == 0.0 {
            1.0
        } else {
            (self.seconds / RATE_WINDOW_S).min(1.0)
        };
        self.per_second += a * (now - self.per_second);
        (self.count, self.seconds) = (0, 0.0);
    }
}

/// The training display: a header, a bar with loss, PSNR and rays/s, validation lines, and
/// a line every 30 s when there is no terminal (logs, CI).
pub struct TrainProgress {
    pb: Option<ProgressBar>,
    steps: u64,
    /// A timed run's clock: when this session started, and the seconds before it. The bar
    /// then counts seconds of the budget, not steps.
    clock: Option<(Instant, f64)>,
    last: Instant,
    rays: SmoothedRate,
    last_line: Instant,
}

impl Default for TrainProgress {
    fn default() -> Self {
        TrainProgress {
            pb: None,
            steps: 0,
            clock: None,
            last: Instant::now(),
            rays: SmoothedRate::default(),
            last_line: Instant::now(),
        }
    }
}

impl TrainProgress {
    /// The run's step target (0 before it started).
    pub fn steps(&self) -> u64 {
        self.steps
    }

    pub fn on_event(&mut self, event: Event) {
        match event {
            Event::Started {
                config,
                views,
                width,
                height,
                params,
                resumed_from,
                elapsed_s,
            } => {
                let views = match config.multiscale {
                    1 => format!("{views} views"),
                    n => format!("{} views at {n} scales", views / n),
                };
                let antialiased = match &config.model {
                    ModelConfig::Fast(m) if m.field.antialias.is_some() => ", anti-aliased",
                    _ => "",
                };
                println!(
                    "training {} on {} ({views}, {width}x{height}): {}{}{antialiased}, {params} parameters",
                    config.preset,
                    config.data.display(),
                    config.model.describe(),
                    match config.model {
                        ModelConfig::Vanilla(_) => format!(", {} rays/step", config.batch_rays),
                        ModelConfig::Fast(_) => String::new(),
                    }
                );
                self.rays = SmoothedRate::default();
                if let Some(step) = resumed_from {
                    println!("resuming from the checkpoint at step {step}");
                }
                let p = match config.time_budget_s {
                    Some(budget) => {
                        self.clock = Some((Instant::now(), elapsed_s));
                        println!(
                            "schedule: {:.1} minutes of training (the learning rate decays by \
                             the clock)",
                            budget / 60.0
                        );
                        let p = seconds_bar(budget.ceil() as u64);
                        p.set_position(elapsed_s as u64);
                        p
                    }
                    None => {
                        let p = styled_bar(config.steps, "train");
                        p.set_position(resumed_from.unwrap_or(0));
                        p
                    }
                };
                p.reset_eta();
                self.steps = config.steps;
                self.last = Instant::now();
                self.pb = Some(p);
            }
            Event::Step(s) => {
                let Some(p) = &self.pb else { return };
                self.rays.add(s.rays, self.last.elapsed().as_secs_f64());
                self.last = Instant::now();
                let at_step = match self.clock {
                    Some((start, before)) => {
                        p.set_position((before + start.elapsed().as_secs_f64()) as u64);
                        format!("step {} ", s.step)
                    }
                    None => {
                        p.set_position(s.step);
                        String::new()
                    }
                };
                p.set_message(format!(
                    "{at_step}loss {:.4} psnr {:.2} {}",
                    s.loss,
                    s.psnr,
                    rate(self.rays.per_second, "rays")
                ));
                if p.is_hidden() && self.last_line.elapsed() >= LOG_EVERY {
                    println!(
                        "step {}: loss {:.4}, batch PSNR {:.2} dB, {}",
                        s.step,
                        s.loss,
                        s.psnr,
                        rate(self.rays.per_second, "rays")
                    );
                    self.last_line = Instant::now();
                }
            }
            Event::Validation { step, psnr, image } => {
                self.say(format!(
                    "step {step}: validation PSNR {psnr:.2} dB ({})",
                    image.display()
                ));
            }
            Event::PoseError { step, error } => {
                self.say(format!(
                    "step {step}: training cameras {:.3} degrees from the true poses (median \
                     {:.3}, worst {:.2}), centres {:.2}% of the radius",
                    error.rotation_deg,
                    error.rotation_deg_median,
                    error.rotation_deg_max,
                    error.translation_percent_of_radius
                ));
            }
            Event::Note(note) => match &self.pb {
                Some(p) if !p.is_hidden() => p.println(format!("note: {note}")),
                _ => eprintln!("note: {note}"),
            },
            Event::Warning(warning) => match &self.pb {
                Some(p) if !p.is_hidden() => p.println(format!("warning: {warning}")),
                _ => eprintln!("warning: {warning}"),
            },
            Event::Checkpoint { .. } | Event::Model { .. } => {}
        }
    }

    /// Prints a line above the bar, or plainly when the bar is hidden (no terminal: logs,
    /// CI), where it would print nothing.
    fn say(&self, line: String) {
        match &self.pb {
            Some(p) if !p.is_hidden() => p.println(line),
            _ => println!("{line}"),
        }
    }

    /// Clears the bar.
    pub fn finish(&mut self) {
        if let Some(p) = self.pb.take() {
            p.finish_and_clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One rate format everywhere, no thousands separators, no 4 decimals.
    #[test]
    fn rates_have_one_format() {
        assert_eq!(rate(26.8454, ""), "26.8/s");
        assert_eq!(rate(46341.309, "rays"), "46341 rays/s");
        assert_eq!(rate(4.2371, "steps"), "4.24 steps/s");
        assert_eq!(rate(f64::NAN, "rays"), "- rays/s");
    }

    /// A step ten times slower than the others (an occupancy refresh) moves
    /// the shown rate by less than a fifth, where a plain per-window rate dropped 10x.
    #[test]
    fn one_slow_step_does_not_make_the_rate_jump() {
        let mut r = SmoothedRate::default();
        for _ in 0..50 {
            r.add(1000, 0.1);
        }
        assert!((r.per_second - 10000.0).abs() < 1.0, "{}", r.per_second);
        let mut lowest = f64::MAX;
        for k in 0..50 {
            r.add(1000, if k == 5 { 1.0 } else { 0.1 });
            lowest = lowest.min(r.per_second);
        }
        assert!(lowest > 8000.0, "dropped to {lowest}");
    }

    /// A `Write` whose bytes the test can read after the bar has taken it.
    #[derive(Clone, Default)]
    struct Shared(std::sync::Arc<Mutex<Vec<u8>>>);

    impl Write for Shared {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0
                .lock()
                .expect("the test's buffer")
                .extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Shared {
        fn lines(&self) -> Vec<String> {
            let bytes = self.0.lock().expect("the test's buffer").clone();
            String::from_utf8(bytes)
                .expect("a bar writes UTF-8")
                .lines()
                .map(str::to_string)
                .collect()
        }
    }

    /// Where there is no terminal, a bar leaves whole lines with its count (no carriage
    /// returns or cursor moves), and none before its interval has passed.
    #[test]
    fn a_bar_without_a_terminal_writes_plain_lines_when_due() {
        let draw = |every: Duration| {
            let out = Shared::default();
            let pb = styled_bar(10, "eval test rays");
            let log = LogLines::new(Box::new(out.clone()), every);
            pb.set_draw_target(ProgressDrawTarget::term_like(Box::new(log)));
            for k in 1..=3 {
                pb.set_position(k);
                pb.tick();
            }
            pb.finish_and_clear();
            out.lines()
        };
        let lines = draw(Duration::ZERO);
        assert!(!lines.is_empty());
        assert!(
            lines
                .iter()
                .any(|l| l.contains("eval test rays") && l.contains("3/10")),
            "{lines:?}"
        );
        assert!(
            lines
                .iter()
                .all(|l| !l.contains('\r') && !l.contains('\x1b')),
            "{lines:?}"
        );
        assert_eq!(draw(Duration::from_secs(3600)), Vec::<String>::new());
    }
}
