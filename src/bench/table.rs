//! The arithmetic of the quality report: when a model first reaches a
//! PSNR, from evaluations at a few training-time marks, and tables that
//! print as Markdown or CSV. The command line's report and the viewer's
//! export both use it, so a table reads the same in either.

use serde::{Deserialize, Serialize};

/// The PSNR targets the report asks "how long until" for, in dB: a blurry
/// but recognisable reconstruction, a good one, and the papers' range.
pub const DEFAULT_TARGETS_DB: [f64; 3] = [25.0, 30.0, 33.0];

/// When a model first reached a PSNR target.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum Reached {
    /// Crossed between two marks: the time where the straight line between
    /// them (PSNR against the logarithm of training time) meets the target.
    Interpolated { seconds: f64 },
    /// Already reached at the first mark that had a score, with nothing
    /// measured before it: some time up to `seconds`.
    AtMost { seconds: f64 },
    /// Not reached at any mark, the last of which was at `seconds`.
    NotReached { seconds: f64 },
    /// There is no mark to tell.
    NoMarks,
}

impl Reached {
    /// The time to show on a bar or a plot: the interpolated time, or the
    /// bound for a target reached by the first mark; none otherwise.
    pub fn seconds(&self) -> Option<f64> {
        match *self {
            Reached::Interpolated { seconds } | Reached::AtMost { seconds } => Some(seconds),
            Reached::NotReached { .. } | Reached::NoMarks => None,
        }
    }

    /// How a table cell says it: `72 s`, `≤ 30 s`, `not in 10 min`, `—`.
    pub fn describe(&self) -> String {
        match *self {
            Reached::Interpolated { seconds } => format_seconds(seconds),
            Reached::AtMost { seconds } => format!("≤ {}", format_seconds(seconds)),
            Reached::NotReached { seconds } => format!("not in {}", format_seconds(seconds)),
            Reached::NoMarks => "—".to_string(),
        }
    }
}

/// When a curve measured at `(training seconds, PSNR)` marks first reaches
/// `target` dB.
///
/// Between two marks the PSNR is taken to change linearly in the logarithm
/// of training time, the axis the report's plots use: PSNR grows roughly
/// by the same amount each time training time doubles, so a straight line
/// in log time follows the curve far better than one in linear time over
/// marks as far apart as 2 and 5 minutes. The first crossing counts (a
/// curve that dips later has still reached the target once). Marks without
/// a finite PSNR (an evaluation that failed) never count as reaching it,
/// and a target met just after one has no lower bound to interpolate from.
pub fn time_to_reach(marks: &[(f64, f64)], target: f64) -> Reached {
    let mut sorted: Vec<(f64, f64)> = marks
        .iter()
        .copied()
        .filter(|(seconds, _)| seconds.is_finite())
        .collect();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
    let Some(&(last_seconds, _)) = sorted.last() else {
        return Reached::NoMarks;
    };
    for (i, &(seconds, psnr)) in sorted.iter().enumerate() {
        // NaN is never at or above a target.
        if psnr.is_nan() || psnr < target {
            continue;
        }
        if psnr == target {
            // Met at the mark itself: its own time, not a rounded one.
            return if i == 0 {
                Reached::AtMost { seconds }
            } else {
                Reached::Interpolated { seconds }
            };
        }
        let Some(&(before_seconds, before_psnr)) = i.checked_sub(1).map(|j| &sorted[j]) else {
            return Reached::AtMost { seconds };
        };
        if !before_psnr.is_finite() || before_seconds <= 0.0 || seconds <= before_seconds {
            return Reached::AtMost { seconds };
        }
        let fraction = (target - before_psnr) / (psnr - before_psnr);
        let log_seconds = before_seconds.ln() + fraction * (seconds.ln() - before_seconds.ln());
        return Reached::Interpolated {
            seconds: log_seconds.exp(),
        };
    }
    Reached::NotReached {
        seconds: last_seconds,
    }
}

