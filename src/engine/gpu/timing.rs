//! Per-stage timing of a gpu training step.
//!
//! A step records many dispatches into one command encoder, so the host's
//! clock only sees the whole submission. Where the device has
//! `TIMESTAMP_QUERY`, a [`StageClock`] writes a GPU timestamp at each stage
//! boundary, resolves them once per step and reads them back with the
//! step's own read-back, converted with `Queue::get_timestamp_period`.
//!
//! A boundary is an empty compute pass whose end-of-pass timestamp is
//! written (wgpu's Vulkan backend writes it at `BOTTOM_OF_PIPE`, i.e. once
//! all earlier commands have finished), so plain `TIMESTAMP_QUERY` suffices;
//! `TIMESTAMP_QUERY_INSIDE_ENCODERS` is not needed.
//!
//! Without timestamps the clock falls back to the wall clock: at each
//! boundary it submits what was recorded so far and waits for the device.
//! The waits serialise the step, so those figures include submission
//! overhead and the step runs a little slower while timed that way.

use std::time::Instant;

use wgpu::Features;

use super::kernel::{MapRequest, Recorder};
use crate::engine::gpu::GpuContext;
use crate::model::{Stage, StageTimes};

/// How stage times are measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageTiming {
    /// GPU timestamps between stages: device time only.
    Timestamps,
    /// Host clock with a wait for the device at every stage boundary.
    WallClock,
}

impl StageTiming {
    /// How stage times are measured, in words for reports.
    pub fn note(self) -> String {
        match self {
            StageTiming::Timestamps => "gpu timestamps: device time of each stage".into(),
            StageTiming::WallClock => "the wall clock, waiting for the device at each stage \
                                       boundary (the device has no timestamp queries)"
                .into(),
        }
    }
}

/// Boundaries one step can mark (a step marks about 20).
const MAX_MARKS: u32 = 128;

struct Queries {
    set: wgpu::QuerySet,
    resolved: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// Nanoseconds per timestamp tick.
    period_ns: f64,
}

/// Times the stages of one step; see the module documentation.
pub struct StageClock {
    queries: Option<Queries>,
    /// The stage each interval belongs to: interval i lies between
    /// boundary i and i + 1; `None` intervals (gaps between submissions)
    /// are not counted.
    intervals: Vec<Option<Stage>>,
    marks: u32,
    wall: StageTimes,
    last: Instant,
}

