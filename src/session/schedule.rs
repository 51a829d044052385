//! How the viewer's training thread shares its time between training,
//! drawing the view and the held-out evaluation, and the trace of where
//! the time went that the stats panel shows.
//!
//! Three rules, each about seconds rather than steps or pixels, so that
//! they hold for a model whose pixel costs fifty times another's:
//!
//! - **The training share.** While the camera rests, training gets
//!   `share` of the thread's busy time and the view and the evaluation
//!   the rest ([`Ledger`]).
//! - **Levels sized by cost.** Each model's render cost per pixel is
//!   measured as it renders ([`RenderCost`]); a new or moving camera's
//!   first level is sized so that it renders within
//!   [`FIRST_LEVEL_SECONDS`].
//! - **A resting picture sharpens to full resolution.** Once the camera
//!   rests, levels refine to full resolution however long each takes on
//!   the machine: they are drawn a chunk or band at a time at the view's
//!   share of the thread, never given up, and the picture never gets
//!   coarser while the camera rests. While training runs, the level on
//!   screen is redrawn as soon as the last redraw is done; a redraw that
//!   takes more than [`refresh_budget`] of render time is shown band by
//!   band, a budget's worth at a time. What is shown is at most two
//!   redraws old ([`lag_bound_seconds`]), which is seconds where a
//!   viewport's render fits the budget and longer, in proportion to the
//!   measured cost of a full-resolution picture, where it does not.

use std::time::Duration;

/// The default training share ([`crate::session::protocol::Balance`]).
pub const DEFAULT_TRAINING_SHARE: f64 = 0.7;

/// Render seconds between two sends of a slow redraw of a resting view at
/// the default training share (issue 27's figure for the cpu engine): at a
/// share of 0.7 a picture that changes ~3.3 s of wall time apart.
pub const REFRESH_SECONDS_AT_DEFAULT_SHARE: f64 = 1.0;

/// Render seconds the first level of a new (or moving) camera may take:
/// it is drawn at once, ahead of training, so it must be short enough for
/// a drag to feel live.
pub const FIRST_LEVEL_SECONDS: f64 = 0.05;

/// The first level is at least this coarse (in each direction): a model
/// whose full view is cheap still shows a coarse picture first and refines
/// it, as the viewer always has.
pub const MIN_FIRST_DOWNSCALE: u32 = 8;

/// Pixels of the first level before the model's cost is known (it is
/// drawn whole, ahead of training): small enough that an untrained NeRF,
/// marched end to end (~500 samples of ~1 M FLOP each per pixel, 5-10 ms a
/// pixel on two busy cores), draws it in well under a second; the next
/// level is sized from what it cost.
pub const FIRST_LEVEL_PIXELS_UNMEASURED: usize = 64;

/// Held-out evaluation takes this share of the training time, as in
/// `zrak train` ([`crate::train::run::Schedule::eval_share`]).
pub const EVAL_SHARE: f64 = 0.05;

/// An evaluation scores at least this many pixels (16 in each of three
/// views), however slow the model: fewer would make the PSNR mostly
/// noise. `zrak train` scores at least 256 every 30 s of training, ~8.5 a
/// training second; the viewer evaluates every 5 s, and 48 pixels keep
/// about that rate. (256 pixels of a NeRF still marching a dense grid,
/// ~5 ms a pixel on two busy cores, took 28 % of the training time; 96
/// still 11 % of the wall time on the demo.)
pub const MIN_EVAL_PIXELS: usize = 48;

/// Render seconds between two sends of a redraw while training runs at
/// `share`: the default share's [`REFRESH_SECONDS_AT_DEFAULT_SHARE`],
/// scaled with the time left to rendering, so that the picture changes
/// about as often in wall time (~3.3 s) at any share.
pub fn refresh_budget(share: f64) -> f64 {
    let left = (1.0 - share.clamp(0.0, 1.0)).max(0.0);
    REFRESH_SECONDS_AT_DEFAULT_SHARE * left / (1.0 - DEFAULT_TRAINING_SHARE)
}

