//! A viewing session without its window: the training thread and the
//! messages it exchanges with a window, how its time is shared between
//! training and drawing, the progressive levels of the view, the free
//! camera and the camera path being edited. Nothing here knows the GUI
//! toolkit; [`crate::app`] draws the window on top of it.

pub mod camera;
pub mod path_state;
pub mod progressive;
pub mod protocol;
pub mod schedule;
pub mod worker;
