//! COLMAP sparse model reader: `cameras`, `images` and `points3D`, in COLMAP's binary
//! (`.bin`) or text (`.txt`) format. Poses are COLMAP's (`x_cam = R(q) x + t`), pixels have
//! their origin at the top-left corner, and an untriangulated keypoint has point id -1.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use gomatch::camera::{CameraModel, MAX_PARAMS};
use gomatch::{Camera, Pose};
use nalgebra::Vector3;

use crate::readers::parse::{field, file_name, token, ByteReader, FormatError};
use crate::scene::{CameraId, Image, ImageId, Keypoint, Point3d, PointId, Scene, TrackElement};

/// COLMAP's marker of an untriangulated keypoint in binary files (`-1` as `u64`).
const INVALID_POINT_ID: u64 = u64::MAX;

/// Smallest binary record sizes in bytes, used to bound declared counts.
const CAMERA_RECORD_MIN_BYTES: usize = 4 + 4 + 8 + 8;
const IMAGE_RECORD_MIN_BYTES: usize = 4 + 7 * 8 + 4 + 1 + 8;
const KEYPOINT_RECORD_BYTES: usize = 8 + 8 + 8;
const POINT_RECORD_MIN_BYTES: usize = 8 + 3 * 8 + 3 + 8 + 8;
const TRACK_ELEMENT_BYTES: usize = 4 + 4;

/// Whether `dir` holds a COLMAP model (`cameras.bin` or `cameras.txt`).
fn holds_model(dir: &Path) -> bool {
    dir.join("cameras.bin").is_file() || dir.join("cameras.txt").is_file()
}

/// Folders up to two levels below `dir` that hold a COLMAP model, sorted.
fn models_below(dir: &Path) -> Vec<PathBuf> {
    let subfolders = |d: &Path| -> Vec<PathBuf> {
        let Ok(entries) = std::fs::read_dir(d) else {
            return Vec::new();
        };
        let mut dirs: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_dir())
            .collect();
        dirs.sort();
        dirs
    };
    subfolders(dir)
        .into_iter()
        .flat_map(|child| {
            let grandchildren = subfolders(&child);
            std::iter::once(child).chain(grandchildren)
        })
        .filter(|d| holds_model(d))
        .collect()
}

/// The model folder `dir` names: `dir` itself when it holds a model, else the one model up
/// to two levels below it (COLMAP's `sparse/0` layout). Several models below, none, or a
/// file instead of a folder are errors that say what was found.
pub fn find_model_dir(dir: &Path) -> anyhow::Result<PathBuf> {
    if dir.is_file() {
        let head: Vec<u8> = std::fs::read(dir)
            .map(|b| b.into_iter().take(64).collect())
            .unwrap_or_default();
        bail!(
            "{} is a file ({}), not a COLMAP model folder (cameras, images, points3D .bin or .txt)",
            dir.display(),
            gomatch_blobs::files::FileKind::of(&head).describe()
        );
    }
    if holds_model(dir) {
        return Ok(dir.to_path_buf());
    }
    match models_below(dir).as_slice() {
        [one] => {
            eprintln!("using the COLMAP model in {}", one.display());
            Ok(one.clone())
        }
        [] => bail!(
            "{} holds no COLMAP model (cameras.bin or cameras.txt), nor do its subfolders",
            dir.display()
        ),
        several => {
            const SHOWN: usize = 5;
            let mut list: Vec<String> = several
                .iter()
                .take(SHOWN)
                .map(|d| d.display().to_string())
                .collect();
            if several.len() > SHOWN {
                list.push(format!("and {} more", several.len() - SHOWN));
            }
            bail!(
                "{} holds no COLMAP model itself; pick one of: {}",
                dir.display(),
                list.join(", ")
            )
        }
    }
}

/// The name of the scene of a COLMAP model folder: `colmap/<folder>`, the scene folder for the
/// `<scene>/sparse/<n>` layout.
pub fn scene_name(dir: &Path) -> String {
    let is_generic = |c: &str| c == "sparse" || c.chars().all(|ch| ch.is_ascii_digit());
    let stem = dir
        .ancestors()
        .filter_map(file_name)
        .find(|c| !is_generic(c))
        .unwrap_or_default();
    format!("colmap/{stem}")
}