/// The share of the thread's time left to the view while training runs at
/// `share` (the evaluation's share of the training time aside).
pub fn rendering_share(share: f64) -> f64 {
    let share = share.clamp(0.0, 1.0);
    (1.0 - share - EVAL_SHARE * share).max(1e-3)
}

/// Wall seconds the picture of a resting camera may lag behind training
/// while it trains at `share`, where a redraw of the level on screen
/// takes `redraw_seconds` of render time (measured: what the whole level
/// cost, or less than the refresh budget where it fits), and a step
/// `step_seconds`. The picture on screen began at most two redraws ago
/// (the one shown, and the one in progress), each at rendering's share of
/// the time and each waiting behind at most one step. At the default share
/// with a level that fits the 1 s budget: 2 × (1 s / 0.265 + a step) ≈
/// 7.5 s + two steps.
pub fn lag_bound_seconds(share: f64, redraw_seconds: f64, step_seconds: f64) -> f64 {
    let redraw = redraw_seconds.max(refresh_budget(share));
    2.0 * (redraw / rendering_share(share) + step_seconds)
}

/// Wall seconds from a camera coming to rest until its full-resolution
/// picture is on screen, while training runs at `share`, where the full
/// level takes `full_level_seconds` of render time (measured) and a step
/// `step_seconds`: the first level and the refinements (each level a
/// quarter of the next one's pixels, so all of them at most 4/3 of the
/// last) at rendering's share of the time, plus a step a level may wait
/// behind. With a full level of 1 s at the default share: (0.05 + 4/3 ×
/// 1 s) / 0.265 + a step ≈ 5.2 s + a step.
pub fn settle_bound_seconds(share: f64, full_level_seconds: f64, step_seconds: f64) -> f64 {
    (FIRST_LEVEL_SECONDS + 4.0 / 3.0 * full_level_seconds.max(0.0)) / rendering_share(share)
        + step_seconds
}

/// Pixels of a `width × height` view at 1/`downscale` in each direction
/// (at least one each way, as [`super::progressive::level_camera`]).
pub fn level_size(width: u32, height: u32, downscale: u32) -> (u32, u32) {
    let d = downscale.max(1);
    ((width / d).max(1), (height / d).max(1))
}

fn level_pixels(width: u32, height: u32, downscale: u32) -> f64 {
    let (w, h) = level_size(width, height, downscale);
    w as f64 * h as f64
}

/// The finest downscale (the smallest, at least 1) whose level has at
/// most `pixels` pixels.
pub fn finest_within_pixels(width: u32, height: u32, pixels: f64) -> u32 {
    let coarsest = width.max(height).max(1);
    // Pixels fall with the downscale, so the first that fits is the finest.
    // A binary search: viewports are at most 8K wide.
    let (mut low, mut high) = (1u32, coarsest);
    if level_pixels(width, height, low) <= pixels {
        return low;
    }
    while high - low > 1 {
        let middle = low + (high - low) / 2;
        if level_pixels(width, height, middle) <= pixels {
            high = middle;
        } else {
            low = middle;
        }
    }
    high
}

/// The finest downscale whose level renders within `seconds` at
/// `seconds_per_pixel`.
pub fn finest_within(width: u32, height: u32, seconds_per_pixel: f64, seconds: f64) -> u32 {
    let per_pixel = seconds_per_pixel.max(1e-12);
    finest_within_pixels(width, height, (seconds / per_pixel).max(1.0))
}

/// The first level of a new or moving camera.
pub fn first_level(width: u32, height: u32, cost: Option<f64>) -> u32 {
    let downscale = match cost {
        Some(per_pixel) => finest_within(width, height, per_pixel, FIRST_LEVEL_SECONDS),
        None => finest_within_pixels(width, height, FIRST_LEVEL_PIXELS_UNMEASURED as f64),
    };
    downscale.max(MIN_FIRST_DOWNSCALE)
}

/// The level after `shown` on the way to `target` (both downscales): half
/// the downscale, never finer than the target, skipping sizes equal to the
/// one shown (tiny views); `None` once the target is reached.
pub fn next_finer_level(width: u32, height: u32, shown: u32, target: u32) -> Option<u32> {
    let target = target.max(1);
    let size = level_size(width, height, shown);
    let mut downscale = shown;
    while downscale > target {
        downscale = (downscale / 2).max(target);
        if level_size(width, height, downscale) != size {
            return Some(downscale);
        }
    }
    None
}

