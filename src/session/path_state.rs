//! The camera-path editor's state, apart from any window: the path being
//! edited, the selected keyframe, the play clock and the export settings.
//!
//! Every edit is a plain function on [`PathEditor`], so tests check the list
//! operations and the clock without opening a window; the window
//! (`ui/path_editor.rs`) only calls them.

use std::path::PathBuf;

use crate::render::camera_path::nerfstudio::CameraPathFile;
use crate::render::camera_path::{CameraPath, Keyframe};
use crate::session::camera::ViewCamera;

/// Frame rate a new path is exported at: nerfstudio's viewer's default.
pub const DEFAULT_FPS: f64 = 30.0;

/// Render size a new path is exported at before a scene says otherwise:
/// 1280×720, the smallest common HD video size.
pub const DEFAULT_RENDER_SIZE: (u32, u32) = (1280, 720);

/// The most keyframes made from a file that has only a baked frame list:
/// a list longer than this is thinned to every n-th frame, so the editor's
/// list stays usable (a 10-second video at 30 fps bakes 300 frames).
pub const MAX_KEYFRAMES_FROM_BAKED: usize = 60;

/// A path file the editor loads as soon as a scene is open.
#[derive(Debug, Clone, PartialEq)]
pub struct PendingLoad {
    pub file: PathBuf,
    /// Where on the path to put the camera (seconds); the start if `None`.
    pub time: Option<f64>,
    /// Start playing once loaded.
    pub play: bool,
}

/// The editor's state.
#[derive(Debug, Clone)]
pub struct PathEditor {
    /// Whether the editor window is shown.
    pub open: bool,
    /// Whether the path is drawn over the viewport while the editor is open.
    pub show_overlay: bool,
    pub path: CameraPath,
    /// The keyframe the per-keyframe controls act on; always a valid index
    /// or `None`.
    pub selected: Option<usize>,
    /// Where on the path the timeline stands, in seconds.
    pub time: f64,
    pub playing: bool,
    /// When the play clock last moved, to advance it by real time.
    pub play_clock: Option<std::time::Instant>,
    /// The viewport camera as the path last put it, to tell when the user
    /// has moved it since.
    pub placed_camera: Option<ViewCamera>,
    /// True in a frame where the path moved the viewport camera (playing,
    /// scrubbing, jumping to a keyframe): the viewport treats it as a
    /// camera move.
    pub driving: bool,
    /// Frame rate and size of an exported video.
    pub fps: f64,
    pub width: u32,
    pub height: u32,
    /// "From training cameras": every n-th camera.
    pub every: usize,
    /// The path file's name in the text field beside Save and Load.
    pub file_text: String,
    /// The last thing the editor has to say (saved, loaded, why not).
    pub message: Option<(String, bool)>,
    /// A path file to load once a scene is there (`zrak view
    /// --camera-path`).
    pub pending_load: Option<PendingLoad>,
}

impl Default for PathEditor {
    fn default() -> Self {
        Self {
            open: false,
            show_overlay: true,
            path: CameraPath::new(Vec::new()),
            selected: None,
            time: 0.0,
            playing: false,
            play_clock: None,
            placed_camera: None,
            driving: false,
            fps: DEFAULT_FPS,
            width: DEFAULT_RENDER_SIZE.0,
            height: DEFAULT_RENDER_SIZE.1,
            every: 1,
            file_text: std::env::temp_dir()
                .join("camera_path.json")
                .display()
                .to_string(),
            message: None,
            pending_load: None,
        }
    }
}

impl PathEditor {
    pub fn keyframes(&self) -> &[Keyframe] {
        &self.path.keyframes
    }

    /// Adds `keyframe` after the selected one (at the end when none is
    /// selected) and selects it, so repeated adds build the path in order.
    pub fn add(&mut self, keyframe: Keyframe) {
        let at = self.selected.map_or(self.path.keyframes.len(), |i| i + 1);
        self.path.keyframes.insert(at, keyframe);
        self.selected = Some(at);
        self.keep_time_on_path();
    }

    /// Moves the selected keyframe to `keyframe`'s pose and field of view;
    /// its transition to the next keyframe stays.
    pub fn set_selected_pose(&mut self, keyframe: &Keyframe) {
        if let Some(k) = self.selected_mut() {
            k.camera_to_world = keyframe.camera_to_world;
            k.fov_degrees = keyframe.fov_degrees;
        }
    }

    /// A copy of the selected keyframe right after it, selected.
    pub fn duplicate_selected(&mut self) {
        if let Some(i) = self.selected {
            let copy = self.path.keyframes[i];
            self.path.keyframes.insert(i + 1, copy);
            self.selected = Some(i + 1);
            self.keep_time_on_path();
        }
    }

