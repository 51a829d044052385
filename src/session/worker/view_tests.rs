//! The view's part without a thread: the cameras it refuses, the balance
//! it keeps, and what it tells the window.

use std::sync::{Arc, Mutex, mpsc};

use glam::Vec3;

use super::{MAX_TRAINING_SHARE, Viewing, check_camera};
use crate::model::RenderMode;
use crate::scene::{Camera, Intrinsics};
use crate::session::protocol::{Balance, Event, RenderRequest};
use crate::session::worker::Outbox;

fn camera(width: u32, height: u32) -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(width, height, 0.7),
        Vec3::new(3.0, 0.0, 1.0),
        Vec3::ZERO,
        Vec3::Z,
    )
}

#[test]
fn cameras_that_cannot_be_drawn_are_refused_with_the_reason() {
    assert_eq!(check_camera(&camera(64, 48)), Ok(()));
    let error = check_camera(&camera(0, 48)).unwrap_err();
    assert!(error.contains("0×48 pixels"), "{error}");
    let error = check_camera(&camera(8193, 8)).unwrap_err();
    assert!(error.contains("1 to 8192"), "{error}");
    let mut bad = camera(64, 48);
    bad.intrinsics.fx = f32::NAN;
    assert!(check_camera(&bad).unwrap_err().contains("intrinsics"));
    let mut bad = camera(64, 48);
    bad.camera_to_world.x_axis.x = f32::INFINITY;
    assert!(check_camera(&bad).unwrap_err().contains("non-finite"));
}

#[test]
fn the_balance_is_kept_in_bounds_and_training_never_takes_all() {
    let mut viewing = Viewing::new(false);
    let default = Balance::default().training_share as f64;
    assert!((viewing.training_share() - default).abs() < 1e-6);
    for (asked, kept) in [
        (0.3, 0.3),
        (-1.0, 0.0),
        (1.0, MAX_TRAINING_SHARE),
        (f32::NAN, default as f32),
    ] {
        viewing.set_balance(Balance {
            training_share: asked,
        });
        let share = viewing.training_share();
        assert!((share - kept as f64).abs() < 1e-6, "{asked}: {share}");
    }
    // No camera: nothing to draw, and the time is counted.
    assert!(!viewing.camera_moving());
    assert!(viewing.pending(None).is_none());
    viewing.record_training(10.0);
    assert!(!viewing.training_due(), "training had all the time");
    viewing.record_other(100.0);
    assert!(viewing.training_due());
}

#[test]
fn a_refused_camera_is_answered_with_an_error_and_no_view() {
    let (events, received) = mpsc::channel();
    let outbox = Outbox {
        events,
        repaint: Arc::new(Mutex::new(None)),
    };
    let mut viewing = Viewing::new(false);
    let request = RenderRequest {
        generation: 7,
        camera: camera(0, 10),
        mode: RenderMode::Rgb,
        moving: false,
        needs_pixels: false,
    };
    viewing.set_view(request, None, &outbox).unwrap();
    match received.try_recv() {
        Ok(Event::Error(message)) => {
            assert!(message.starts_with("render request 7 refused"), "{message}")
        }
        other => panic!("{other:?}"),
    }
    // A good camera but no model: the view waits for one.
    let request = RenderRequest {
        generation: 8,
        camera: camera(32, 24),
        mode: RenderMode::Rgb,
        moving: true,
        needs_pixels: false,
    };
    viewing.set_view(request, None, &outbox).unwrap();
    assert!(received.try_recv().is_err(), "nothing to send yet");
    assert!(viewing.camera_moving());
    assert!(viewing.pending(None).is_none(), "no model to draw with");
}