/// A model's render cost per pixel, measured on whole levels and
/// evaluations (a level's average over the viewport, not one chunk's: the
/// chunks of the sky and of the object differ many times over), and
/// carried forward in proportion to the samples training marches per ray:
/// a render marches the same occupancy grid, and early in NeRF's training
/// that grid fills within a few steps (lego_400: 26 samples per ray at
/// step 16, 336 at step 32), so a cost measured a few steps earlier would
/// understate the next level many times over.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderCost {
    /// Seconds per pixel and per sample marched per training ray.
    seconds_per_pixel_sample: Option<f64>,
    /// Samples marched per training ray in the last step, once known.
    march: Option<f64>,
}

impl RenderCost {
    /// What a pixel is expected to cost now.
    pub fn seconds_per_pixel(&self) -> Option<f64> {
        self.seconds_per_pixel_sample
            .map(|per_sample| per_sample * self.march.unwrap_or(1.0))
    }

    /// Follows the samples training marched per ray in its last step.
    pub fn follow_march(&mut self, samples_per_ray: f64) {
        if !samples_per_ray.is_finite() {
            return;
        }
        // A ray that marches nothing still costs its setup.
        let samples_per_ray = samples_per_ray.max(1.0);
        if self.march.is_none()
            && let Some(per_sample) = self.seconds_per_pixel_sample.as_mut()
        {
            // Measured before the first step: that cost was this march's.
            *per_sample /= samples_per_ray;
        }
        self.march = Some(samples_per_ray);
    }

    /// Records that `pixels` took `seconds`, forgetting the estimate so
    /// far (which a level just proved wrong).
    pub fn replace(&mut self, pixels: usize, seconds: f64) {
        let old = std::mem::take(&mut self.seconds_per_pixel_sample);
        self.record(pixels, seconds);
        if self.seconds_per_pixel_sample.is_none() {
            self.seconds_per_pixel_sample = old;
        }
    }

    /// Records that `pixels` took `seconds` at the current march.
    /// Half-and-half smoothing: the cost of a sample changes too (rays
    /// end sooner as the field turns opaque), and the estimate should
    /// follow within a few levels.
    pub fn record(&mut self, pixels: usize, seconds: f64) {
        if pixels == 0 || !seconds.is_finite() || seconds <= 0.0 {
            return;
        }
        let now = seconds / pixels as f64 / self.march.unwrap_or(1.0);
        self.seconds_per_pixel_sample = Some(match self.seconds_per_pixel_sample {
            None => now,
            Some(old) => 0.5 * old + 0.5 * now,
        });
    }
}

/// Seconds of training and of everything else the thread does for the
/// view (rendering, evaluation) while the camera rests, with the older
/// seconds fading: training is due while its part is at most the share.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Ledger {
    training: f64,
    other: f64,
}

impl Ledger {
    /// Seconds of work over which older seconds fade to 1/e: long enough
    /// to hold many units of work (steps of up to a second or two with
    /// grid updates), short enough that a past imbalance (a long level
    /// drawn while training was paused) is not paid back for minutes.
    const MEMORY_SECONDS: f64 = 20.0;

    pub fn record_training(&mut self, seconds: f64) {
        self.fade(seconds);
        self.training += seconds.max(0.0);
    }

    pub fn record_other(&mut self, seconds: f64) {
        self.fade(seconds);
        self.other += seconds.max(0.0);
    }

    fn fade(&mut self, seconds: f64) {
        let keep = (-seconds.max(0.0) / Self::MEMORY_SECONDS).exp();
        self.training *= keep;
        self.other *= keep;
    }

    /// Whether training is due for a share of `share` of the time.
    pub fn training_due(&self, share: f64) -> bool {
        self.training <= share * (self.training + self.other)
    }
}