/// Seconds as a person reads them: `4.2 s`, `42 s`, `3.5 min`, `1.6 h`.
pub fn format_seconds(seconds: f64) -> String {
    if !seconds.is_finite() {
        return "—".to_string();
    }
    if seconds < 10.0 {
        format!("{seconds:.1} s")
    } else if seconds < 90.0 {
        format!("{seconds:.0} s")
    } else if seconds < 90.0 * 60.0 {
        let minutes = seconds / 60.0;
        if (minutes - minutes.round()).abs() < 0.05 {
            format!("{minutes:.0} min")
        } else {
            format!("{minutes:.1} min")
        }
    } else {
        format!("{:.1} h", seconds / 3600.0)
    }
}

/// A mark as its column is headed: `30 s`, `1 min`, `10 min`.
pub fn format_mark(seconds: f64) -> String {
    if seconds >= 60.0 && (seconds / 60.0).fract() == 0.0 {
        format!("{:.0} min", seconds / 60.0)
    } else if seconds.fract() == 0.0 {
        format!("{seconds:.0} s")
    } else {
        format!("{seconds} s")
    }
}

/// A PSNR for a table cell (two decimals, as the papers print them).
pub fn format_psnr(psnr: f64) -> String {
    if psnr.is_finite() {
        format!("{psnr:.2}")
    } else {
        "—".to_string()
    }
}

/// An SSIM for a table cell (three decimals, as the papers print them).
pub fn format_ssim(ssim: f64) -> String {
    if ssim.is_finite() {
        format!("{ssim:.3}")
    } else {
        "—".to_string()
    }
}

/// Bytes as MiB for a table cell.
pub fn format_mib(bytes: Option<u64>) -> String {
    bytes.map_or("—".to_string(), |b| {
        format!("{:.0} MiB", b as f64 / (1u64 << 20) as f64)
    })
}

/// A table of text cells with a header row.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Table {
    pub headers: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Table {
    pub fn new(headers: impl IntoIterator<Item = impl Into<String>>) -> Self {
        Self {
            headers: headers.into_iter().map(Into::into).collect(),
            rows: Vec::new(),
        }
    }

    /// Adds a row; missing cells are left empty, extra ones dropped, so
    /// every row has a cell per header.
    pub fn push(&mut self, cells: impl IntoIterator<Item = impl Into<String>>) {
        let mut row: Vec<String> = cells.into_iter().map(Into::into).collect();
        row.resize(self.headers.len(), String::new());
        self.rows.push(row);
    }

    /// A GitHub-flavoured Markdown table; `|` inside a cell is escaped.
    pub fn to_markdown(&self) -> String {
        let line = |cells: &[String]| {
            let escaped: Vec<String> = cells.iter().map(|c| c.replace('|', "\\|")).collect();
            format!("| {} |\n", escaped.join(" | "))
        };
        let mut out = line(&self.headers);
        out.push_str(&format!(
            "|{}\n",
            self.headers.iter().map(|_| "---|").collect::<String>()
        ));
        for row in &self.rows {
            out.push_str(&line(row));
        }
        out
    }

    /// RFC 4180 CSV: cells holding a comma, quote or line break are quoted.
    pub fn to_csv(&self) -> String {
        let line = |cells: &[String]| {
            let quoted: Vec<String> = cells.iter().map(|c| csv_cell(c)).collect();
            format!("{}\n", quoted.join(","))
        };
        let mut out = line(&self.headers);
        for row in &self.rows {
            out.push_str(&line(row));
        }
        out
    }
}