impl StageClock {
    /// A clock using timestamps when the device has them and `timing` asks
    /// for them, else the wall clock.
    pub fn new(context: &GpuContext, timing: StageTiming) -> Self {
        let queries = (timing == StageTiming::Timestamps
            && context.features.contains(Features::TIMESTAMP_QUERY))
        .then(|| {
            let bytes = 8 * MAX_MARKS as u64;
            let buffer = |label: &str, usage| {
                context.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: bytes,
                    usage,
                    mapped_at_creation: false,
                })
            };
            Queries {
                set: context.device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("stage timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count: MAX_MARKS,
                }),
                resolved: buffer(
                    "stage timestamps resolved",
                    wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                ),
                staging: buffer(
                    "stage timestamps read-back",
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                ),
                period_ns: context.queue.get_timestamp_period() as f64,
            }
        });
        Self {
            queries,
            intervals: Vec::new(),
            marks: 0,
            wall: StageTimes::default(),
            last: Instant::now(),
        }
    }

    /// How this clock measures.
    pub fn timing(&self) -> StageTiming {
        if self.queries.is_some() {
            StageTiming::Timestamps
        } else {
            StageTiming::WallClock
        }
    }

    /// Forgets the last step's marks; call before the step's first
    /// [`Self::restart`].
    pub fn reset(&mut self) {
        self.intervals.clear();
        self.marks = 0;
        self.wall = StageTimes::default();
        self.last = Instant::now();
    }

    /// Starts a new interval without counting the time since the last
    /// boundary (the first boundary of a submission: the gap before it is
    /// host time between submissions).
    pub fn restart(&mut self, rec: &mut Recorder) {
        self.boundary(rec, None);
    }

    /// Ends the interval since the last boundary and counts it to `stage`.
    pub fn mark(&mut self, rec: &mut Recorder, stage: Stage) {
        self.boundary(rec, Some(stage));
    }

    fn boundary(&mut self, rec: &mut Recorder, stage: Option<Stage>) {
        match &self.queries {
            Some(queries) => {
                if self.marks >= MAX_MARKS {
                    return;
                }
                if self.marks > 0 {
                    self.intervals.push(stage);
                }
                rec.encoder
                    .begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("stage boundary"),
                        timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                            query_set: &queries.set,
                            beginning_of_pass_write_index: None,
                            end_of_pass_write_index: Some(self.marks),
                        }),
                    });
                self.marks += 1;
            }
            None => {
                rec.submit_so_far();
                rec.context
                    .device
                    .poll(wgpu::PollType::wait_indefinitely())
                    .expect("waiting for the GPU");
                let now = Instant::now();
                if let Some(stage) = stage {
                    self.wall[stage] += (now - self.last).as_secs_f64();
                }
                self.last = now;
            }
        }
    }

    /// Records the resolve and copy of this step's timestamps; call once,
    /// in the step's last encoder, after its last boundary.
    pub fn resolve(&self, rec: &mut Recorder) {
        if let Some(queries) = &self.queries
            && self.marks > 0
        {
            rec.encoder
                .resolve_query_set(&queries.set, 0..self.marks, &queries.resolved, 0);
            rec.encoder.copy_buffer_to_buffer(
                &queries.resolved,
                0,
                &queries.staging,
                0,
                8 * self.marks as u64,
            );
        }
    }

    /// Seconds per stage of the step, once the submission holding
    /// [`Self::resolve`] has completed.
    /// Waits only if that submission has not finished already.
    pub fn read(&self, context: &GpuContext) -> StageTimes {
        self.read_later().take(context)
    }

    /// As [`Self::read`] without waiting: call right after submitting the
    /// encoder holding [`Self::resolve`]; [`PendingTimes::take`] gives the
    /// times once a later read-back has waited for the device. The clock
    /// may be reset and used for the next step meanwhile, but that step's
    /// `resolve` must be submitted only after the take.
    pub fn read_later(&self) -> PendingTimes {
        match &self.queries {
            Some(queries) if self.marks >= 2 => PendingTimes::Ticks {
                request: MapRequest::new(&queries.staging, 8 * self.marks as u64),
                intervals: self.intervals.clone(),
                period_ns: queries.period_ns,
            },
            Some(_) => PendingTimes::Ready(StageTimes::default()),
            None => PendingTimes::Ready(self.wall),
        }
    }
}

/// A step's stage times on their way back from the device
/// ([`StageClock::read_later`]).
pub enum PendingTimes {
    Ready(StageTimes),
    Ticks {
        request: MapRequest,
        intervals: Vec<Option<Stage>>,
        period_ns: f64,
    },
}

impl PendingTimes {
    pub fn take(self, context: &GpuContext) -> StageTimes {
        match self {
            PendingTimes::Ready(times) => times,
            PendingTimes::Ticks {
                request,
                intervals,
                period_ns,
            } => stage_times(&intervals, &request.take::<u64>(context), period_ns),
        }
    }
}

/// Seconds per stage from the timestamps at the boundaries of `intervals`.
fn stage_times(intervals: &[Option<Stage>], ticks: &[u64], period_ns: f64) -> StageTimes {
    let mut times = StageTimes::default();
    for (i, stage) in intervals.iter().enumerate() {
        if let Some(stage) = stage {
            // Timestamps may wrap or (on some drivers) go backwards
            // across submissions: such an interval counts as 0.
            let delta = ticks[i + 1].saturating_sub(ticks[i]);
            times[*stage] += delta as f64 * period_ns * 1e-9;
        }
    }
    times
}