/// Seconds spent drawing levels of one downscale.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LevelTime {
    pub downscale: u32,
    pub seconds: f64,
    /// Levels of this downscale finished (and sent).
    pub finished: u32,
}

/// Where the training thread's time went over a stretch of wall time:
/// what the stats panel shows as "where the time goes".
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScheduleTrace {
    /// Wall seconds the trace covers.
    pub wall_seconds: f64,
    /// Inside training steps (grid updates included).
    pub training_seconds: f64,
    /// Of the training seconds, the occupancy-grid updates.
    pub grid_update_seconds: f64,
    pub steps: u32,
    /// Drawing the view, per level downscale, coarse first.
    pub rendering: Vec<LevelTime>,
    /// Held-out evaluations.
    pub evaluation_seconds: f64,
    pub evaluations: u32,
    /// Waiting for a command with nothing to do.
    pub idle_seconds: f64,
}

impl ScheduleTrace {
    pub fn rendering_seconds(&self) -> f64 {
        self.rendering.iter().map(|l| l.seconds).sum()
    }

    /// Wall time not in any other part: commands, events, exports,
    /// scene loading.
    pub fn other_seconds(&self) -> f64 {
        (self.wall_seconds
            - self.training_seconds
            - self.rendering_seconds()
            - self.evaluation_seconds
            - self.idle_seconds)
            .max(0.0)
    }

    pub fn add_rendering(&mut self, downscale: u32, seconds: f64, finished: bool) {
        let index = match self.rendering.iter().position(|l| l.downscale == downscale) {
            Some(index) => index,
            None => {
                // Coarse (large downscale) first.
                let at = self
                    .rendering
                    .iter()
                    .position(|l| l.downscale < downscale)
                    .unwrap_or(self.rendering.len());
                self.rendering.insert(
                    at,
                    LevelTime {
                        downscale,
                        seconds: 0.0,
                        finished: 0,
                    },
                );
                at
            }
        };
        let level = &mut self.rendering[index];
        level.seconds += seconds;
        level.finished += u32::from(finished);
    }

    /// Adds `other`'s seconds and counts to these.
    pub fn merge(&mut self, other: &ScheduleTrace) {
        self.wall_seconds += other.wall_seconds;
        self.training_seconds += other.training_seconds;
        self.grid_update_seconds += other.grid_update_seconds;
        self.steps += other.steps;
        self.evaluation_seconds += other.evaluation_seconds;
        self.evaluations += other.evaluations;
        self.idle_seconds += other.idle_seconds;
        for level in &other.rendering {
            self.add_rendering(level.downscale, level.seconds, false);
            if let Some(mine) = self
                .rendering
                .iter_mut()
                .find(|l| l.downscale == level.downscale)
            {
                mine.finished += level.finished;
            }
        }
    }

    /// True when nothing but waiting happened.
    pub fn only_idle(&self) -> bool {
        self.training_seconds == 0.0 && self.rendering.is_empty() && self.evaluation_seconds == 0.0
    }
}