fn csv_cell(cell: &str) -> String {
    if cell.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", cell.replace('"', "\"\""))
    } else {
        cell.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9 * b.abs().max(1.0)
    }

    #[test]
    fn a_crossing_is_interpolated_in_log_time() {
        // 20 dB at 30 s, 30 dB at 120 s: 25 dB is half-way in log time,
        // the geometric mean 60 s (linear time would say 75 s).
        let marks = [(30.0, 20.0), (120.0, 30.0)];
        match time_to_reach(&marks, 25.0) {
            Reached::Interpolated { seconds } => assert!(close(seconds, 60.0), "{seconds}"),
            other => panic!("{other:?}"),
        }
        // A quarter of the way: 30 · 4^0.25 = 30 √2.
        match time_to_reach(&marks, 22.5) {
            Reached::Interpolated { seconds } => {
                assert!(close(seconds, 30.0 * 2f64.sqrt()), "{seconds}")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_target_met_exactly_at_a_mark_is_that_mark() {
        let marks = [(30.0, 20.0), (60.0, 25.0), (120.0, 30.0)];
        assert_eq!(
            time_to_reach(&marks, 25.0),
            Reached::Interpolated { seconds: 60.0 }
        );
    }

    #[test]
    fn the_first_crossing_counts_and_the_marks_may_come_unsorted() {
        // Up past 30 dB at 60 s, down at 120 s, up again at 300 s.
        let marks = [(300.0, 31.0), (30.0, 28.0), (120.0, 29.0), (60.0, 32.0)];
        match time_to_reach(&marks, 30.0) {
            Reached::Interpolated { seconds } => {
                // Half-way from 28 to 32 dB between 30 and 60 s.
                assert!(close(seconds, (30f64 * 60.0).sqrt()), "{seconds}");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn reached_by_the_first_mark_is_only_a_bound() {
        let marks = [(30.0, 26.0), (60.0, 28.0)];
        let reached = time_to_reach(&marks, 25.0);
        assert_eq!(reached, Reached::AtMost { seconds: 30.0 });
        assert_eq!(reached.describe(), "≤ 30 s");
        assert_eq!(reached.seconds(), Some(30.0));
    }

    #[test]
    fn never_reached_says_within_what_time() {
        let marks = [(30.0, 20.0), (600.0, 29.9)];
        let reached = time_to_reach(&marks, 30.0);
        assert_eq!(reached, Reached::NotReached { seconds: 600.0 });
        assert_eq!(reached.describe(), "not in 10 min");
        assert_eq!(reached.seconds(), None);
        assert_eq!(time_to_reach(&[], 30.0), Reached::NoMarks);
        assert_eq!(Reached::NoMarks.describe(), "—");
    }

    #[test]
    fn a_failed_evaluation_neither_reaches_nor_anchors_an_interpolation() {
        let marks = [(30.0, f64::NAN), (60.0, 31.0)];
        assert_eq!(
            time_to_reach(&marks, 30.0),
            Reached::AtMost { seconds: 60.0 }
        );
        let marks = [(30.0, 20.0), (60.0, f64::NAN)];
        assert_eq!(
            time_to_reach(&marks, 30.0),
            Reached::NotReached { seconds: 60.0 }
        );
    }

    #[test]
    fn durations_read_as_people_write_them() {
        assert_eq!(format_seconds(4.24), "4.2 s");
        assert_eq!(format_seconds(42.4), "42 s");
        assert_eq!(format_seconds(210.0), "3.5 min");
        assert_eq!(format_seconds(600.0), "10 min");
        assert_eq!(format_seconds(6000.0), "1.7 h");
        assert_eq!(format_mark(30.0), "30 s");
        assert_eq!(format_mark(120.0), "2 min");
        assert_eq!(format_mark(90.0), "90 s");
        assert_eq!(format_mark(1.5), "1.5 s");
        assert_eq!(format_psnr(31.234), "31.23");
        assert_eq!(format_psnr(f64::NAN), "—");
        assert_eq!(format_ssim(0.95678), "0.957");
        assert_eq!(format_mib(Some(3 << 20)), "3 MiB");
    }

    #[test]
    fn tables_print_as_markdown_and_csv() {
        let mut table = Table::new(["model", "PSNR", "note"]);
        table.push(["NeRF", "31.00", "a, b"]);
        table.push(["Mip|NeRF", "33.09"]);
        assert_eq!(
            table.to_markdown(),
            "| model | PSNR | note |\n|---|---|---|\n| NeRF | 31.00 | a, b |\n\
             | Mip\\|NeRF | 33.09 |  |\n"
        );
        assert_eq!(
            table.to_csv(),
            "model,PSNR,note\nNeRF,31.00,\"a, b\"\nMip|NeRF,33.09,\n"
        );
        let mut quoted = Table::new(["say"]);
        quoted.push(["\"hi\""]);
        assert_eq!(quoted.to_csv(), "say\n\"\"\"hi\"\"\"\n");
    }
}