/// Reads a COLMAP sparse model folder ([`find_model_dir`]: or the one model below it).
/// Uses the `.bin` files when `cameras.bin` exists, the `.txt` files otherwise. The scene
/// is named after the folder ([`scene_name`]) and is not yet validated.
pub fn read_model(dir: &Path) -> anyhow::Result<Scene> {
    let dir = &find_model_dir(dir)?;
    let binary = dir.join("cameras.bin").exists();
    let read = |stem: &str| -> anyhow::Result<Vec<u8>> {
        let ext = if binary { "bin" } else { "txt" };
        let path = dir.join(format!("{stem}.{ext}"));
        std::fs::read(&path).with_context(|| format!("reading {}", path.display()))
    };
    let (cameras, images, points) = (read("cameras")?, read("images")?, read("points3D")?);
    let context = |stem: &str| format!("parsing {}/{stem}", dir.display());
    let scene = if binary {
        Scene {
            name: scene_name(dir),
            cameras: parse_cameras_bin(&cameras).with_context(|| context("cameras.bin"))?,
            images: parse_images_bin(&images).with_context(|| context("images.bin"))?,
            points: parse_points_bin(&points).with_context(|| context("points3D.bin"))?,
        }
    } else {
        let text = |bytes: &[u8], stem: &str| -> anyhow::Result<String> {
            String::from_utf8(bytes.to_vec()).with_context(|| context(stem))
        };
        Scene {
            name: scene_name(dir),
            cameras: parse_cameras_txt(&text(&cameras, "cameras.txt")?)
                .with_context(|| context("cameras.txt"))?,
            images: parse_images_txt(&text(&images, "images.txt")?)
                .with_context(|| context("images.txt"))?,
            points: parse_points_txt(&text(&points, "points3D.txt")?)
                .with_context(|| context("points3D.txt"))?,
        }
    };
    Ok(scene)
}

fn camera_from_params(
    camera_id: u64,
    model: CameraModel,
    width: u64,
    height: u64,
    params: &[f64],
) -> Result<Camera, FormatError> {
    let size = |v: u64, what| {
        u32::try_from(v).map_err(|_| FormatError::OutOfRange {
            what,
            value: v,
            limit: u64::from(u32::MAX) + 1,
        })
    };
    Camera::from_colmap(
        model,
        size(width, "width")?,
        size(height, "height")?,
        params,
    )
    .map_err(|reason| FormatError::InvalidCamera { camera_id, reason })
}

fn insert_unique<K: Ord + Copy + Into<u64>, V>(
    map: &mut BTreeMap<K, V>,
    id: K,
    value: V,
    what: &'static str,
) -> Result<(), FormatError> {
    if map.insert(id, value).is_some() {
        return Err(FormatError::DuplicateId {
            what,
            id: id.into(),
        });
    }
    Ok(())
}

fn pose_from_colmap(image_id: u64, q: [f64; 4], t: [f64; 3]) -> Result<Pose, FormatError> {
    Pose::from_colmap(q, t).map_err(|reason| FormatError::InvalidPose { image_id, reason })
}

/// Parses `cameras.bin`.
pub fn parse_cameras_bin(data: &[u8]) -> Result<BTreeMap<CameraId, Camera>, FormatError> {
    let mut reader = ByteReader::new(data);
    let count = reader.count("camera count", CAMERA_RECORD_MIN_BYTES)?;
    let mut cameras = BTreeMap::new();
    for _ in 0..count {
        let id = reader.u32("camera id")?;
        let model_id = reader.i32("camera model")?;
        let model = CameraModel::from_colmap_id(model_id).map_err(|_| {
            FormatError::UnsupportedCameraModel {
                camera_id: id.into(),
                model: format!("id {model_id}"),
            }
        })?;
        let width = reader.u64("camera width")?;
        let height = reader.u64("camera height")?;
        let mut params = [0.0; MAX_PARAMS];
        for p in params.iter_mut().take(model.param_count()) {
            *p = reader.f64("camera parameter")?;
        }
        let camera = camera_from_params(
            id.into(),
            model,
            width,
            height,
            &params[..model.param_count()],
        )?;
        insert_unique(&mut cameras, id, camera, "camera")?;
    }
    reader.finish()?;
    Ok(cameras)
}

