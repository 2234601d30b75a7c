//! Progress bars: a live bar on a terminal; without one (background runs, `nohup`, CI) a plain
//! line on stderr at most every [`LOG_EVERY`], so a log file shows how far a long phase is.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle, TermLike};

/// Least time between two progress lines without a terminal.
pub const LOG_EVERY: Duration = Duration::from_secs(30);

/// A bar over `len` items with a message slot for live figures.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let template = if terminal {
        format!("{what:>10} [{{elapsed_precise}}] {{bar:30.cyan/blue}} {{pos}}/{{len}} ({{eta}} left) {{msg}}")
    } else {
        format!("{what}: {{pos}}/{{len}} after {{elapsed_precise}} ({{eta}} left) {{msg}}")
    };
    let style = ProgressStyle::with_template(&template).unwrap_or_else(|_| ProgressStyle::default_bar());
    let pb = if terminal {
        ProgressBar::new(len)
    } else {
        ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::term_like(Box::new(LogLines::new(LOG_EVERY))))
    };
    pb.set_style(style);
    pb
}

/// Prints a line above `pb` on a terminal, and as a plain log line otherwise (a log's bar keeps
/// only its own last line, so a line handed to it would be lost).
pub fn println(pb: &ProgressBar, line: impl AsRef<str>) {
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) && !pb.is_hidden() {
        pb.println(line);
    } else {
        eprintln!("{}", line.as_ref());
    }
}

/// A [`TermLike`] that turns a bar's redraws into log lines: the last line drawn is printed
/// when at least `every` has passed since the previous one, or since the bar was made (cursor
/// moves and clears are ignored).
#[derive(Debug)]
struct LogLines {
    every: Duration,
    state: Mutex<(Option<Instant>, String)>,
}

impl LogLines {
    fn new(every: Duration) -> Self {
        // the first line after one interval too: a short phase prints nothing
        Self { every, state: Mutex::new((Some(Instant::now()), String::new())) }
    }

    /// The line to print now, if one is due (and `every` has passed since the last).
    fn due(&self, now: Instant) -> Option<String> {
        let mut s = self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let line = s.1.trim().to_string();
        if line.is_empty() || s.0.is_some_and(|last| now.duration_since(last) < self.every) {
            return None;
        }
        s.0 = Some(now);
        Some(line)
    }
}

impl TermLike for LogLines {
    fn width(&self) -> u16 {
        160
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
        if !s.trim().is_empty() {
            self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner).1 = s.to_string();
        }
        Ok(())
    }
    fn clear_line(&self) -> std::io::Result<()> {
        Ok(())
    }
    fn flush(&self) -> std::io::Result<()> {
        if let Some(line) = self.due(Instant::now()) {
            eprintln!("{line}");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_a_terminal_the_last_drawn_line_is_logged_at_most_once_per_interval() {
        let log = LogLines::new(Duration::from_secs(30));
        let t0 = Instant::now();
        assert_eq!(log.due(t0 + Duration::from_secs(40)), None, "nothing drawn yet");
        log.write_str("pairs: 10/100").unwrap();
        assert_eq!(log.due(t0), None, "a phase shorter than the interval prints nothing");
        assert_eq!(log.due(t0 + Duration::from_secs(31)).as_deref(), Some("pairs: 10/100"));
        log.write_str("pairs: 20/100").unwrap();
        log.write_str("").unwrap(); // a clear does not erase the line
        assert_eq!(log.due(t0 + Duration::from_secs(60)), None, "too soon after the last line");
        assert_eq!(log.due(t0 + Duration::from_secs(61)).as_deref(), Some("pairs: 20/100"));
    }
}
