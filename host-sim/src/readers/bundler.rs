//! Bundler v0.3 `bundle.out` reader. Same camera model as BAL (see [`crate::readers::bal`] for the
//! exact conversion), with the rotation stored as a 3x3 matrix; cameras with `f = 0` were
//! not placed by Bundler and are skipped together with their observations. Image names
//! come from the name list beside the file (`list.txt` or `name_list.txt`, one image per
//! camera, the name first on each line), when there is one.

use std::path::Path;

use anyhow::Context;
use nalgebra::{Matrix3, Vector3};

use crate::readers::bal::{assemble_scene, BundlerCamera, Observation};
use crate::readers::parse::{file_name, FormatError, Tokens};
use crate::scene::Scene;

/// First line of every Bundler v0.3 file.
const HEADER: &str = "# Bundle file v0.3";

/// Tokens of one camera record: `f k1 k2`, `R` and `t`.
const CAMERA_TOKENS: usize = 15;
/// Tokens of a point record without views: position, colour, view count.
const POINT_MIN_TOKENS: usize = 7;

/// Reads a Bundler v0.3 `bundle.out`.
pub fn read_bundler(path: &Path) -> anyhow::Result<Scene> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let name = scene_name(path);
    let mut scene =
        parse_bundler(&text, name).with_context(|| format!("parsing {}", path.display()))?;
    let folder = path.parent().unwrap_or(Path::new("."));
    let list = NAME_LISTS
        .iter()
        .map(|n| folder.join(n))
        .find(|p| p.is_file());
    if let Some(list) = list {
        let names = std::fs::read_to_string(&list)
            .with_context(|| format!("reading {}", list.display()))?;
        apply_name_list(&mut scene, &names)
            .with_context(|| format!("parsing {}", list.display()))?;
    }
    Ok(scene)
}

/// The name of the scene of a Bundler file: `bundler/<the folder holding bundle.out>` (the
/// file stem for another file name).
pub fn scene_name(path: &Path) -> String {
    let stem = match file_name(path).as_deref() {
        Some("bundle.out") => path.parent().and_then(file_name),
        _ => path.file_stem().map(|s| s.to_string_lossy().into_owned()),
    };
    format!("bundler/{}", stem.unwrap_or_default())
}

/// Name lists Bundler's tools write beside `bundle.out`, in the order they are looked for.
const NAME_LISTS: [&str; 2] = ["list.txt", "name_list.txt"];

/// Names the images from a name list: line `i` (its first token) names camera `i`. The list
/// must have one non-empty line per camera of the file.
pub fn apply_name_list(scene: &mut Scene, list: &str) -> Result<(), FormatError> {
    let names: Vec<&str> = list
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .collect();
    for image in scene.images.values_mut() {
        let index = image.id as usize;
        let name = names.get(index).ok_or(FormatError::OutOfRange {
            what: "camera index in the name list",
            value: index as u64,
            limit: names.len() as u64,
        })?;
        image.name = (*name).to_string();
    }
    Ok(())
}

/// Parses the text of a Bundler v0.3 file: header, `num_cameras num_points`, per camera
/// `f k1 k2`, three rows of `R` and `t`, per point its position, colour and view list
/// `n (camera key x y)^n`. Observation keys (SIFT indices) are not kept: each image's
/// keypoints are its observations in file order.
pub fn parse_bundler(text: &str, name: String) -> Result<Scene, FormatError> {
    if text.lines().next().map(str::trim) != Some(HEADER) {
        return Err(FormatError::Syntax {
            line: 1,
            message: format!("expected the header {HEADER:?}"),
        });
    }
    let mut tokens = Tokens::new(text, 1);
    // Each count is bounded by the records the rest of the file can hold, so that the
    // reservations below never exceed what the file holds.
    let camera_count = tokens.count("the camera count", CAMERA_TOKENS)?;
    let point_count = tokens.count("the point count", POINT_MIN_TOKENS)?;
    let mut cameras = Vec::with_capacity(camera_count);
    for _ in 0..camera_count {
        let [focal, k1, k2] = tokens.f64s::<3>("f k1 k2")?;
        let rows = tokens.f64s::<9>("a rotation entry")?;
        let translation = Vector3::from(tokens.f64s::<3>("a translation entry")?);
        cameras.push((focal != 0.0).then(|| BundlerCamera {
            rotation: Matrix3::from_row_slice(&rows),
            translation,
            focal,
            k1,
            k2,
        }));
    }
    let mut points = Vec::with_capacity(point_count);
    let mut observations = Vec::new();
    for point in 0..point_count {
        points.push(Vector3::from(tokens.f64s::<3>("a point coordinate")?));
        tokens.f64s::<3>("a colour channel")?;
        let views: usize = tokens.parse("the view count")?;
        for _ in 0..views {
            let camera: usize = tokens.parse("a view's camera index")?;
            let _key: u64 = tokens.parse("a view's keypoint index")?;
            let position = tokens.f64s::<2>("a view's coordinates")?;
            observations.push(Observation {
                camera,
                point,
                position,
            });
        }
    }
    tokens.finish()?;
    assemble_scene(name, &cameras, &points, &observations)
}

#[cfg(test)]
mod tests {
    use super::*;

    const TINY: &str = "# Bundle file v0.3\n2 1\n\
        500 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 -5\n\
        0 0 0\n0 0 0\n0 0 0\n0 0 0\n0 0 0\n\
        0 0 0\n255 0 0\n2 0 17 3.5 -2.0 1 4 0 0\n";

    #[test]
    fn unplaced_cameras_are_skipped_with_their_observations() {
        let scene = parse_bundler(TINY, "bundler/tiny".into()).unwrap();
        scene.validate().unwrap();
        assert_eq!(scene.images.len(), 1);
        assert_eq!(scene.points[&0].track.len(), 1);
        assert_eq!(scene.images[&0].keypoints[0].pixel, [3.5, 2.0]);
        // The point at the origin seen by a camera 5 units in front projects at the centre.
        let bearing = scene.images[&0]
            .pose
            .bearing(&scene.points[&0].xyz, 0)
            .unwrap();
        assert_eq!(bearing, [0.0, 0.0]);
    }

    #[test]
    fn name_lists_name_images_by_camera_index() {
        let mut scene = parse_bundler(TINY, "bundler/tiny".into()).unwrap();
        apply_name_list(&mut scene, "a.jpg 0 500\nb.jpg\n").unwrap();
        assert_eq!(scene.images[&0].name, "a.jpg");
        assert!(matches!(
            apply_name_list(&mut scene, ""),
            Err(FormatError::OutOfRange { .. })
        ));
    }

    #[test]
    fn malformed_files_are_typed_errors() {
        assert!(matches!(
            parse_bundler("# Bundle file v0.2\n0 0\n", "x".into()),
            Err(FormatError::Syntax { line: 1, .. })
        ));
        let truncated = &TINY[..TINY.len() - 8];
        assert!(matches!(
            parse_bundler(truncated, "x".into()),
            Err(FormatError::Syntax { .. })
        ));
        let bad_camera = TINY.replace("2 0 17 3.5", "2 5 17 3.5");
        assert!(matches!(
            parse_bundler(&bad_camera, "x".into()),
            Err(FormatError::OutOfRange {
                what: "camera index",
                ..
            })
        ));
    }
}