    /// Removes the selected keyframe; the one that took its place is
    /// selected next (the new last one when it was the last).
    pub fn delete_selected(&mut self) {
        if let Some(i) = self.selected {
            self.path.keyframes.remove(i);
            let n = self.path.keyframes.len();
            self.selected = (n > 0).then(|| i.min(n - 1));
            self.keep_time_on_path();
        }
    }

    /// Swaps the selected keyframe with the one before (`up`) or after it;
    /// the selection follows it. Nothing happens at either end.
    pub fn move_selected(&mut self, up: bool) {
        let Some(i) = self.selected else {
            return;
        };
        let other = if up {
            i.checked_sub(1)
        } else {
            Some(i + 1).filter(|&j| j < self.path.keyframes.len())
        };
        if let Some(j) = other {
            self.path.keyframes.swap(i, j);
            self.selected = Some(j);
        }
    }

    /// Replaces the keyframes (a path from training cameras, a file),
    /// keeping the path's settings; selects the first keyframe and goes
    /// back to the start.
    pub fn replace_keyframes(&mut self, keyframes: Vec<Keyframe>) {
        self.path.keyframes = keyframes;
        self.selected = (!self.path.keyframes.is_empty()).then_some(0);
        self.time = 0.0;
        self.playing = false;
    }

    /// No keyframes left.
    pub fn clear(&mut self) {
        self.replace_keyframes(Vec::new());
    }

    pub fn select(&mut self, index: usize) {
        if index < self.path.keyframes.len() {
            self.selected = Some(index);
        }
    }

    pub fn selected_mut(&mut self) -> Option<&mut Keyframe> {
        self.selected.and_then(|i| self.path.keyframes.get_mut(i))
    }

    /// The time the path reaches keyframe `index`.
    pub fn knot_time(&self, index: usize) -> Option<f64> {
        (index < self.path.keyframes.len()).then(|| self.path.knot_times()[index])
    }

    /// Whether the path can be sampled (at least one keyframe and sane
    /// settings).
    pub fn can_sample(&self) -> bool {
        self.path.problem().is_none()
    }

    /// Starts playing, from the start when the clock stands at the end of
    /// an open path.
    pub fn play(&mut self) {
        let duration = self.path.duration();
        if !self.path.is_cycle && self.time >= duration {
            self.time = 0.0;
        }
        self.playing = duration > 0.0 && self.can_sample();
    }

    /// One frame of playing: the clock moves on by `dt` seconds.
    pub fn tick(&mut self, dt: f64) {
        if self.playing {
            let (time, playing) =
                advance_clock(self.time, dt, self.path.duration(), self.path.is_cycle);
            self.time = time;
            self.playing = playing;
        }
    }

    /// The clock stays within the path after an edit shortened it.
    fn keep_time_on_path(&mut self) {
        self.time = self.time.clamp(0.0, self.path.duration());
        if self.path.duration() <= 0.0 {
            self.playing = false;
        }
    }
}

/// The play clock: `time` moved on by `dt` seconds (a negative or
/// non-finite `dt` counts as none) on a path of `duration` seconds; a cycle
/// wraps round, an open path stops at its end. Returns the new time and
/// whether it is still playing.
pub fn advance_clock(time: f64, dt: f64, duration: f64, is_cycle: bool) -> (f64, bool) {
    if !(duration.is_finite() && duration > 0.0) {
        return (0.0, false);
    }
    let dt = if dt.is_finite() { dt.max(0.0) } else { 0.0 };
    let time = if time.is_finite() { time } else { 0.0 };
    let next = time + dt;
    if is_cycle {
        (next.rem_euclid(duration), true)
    } else if next >= duration {
        (duration, false)
    } else {
        (next.max(0.0), true)
    }
}