/// How often the thread sends its trace.
pub const TRACE_INTERVAL: Duration = Duration::from_secs(1);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_refresh_budget_is_a_second_at_the_default_share_and_follows_the_share() {
        assert!((refresh_budget(DEFAULT_TRAINING_SHARE) - 1.0).abs() < 1e-12);
        assert!((refresh_budget(0.85) - 0.5).abs() < 1e-12);
        assert!(refresh_budget(0.0) > 3.0);
        assert_eq!(refresh_budget(1.0), 0.0);
        // At the default share: two redraws of 1 s at 26.5 % of the time,
        // each behind a step; a redraw slower than the budget counts whole.
        let bound = lag_bound_seconds(0.7, 0.2, 0.1);
        assert!((bound - 2.0 * (1.0 / 0.265 + 0.1)).abs() < 1e-9, "{bound}");
        let slow = lag_bound_seconds(0.7, 5.0, 0.1);
        assert!((slow - 2.0 * (5.0 / 0.265 + 0.1)).abs() < 1e-9, "{slow}");
        let settle = settle_bound_seconds(0.7, 1.0, 0.5);
        assert!(
            (settle - ((0.05 + 4.0 / 3.0) / 0.265 + 0.5)).abs() < 1e-9,
            "{settle}"
        );
    }

    #[test]
    fn the_finest_level_within_a_budget_fits_it_and_the_next_finer_does_not() {
        for &(width, height) in &[(930, 500), (64, 64), (5, 3), (1, 1), (8192, 8192)] {
            for &per_pixel in &[1e-7, 3e-6, 1e-4, 2e-3, 1.0] {
                let seconds = 1.0;
                let d = finest_within(width, height, per_pixel, seconds);
                assert!(d >= 1);
                let fits = |d: u32| level_pixels(width, height, d) * per_pixel <= seconds;
                if d > 1 {
                    assert!(!fits(d - 1), "{width}×{height} at {per_pixel}: 1/{d}");
                }
                // The level found fits, unless even one pixel does not.
                assert!(
                    fits(d) || level_size(width, height, d) == (1, 1),
                    "{width}×{height} at {per_pixel}: 1/{d}"
                );
            }
        }
        // NeRF-like cost (0.1 ms a pixel) on a 930 × 500 viewport: 10 000
        // pixels in a second, 1/7 (132 × 71 = 9372 px).
        assert_eq!(finest_within(930, 500, 1e-4, 1.0), 7);
        // Instant-NGP-like (2 µs a pixel): the full viewport.
        assert_eq!(finest_within(930, 500, 2e-6, 1.0), 1);
    }

    #[test]
    fn first_levels_are_coarse_and_fit_their_budget() {
        // Cheap: the familiar 1/8.
        assert_eq!(first_level(930, 500, Some(1e-8)), 8);
        // Unmeasured: at most 64 pixels.
        let d = first_level(930, 500, None);
        assert!(level_pixels(930, 500, d) <= 64.0 && d >= 8, "1/{d}");
        // An untrained NeRF (~2 ms a pixel): 25 pixels in 50 ms.
        let d = first_level(930, 500, Some(2e-3));
        assert!(level_pixels(930, 500, d) <= 25.0, "1/{d}");
    }

    #[test]
    fn refinement_halves_towards_the_target_and_skips_repeated_sizes() {
        let walk = |width, height, first, target| {
            let mut levels = vec![first];
            while let Some(next) = next_finer_level(width, height, *levels.last().unwrap(), target)
            {
                levels.push(next);
            }
            levels
        };
        assert_eq!(walk(64, 64, 8, 1), vec![8, 4, 2, 1]);
        assert_eq!(walk(64, 64, 8, 3), vec![8, 4, 3]);
        assert_eq!(walk(930, 500, 37, 7), vec![37, 18, 9, 7]);
        // 4 px: 1/8 and 1/4 are both one pixel.
        assert_eq!(walk(4, 4, 8, 1), vec![8, 2, 1]);
        assert_eq!(walk(1, 1, 8, 1), vec![8]);
        // Already at or finer than the target.
        assert_eq!(next_finer_level(64, 64, 2, 4), None);
    }

    #[test]
    fn the_ledger_gives_training_its_share_of_the_time() {
        // Steps of 0.3 s against render chunks of 0.04 s: the ledger's
        // choices add up to the share within a step.
        for share in [0.2, 0.5, 0.7, 0.95] {
            let mut ledger = Ledger::default();
            let (mut training, mut other) = (0.0, 0.0);
            while training + other < 120.0 {
                if ledger.training_due(share) {
                    ledger.record_training(0.3);
                    training += 0.3;
                } else {
                    ledger.record_other(0.04);
                    other += 0.04;
                }
            }
            let got = training / (training + other);
            assert!((got - share).abs() < 0.01, "share {share}: {got}");
        }
    }

    #[test]
    fn a_resting_views_redraws_keep_within_the_lag_bound_for_given_step_times() {
        // The thread's choice while the camera rests, as the worker makes
        // it (a training step when the ledger says training is due, else a
        // chunk of the view), with steps and chunks of given lengths: once
        // under way, each redraw of a level that takes `redraw` render
        // seconds is done within half the lag bound (which allows for the
        // redraw on screen and the one in progress).
        for (share, step, chunk, redraw) in [
            (0.7, 0.3, 0.04, 1.0),
            (0.5, 0.05, 0.04, 3.0),
            (0.2, 1.2, 0.04, 0.5),
            (0.95, 0.02, 0.01, 0.2),
        ] {
            let mut ledger = Ledger::default();
            let (mut wall, mut drawn) = (0.0, 0.0);
            let mut finished: Vec<f64> = Vec::new();
            while wall < 300.0 {
                if ledger.training_due(share) {
                    ledger.record_training(step);
                    wall += step;
                } else {
                    ledger.record_other(chunk);
                    wall += chunk;
                    drawn += chunk;
                    if drawn >= redraw - 1e-9 {
                        drawn = 0.0;
                        finished.push(wall);
                    }
                }
            }
            let longest = finished.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
            let bound = lag_bound_seconds(share, redraw, step) / 2.0;
            assert!(finished.len() > 10, "share {share}: {finished:?}");
            assert!(
                longest <= bound,
                "share {share}, steps of {step} s, redraws of {redraw} s: {longest} s > {bound} s"
            );
        }
    }

    #[test]
    fn the_cost_follows_the_levels_it_is_given() {
        let mut cost = RenderCost::default();
        assert_eq!(cost.seconds_per_pixel(), None);
        cost.record(1000, 1.0);
        assert_eq!(cost.seconds_per_pixel(), Some(1e-3));
        cost.record(1000, 0.0); // not a measurement
        cost.record(0, 1.0);
        cost.replace(0, 1.0);
        assert_eq!(cost.seconds_per_pixel(), Some(1e-3));
        cost.replace(100, 1.0);
        assert_eq!(cost.seconds_per_pixel(), Some(1e-2));
        for _ in 0..20 {
            cost.record(1000, 0.1);
        }
        let now = cost.seconds_per_pixel().unwrap();
        assert!((now - 1e-4).abs() < 1e-6, "{now}");
    }

    #[test]
    fn the_cost_follows_the_samples_training_marches() {
        let mut cost = RenderCost::default();
        // Measured before any step: taken as the first step's march.
        cost.record(1000, 1.0);
        cost.follow_march(25.0);
        assert_eq!(cost.seconds_per_pixel(), Some(1e-3));
        // The grid fills: 13 times the samples, 13 times the cost, before
        // any level has measured it.
        cost.follow_march(325.0);
        let filled = cost.seconds_per_pixel().unwrap();
        assert!((filled - 13e-3).abs() < 1e-12, "{filled}");
        // A level at that march that cost what was foreseen changes nothing.
        cost.record(100, 1.3);
        let after = cost.seconds_per_pixel().unwrap();
        assert!((after - 13e-3).abs() < 1e-12, "{after}");
        // Marching nothing still costs the setup of a ray; NaN is no news.
        cost.follow_march(0.0);
        cost.follow_march(f64::NAN);
        let empty = cost.seconds_per_pixel().unwrap();
        assert!((empty - 4e-5).abs() < 1e-12, "{empty}");
    }

    #[test]
    fn a_trace_sums_its_parts_and_keeps_levels_coarse_first() {
        let mut trace = ScheduleTrace {
            wall_seconds: 10.0,
            training_seconds: 6.0,
            idle_seconds: 0.5,
            evaluation_seconds: 0.3,
            ..Default::default()
        };
        trace.add_rendering(2, 1.0, false);
        trace.add_rendering(8, 0.2, true);
        trace.add_rendering(2, 1.0, true);
        let downscales: Vec<u32> = trace.rendering.iter().map(|l| l.downscale).collect();
        assert_eq!(downscales, vec![8, 2]);
        assert_eq!(trace.rendering[1].finished, 1);
        assert!((trace.rendering_seconds() - 2.2).abs() < 1e-12);
        assert!((trace.other_seconds() - 1.0).abs() < 1e-12);
        let mut total = ScheduleTrace::default();
        total.merge(&trace);
        total.merge(&trace);
        assert_eq!(total.rendering[1].finished, 2);
        assert!((total.wall_seconds - 20.0).abs() < 1e-12);
    }
}