/// Parses `images.bin`.
pub fn parse_images_bin(data: &[u8]) -> Result<BTreeMap<ImageId, Image>, FormatError> {
    let mut reader = ByteReader::new(data);
    let count = reader.count("image count", IMAGE_RECORD_MIN_BYTES)?;
    let mut images = BTreeMap::new();
    for _ in 0..count {
        let id = reader.u32("image id")?;
        let q = reader.f64s::<4>("image quaternion")?;
        let t = reader.f64s::<3>("image translation")?;
        let camera_id = reader.u32("image camera id")?;
        let name = reader.c_string("image name")?;
        let keypoint_count = reader.count("keypoint count", KEYPOINT_RECORD_BYTES)?;
        let mut keypoints = Vec::with_capacity(keypoint_count);
        for _ in 0..keypoint_count {
            let pixel = reader.f64s::<2>("keypoint position")?;
            let point_id = reader.u64("keypoint point id")?;
            keypoints.push(Keypoint {
                pixel,
                point3d: (point_id != INVALID_POINT_ID).then_some(point_id),
            });
        }
        let image = Image {
            id,
            name,
            camera_id,
            pose: pose_from_colmap(id.into(), q, t)?,
            keypoints,
        };
        insert_unique(&mut images, id, image, "image")?;
    }
    reader.finish()?;
    Ok(images)
}

/// Parses `points3D.bin`.
pub fn parse_points_bin(data: &[u8]) -> Result<BTreeMap<PointId, Point3d>, FormatError> {
    let mut reader = ByteReader::new(data);
    let count = reader.count("point count", POINT_RECORD_MIN_BYTES)?;
    let mut points = BTreeMap::new();
    for _ in 0..count {
        let id = reader.u64("point id")?;
        let xyz = reader.f64s::<3>("point position")?;
        for _ in 0..3 {
            reader.u8("point color")?;
        }
        reader.f64("point error")?;
        let track_length = reader.count("track length", TRACK_ELEMENT_BYTES)?;
        let mut track = Vec::with_capacity(track_length);
        for _ in 0..track_length {
            track.push(TrackElement {
                image_id: reader.u32("track image id")?,
                keypoint_index: reader.u32("track keypoint index")?,
            });
        }
        let point = Point3d {
            id,
            xyz: Vector3::from(xyz),
            track,
        };
        insert_unique(&mut points, id, point, "point")?;
    }
    reader.finish()?;
    Ok(points)
}

/// Non-empty, non-comment lines with their 1-based numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// Parses `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`.
pub fn parse_cameras_txt(text: &str) -> Result<BTreeMap<CameraId, Camera>, FormatError> {
    let mut cameras = BTreeMap::new();
    for (line, content) in data_lines(text) {
        let mut fields = content.split_whitespace();
        let id: CameraId = field(&mut fields, line, "camera id")?;
        let camera = parse_camera_fields(fields, id, line)?;
        insert_unique(&mut cameras, id, camera, "camera")?;
    }
    Ok(cameras)
}

/// Parses a camera without its id, as in `cameras.txt` and hloc's query lists:
/// `MODEL WIDTH HEIGHT PARAMS[]` (line 1 in errors).
pub fn parse_camera_line(text: &str) -> Result<Camera, FormatError> {
    parse_camera_fields(text.split_whitespace(), 0, 1)
}

/// `MODEL WIDTH HEIGHT PARAMS[]` of camera `id` on `line`.
fn parse_camera_fields(
    mut fields: std::str::SplitWhitespace<'_>,
    id: CameraId,
    line: usize,
) -> Result<Camera, FormatError> {
    let model_name: String = field(&mut fields, line, "camera model")?;
    let model = CameraModel::from_colmap_name(&model_name).map_err(|_| {
        FormatError::UnsupportedCameraModel {
            camera_id: id.into(),
            model: model_name.clone(),
        }
    })?;
    let width: u64 = field(&mut fields, line, "camera width")?;
    let height: u64 = field(&mut fields, line, "camera height")?;
    let params = fields
        .map(|t| {
            t.parse::<f64>().map_err(|_| FormatError::Syntax {
                line,
                message: format!("expected a camera parameter, found {t:?}"),
            })
        })
        .collect::<Result<Vec<f64>, _>>()?;
    if params.len() != model.param_count() {
        return Err(FormatError::Syntax {
            line,
            message: format!(
                "{model_name} takes {} parameters, found {}",
                model.param_count(),
                params.len()
            ),
        });
    }
    camera_from_params(id.into(), model, width, height, &params)
}

/// A camera as COLMAP's text line without the id: `MODEL WIDTH HEIGHT PARAMS[]`.
pub fn camera_line(camera: &Camera) -> String {
    let (params, count) = camera.colmap_params();
    let params: Vec<String> = params[..count].iter().map(f64::to_string).collect();
    format!(
        "{} {} {} {}",
        camera.model.colmap_name(),
        camera.width,
        camera.height,
        params.join(" ")
    )
}

