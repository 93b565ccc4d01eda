//! The images a session names, one list for the API (uploads, missing images) and the
//! detection stage.

use super::Session;

/// One image slot the manifest announces: (camera, frame index) and its path. Ring
/// images of the vanishing method are slots of the auxiliary camera, by ring index.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ImageSlot {
    pub camera: String,
    pub frame: i64,
    /// Position in `frames[]` (`None` for ring images of the vanishing method).
    #[serde(skip)]
    pub frame_pos: Option<usize>,
    pub path: String,
    /// The manifest field naming it (`frames[2].images.front`, `ring[3].image`).
    pub field: String,
    /// The size the camera's images must have.
    #[serde(skip)]
    pub size: (u32, u32),
}

pub fn image_slots(session: &Session) -> Vec<ImageSlot> {
    let mut out = Vec::new();
    for (fi, f) in session.manifest.frames.iter().enumerate() {
        for (cam, path) in &f.images {
            let Some(c) = session
                .camera_index(cam)
                .map(|i| &session.cameras[i].camera)
            else {
                continue;
            };
            out.push(ImageSlot {
                camera: cam.clone(),
                frame: f.index,
                frame_pos: Some(fi),
                path: path.clone(),
                field: format!("frames[{fi}].images.{cam}"),
                size: (c.width, c.height),
            });
        }
    }
    if let Some(v) = &session.vanishing {
        for (ri, r) in session.manifest.ring.iter().enumerate() {
            if let Some(path) = &r.image {
                out.push(ImageSlot {
                    camera: v.auxiliary.id.clone(),
                    frame: r.index,
                    frame_pos: None,
                    path: path.clone(),
                    field: format!("ring[{ri}].image"),
                    size: (v.auxiliary.camera.width, v.auxiliary.camera.height),
                });
            }
        }
    }
    out
}

/// Images of the session that have no detections yet, as field paths
/// (`frames[3].images.front`).
pub fn undetected_images(session: &Session) -> Vec<String> {
    let mut out = Vec::new();
    for (fi, f) in session.manifest.frames.iter().enumerate() {
        for cam in f.images.keys() {
            let detected = f.observations.get(cam).is_some_and(|o| !o.is_empty())
                || f.lines.get(cam).is_some_and(|l| !l.is_empty());
            if !detected {
                out.push(format!("frames[{fi}].images.{cam}"));
            }
        }
    }
    for (ri, r) in session.manifest.ring.iter().enumerate() {
        if r.image.is_some() && r.lines.is_empty() {
            out.push(format!("ring[{ri}].image"));
        }
    }
    out
}
