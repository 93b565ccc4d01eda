//! What a printed target is: the tag family's codes, the AprilGrid layout and Wu's line
//! target, in their own frames. The detector, the renderer and the session resolver all
//! read the print from here.

pub mod board;
pub mod line_layout;
pub mod line_target;
pub mod tag36h11;