/// Parses `images.txt`: per image a header line
/// `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` followed by one line (possibly empty) of
/// `X Y POINT3D_ID` triples.
pub fn parse_images_txt(text: &str) -> Result<BTreeMap<ImageId, Image>, FormatError> {
    let mut images = BTreeMap::new();
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    while let Some((line, header)) = lines.next() {
        if header.is_empty() || header.starts_with('#') {
            continue;
        }
        let mut fields = header.split_whitespace();
        let id: ImageId = field(&mut fields, line, "image id")?;
        let mut numbers = [0.0; 7];
        for v in &mut numbers {
            *v = field(&mut fields, line, "a pose value")?;
        }
        let camera_id: CameraId = field(&mut fields, line, "camera id")?;
        let name = fields.collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(FormatError::Syntax {
                line,
                message: "line ends where the image name was expected".into(),
            });
        }
        let (points_line, points_text) = lines.next().unwrap_or((line + 1, ""));
        let keypoints = parse_keypoints_line(points_text, points_line)?;
        let [qw, qx, qy, qz, tx, ty, tz] = numbers;
        let image = Image {
            id,
            name,
            camera_id,
            pose: pose_from_colmap(id.into(), [qw, qx, qy, qz], [tx, ty, tz])?,
            keypoints,
        };
        insert_unique(&mut images, id, image, "image")?;
    }
    Ok(images)
}

fn parse_keypoints_line(text: &str, line: usize) -> Result<Vec<Keypoint>, FormatError> {
    let tokens: Vec<&str> = text.split_whitespace().collect();
    if !tokens.len().is_multiple_of(3) {
        return Err(FormatError::Syntax {
            line,
            message: format!(
                "keypoints come in (X, Y, POINT3D_ID) triples, found {} values",
                tokens.len()
            ),
        });
    }
    tokens
        .chunks_exact(3)
        .map(|triple| {
            let point_id: i64 = token(triple[2], line, "a keypoint point id")?;
            let point3d = match point_id {
                -1 => None,
                id => Some(u64::try_from(id).map_err(|_| FormatError::Syntax {
                    line,
                    message: format!("point id {id} is neither -1 nor non-negative"),
                })?),
            };
            Ok(Keypoint {
                pixel: [
                    token(triple[0], line, "a keypoint x")?,
                    token(triple[1], line, "a keypoint y")?,
                ],
                point3d,
            })
        })
        .collect()
}

/// Parses `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR TRACK[]` with the track as
/// `IMAGE_ID POINT2D_IDX` pairs.
pub fn parse_points_txt(text: &str) -> Result<BTreeMap<PointId, Point3d>, FormatError> {
    let mut points = BTreeMap::new();
    for (line, content) in data_lines(text) {
        let mut fields = content.split_whitespace();
        let id: PointId = field(&mut fields, line, "point id")?;
        let mut xyz = [0.0; 3];
        for v in &mut xyz {
            *v = field(&mut fields, line, "a point coordinate")?;
        }
        for _ in 0..3 {
            field::<u8>(&mut fields, line, "a color channel")?;
        }
        field::<f64>(&mut fields, line, "the point error")?;
        let rest: Vec<&str> = fields.collect();
        if !rest.len().is_multiple_of(2) {
            return Err(FormatError::Syntax {
                line,
                message: "track elements come in (IMAGE_ID, POINT2D_IDX) pairs".into(),
            });
        }
        let track = rest
            .chunks_exact(2)
            .map(|pair| {
                Ok(TrackElement {
                    image_id: token(pair[0], line, "a track image id")?,
                    keypoint_index: token(pair[1], line, "a track keypoint index")?,
                })
            })
            .collect::<Result<Vec<_>, FormatError>>()?;
        let point = Point3d {
            id,
            xyz: Vector3::from(xyz),
            track,
        };
        insert_unique(&mut points, id, point, "point")?;
    }
    Ok(points)
}