/// Keyframes from a file's baked frames (when it has no keyframes): every
/// frame when there are at most [`MAX_KEYFRAMES_FROM_BAKED`], else every
/// n-th with the last one kept, each transition the time between the
/// frames kept, so the path lasts as the baked video did. Returns the
/// keyframes and the step n.
pub fn keyframes_from_baked(file: &CameraPathFile) -> (Vec<Keyframe>, usize) {
    let frames = file.frames().unwrap_or_default();
    let n = frames.len();
    let every = n.div_ceil(MAX_KEYFRAMES_FROM_BAKED).max(1);
    let mut chosen: Vec<usize> = (0..n).step_by(every).collect();
    if n > 0 && chosen.last() != Some(&(n - 1)) {
        chosen.push(n - 1);
    }
    let seconds_per_frame = if file.fps.is_finite() && file.fps > 0.0 {
        1.0 / file.fps
    } else {
        1.0 / DEFAULT_FPS
    };
    let keyframes = chosen
        .windows(2)
        .map(|w| (w[0], Some((w[1] - w[0]) as f64 * seconds_per_frame)))
        .chain(chosen.last().map(|&i| (i, None)))
        .map(|(i, transition)| Keyframe {
            camera_to_world: frames[i].camera_to_world,
            fov_degrees: frames[i].fov_degrees,
            transition_seconds: transition,
        })
        .collect();
    (keyframes, every)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera_path::nerfstudio::BakedFrame;
    use crate::render::camera_path::{PathSample, look_at};
    use glam::{DMat4, DVec3};

    /// A keyframe told apart by its x position.
    fn key(x: f64) -> Keyframe {
        Keyframe::new(
            look_at(DVec3::new(x, -4.0, 1.0), DVec3::ZERO, DVec3::Z),
            40.0,
        )
    }

    fn xs(editor: &PathEditor) -> Vec<f64> {
        editor.keyframes().iter().map(|k| k.position().x).collect()
    }

    fn editor_with(n: usize) -> PathEditor {
        let mut editor = PathEditor::default();
        for i in 0..n {
            editor.add(key(i as f64));
        }
        editor
    }

    #[test]
    fn adding_appends_after_the_selection_and_selects_the_new_keyframe() {
        let mut editor = editor_with(3);
        assert_eq!(xs(&editor), vec![0.0, 1.0, 2.0]);
        assert_eq!(editor.selected, Some(2));
        editor.select(0);
        editor.add(key(9.0));
        assert_eq!(xs(&editor), vec![0.0, 9.0, 1.0, 2.0]);
        assert_eq!(editor.selected, Some(1));
        // Selecting past the end changes nothing.
        editor.select(7);
        assert_eq!(editor.selected, Some(1));
    }

    #[test]
    fn duplicating_inserts_a_copy_after_and_selects_it() {
        let mut editor = editor_with(3);
        editor.select(1);
        editor.selected_mut().unwrap().transition_seconds = Some(2.5);
        editor.duplicate_selected();
        assert_eq!(xs(&editor), vec![0.0, 1.0, 1.0, 2.0]);
        assert_eq!(editor.selected, Some(2));
        assert_eq!(editor.keyframes()[2], editor.keyframes()[1]);
        // Nothing selected: nothing duplicated.
        editor.selected = None;
        editor.duplicate_selected();
        assert_eq!(editor.keyframes().len(), 4);
    }

    #[test]
    fn deleting_selects_the_keyframe_that_took_its_place() {
        let mut editor = editor_with(4);
        editor.select(1);
        editor.delete_selected();
        assert_eq!(xs(&editor), vec![0.0, 2.0, 3.0]);
        assert_eq!(editor.selected, Some(1));
        // The last one: the new last is selected.
        editor.select(2);
        editor.delete_selected();
        assert_eq!(xs(&editor), vec![0.0, 2.0]);
        assert_eq!(editor.selected, Some(1));
        editor.delete_selected();
        editor.delete_selected();
        assert!(editor.keyframes().is_empty());
        assert_eq!(editor.selected, None);
        // Deleting from an empty path is harmless.
        editor.delete_selected();
        assert_eq!(editor.selected, None);
    }

    #[test]
    fn deleting_keeps_the_clock_on_the_shorter_path() {
        let mut editor = editor_with(4);
        editor.time = 3.0;
        editor.select(3);
        editor.delete_selected();
        assert_eq!(editor.path.duration(), 2.0);
        assert_eq!(editor.time, 2.0);
    }

    #[test]
    fn reordering_swaps_neighbours_and_the_selection_follows() {
        let mut editor = editor_with(3);
        editor.select(0);
        editor.move_selected(false);
        assert_eq!(xs(&editor), vec![1.0, 0.0, 2.0]);
        assert_eq!(editor.selected, Some(1));
        editor.move_selected(false);
        assert_eq!(xs(&editor), vec![1.0, 2.0, 0.0]);
        assert_eq!(editor.selected, Some(2));
        // At the end: stays.
        editor.move_selected(false);
        assert_eq!(xs(&editor), vec![1.0, 2.0, 0.0]);
        assert_eq!(editor.selected, Some(2));
        editor.move_selected(true);
        editor.move_selected(true);
        assert_eq!(xs(&editor), vec![0.0, 1.0, 2.0]);
        assert_eq!(editor.selected, Some(0));
        editor.move_selected(true);
        assert_eq!(xs(&editor), vec![0.0, 1.0, 2.0]);
        assert_eq!(editor.selected, Some(0));
    }

    #[test]
    fn moving_a_keyframe_keeps_its_transition() {
        let mut editor = editor_with(2);
        editor.select(0);
        editor.selected_mut().unwrap().transition_seconds = Some(3.0);
        let mut target = key(7.0);
        target.fov_degrees = 65.0;
        editor.set_selected_pose(&target);
        let k = editor.keyframes()[0];
        assert_eq!(k.position().x, 7.0);
        assert_eq!(k.fov_degrees, 65.0);
        assert_eq!(k.transition_seconds, Some(3.0));
        assert_eq!(editor.keyframes()[1].position().x, 1.0);
    }

    #[test]
    fn clearing_and_replacing_reset_selection_and_clock() {
        let mut editor = editor_with(3);
        editor.time = 1.5;
        editor.playing = true;
        editor.replace_keyframes(vec![key(5.0), key(6.0)]);
        assert_eq!(
            (editor.selected, editor.time, editor.playing),
            (Some(0), 0.0, false)
        );
        editor.clear();
        assert_eq!(editor.selected, None);
        assert!(!editor.can_sample());
    }

    #[test]
    fn the_clock_advances_by_dt() {
        assert_eq!(advance_clock(0.5, 0.25, 3.0, false), (0.75, true));
        assert_eq!(advance_clock(0.5, 0.25, 3.0, true), (0.75, true));
        // A stalled or bogus frame time does not move it backwards.
        assert_eq!(advance_clock(0.5, -1.0, 3.0, false), (0.5, true));
        assert_eq!(advance_clock(0.5, f64::NAN, 3.0, false), (0.5, true));
    }

    #[test]
    fn a_cycle_wraps_round_and_keeps_playing() {
        let (time, playing) = advance_clock(2.9, 0.25, 3.0, true);
        assert!((time - 0.15).abs() < 1e-12, "{time}");
        assert!(playing);
        // Several laps in one step still land inside the path.
        let (time, _) = advance_clock(1.0, 7.5, 3.0, true);
        assert!((time - 2.5).abs() < 1e-12, "{time}");
    }

    #[test]
    fn an_open_path_stops_at_its_end() {
        assert_eq!(advance_clock(2.9, 0.25, 3.0, false), (3.0, false));
        assert_eq!(advance_clock(3.0, 0.0, 3.0, false), (3.0, false));
        // A path of one keyframe has no time to play.
        assert_eq!(advance_clock(0.0, 0.1, 0.0, true), (0.0, false));
    }

    #[test]
    fn playing_from_the_end_starts_again_and_stops_at_the_end() {
        let mut editor = editor_with(3);
        editor.time = 2.0;
        editor.play();
        assert!(editor.playing);
        assert_eq!(editor.time, 0.0);
        for _ in 0..30 {
            editor.tick(0.1);
        }
        assert!(!editor.playing);
        assert_eq!(editor.time, 2.0);
        // A cycle of the same three keyframes lasts 3 s, plays on from
        // where the clock stands (2 s) and keeps going round: 2 + 3.5 is
        // 2.5 into the second lap.
        editor.path.is_cycle = true;
        editor.play();
        assert_eq!(editor.time, 2.0);
        for _ in 0..35 {
            editor.tick(0.1);
        }
        assert!(editor.playing);
        assert!((editor.time - 2.5).abs() < 1e-9, "{}", editor.time);
        // One keyframe cannot play.
        let mut one = editor_with(1);
        one.play();
        assert!(!one.playing);
    }

    #[test]
    fn baked_frames_become_keyframes_lasting_as_long() {
        let sample = |i: usize| PathSample {
            camera_to_world: DMat4::from_translation(DVec3::new(i as f64, 0.0, 0.0)),
            fov_degrees: 30.0 + i as f64,
        };
        let mut file = CameraPathFile::new(
            CameraPath::new(vec![key(0.0)]),
            64,
            48,
            10.0,
            DMat4::IDENTITY,
        );
        file.path = None;
        file.baked = (0..5)
            .map(|i| BakedFrame::from_sample(&sample(i), 4.0 / 3.0))
            .collect();
        let (keyframes, every) = keyframes_from_baked(&file);
        assert_eq!(every, 1);
        assert_eq!(keyframes.len(), 5);
        assert_eq!(keyframes[3].position().x, 3.0);
        assert_eq!(keyframes[3].fov_degrees, 33.0);
        let path = CameraPath::new(keyframes);
        assert!((path.duration() - 0.4).abs() < 1e-12);
        // A long list is thinned, keeping the last frame and the duration.
        file.baked = (0..301)
            .map(|i| BakedFrame::from_sample(&sample(i), 4.0 / 3.0))
            .collect();
        let (keyframes, every) = keyframes_from_baked(&file);
        assert_eq!(every, 6);
        assert!(keyframes.len() <= MAX_KEYFRAMES_FROM_BAKED + 1);
        assert_eq!(keyframes.last().unwrap().position().x, 300.0);
        assert_eq!(keyframes[1].position().x, 6.0);
        let path = CameraPath::new(keyframes);
        assert!((path.duration() - 30.0).abs() < 1e-9);
    }
}
