//! Where the thread's time went since the last report, sent every
//! [`TRACE_INTERVAL`] as [`crate::session::protocol::Event::Schedule`].

use std::time::{Duration, Instant};

use crate::session::schedule::{ScheduleTrace, TRACE_INTERVAL};

/// The trace being gathered and when it began.
pub(super) struct Trace {
    pub(super) time: ScheduleTrace,
    started: Instant,
}

impl Trace {
    pub(super) fn new(now: Instant) -> Self {
        Self {
            time: ScheduleTrace::default(),
            started: now,
        }
    }

    /// Once a [`TRACE_INTERVAL`] has passed at `now`, the trace so far
    /// (nothing when the thread only waited); the next one begins.
    pub(super) fn take_if_due(&mut self, now: Instant) -> Option<ScheduleTrace> {
        let elapsed = now.saturating_duration_since(self.started);
        if elapsed < TRACE_INTERVAL {
            return None;
        }
        let mut trace = std::mem::take(&mut self.time);
        trace.wall_seconds = elapsed.as_secs_f64();
        self.started = now;
        (!trace.only_idle()).then_some(trace)
    }

    /// How long a wait may last at `now` before the trace is due, when
    /// something besides waiting is in it (wake to send what was done
    /// before the wait).
    pub(super) fn wake_within(&self, now: Instant) -> Option<Duration> {
        (!self.time.only_idle())
            .then(|| TRACE_INTERVAL.saturating_sub(now.saturating_duration_since(self.started)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_trace_goes_out_each_interval_unless_the_thread_only_waited() {
        let start = Instant::now();
        let mut trace = Trace::new(start);
        trace.time.idle_seconds = 0.5;
        assert_eq!(trace.wake_within(start), None, "only waiting");
        let later = start + TRACE_INTERVAL + Duration::from_millis(10);
        assert_eq!(trace.take_if_due(later), None, "only waiting");
        // The next interval begins at `later`.
        trace.time.training_seconds = 0.25;
        trace.time.steps = 3;
        let half = later + TRACE_INTERVAL / 2;
        assert_eq!(trace.wake_within(half), Some(TRACE_INTERVAL / 2));
        assert_eq!(trace.take_if_due(half), None, "not due yet");
        let due = later + TRACE_INTERVAL;
        let sent = trace.take_if_due(due).expect("due");
        assert_eq!((sent.steps, sent.training_seconds), (3, 0.25));
        assert!((sent.wall_seconds - TRACE_INTERVAL.as_secs_f64()).abs() < 1e-9);
        assert_eq!(trace.time, ScheduleTrace::default());
        assert_eq!(trace.wake_within(due), None);
    }
}