/// Writes a scene as a COLMAP text model (`cameras.txt`, `images.txt`, `points3D.txt`).
/// Used to export synthetic scenes and to test the readers on a known model.
pub fn write_model_txt(scene: &Scene, dir: &Path) -> anyhow::Result<()> {
    use std::fmt::Write as _;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut cameras = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    for (id, camera) in &scene.cameras {
        let (params, count) = camera.colmap_params();
        let params: Vec<String> = params[..count].iter().map(|p| format!("{p:?}")).collect();
        writeln!(
            cameras,
            "{id} {} {} {} {}",
            camera.model.colmap_name(),
            camera.width,
            camera.height,
            params.join(" ")
        )?;
    }
    let mut images = String::from(
        "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    for image in scene.images.values() {
        let q = nalgebra::UnitQuaternion::from_rotation_matrix(&image.pose.rotation);
        let t = image.pose.translation;
        writeln!(
            images,
            "{} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {} {}",
            image.id, q.w, q.i, q.j, q.k, t.x, t.y, t.z, image.camera_id, image.name
        )?;
        let keypoints: Vec<String> = image
            .keypoints
            .iter()
            .map(|k| {
                let id = k.point3d.map_or(-1, |p| p as i64);
                format!("{:?} {:?} {id}", k.pixel[0], k.pixel[1])
            })
            .collect();
        writeln!(images, "{}", keypoints.join(" "))?;
    }
    let mut points =
        String::from("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    for point in scene.points.values() {
        let track: Vec<String> = point
            .track
            .iter()
            .map(|e| format!("{} {}", e.image_id, e.keypoint_index))
            .collect();
        let [x, y, z] = [point.xyz.x, point.xyz.y, point.xyz.z];
        writeln!(
            points,
            "{} {x:?} {y:?} {z:?} 128 128 128 0 {}",
            point.id,
            track.join(" ")
        )?;
    }
    for (name, content) in [
        ("cameras.txt", cameras),
        ("images.txt", images),
        ("points3D.txt", points),
    ] {
        let path = dir.join(name);
        std::fs::write(&path, content).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_model_parses_cameras_images_and_points() {
        let cameras =
            parse_cameras_txt("# comment\n1 SIMPLE_RADIAL 2832 2128 2971.71 1416 1064 -0.164224\n")
                .unwrap();
        assert_eq!(cameras[&1].model, CameraModel::SimpleRadial);
        assert_eq!(cameras[&1].distortion[0], -0.164224);

        let images = parse_images_txt(
            "# c\n10 1 0 0 0 1 2 3 1 a b.jpg\n5.5 6.5 -1 7 8 42\n11 1 0 0 0 0 0 0 1 c.jpg\n\n",
        )
        .unwrap();
        assert_eq!(images[&10].name, "a b.jpg");
        assert_eq!(images[&10].keypoints.len(), 2);
        assert_eq!(images[&10].keypoints[0].point3d, None);
        assert_eq!(images[&10].keypoints[1].point3d, Some(42));
        assert_eq!(images[&10].pose.translation, Vector3::new(1.0, 2.0, 3.0));
        assert!(images[&11].keypoints.is_empty());

        let points = parse_points_txt("42 1 2 3 10 20 30 0.5 10 1 11 0\n").unwrap();
        assert_eq!(points[&42].track.len(), 2);
        assert_eq!(points[&42].track[1].image_id, 11);
    }

    #[test]
    fn malformed_text_is_a_typed_error() {
        assert!(matches!(
            parse_cameras_txt("1 FISHEYE_X 10 10 1 2 3"),
            Err(FormatError::UnsupportedCameraModel { camera_id: 1, .. })
        ));
        assert!(matches!(
            parse_cameras_txt("1 PINHOLE 10 10 1 2 3"),
            Err(FormatError::Syntax { line: 1, .. })
        ));
        assert!(matches!(
            parse_cameras_txt("1 PINHOLE 10 10 0 1 2 3"),
            Err(FormatError::InvalidCamera { camera_id: 1, .. })
        ));
        assert!(matches!(
            parse_images_txt("1 0 0 0 0 0 0 0 1 a.jpg\n1 2\n"),
            Err(FormatError::Syntax { line: 2, .. })
        ));
        assert!(matches!(
            parse_images_txt("1 0 0 0 0 0 0 0 1 a.jpg\n\n"),
            Err(FormatError::InvalidPose { image_id: 1, .. })
        ));
        assert!(matches!(
            parse_points_txt("1 0 0 0 1 1 1 0 3\n"),
            Err(FormatError::Syntax { line: 1, .. })
        ));
        assert!(matches!(
            parse_points_txt("1 0 0 0 1 1 1 0\n1 0 0 0 1 1 1 0\n"),
            Err(FormatError::DuplicateId { id: 1, .. })
        ));
    }

    fn camera_record(id: u32, model: i32, params: &[f64]) -> Vec<u8> {
        let mut bytes = Vec::new();
        bytes.extend(id.to_le_bytes());
        bytes.extend(model.to_le_bytes());
        bytes.extend(640u64.to_le_bytes());
        bytes.extend(480u64.to_le_bytes());
        for p in params {
            bytes.extend(p.to_le_bytes());
        }
        bytes
    }

    #[test]
    fn model_folders_are_found_one_level_down() {
        let root = std::env::temp_dir().join(format!("gomatch-find-model-{}", std::process::id()));
        let model = root.join("garden/sparse/0");
        std::fs::create_dir_all(&model).unwrap();
        assert!(find_model_dir(&root.join("garden"))
            .unwrap_err()
            .to_string()
            .contains("holds no COLMAP model"));
        std::fs::write(model.join("cameras.txt"), "").unwrap();
        assert_eq!(find_model_dir(&model).unwrap(), model);
        assert_eq!(find_model_dir(&root.join("garden")).unwrap(), model);
        assert_eq!(find_model_dir(&root.join("garden/sparse")).unwrap(), model);
        let second = root.join("garden/sparse/1");
        std::fs::create_dir_all(&second).unwrap();
        std::fs::write(second.join("cameras.bin"), "").unwrap();
        let error = find_model_dir(&root.join("garden"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("pick one of") && error.contains("sparse/1"),
            "{error}"
        );
        let blob = root.join("map.bin");
        std::fs::write(&blob, b"GMAP\x02\0\0\0").unwrap();
        let error = find_model_dir(&blob).unwrap_err().to_string();
        assert!(error.contains("a gomatch map blob"), "{error}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn binary_cameras_parse_and_reject_corruption() {
        let mut data = 1u64.to_le_bytes().to_vec();
        data.extend(camera_record(3, 1, &[500.0, 501.0, 320.0, 240.0]));
        let cameras = parse_cameras_bin(&data).unwrap();
        assert_eq!(cameras[&3].focal, [500.0, 501.0]);

        assert!(matches!(
            parse_cameras_bin(&data[..data.len() - 1]),
            Err(FormatError::Truncated { .. })
        ));
        let mut trailing = data.clone();
        trailing.push(0);
        assert!(matches!(
            parse_cameras_bin(&trailing),
            Err(FormatError::TrailingBytes { .. })
        ));
        let mut unsupported = 1u64.to_le_bytes().to_vec();
        unsupported.extend(camera_record(3, 8, &[500.0, 320.0, 240.0, 0.0]));
        assert!(matches!(
            parse_cameras_bin(&unsupported),
            Err(FormatError::UnsupportedCameraModel { camera_id: 3, .. })
        ));
    }

    #[test]
    fn binary_images_and_points_parse() {
        let mut images = 1u64.to_le_bytes().to_vec();
        images.extend(7u32.to_le_bytes());
        for v in [1.0f64, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0] {
            images.extend(v.to_le_bytes());
        }
        images.extend(3u32.to_le_bytes());
        images.extend(b"img.png\0");
        images.extend(2u64.to_le_bytes());
        for (x, y, id) in [(1.0f64, 2.0f64, u64::MAX), (3.0, 4.0, 9)] {
            images.extend(x.to_le_bytes());
            images.extend(y.to_le_bytes());
            images.extend(id.to_le_bytes());
        }
        let parsed = parse_images_bin(&images).unwrap();
        assert_eq!(parsed[&7].name, "img.png");
        assert_eq!(parsed[&7].keypoints[0].point3d, None);
        assert_eq!(parsed[&7].keypoints[1].point3d, Some(9));

        let mut points = 1u64.to_le_bytes().to_vec();
        points.extend(9u64.to_le_bytes());
        for v in [1.0f64, 2.0, 3.0] {
            points.extend(v.to_le_bytes());
        }
        points.extend([1u8, 2, 3]);
        points.extend(0.25f64.to_le_bytes());
        points.extend(1u64.to_le_bytes());
        points.extend(7u32.to_le_bytes());
        points.extend(1u32.to_le_bytes());
        let parsed = parse_points_bin(&points).unwrap();
        assert_eq!(parsed[&9].xyz, Vector3::new(1.0, 2.0, 3.0));
        assert_eq!(
            parsed[&9].track,
            vec![TrackElement {
                image_id: 7,
                keypoint_index: 1
            }]
        );
        for cut in 0..points.len() {
            assert!(parse_points_bin(&points[..cut]).is_err());
        }
    }
}
